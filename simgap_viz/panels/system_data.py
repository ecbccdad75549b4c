"""System & data tab: system, simulator, epsilon, N1hat; collect or load a dataset."""

from __future__ import annotations

from simgap.dataset import load_dataset

from .. import engine
from .base import Panel


class SystemDataPanel(Panel):
    def __init__(self, app):
        super().__init__(app)
        gui = app.server.gui
        s = app.settings
        self.run_method = gui.add_dropdown(
            "Run results", options=("stochastic", "deterministic"), initial_value="stochastic", visible=False,
            hint="which certificate's results of the loaded run to show (the run's data, certificate, "
                 "controller and rollouts)")
        self.run_method.on_update(lambda _: app.guarded(self._switch_method))
        self.system = gui.add_dropdown("System", options=engine.SYSTEMS, initial_value=s.system)
        self.simulator = gui.add_dropdown("Simulator", options=engine.SIMULATORS, initial_value=s.simulator)
        self.noise = gui.add_number("Noise std", initial_value=s.noise_std, step=0.001,
                                    hint="actuation noise standard deviation of the simulator [input units]")
        self.epsilon = gui.add_number("epsilon", initial_value=s.epsilon, step=0.001,
                                      hint="cover radius: every x in X within epsilon of a cover point")
        self.n_runs = gui.add_number("N1hat", initial_value=s.n_runs, step=1,
                                     hint="simulator runs per (x_r, u) pair")
        self.steps = gui.add_number("Steps k", initial_value=s.steps, step=1,
                                    hint="sampling period tau = k * base tau, input held")
        self.seed = gui.add_number("Seed", initial_value=s.seed, step=1)
        self.buttons["collect"] = gui.add_button("Collect", icon=None)
        self.buttons["collect"].on_click(lambda _: app.collect())
        with gui.add_folder("Load a dataset", expand_by_default=False):
            self.path = gui.add_text("Path (.npz or store)", initial_value="")
            self.load_button = gui.add_button("Load")
            self.load_button.on_click(lambda _: app.guarded(self.load, self.path.value))
        self.info = gui.add_markdown("")
        on = self.on
        on(self.system, lambda v: app.update_settings(system=v, simulator=engine.default_simulator(v, app.settings.simulator),
                                                    eta=engine.default_eta(engine.system_by_name(v))))
        on(self.simulator, lambda v: app.update_settings(simulator=v))
        on(self.noise, lambda v: app.update_settings(noise_std=float(v)))
        on(self.epsilon, lambda v: app.update_settings(epsilon=float(v)))
        on(self.n_runs, lambda v: app.update_settings(n_runs=int(v) if float(v) == int(v) else float(v)))
        on(self.steps, lambda v: app.update_settings(steps=int(v) if float(v) == int(v) else float(v)))
        on(self.seed, lambda v: app.update_settings(seed=int(v)))
        self.sync_from_settings()

    def _switch_method(self) -> None:
        app = self.app
        if getattr(app, "_syncing", False) or app.run is None or self.run_method.value == app.run_method:
            return
        app.load_run(app.run, self.run_method.value)

    def load(self, path: str) -> None:
        """Load a dataset file (or store directory) and make it the current data."""
        self.app.set_dataset(load_dataset(path.strip()))

    def sync_from_settings(self) -> None:
        s = self.app.settings
        for h, v in ((self.system, s.system), (self.simulator, s.simulator), (self.noise, s.noise_std),
                     (self.epsilon, s.epsilon), (self.n_runs, s.n_runs), (self.steps, s.steps), (self.seed, s.seed)):
            self.set_quiet(h, v)
        run = self.app.run
        if run is not None:
            self.run_method.options = tuple(run.methods) + (("nominal",) if getattr(run, "nominal", None) else ())
            self.set_quiet(self.run_method, self.app.run_method)
        self.run_method.visible = run is not None
        d = self.app.results.get("collect")
        sysd = self.app.system
        txt = ([f"run: `{run.path}` ({run.summary.get('experiment')}, profile {run.summary.get('profile')})"]
               if run is not None else []) + [f"**{sysd.name}**: n = {sysd.n}, m = {sysd.m}, |U| = {sysd.inputs.shape[0]}, tau = {sysd.tau:g} s"]
        if d is not None:
            txt.append(f"data: K = {d.K} pairs, N1hat = {d.n_runs}, epsilon = {d.epsilon:g}, "
                       f"max gap = {', '.join(f'{g:.3g}' for g in d.gap().max(axis=0))}")
        self.info.content = "  \n".join(txt)


def build(app) -> SystemDataPanel:
    return SystemDataPanel(app)
