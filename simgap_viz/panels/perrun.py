"""Per run tab: guarantees about single runs from a ``simgap run`` with ``[perrun]``.

Shows what the engine wrote (:mod:`simgap_viz.results_perrun`): the p_cert map and the p_emp
markers in the scene (toggles, which controller's states), their color scale, a table per
controller and per initial state, and a plot of p_emp (with its 95 % Clopper-Pearson interval)
against p_cert per initial state, with the diagonal p_emp = p_cert: a sound bound puts every
point on or above it (within the sampling error), a tight one close to it.
"""

from __future__ import annotations

import numpy as np

from simgap.perrun.stage import containment_line, sound

from ..layers import perrun as layer
from . import plots
from .base import Panel

NO_RESULTS = ("*No per-run results.* Open a `simgap run` folder of an experiment with a `[perrun]` section "
              "(e.g. `simgap run pendulum --profile perrun`, then `simgap gui results/pendulum-perrun`): "
              "its p_cert map, p_emp markers and this tab's table and plot appear here.")
NAMES = {"perrun": "per-run (interval MDP)", "run_baseline": "union-bound baseline",
         "stochastic": "stochastic gap (paper)", "deterministic": "deterministic gap"}
COLORS = {"perrun": "#2850c8", "run_baseline": "#e07020"}
OTHER_COLORS = ("#a040c0", "#30a0a0")
CI_COLOR, DIAGONAL_COLOR = "#505050", "#909090"
BAR_POINTS = 24  # points per CI bar (uPlot draws a line series through NaN, so bars are dense points)


def label(name: str) -> str:
    """How a controller of the summary is named in the tab."""
    return NAMES.get(name, name)


def plot_data(per_run) -> dict:
    """What the p_emp-against-p_cert plot shows (sent to uPlot as it is).

    Rows sorted by x = p_cert: one row per (controller, state) with a p_cert (its p_emp in that
    controller's series), ``BAR_POINTS`` rows per state for its 95 % interval (one "95 % CI"
    series, points from lo to hi at the same x), and the diagonal's two ends. Controllers that
    state no per-run probability (p_cert None) are left out (their p_emp is in the table).
    Returns dict(data tuple of arrays, series tuple, names [controllers plotted], points int).
    """
    names = [n for n, c in per_run.controllers.items() if c.certified]
    xs, cols, ys = [np.array([0.0, 1.0])], [np.full(2, -2)], [np.array([0.0, 1.0])]
    for k, n in enumerate(names):
        c = per_run.controllers[n]
        ok = np.isfinite(c.p_cert)
        x = c.p_cert[ok]
        xs += [x, np.repeat(x, BAR_POINTS)]
        cols += [np.full(x.size, k), np.full(x.size * BAR_POINTS, -1)]
        t = np.linspace(0.0, 1.0, BAR_POINTS)
        ys += [c.p_emp[ok], (c.ci95[ok, :1] + t * (c.ci95[ok, 1:] - c.ci95[ok, :1])).ravel()]
    x, col, y = np.concatenate(xs), np.concatenate(cols), np.concatenate(ys)
    order = np.argsort(x, kind="stable")
    x, col, y = x[order], col[order], y[order]
    series = [{"label": "p_cert"}]
    data = [x]
    for k, n in enumerate(names):
        color = COLORS.get(n, OTHER_COLORS[k % len(OTHER_COLORS)])
        data.append(np.where(col == k, y, np.nan))
        series.append({"label": label(n), "stroke": color, "width": 0,
                       "points": {"show": True, "size": 9, "fill": color, "stroke": color}})
    data.append(np.where(col == -1, y, np.nan))
    series.append({"label": "95 % CI", "stroke": CI_COLOR, "width": 0,
                   "points": {"show": True, "size": 2.5, "fill": CI_COLOR, "stroke": CI_COLOR}})
    data.append(np.where(col == -2, y, np.nan))
    series.append({"label": "p_emp = p_cert", "stroke": DIAGONAL_COLOR, "width": 1.5, "dash": [6, 4],
                   "spanGaps": True, "points": {"show": False}})
    return {"data": tuple(data), "series": tuple(series), "names": names, "points": int(np.sum(col >= 0))}


def overview_markdown(per_run) -> str:
    """Per controller: p_cert and p_emp at x0, and how many states pass p_emp >= p_cert - 3 SE."""
    rows = ["| controller | p_cert(x0) | p_emp(x0) [95 % CI] | sound |", "|---|---|---|---|"]
    for n, c in per_run.controllers.items():
        ok = sum(sound(None if np.isnan(pc) else float(pc), float(pe), float(se), c.n_rollouts)
                 for pc, pe, se in zip(c.p_cert, c.p_emp, c.se))
        pc = "-" if np.isnan(c.p_cert[0]) else f"{c.p_cert[0]:.4f}"
        rows.append(f"| {label(n)} | {pc} | {c.p_emp[0]:.4f} [{c.ci95[0, 0]:.4f}, {c.ci95[0, 1]:.4f}] | "
                    f"{ok} / {c.p_emp.size} |")
    return "\n".join(rows)


def states_markdown(states) -> str:
    """One controller's validated initial states (row numbers = the markers' labels)."""
    rows = ["| # | x0 | p_cert | p_emp [95 % CI] |", "|---|---|---|---|"]
    for i in range(states.p_emp.size):
        x0 = ", ".join(f"{v:.4g}" for v in states.x0[i])
        pc = "-" if np.isnan(states.p_cert[i]) else f"{states.p_cert[i]:.4f}"
        rows.append(f"| {i}{' (x0)' if i == 0 else ''} | {x0} | {pc} | {states.p_emp[i]:.4f} "
                    f"[{states.ci95[i, 0]:.4f}, {states.ci95[i, 1]:.4f}] |")
    return "\n".join(rows)


class PerRunPanel(Panel):
    def __init__(self, app):
        super().__init__(app)
        gui = app.server.gui
        v = app.perrun_view
        self._names = {}  # dropdown label -> controller name in the summary
        self.note = gui.add_markdown(NO_RESULTS)
        self.show_map = gui.add_checkbox("p_cert map", initial_value=v["map"],
                                         hint="certified success probability per cell of the interval MDP")
        self.show_markers = gui.add_checkbox("p_emp markers", initial_value=v["markers"],
                                             hint="the validated initial states, colored by their empirical rate")
        self.controller = gui.add_dropdown("Markers of", options=(label(v["controller"]),),
                                           initial_value=label(v["controller"]),
                                           hint="whose validated initial states the markers and the table show")
        self.colorbar = gui.add_image(layer.pcolorbar(256, 12), format="png")
        self.legend = gui.add_markdown("")
        self.plot = plots.add(gui, "p_emp against p_cert")
        self.overview = gui.add_markdown("")
        self.states = gui.add_markdown("")
        self.on(self.show_map, lambda val: self.set_view(map=bool(val)))
        self.on(self.show_markers, lambda val: self.set_view(markers=bool(val)))
        self.on(self.controller, lambda val: self.set_view(controller=self._names.get(val, val)))
        self.show()

    def set_view(self, **changes) -> None:
        """Change what the layer shows (``map``, ``markers``, ``controller``) and redraw it."""
        with self.app.lock:
            self.app.perrun_view.update(changes)
        self.show()
        self.app.panels["view"].show_legend()

    def show(self) -> dict:
        """Draw the layer and fill the tab from the loaded run's per-run results; returns what was drawn."""
        app = self.app
        pr = getattr(app.run, "per_run", None) if app.run is not None else None
        have = pr is not None
        for h in (self.show_map, self.show_markers, self.controller, self.colorbar, self.legend, self.overview,
                  self.states):
            h.visible = have
        self.note.visible = not have
        if not have:
            self.plot.visible = False
            stated = method_statements(app.run)
            self.note.content = stated or NO_RESULTS
            return layer.draw(app)
        names = tuple(pr.controllers)
        with app.lock:
            if app.perrun_view["controller"] not in names:
                app.perrun_view["controller"] = "perrun" if "perrun" in names else names[0]
        self._names = {label(n): n for n in names}
        self.controller.options = tuple(self._names)
        self.set_quiet(self.controller, label(app.perrun_view["controller"]))
        drawn = layer.draw(app)
        st = pr.controllers[app.perrun_view["controller"]]
        m = drawn["map"]
        red = (f", the largest over {m['reduced_dims']} further state dimension(s)" if m and m["reduced_dims"] else "")
        self.legend.content = (
            f"**{pr.controller.statement().headline}**  \n"  # the interval MDP's statement, in its words
            f"0 (red) .. 0.5 (yellow) .. 1 (green), for both layers.  \n**map**: p_cert of the per-run controller, "
            f"a certified lower bound on P(one run satisfies the spec for {pr.horizon} periods) from every state of "
            f"the cell{red}; 0 where nothing is certified (also every cell outside the safe set). "
            f"{conditional_note(pr.controller.meta)}  \n"
            f"**markers** (ringed, numbered as the table): p_emp of {label(st.name)} from {st.n_rollouts} "
            f"rollouts per state.")
        pd = plot_data(pr)
        if pd["points"]:
            self.plot.data = pd["data"]
            self.plot.series = pd["series"]
            self.plot.axes = ({"label": "p_cert (certified)", "size": 36}, {"label": "p_emp (95 % CI)", "size": 48})
            self.plot.scales = {"x": {"time": False, "range": (-0.02, 1.02)}, "y": {"range": (-0.02, 1.02)}}
            self.plot.title = (f"p_emp against p_cert at {pd['points']} initial states ({pr.n_rollouts} rollouts "
                               f"each): on or above the diagonal = sound")
        self.plot.visible = bool(pd["points"])
        self.overview.content = overview_markdown(pr)
        self.states.content = f"**{label(st.name)}**, per initial state:\n\n" + states_markdown(st)
        return drawn


def method_statements(run) -> str:
    """The per-run statement of every method of ``run`` that states one (a box tube's noise tube; the
    method's own :class:`~simgap.synthesis.statement.PerRunStatement`) beside the p_emp of the run's
    rollouts from x0, as a table; "" when no method states one."""
    if run is None:
        return ""
    entries = dict(run.methods)
    if getattr(run, "nominal", None) is not None:
        entries["nominal"] = run.nominal
    rows, notes = [], []
    for m, r in entries.items():
        st = getattr(r, "statement", None)
        if st is None or st.per_run is None:
            continue
        pr = st.per_run
        e = ((run.summary or {}).get("methods", {}).get(m) or {}).get("per_run_empirical") or {}
        emp = (f"{e['p_emp']:.4f} [{e['ci95'][0]:.4f}, {e['ci95'][1]:.4f}] ({e['successes']} / {e['n_rollouts']})"
               if "p_emp" in e else "-")
        inside = f"{e['in_noise_tube']} / {e['n_rollouts']}" if "in_noise_tube" in e else "-"
        ok = "-" if "p_emp" not in e else ("yes" if sound(pr.p_cert, e["p_emp"], e["se"], e["n_rollouts"]) else "**NO**")
        rows.append(f"| {m} | **{pr.p_cert:.4f}** | {emp} | {inside} | {ok} |")
        notes.append(f"**{m}** ({st.name}): P({pr.event}) >= p_cert; rests on {pr.rests_on}.")
    if not rows:
        return ""
    return ("**Per-run statements of the methods** (proved about single runs, beside the run's rollouts from x0; "
            "p_emp: successes of the spec, 95 % Clopper-Pearson interval)\n\n"
            "| method | p_cert | p_emp [95 % CI] | runs in p_cert's event | p_emp >= p_cert - 3 SE |\n|---|---|---|---|---|\n"
            + "\n".join(rows) + "\n\n" + "  \n".join(notes))


def conditional_note(meta: dict) -> str:
    """What p_cert rests on (from the controller file's digest-checked meta): the estimated Lipschitz
    constants and the Markov assumption, and the containment check's outcome."""
    return ("*Conditional on the estimated Lipschitz constants and the Markov assumption* (not proven; "
            f"{containment_line(meta.get('containment'))}).")


def build(app) -> PerRunPanel:
    return PerRunPanel(app)
