"""View tab: which layers are visible, and the gamma-surface slice (dimension, two variables,
the others fixed by sliders)."""

from __future__ import annotations

import numpy as np

from ..layers import scene
from ..layers.geometry import colorbar, variable_names, variable_ranges
from .base import Panel


class ViewPanel(Panel):
    def __init__(self, app):
        super().__init__(app)
        gui = app.server.gui
        self.checks = {}
        with gui.add_folder("Layers"):
            for lay in scene.LAYERS:
                if lay.label is None:
                    continue
                h = gui.add_checkbox(lay.label, initial_value=app.layers_visible[lay.key])
                h.on_update(lambda _e, key=lay.key, h=h: app.set_layer_visible(key, bool(h.value)))
                self.checks[lay.key] = h
            self.flat = gui.add_checkbox("Flat gamma too", initial_value=bool(app.view.get("flat_gamma")),
                                         hint=f"draw gamma as a surface even where it varies by less than "
                                              f"{100 * scene.GAMMA_VISIBLE:.0f} % on the slice")
            self.flat.on_update(lambda _e: app.set_flat_gamma(bool(self.flat.value)))
        with gui.add_folder("Plane"):
            names = list(app.system.state_names)
            self.plane = [gui.add_dropdown(f"plane {ax}", options=names, initial_value=names[min(i, len(names) - 1)],
                                           hint="the two states the map plane shows (the proved sets, runs and "
                                                "safe set projected onto them); a grid run: its first two")
                          for i, ax in enumerate(("x", "y"))]
            for h in self.plane:
                h.on_update(lambda _e: self._plane_changed())
        with gui.add_folder("Legend"):
            self.colorbar = gui.add_image(colorbar(256, 12), format="png")
            self.legend = gui.add_markdown("*no certificate yet*")
        with gui.add_folder("Rollouts"):
            self.n_draw = gui.add_slider("Drawn", min=0, max=1000, step=10, initial_value=app.view["n_draw"],
                                         hint="rollouts drawn (failures first); all are counted")
            self.time = gui.add_slider("Time step", min=0, max=100, step=1, initial_value=0,
                                       hint="marks the drawn rollouts' states and poses the simulator bodies")
            self.rollout_index = gui.add_number("Bodies follow rollout", initial_value=0, min=0, step=1)
            self.n_draw.on_update(lambda _e: None if getattr(app, "_syncing", False)
                                  else app.set_time(n_draw=int(self.n_draw.value)))
            self.time.on_update(lambda _e: app.set_time(t=int(self.time.value)))
            self.rollout_index.on_update(lambda _e: app.guarded(app.set_time, rollout_index=int(self.rollout_index.value)))
        self.folder = gui.add_folder("Gamma surface")
        self.sliders = []
        self.handles = []
        self.rebuild_sliders()

    def show_legend(self) -> None:
        """What is drawn, and only that: the winning map's colors (the winning-cell count as the CLI
        table gives it), the rollouts, the bold lines, gamma (a surface with its scale, or its value
        when it is too flat to draw) and the data gaps, as a table that fits the panel."""
        app = self.app
        lg = app.legend
        rows = []
        wc = app.winning_counts
        if wc is not None:
            reach = wc.get("kind") == "reach_avoid"
            shade = ("dark near the target, light " + (f"{wc['max_steps']} steps away" if wc.get("max_steps") else "far")
                     if reach else "paler: a smaller share of the other dimensions' cells" if wc.get("reduced_dims")
                     else "")
            cols = f"; {wc['reduced_dims'] + 2}-D grid seen from above" if wc.get("reduced_dims") else ""
            parts = [f"green: **{wc['winning_cells']:,} winning cells**" + (f" ({shade})" if shade else "") + cols]
            if wc.get("losing"):
                parts.append("beige: safe but losing")
            if wc.get("unsafe_inner"):
                parts.append("red-brown: unsafe (obstacle" + ("" if reach else " or outside the safe set") + ")")
            elif wc.get("unsafe"):
                parts.append("red-brown edge: cells that straddle X's border")
            if reach and wc.get("target"):
                parts.append("blue: target")
            rows.append("| winning map | " + "; ".join(parts) + " |")
        if app.layers_visible.get("map"):
            try:
                spec = app.current_spec()
            except Exception:  # no specification for this system: no outlines drawn (scene.draw_map)
                spec = None
            if spec is not None:
                outl = ["blue: safe set"] + (["green: target"] if getattr(spec, "target", None) is not None else []) \
                    + (["red: obstacles (grown by the robot)"] if getattr(spec, "obstacles", None) else [])
                rows.append("| outlines | " + ", ".join(outl) + " |")
        sets = getattr(app, "invariant_drawn", None) or []
        if sets:
            from ..results import unproved_sets
            names = [app.system.state_names[d] for d in scene.plane_dims(app)]
            parts = [f"{_color_word(c)}: {label}" + ("" if m == app.run_method else f" ({m})") for m, _r, label, c, _hw in sets]
            fails = [m + ("" if s_ is None else f" (gap margin s = {s_:.2g})") for m, s_ in unproved_sets(app.run)]
            rows.append(f"| proved sets | projection onto ({', '.join(names)}); " + "; ".join(parts)
                        + (f"; not proved: {', '.join(fails)}" if fails else "") + " |")
        if getattr(app.run, "per_run", None) is not None and app.perrun_view["map"]:
            rows.append("| p_cert map | drawn over the winning map (Per run tab: colors, toggle) |")
        rd = app.rollout_drawn
        res = app.results.get("rollout")
        if rd is not None and res is not None:
            fail = f"; red: failures, {rd['failed']} of {rd['total']}" if rd["failed"] else f"; no failure of {rd['total']}"
            rows.append(f"| rollouts | dark blue, translucent: {rd['drawn']} of {rd['total']} drawn (darker where "
                        f"more pass){fail} |")
            bold = ["yellow: mean", "black: nominal model"]
            if getattr(res, "mean_map_trajectory", None) is not None:
                bold.append("magenta: mean map (the guarantee)")
            rows.append("| bold | " + ", ".join(bold) + " |")
            T = int(res.trajectories.shape[1]) - 1
            self.time.max = max(T, 1)
            self.n_draw.max = max(int(rd["total"]), 1)
            self.set_quiet(self.n_draw, min(int(app.view["n_draw"]), int(rd["total"])))
            self.rollout_index.max = int(rd["total"]) - 1
        self.colorbar.visible = bool(lg is not None and lg.get("shown"))
        if lg is not None:
            d, u = lg["dim"], (f" {lg['unit']}" if lg.get("unit") else "")
            if "range" in lg:
                lo, hi = lg["range"]
                var = "constant" if lg.get("constant") else f"varies by {100 * (hi - lo) / hi:.2g} %"
                if lg.get("shown"):
                    rows.append(f"| gamma_{d} surface | {lo:.4g} .. {hi:.4g}{u} on this slice ({var}); height and "
                                f"color: 0 (dark blue) .. {lg['top']:.4g}{u} (yellow), one scale for the session |")
                else:
                    val = f"{hi:.4g}{u}" if lg.get("constant") else f"{lo:.4g} .. {hi:.4g}{u}"
                    why = "layer hidden" if not app.layers_visible.get("gamma") else \
                        f"under {100 * scene.GAMMA_VISIBLE:.0f} %: not drawn; *Flat gamma too* draws it"
                    rows.append(f"| gamma_{d} | **{val}** on this slice ({var}; {why}) |")
            if "margin_scale" in lg:
                rows.append(f"| data gaps ({lg['points']}) | margin gamma - gap: orange 0 .. grey-blue "
                            f">= {lg['margin_scale']:.3g}" + (f"; red < 0: {lg['uncovered']}" if lg["uncovered"] else "")
                            + " |")
            elif "points" in lg:
                rows.append(f"| data gaps ({lg['points']}) | grey: no certificate yet |")
        self.legend.content = ("| layer | shows |\n|---|---|\n" + "\n".join(rows)) if rows else "*nothing drawn yet*"

    def _plane_changed(self) -> None:
        app = self.app
        names = list(app.system.state_names)
        if getattr(app, "_syncing", False) or any(p.value not in names for p in self.plane):
            return
        app.guarded(app.set_plane, [names.index(p.value) for p in self.plane])

    def rebuild_sliders(self) -> None:
        """(Re)create the slice controls for the current system's variables."""
        app = self.app
        for h in self.handles:
            h.remove()
        self.handles, self.sliders = [], []
        sysm = app.system
        states, d = list(sysm.state_names), scene.plane_dims(app)
        prev, app._syncing = getattr(app, "_syncing", False), True
        try:
            for h, i in zip(self.plane, d if sysm.n >= 2 else (0, 0)):
                h.options = states
                h.value = states[i]
                h.disabled = sysm.n < 3
        finally:
            app._syncing = prev
        names = variable_names(sysm)
        rng = variable_ranges(sysm)
        if app.view.get("fixed") is None:
            app.view["fixed"] = list(rng.mean(axis=1))
        gui = app.server.gui
        with self.folder:
            self.dim = gui.add_dropdown("gamma of", options=list(sysm.state_names),
                                        initial_value=sysm.state_names[app.view["dim"]])
            self.a = gui.add_dropdown("over", options=names, initial_value=names[app.view["a"]])
            self.b = gui.add_dropdown("and", options=names, initial_value=names[app.view["b"]])
            self.handles += [self.dim, self.a, self.b]
            for j, name in enumerate(names):
                lo, hi = float(rng[j, 0]), float(rng[j, 1])
                s = gui.add_slider(f"{name} =", min=lo, max=hi, step=(hi - lo) / 100 if hi > lo else 1.0,
                                   initial_value=float(np.clip(app.view["fixed"][j], lo, hi)))
                s.on_update(lambda _e, j=j, s=s: app.set_view(fixed_index=j, fixed_value=float(s.value)))
                self.sliders.append(s)
                self.handles.append(s)
        self.dim.on_update(lambda _e: app.set_view(dim=list(sysm.state_names).index(self.dim.value)))
        self.a.on_update(lambda _e: app.guarded(app.set_view, a=names.index(self.a.value)))
        self.b.on_update(lambda _e: app.guarded(app.set_view, b=names.index(self.b.value)))
        self._mark_free()

    def _mark_free(self) -> None:
        v = self.app.view
        for j, s in enumerate(self.sliders):
            s.disabled = j in (v["a"], v["b"])


#: the words for the colors the proved-sets layer draws with (scene.ROLE_STYLE, scene.SET_COLORS)
COLOR_WORDS = {(230, 110, 0): "orange", (150, 150, 150): "grey", (120, 40, 0): "dark brown", (20, 150, 60): "green",
               (31, 119, 180): "blue", (255, 127, 14): "orange", (44, 160, 44): "green"}


def _color_word(rgb) -> str:
    return COLOR_WORDS.get(tuple(int(v) for v in rgb), "line")


def build(app) -> ViewPanel:
    return ViewPanel(app)
