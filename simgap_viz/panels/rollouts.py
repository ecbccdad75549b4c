"""Rollouts tab: count, horizon, initial state, seed; run the closed loop in the simulator."""

from __future__ import annotations

from .. import engine
from ..settings import parse_vector
from .base import Panel, fmt_vec


class RolloutsPanel(Panel):
    def __init__(self, app):
        super().__init__(app)
        gui = app.server.gui
        s = app.settings
        self.count = gui.add_number("Rollouts", initial_value=s.n_rollouts, step=1)
        self.horizon = gui.add_number("Horizon T", initial_value=s.horizon, step=1,
                                      hint="simulator steps per rollout")
        self.x0 = gui.add_text("Initial state", initial_value=fmt_vec(s.x0),
                               hint="comma separated; empty: the experiment's x0")
        self.seed = gui.add_number("Rollout seed", initial_value=s.rollout_seed, step=1)
        self.buttons["rollout"] = gui.add_button("Roll out")
        self.buttons["rollout"].on_click(lambda _: app.rollout())
        self.note = gui.add_markdown(engine.unavailable_note("rollout"))
        self.stats = gui.add_markdown("")
        self.on(self.count, lambda v: app.update_settings(n_rollouts=int(v) if float(v) == int(v) else float(v)))
        self.on(self.horizon, lambda v: app.update_settings(horizon=int(v) if float(v) == int(v) else float(v)))
        self.on(self.x0, lambda v: app.update_settings(
            x0=parse_vector(v, "initial state", app.system.n, allow_empty=True)), debounce=0.6)
        self.on(self.seed, lambda v: app.update_settings(rollout_seed=int(v)))

    def sync_from_settings(self) -> None:
        s = self.app.settings
        self.set_quiet(self.count, s.n_rollouts)
        self.set_quiet(self.horizon, s.horizon)
        self.set_quiet(self.x0, fmt_vec(s.x0))
        self.set_quiet(self.seed, s.rollout_seed)

    def show_stats(self) -> None:
        res = self.app.results.get("rollout")
        self.stats.content = "" if res is None else self.app.stale_note("rollout") + engine.rollout_markdown(res)


def build(app) -> RolloutsPanel:
    return RolloutsPanel(app)
