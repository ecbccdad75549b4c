"""The simgap web app: one class owns the viser server, the state, the cache and the job runner.

Layout: a header (status line, progress bar, cancel button) and one tab per stage
(System & data, Certificate, Synthesis, Rollouts, Refine, View), each filled by a module in
:mod:`simgap_viz.panels`. Scene layers (gamma surfaces, data points, obstacle map, winning
domain, rollouts, simulator bodies) are drawn by :mod:`simgap_viz.layers`.

Threading: viser runs callbacks on a thread pool; every read/write of the app state takes
``self.lock``. Long stages run on the :class:`~simgap_viz.jobs.JobRunner` thread, so the GUI
stays responsive and a cancel button can stop them. Button handlers are one-line calls into
the public methods (:meth:`collect`, :meth:`certify`, ...), which tests call directly.

Caching: each stage's result is stored under ``(stage, settings.stage_key(stage))``;
asking again for a configuration already computed is a dictionary look-up.
"""

from __future__ import annotations

import threading
import time
from typing import Any, Callable, Optional

import numpy as np

from simgap.errors import SimgapError

from . import engine, origin
from .jobs import JobContext, JobRunner
from .settings import STAGES, Settings

# results kept (marked stale) when an upstream stage changes, and what the mark says
KEEP_STALE = ("synthesize", "rollout")
STALE_ACTION = {"synthesize": "re-synthesize", "rollout": "roll out again"}
STALE_WHAT = {"synthesize": "winning domain", "rollout": "rollouts"}
# the pipeline's stages in order, what each shows (status line) and the button that computes it
SHOWN = {"collect": "data (data gaps)", "certify": "certificate (gamma)", "synthesize": "winning domain",
         "rollout": "rollouts"}
# settings as the panels label them (the status line names what changed)
LABELS = {"n_runs": "N1hat", "noise_std": "Noise std", "steps": "Steps k", "seed": "Seed", "degree": "Basis degree",
          "terms": "Extra terms", "concentration": "Concentration", "value_range": "Range b", "hold": "Hold",
          "use_gap": "Use gamma", "n_rollouts": "Rollouts", "rollout_seed": "Rollout seed", "system": "System",
          "simulator": "Simulator", "confidence": "Confidence"}
BUTTON = {"collect": "Collect", "certify": "Certify", "synthesize": "Synthesize", "rollout": "Roll out"}



class _OneLineHandlerErrors:
    """A logging filter for websockets' server logger: a connection whose handler failed (viser
    cannot decode what the client sent: not MessagePack, a text frame, an unknown message) is
    logged as one line naming the error, without the traceback; the connection is closed as before."""

    def filter(self, record) -> bool:
        if record.exc_info and record.getMessage() == "connection handler failed":
            e = record.exc_info[1]
            record.msg, record.args = "simgap gui: dropped a client connection after a malformed message (%s: %s)", (
                type(e).__name__, e)
            record.exc_info, record.exc_text = None, None
        return True


def quiet_bad_messages() -> None:
    """Install :class:`_OneLineHandlerErrors` once (idempotent)."""
    import logging
    log = logging.getLogger("websockets.server")
    if not any(isinstance(f, _OneLineHandlerErrors) for f in log.filters):
        log.addFilter(_OneLineHandlerErrors())

#: the control panel's width [px] against the window's: a fixed share with bounds, so that the tabs
#: fit in one row at 1280 px and the scene keeps most of a wide window
PANEL_SHARE, PANEL_MIN, PANEL_MAX = 0.27, 440, 600

#: tab labels in one row (viser 1.1 pads each tab by 0.75 em on every side; the panel's width alone
#: would have to be about 600 px for the seven tabs at that padding)
TAB_STYLE = ("<style>[role=tablist]{flex-wrap:nowrap !important}"
             "[role=tab]{padding-left:0.4em !important;padding-right:0.4em !important}</style>")


def panel_width(window_px: int) -> int:
    """The control panel's width [px] in a window ``window_px`` wide: PANEL_SHARE of it within
    [PANEL_MIN, PANEL_MAX], never more than half the window."""
    return int(min(max(PANEL_SHARE * window_px, PANEL_MIN), PANEL_MAX, 0.5 * window_px))


class SimgapApp:
    """The interactive app (see module docstring).

    Parameters
    ----------
    host, port : str, int
        Where the viser server listens (port 0 picks a free port).
    settings : Settings, optional
        Initial knobs (e.g. from ``--experiment``/``--profile``).
    dataset : Dataset, optional
        Pre-collected data (skips the collect stage).
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 8080, settings: Optional[Settings] = None,
                 dataset=None, spec=None, arena=None, experiment=None, executor: str = "local"):
        import viser

        self.lock = threading.RLock()
        self.fit_lock = threading.RLock()  # window sizes and camera fits (scene.fit_camera, _fit_window)
        self.settings = (settings or Settings())
        self.experiment = experiment
        self.executor = executor
        self.system = engine.make_system(self.settings, experiment)
        self.spec = spec
        self.arena = arena
        self.cache: dict = {}
        self.results: dict = {s: None for s in STAGES}
        self.result_keys: dict = {s: None for s in STAGES}
        # stages whose shown result was computed from earlier upstream results (e.g. the winning
        # domain after a re-certification): kept on screen, marked "stale" until recomputed
        self.stale: set = set()
        self.notifications: list = []  # (title, body, color) in order, also for tests
        self.timings: dict = {}  # stage -> seconds of the last run of that stage alone (or cache hit)
        self._estimates: dict = {}  # stage -> the engine's estimate [s] for the running job (collection)
        self.auto_certify = True
        from .layers import scene
        self.view = {"dim": 0, "a": 0, "b": 1, "fixed": None, "zscale": None, "n_draw": scene.N_DRAW, "t": None,
                     "rollout_index": 0, "flat_gamma": False}
        self.legend = None  # what the gamma layer drew (range, height scale), for the View tab
        self.winning_counts = None
        self.rollout_drawn = None
        self.body_frame = None
        self.layers_visible = scene.default_visibility()
        self.jobs = JobRunner(on_progress=self._job_progress, on_finish=self._job_finished)
        self._scene_version = 0
        self.run = None  # a loaded `simgap run` folder (results.RunResults) and the method shown
        self.run_method = None
        self.audit = None  # the shown certificate's audit report (from a run folder)
        self.perrun_view = {"map": True, "markers": True, "controller": "perrun"}  # the per-run layer
        self.windows: dict = {}  # client id -> {"size": (w, h) of its canvas, "panel": panel width [px]}

        origin.install()  # refuse websockets from other pages before the server starts
        quiet_bad_messages()  # a malformed client message: one line, not a traceback
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.server.gui.configure_theme(control_width="large", dark_mode=False, show_logo=False)
        self.server.scene.set_up_direction("+z")
        self._build_gui()
        self.server.on_client_connect(self._on_connect)
        if dataset is not None:
            self.set_dataset(dataset)
        self.refresh_system_layers()

    # ----- GUI construction -----------------------------------------------------------
    def _build_gui(self) -> None:
        from .panels import certificate, perrun, refinement, rollouts, synthesis, system_data, view

        gui = self.server.gui
        self.tab_style = gui.add_html(TAB_STYLE, order=-1)
        self.status = gui.add_markdown("**simgap** ready", order=0)
        self.progress = gui.add_progress_bar(0.0, visible=False, animated=False, order=1)
        self.cancel_button = gui.add_button("Cancel", color="red", disabled=True, order=2)
        self.cancel_button.on_click(lambda _: self.cancel())
        tabs = gui.add_tab_group(order=3)
        self.panels = {}
        with tabs.add_tab("Data"):
            self.panels["system"] = system_data.build(self)
        with tabs.add_tab("Certificate"):
            self.panels["certificate"] = certificate.build(self)
        with tabs.add_tab("Synthesis"):
            self.panels["synthesis"] = synthesis.build(self)
        with tabs.add_tab("Rollouts"):
            self.panels["rollouts"] = rollouts.build(self)
        with tabs.add_tab("Per run"):
            self.panels["perrun"] = perrun.build(self)
        with tabs.add_tab("Refine"):
            self.panels["refine"] = refinement.build(self)
        with tabs.add_tab("View"):
            self.panels["view"] = view.build(self)
        self.tabs = tabs
        self._update_buttons()

    def _on_connect(self, client) -> None:
        # the canvas size arrives with the client's camera: fit the panel and the scene to the window
        # once it is known (on_update), the default camera only while it is not
        client.camera.on_update(lambda cam: self._fit_window(client))
        self._fit_window(client, initial=True)

    def _fit_window(self, client, initial: bool = False) -> None:
        """Size the control panel for the browser window and refit the camera, when the window's size
        is new (a camera move alone changes nothing): ``panel_width`` of the canvas width.

        viser runs the connect handler and each camera message's callback on its thread pool, so two
        of these can run at once (a window resized twice, a connect and the first camera message):
        ``fit_lock`` makes each check-and-fit one step. Before it, the connect handler's default camera
        (computed without the window's size) could be sent after the fitted one of a camera message
        handled meanwhile, and the size, then already recorded, never refitted the scene.
        ``initial``: the connect handler, which sends the default camera while no size is known."""
        from .layers import scene
        with self.fit_lock:
            try:
                size = (int(client.camera.image_width), int(client.camera.image_height))
            except (AssertionError, AttributeError):  # no camera message from this client yet
                size = None
            if size is None or size[0] <= 0:
                if initial:
                    scene.fit_camera(self, [client])
                return
            if self.windows.get(client.client_id, {}).get("size") == size:
                if self._shows_default_camera(client):  # the client went (back) to the initial camera
                    scene.fit_camera(self, [client])
                return
            width = panel_width(size[0])
            self.windows[client.client_id] = {"size": size, "panel": width}
            try:
                client.gui.main_panel.set_width(width)
            except Exception:  # a client that just went away
                return
            scene.fit_camera(self, [client])

    def _shows_default_camera(self, client) -> bool:
        """The client reports the server's initial camera while its window's fit is another one.

        The browser applies the initial camera when it sets up its view, and now and then that came
        after the fit sent for its window (seen at 1280 x 800 in the browser test: the client reported
        the initial camera after the fit, the scene stood partly under the panel). No one moves the
        camera by hand to exactly that pose, so it is refitted."""
        from .layers import scene
        try:
            look, pos = np.asarray(client.camera.look_at, float), np.asarray(client.camera.position, float)
        except (AssertionError, AttributeError):
            return False
        init = self.server.initial_camera
        if not (np.allclose(look, init.look_at, atol=1e-6) and np.allclose(pos, init.position, atol=1e-6)):
            return False
        fit_look, fit_pos = scene.window_camera(self, self.windows.get(client.client_id))
        return not (np.allclose(fit_look, look, atol=1e-6) and np.allclose(fit_pos, pos, atol=1e-6))

    @property
    def url(self) -> str:
        host = self.server.get_host()
        host = "127.0.0.1" if host in ("0.0.0.0", "", "::") else host
        return f"http://{host}:{self.server.get_port()}"

    def stop(self) -> None:
        self.jobs.cancel()
        try:
            self.jobs.wait(10)
        except TimeoutError:
            pass
        self.server.stop()

    # ----- notifications ----------------------------------------------------------------
    def notify(self, title: str, body: str, color: str = "red") -> None:
        """Show a notification in every connected browser (and keep it in ``self.notifications``)."""
        self.notifications.append((title, body, color))
        for client in self.server.get_clients().values():
            try:
                client.add_notification(title, body, auto_close_seconds=8.0, color=color)
            except Exception:  # a client that just went away
                pass
        self.set_status(f"**{title}**: {body}")

    def set_status(self, text: str) -> None:
        self.status.content = text

    def guarded(self, fn: Callable, *args, **kwargs) -> Any:
        """Run ``fn``; a SimgapError (bad value) becomes a visible notification, never a dead GUI."""
        try:
            return fn(*args, **kwargs)
        except SimgapError as e:
            self.notify("Invalid value", str(e))
            return None

    # ----- settings -----------------------------------------------------------------------
    def update_settings(self, **changes) -> bool:
        """Apply validated changes to the settings; on a bad value notify and keep the old ones.

        Returns True if the settings changed. Changes of certification knobs re-certify from
        the cached data when ``auto_certify`` is on (the cheap path).
        """
        with self.lock:
            try:
                new = self.settings.replace(**changes)
                system = self.system
                if (new.system, int(new.steps)) != (self.system.name, int(self.system.steps)):
                    system = engine.make_system(new, self.experiment)
                new.validate(system.n)
            except SimgapError as e:
                self.notify("Invalid value", str(e))
                return False
            old = self.settings
            if new.data_source and any(k != "data_source" and v != old.stage_fields("collect")[k]
                                       for k, v in new.stage_fields("collect").items()):
                new = new.replace(data_source="")  # no longer the loaded dataset's settings
            self.settings = new
            if system is not self.system:
                self.system = system
                self._on_system_changed()
        cert_changed = old.stage_key("certify") != new.stage_key("certify")
        if cert_changed and self.auto_certify and self.results["collect"] is not None \
                and engine.availability()["certify"][0] \
                and self.result_keys["collect"] == new.stage_key("collect"):
            if self.jobs.busy:  # re-certify once the running job is done, without a notification
                if self.jobs.current == "certify":  # its settings are superseded: stop it quietly
                    self.jobs.cancel(superseded=True)
                self._schedule_after_job(self.certify)
                self.set_status(f"{self.jobs.current} running; will re-certify when it is done")
            else:
                self.certify()
        elif not self.jobs.busy:
            self._changed = [LABELS.get(k, k) for k, v in new.to_dict().items()
                             if old.to_dict().get(k) != v and k != "data_source"]
            self.set_status(self.settings_status(self._changed))
        return True

    def stale_stages(self) -> list:
        """The stages whose shown result no longer matches the current settings, in pipeline order:
        computed with settings since changed (its configuration key differs) or from an upstream
        result since replaced (``self.stale``)."""
        s = self.settings
        out = []
        for st in SHOWN:
            if self.results.get(st) is None:
                continue
            try:
                key = s.stage_key(st)
            except SimgapError:
                key = None
            if st in self.stale or self.result_keys.get(st) != key:
                out.append(st)
        return out

    def next_action(self) -> Optional[str]:
        """The stage to run next for the current settings: the first one, in pipeline order, whose
        result is stale or missing, up to the last stage shown (at least the certificate: data and a
        certificate are what every session needs); None when everything shown is current."""
        order = list(SHOWN)
        stale = set(self.stale_stages())
        last = max([i for i, st in enumerate(order) if self.results.get(st) is not None] + [1])
        for st in order[:last + 1]:
            if st in stale or self.results.get(st) is None:
                return st
        return None

    def estimate_text(self, stage: str) -> str:
        """Time a press of ``stage``'s button will take: a collection's from the engine's cost model
        (:func:`engine.collect_estimate`; pairs x N1hat / the simulator's rate), the other stages' from
        their last run in this session; "" when nothing is known. A stage whose data must be collected
        first adds the collection's estimate."""
        from simgap.cover import format_duration
        s = self.settings
        parts = []
        need_collect = stage in ("collect", "certify", "refine") and (
            stage == "collect" or self.cache.get(("collect", s.stage_key("collect"))) is None)
        if need_collect:
            try:
                est = engine.collect_estimate(s, self.system, self.experiment, self.executor)
            except SimgapError:
                est = None
            if est is not None:
                parts.append("collect: " + engine.collect_estimate_text(est))
                if est.seconds is None:
                    self._calibrate_later()
        if stage != "collect":
            t = self.timings.get(stage)
            parts.append(f"{stage}: about {format_duration(t)} (its last run here)" if t is not None
                         else f"{stage}: no estimate before its first run (the engine has no cost model for it)")
        return ", then ".join(parts)

    def _calibrate_later(self) -> None:
        """Time the simulator on a background thread (about a second), then show the estimate."""
        if getattr(self, "_calibrating", False):
            return
        self._calibrating = True
        s = self.settings

        def work():
            try:
                engine.collect_estimate(s, self.system, self.experiment, self.executor, calibrate=True)
            except Exception:  # no estimate is not an error: the status keeps saying so
                return
            finally:
                self._calibrating = False
            # Refresh whatever status still waits for a time, from the settings now current: a change made
            # while this ran found the calibration busy and was not timed itself. The rate does not
            # depend on N1hat or the cover; a change of simulator starts one more calibration from here.
            if "time not estimated yet" in self.status.content and not self.jobs.busy:
                self.set_status(self.settings_status(getattr(self, "_changed", [])))

        threading.Thread(target=work, name="simgap-calibrate", daemon=True).start()

    def settings_status(self, changed=()) -> str:
        """The status line after a settings change: what changed, which shown layers are stale, and
        the button to press next with its time estimate."""
        head = ("changed: " + ", ".join(f"**{k}**" for k in changed)) if changed else "settings"
        stale = self.stale_stages()
        text = head
        if stale:
            text += "; stale (from earlier settings): " + ", ".join(SHOWN[st] for st in stale)
        nxt = self.next_action()
        if nxt is not None:
            est = self.estimate_text(nxt)
            # after a dash, not in parentheses: the estimate ends with its own "(calibrated here, ...)",
            # which doubled the closing parenthesis
            text += f"; next: press **{BUTTON[nxt]}**" + (f" — {est}" if est else "")
        elif not stale:
            text += "; everything shown is current"
        return text

    def _schedule_after_job(self, fn) -> None:
        """Run ``fn`` once the current job has ended (one pending call at most)."""
        with self.lock:
            if getattr(self, "_pending", None) is not None:
                self._pending = fn
                return
            self._pending = fn

        def waiter():
            try:
                self.jobs.wait(24 * 3600)
            except TimeoutError:
                return
            with self.lock:
                f, self._pending = self._pending, None
            if f is not None:
                f()

        threading.Thread(target=waiter, name="simgap-pending", daemon=True).start()

    def stale_status(self) -> str:
        """What the status line adds while shown results are stale or a stage is missing ("" if
        none): the stale layers and the next button to press."""
        stale = [st for st in KEEP_STALE if st in self.stale_stages()]
        text = ""
        if stale:
            text = ("; **stale: " + ", ".join(STALE_ACTION[st] for st in stale) + "** (the "
                    + " and the ".join(STALE_WHAT[st] for st in stale) + " shown are from earlier settings)")
        nxt = self.next_action()
        if nxt is not None:
            text += f"; next: press **{BUTTON[nxt]}**"
        return text

    def stale_note(self, stage: str) -> str:
        """Markdown warning for a panel whose shown result is stale ("" if it is current)."""
        if stage not in self.stale:
            return ""
        return (f"**stale: {STALE_ACTION[stage]}**: the {STALE_WHAT[stage]} below were computed with the previous "
                f"{'certificate' if stage == 'synthesize' else 'controller or certificate'}; press "
                f"{'Synthesize' if stage == 'synthesize' else 'Roll out'} for the current settings.\n\n")

    def _on_system_changed(self) -> None:
        self.view["fixed"] = None
        self.view["zscale"] = None
        self.view.update(dim=0, a=0, b=1)
        for s in STAGES:
            self.results[s] = None
            self.result_keys[s] = None
        self.stale.clear()
        self.panels["view"].rebuild_sliders()
        self.refresh_system_layers()
        self.refresh_result_layers()
        if "perrun" in self.panels:
            self.panels["perrun"].show()

    # ----- data -----------------------------------------------------------------------
    def set_dataset(self, dataset) -> None:
        """Use an already collected dataset (its system and epsilon become the current ones)."""
        with self.lock:
            s = self.settings.replace(system=dataset.system.name, steps=int(dataset.system.steps),
                                      epsilon=float(dataset.epsilon), n_runs=int(dataset.n_runs),
                                      data_source=f"dataset:{dataset.hash or id(dataset)}")
            s = s.replace(eta=self.settings.eta if len(self.settings.eta) == dataset.system.n
                          else engine.default_eta(dataset.system))
            self.settings = s
            self.system = dataset.system
            self._on_system_changed()
            key = s.stage_key("collect")
            self.cache[("collect", key)] = dataset
            self.results["collect"] = dataset
            self.result_keys["collect"] = key
        self.panels["system"].sync_from_settings()
        self.panels["certificate"].sync_from_settings()
        self.panels["synthesis"].sync_from_settings()
        self.set_status(f"dataset: {dataset.K} pairs (x_r, u), N1hat = {dataset.n_runs}, "
                        f"epsilon = {dataset.epsilon:g}")
        engine.warm_up()  # data in hand: a certification (a knob change) is what comes next
        self.refresh_result_layers()
        self._update_buttons()

    def load_run(self, run, method: str = "stochastic") -> None:
        """Show a finished ``simgap run`` (:class:`~simgap_viz.results.RunResults`): its data,
        certificate, audit, controller and rollouts of ``method``, with the run's settings.

        The loaded results are cached under the settings' stage keys, so every knob works from
        here (a changed delta re-certifies from the run's data).
        """
        from .experiment import from_experiment, from_stages
        from .results import run_spec
        if method == "nominal" and getattr(run, "nominal", None) is not None:
            # an invariant-set run's nominal-model set (no gap, use_gap off) and its rollouts, beside the
            # run's data and their certificate (shown, not used: without it the app would re-certify)
            from .results import MethodResults
            src = run.methods.get("stochastic") or next(iter(run.methods.values()))
            m = MethodResults(dataset=src.dataset, certificate=src.certificate, audit=src.audit, synthesis=None,
                              rollouts=run.nominal.rollouts, invariant_set=run.nominal.invariant_set,
                              statement=run.nominal.statement)
        elif method not in run.methods:
            raise SimgapError(f"the run has no {method!r} results; it has "
                              f"{', '.join(list(run.methods) + (['nominal'] if getattr(run, 'nominal', None) else []))}")
        else:
            m = run.methods[method]
        exp = run.experiment
        st = from_experiment(exp)[0] if exp is not None else from_stages(run)  # stage outputs: no experiment
        spec, x0, arena = run_spec(run)
        ro = run.summary.get("sections", {}).get("rollout", {})
        x0 = run.summary.get("x0", x0)
        with self.lock:
            self.experiment, self.spec, self.arena = exp, spec, arena
            self.run, self.run_method, self.audit = run, method, m.audit
            self.view["dims"] = (0, 1)  # the plane starts over the first two states (a grid's map is there)
            self.settings = st.replace(use_gap=method != "nominal", x0=None if x0 is None else tuple(float(v) for v in x0),
                                       n_rollouts=int(ro.get("n", st.n_rollouts)),
                                       horizon=int(m.rollouts.horizon) if m.rollouts is not None else st.horizon,
                                       rollout_seed=int(ro.get("seed", 11)),
                                       # an invariant-set run has no grid controller to take them from
                                       hold=int(m.synthesis.controller.hold) if m.synthesis is not None else st.hold,
                                       eta=tuple(float(e) for e in m.synthesis.controller.grid.eta)
                                       if m.synthesis is not None else st.eta)
        if m.dataset is not None:
            self.set_dataset(m.dataset)
        else:  # stage outputs without their data: the model is theirs
            with self.lock:
                self.system = engine.make_system(self.settings, exp)
                self._on_system_changed()
        with self.lock:
            for stage, res in (("certify", m.certificate), ("synthesize", m.synthesis), ("rollout", m.rollouts)):
                if res is None:
                    continue
                key = self.settings.stage_key(stage)
                self.cache[(stage, key)] = res
                self.results[stage] = res
                self.result_keys[stage] = key
        for p in self.panels.values():
            p.sync_from_settings()
        self._show_results()
        self.panels["perrun"].show()
        if run.stages is not None:
            from .results import describe_stages
            self.set_status("**stage outputs** (" + method + "):\n\n" + "\n".join(f"* {line}" for line in describe_stages(run)))
            return
        st = m.statement  # the method's own words (the grid's winning cells, a tube's T0 and p_cert)
        said = st.headline if st is not None else "no controller"
        self.set_status(f"run **{run.path.name}** ({method}): data K = {m.dataset.K}, {said}"
                        + (f", {m.rollouts.n_rollouts} rollouts" if m.rollouts is not None else ""))

    def _show_results(self) -> None:
        """Refresh every panel's summary and the result layers."""
        self.panels["certificate"].show_summary()
        self.panels["synthesis"].show_stats()
        self.panels["rollouts"].show_stats()
        self.panels["refine"].show_report()
        self.refresh_result_layers()
        self._update_buttons()

    # ----- stages -------------------------------------------------------------------------
    def _run_stage(self, stage: str, background: bool = True) -> None:
        """Show the stage's cached result for the current settings, or compute it (and any
        missing upstream stage) on the job thread."""
        with self.lock:
            s = self.settings.validate(self.system.n)
            key = s.stage_key(stage)
            hit = self.cache.get((stage, key))
        if hit is not None:
            t0 = time.perf_counter()
            self._accept(stage, key, hit)
            self.timings[stage] = time.perf_counter() - t0
            self.set_status(f"{stage}: from cache ({key})" + self.stale_status())
            return
        engine.require(stage)
        compute = lambda ctx: self._result_for(stage, s, ctx)  # noqa: E731
        if background:
            self.start_job(stage, compute)
        else:
            compute(JobContext(name=stage))

    def _result_for(self, stage: str, s: Settings, ctx: JobContext):
        """The result of ``stage`` for settings ``s``: from the cache, else computed by the engine
        after its upstream stages (runs on the job thread)."""
        key = s.stage_key(stage)
        with self.lock:
            hit = self.cache.get((stage, key))
            system, exp = self.system, self.experiment
        if hit is not None:
            return hit
        engine.require(stage)
        ctx.check()
        # upstream results first; then ctx.begin names the stage that runs (the progress bar's label)
        if stage == "collect":
            ctx.begin(stage)
            try:
                self._estimates["collect"] = engine.collect_estimate(s, system, exp, self.executor,
                                                                     calibrate=True).seconds
            except Exception:  # a simulator that cannot be timed: progress then says "no estimate yet"
                self._estimates["collect"] = None
            ctx.begin(stage)  # the calibration is not part of the collection's elapsed time
            res = engine.collect(s, system, ctx, experiment=exp, executor=self.executor)
        elif stage == "certify":
            data = self._result_for("collect", s, ctx)
            ctx.begin(stage)
            res = engine.certify(data, s, ctx)
        elif stage == "synthesize":
            cert = self._result_for("certify", s, ctx) if s.use_gap else None
            ctx.begin(stage)
            res = engine.synthesize(system, self.current_spec(), cert, s, ctx)
            if res.empty:  # a result, but the user must see it at once
                self.notify("Empty winning domain", res.stats.get("diagnosis") or "no winning cell")
        elif stage == "rollout":
            syn = self._result_for("synthesize", s, ctx)
            ctx.begin(stage)
            res = engine.rollout(system, self.current_spec(), syn, s, ctx, experiment=exp,
                                 arena=self.arena if engine.base_system(system).name == "turtlebot" else None)
        elif stage == "refine":
            data = self._result_for("collect", s, ctx)
            ctx.begin(stage)
            res = engine.refine(data, s, ctx)
        else:
            raise SimgapError(f"unknown stage {stage!r}")
        ctx.check()
        self.timings[stage] = ctx.elapsed()  # this stage alone (a job's total would include upstream ones)
        self._accept(stage, key, res)
        return res

    def _accept(self, stage: str, key: str, result) -> None:
        with self.lock:
            self.cache[(stage, key)] = result
            self.results[stage] = result
            self.result_keys[stage] = key
            # results downstream of this stage no longer match it
            downstream = {"collect": ("certify", "synthesize", "rollout", "refine"),
                          "certify": ("synthesize", "rollout", "refine"),
                          "synthesize": ("rollout",), "rollout": (), "refine": ()}[stage]
            self.stale.discard(stage)
            for st in downstream:
                k = self.settings.stage_key(st)
                hit = self.cache.get((st, k))
                # a new data set too: the winning domain and the rollouts stay, marked, never vanish silently
                if hit is None and st in KEEP_STALE and self.results[st] is not None:
                    self.stale.add(st)  # keep it on screen, marked, until it is recomputed
                    continue
                self.results[st] = hit
                self.result_keys[st] = k if hit is not None else None
                self.stale.discard(st)
        if stage == "collect":
            self.panels["system"].sync_from_settings()
        self._show_results()

    def start_job(self, name: str, fn: Callable[[JobContext], Any], then: Optional[Callable] = None) -> None:
        """Run ``fn(ctx)`` on the job thread (progress bar, cancel button enabled)."""
        self.jobs.submit(name, fn, then)
        self.progress.visible = True
        self._update_buttons()

    def collect(self, background: bool = True) -> None:
        """Collect data for the current settings (engine: ``simgap.collect``)."""
        if self.settings.data_source:  # collecting replaces a loaded dataset
            self.settings = self.settings.replace(data_source="")
        self.guarded(self._run_stage, "collect", background)

    def certify(self, background: bool = True) -> None:
        """Certify gamma for the current settings (engine: ``simgap.certify``); collects first if
        the data for these settings are not cached."""
        self.guarded(self._run_stage, "certify", background)

    def synthesize(self, background: bool = True) -> None:
        """Synthesize a controller for f + [-gamma, gamma] (engine: ``simgap.synthesis``): a loaded
        set-method run (ellipsoid, box tube) with its own method and [synthesis] keys, else the grid."""
        if self.set_method() is not None:
            self.guarded(self._synthesize_set_method, background)
            return
        self.guarded(self._run_stage, "synthesize", background)

    def set_method(self) -> Optional[str]:
        """The loaded run's set method (``invariant_set``, ``box_tube``), or None (a grid or no run)."""
        from simgap.synthesis.set_synthesis import SET_METHODS

        from .results import run_method
        run = getattr(self, "run", None)
        m = run_method(run.summary) if run is not None and run.stages is None else None
        return m if m in SET_METHODS else None

    def _synthesize_set_method(self, background: bool = True) -> None:
        """Re-synthesize the loaded run's method (its [synthesis] keys, its certificate, x0 and the
        rollouts' horizon) on the job thread; the result replaces the method's set and statement."""
        from simgap.synthesis import set_synthesis
        from simgap.synthesis.statement import statement_of
        run, method = self.run, self.run_method
        syn = dict(run.summary.get("sections", {}).get("synthesis") or {})
        src = run.methods.get(method) or run.methods.get("stochastic")
        gap = None if method == "nominal" or src is None else src.certificate
        x0 = None if self.settings.x0 is None else np.asarray(self.settings.x0, float)
        horizon = (run.summary.get("sections", {}).get("rollout") or {}).get("horizon")

        def compute(ctx):
            ctx.begin("synthesize")
            res = set_synthesis.synthesize(self.experiment.system if self.experiment is not None else self.system,
                                           self.spec, gap, syn, x0=x0, horizon=horizon)
            ctx.check()
            target = run.nominal if method == "nominal" else run.methods[method]
            target.invariant_set = None if res.empty else res.controller
            target.statement = statement_of(set_synthesis.method_of(syn), target.invariant_set, res.stats)
            self.timings["synthesize"] = ctx.elapsed()
            if res.empty:
                self.notify("Nothing proved", res.stats.get("diagnosis") or "no set proved")
            self.invariant_drawn = None
            self._show_results()
            return res
        if background:
            self.start_job("synthesize", compute)
        else:
            compute(JobContext(name="synthesize"))

    def rollout(self, background: bool = True) -> None:
        """Roll the controller out in the simulator (engine: ``simgap.rollout``)."""
        self.guarded(self._run_stage, "rollout", background)

    def refine(self, background: bool = True) -> None:
        """Refine the nominal model from the data's residuals (engine: ``simgap.refine``)."""
        self.guarded(self._run_stage, "refine", background)

    def use_refined(self) -> None:
        """Switch the nominal model to the refined f' of the last refinement; the data are kept
        (the same empirical means, the gap now measured to f') and the simulator stays the same."""
        res = self.results.get("refine")
        data = self.results.get("collect")
        if res is None or data is None:
            raise SimgapError("refine first")
        base = engine.base_system(data.system)
        name = engine.register_refined(res.refined.with_steps(base.steps), base)
        ds = engine.rebase(data, engine.REFINED[name][0])
        self.panels["system"].system.options = list(engine.SYSTEMS)
        self.set_dataset(ds)
        self.set_status(f"nominal model: {name} (refined); data re-based, certify to see the new gap")

    def compare_refined(self) -> None:
        """Certify (and synthesize) with f and f' on the same data, on the job thread."""
        res, data = self.results.get("refine"), self.results.get("collect")
        if res is None or data is None:
            self.notify("Nothing to compare", "refine first")
            return
        s = self.settings
        spec = self.guarded(self.current_spec)

        def job(ctx):
            d = engine.compare_refined(data, res, s, spec)
            self.panels["refine"].comparison.content = engine.comparison_markdown(d)
            return d

        self.guarded(self.start_job, "compare", job)

    def cancel(self) -> None:
        if self.jobs.cancel():
            self.set_status(f"cancelling {self.jobs.current} ...")

    def current_spec(self):
        """The specification for synthesis/rollouts: the experiment's, else the system's default."""
        if self.spec is not None:
            box = self.spec.target if self.spec.target is not None else self.spec.safe
            if box.lo.size == self.system.n:
                return self.spec
        return engine.default_spec(self.system, self.arena if engine.base_system(self.system).name == "turtlebot" else None)

    # ----- job callbacks (worker thread) -------------------------------------------------
    def _job_progress(self, name: str, frac: float) -> None:
        """Progress of the stage running now (``name``: a certify job that must collect reports
        "collect" first) with its elapsed time and the time left: from the rate so far once 2 % is
        done, before that the engine's estimate (collection) or the stage's last run."""
        from simgap.cover import format_duration
        self.progress.visible = True
        self.progress.animated = True
        self.progress.value = float(np.clip(100.0 * frac, 0.0, 100.0))
        ctx = self.jobs.context
        el = ctx.elapsed() if ctx is not None else 0.0
        total = self._estimates.get(name) if name == "collect" else self.timings.get(name)
        # the estimate until a tenth is done (a pool's start-up would make the first rate far too
        # slow), then the rate so far
        if total is not None and (frac < 0.1 or el <= 0.5) and total > el:
            left = f"about {format_duration(total - el)} left (estimate)"
        elif frac >= 0.02 and el > 0.5:
            left = f"about {format_duration(el * (1.0 - frac) / frac)} left"
        else:
            left = "no estimate yet"
        job = f" (then {ctx.name})" if ctx is not None and ctx.name != name else ""
        self.set_status(f"**{name}**{job}: {100 * frac:.0f} %, {format_duration(el)} elapsed, {left}")
        self._update_buttons()

    def _job_finished(self, out) -> None:
        self.progress.visible = False
        self.progress.animated = False
        if out.name not in STAGES:  # a stage's own time was taken in _result_for
            self.timings[out.name] = out.seconds
        if out.ok:
            self.set_status(f"{out.name}: done in {out.seconds:.2f} s ({self.result_keys.get(out.name)})"
                            + self.stale_status())
        elif out.cancelled:
            if not out.superseded:
                self.notify("Cancelled", f"{out.name} was cancelled", color="yellow")
        else:
            self.notify(f"{out.name} failed", out.error or "unknown error")
        self._update_buttons(busy=False)  # still on the (ending) worker thread

    def _update_buttons(self, busy: Optional[bool] = None) -> None:
        if not hasattr(self, "panels"):
            return
        busy = self.jobs.busy if busy is None else busy
        self.cancel_button.disabled = not busy
        avail = {k: v[0] for k, v in engine.availability().items()}
        cached = {k: v is not None for k, v in self.results.items()}
        # a stage can run if the engine offers it and every upstream stage is cached or offered
        up = {"collect": (), "certify": ("collect",), "synthesize": ("collect", "certify"),
              "rollout": ("collect", "certify", "synthesize"), "refine": ("collect",)}
        state = {st: avail[st] and all(cached[u] or avail[u] for u in up[st]) for st in up}
        for stage, ok in state.items():
            for p in self.panels.values():
                b = getattr(p, "buttons", {}).get(stage)
                if b is not None:
                    b.disabled = busy or not ok

    # ----- scene ------------------------------------------------------------------------
    def refresh_system_layers(self) -> None:
        from .layers import scene
        scene.draw_system(self)

    def refresh_result_layers(self) -> None:
        from .layers import scene
        with self.lock:
            self._scene_version += 1
        scene.draw_results(self)
        self.panels["view"].show_legend()

    def set_layer_visible(self, layer: str, visible: bool) -> None:
        """Show or hide one layer (redraws it)."""
        from .layers import scene
        self.layers_visible[layer] = bool(visible)
        if any(lay.key == layer and lay.system for lay in scene.LAYERS):
            self.refresh_system_layers()
        else:
            self.refresh_result_layers()

    def set_plane(self, dims) -> tuple:
        """Show the map plane over two other states (a projection selector): the proved sets, the
        runs, the safe set and the axes are redrawn projected onto ``dims``. Only without a grid
        controller (a grid's winning map is over its first two states); returns the plane's dims."""
        from .layers import scene
        d = tuple(int(i) for i in dims)
        if len(d) != 2 or d[0] == d[1] or not all(0 <= i < self.system.n for i in d):
            raise SimgapError(f"the plane needs two different states of {', '.join(self.system.state_names)}")
        if self.results.get("synthesize") is not None and d != (0, 1):
            raise SimgapError("a grid controller's winning map is drawn over the first two states only")
        with self.lock:
            self.view["dims"] = d
        scene.draw_axes(self)
        scene.draw_map(self)
        self.refresh_result_layers()
        return scene.plane_dims(self)

    def set_flat_gamma(self, flat: bool) -> None:
        """Draw gamma as a surface even where it is nearly flat on the slice (default: only where it varies)."""
        with self.lock:
            self.view["flat_gamma"] = bool(flat)
        from .layers import scene
        scene.draw_gamma(self)
        self.panels["view"].show_legend()

    def set_view(self, dim=None, a=None, b=None, fixed_index=None, fixed_value=None) -> dict:
        """Change the gamma-surface slice and redraw it; returns what was drawn (see layers.scene.draw_gamma)."""
        from .layers import scene
        with self.lock:
            v = dict(self.view)
            if dim is not None:
                if not 0 <= int(dim) < self.system.n:
                    raise SimgapError(f"gamma dimension must be in 1..{self.system.n}, got {int(dim) + 1}")
                if int(dim) != v["dim"]:
                    v["zscale"] = None
                v["dim"] = int(dim)
            if a is not None:
                v["a"] = int(a)
            if b is not None:
                v["b"] = int(b)
            if v["a"] == v["b"]:
                raise SimgapError("the gamma surface needs two different variables")
            if fixed_index is not None:
                fixed = list(v["fixed"])
                fixed[int(fixed_index)] = float(fixed_value)
                v["fixed"] = fixed
            self.view = v
        drawn = scene.draw_gamma(self)
        view_panel = self.panels.get("view")
        if view_panel is not None:
            view_panel._mark_free()
            view_panel.show_legend()
            self.panels["certificate"].show_plots()
        if dim is not None or a is not None or b is not None:
            scene.fit_camera(self)
        return drawn

    def set_time(self, t=None, n_draw=None, rollout_index=None) -> None:
        """Rollout display: step ``t`` of the drawn rollouts (moves the bodies along rollout
        ``rollout_index``), how many rollouts are drawn (every rollout is counted regardless)."""
        from .layers import scene
        with self.lock:
            if n_draw is not None:
                self.view["n_draw"] = max(0, int(n_draw))
            if rollout_index is not None:
                self.view["rollout_index"] = max(0, int(rollout_index))
            if t is not None:
                self.view["t"] = int(t)
        if n_draw is not None:
            scene.draw_rollouts(self)
            self.panels["view"].show_legend()
        else:
            scene.show_time(self, self.view["t"])

    def wait(self, timeout: float = 120.0):
        """Block until the running job (if any) ends; returns its outcome (tests, scripts)."""
        return self.jobs.wait(timeout)
