"""View tab: which layers are visible, and the gamma-surface slice (dimension, two variables,
the others fixed by sliders)."""

from __future__ import annotations

import numpy as np

from ..layers.geometry import colorbar, variable_names, variable_ranges
from .base import Panel

LAYERS = (("gamma", "Gamma surface"), ("data", "Data gaps"), ("map", "Map / spec"),
          ("winning", "Winning domain"), ("rollouts", "Rollouts"), ("bodies", "Simulator bodies"))


class ViewPanel(Panel):
    def __init__(self, app):
        super().__init__(app)
        gui = app.server.gui
        self.checks = {}
        with gui.add_folder("Layers"):
            for key, label in LAYERS:
                h = gui.add_checkbox(label, initial_value=app.layers_visible[key])
                h.on_update(lambda _e, key=key, h=h: app.set_layer_visible(key, bool(h.value)))
                self.checks[key] = h
        with gui.add_folder("Legend"):
            self.colorbar = gui.add_image(colorbar(256, 12), format="png")
            self.legend = gui.add_markdown("*no certificate yet*")
        with gui.add_folder("Rollouts"):
            self.n_draw = gui.add_slider("Drawn", min=0, max=1000, step=10, initial_value=app.view["n_draw"],
                                         hint="rollouts drawn (failures first); all are counted")
            self.time = gui.add_slider("Time step", min=0, max=100, step=1, initial_value=0,
                                       hint="marks the drawn rollouts' states and poses the simulator bodies")
            self.rollout_index = gui.add_number("Bodies follow rollout", initial_value=0, min=0, step=1)
            self.n_draw.on_update(lambda _e: app.set_time(n_draw=int(self.n_draw.value)))
            self.time.on_update(lambda _e: app.set_time(t=int(self.time.value)))
            self.rollout_index.on_update(lambda _e: app.guarded(app.set_time, rollout_index=int(self.rollout_index.value)))
        self.folder = gui.add_folder("Gamma surface")
        self.sliders = []
        self.handles = []
        self.rebuild_sliders()

    def show_legend(self) -> None:
        """The color map's range, the height scale, the data-gap colors, the winning-map colors and
        the rollout counts, as a table that fits the panel."""
        app = self.app
        lg = app.legend
        rows = []
        if lg is not None:
            d, u = lg["dim"], (f" {lg['unit']}" if lg.get("unit") else "")
            rows.append(f"| color and height | gamma_{d} = 0 (dark blue, 0) .. {lg['top']:.4g}{u} (yellow, 1): "
                        "one scale for the session, widened only when a larger gamma comes |")
            if "range" in lg:
                lo, hi = lg["range"]
                rows.append(f"| gamma_{d} on this slice | **constant: {hi:.4g}{u}** (a flat plane, drawn translucent) |"
                            if lg.get("constant") else
                            f"| gamma_{d} on this slice | {lo:.4g} .. {hi:.4g}{u} (varies by "
                            f"{100 * (hi - lo) / hi:.2g} % of its largest value) |")
            if "margin_scale" in lg:
                rows.append(f"| data gaps ({lg['points']}) | margin gamma - gap: orange 0 .. grey-blue "
                            f">= {lg['margin_scale']:.3g}; red < 0: {lg['uncovered']} |")
            elif "points" in lg:
                rows.append(f"| data gaps ({lg['points']}) | grey: no certificate yet |")
        wc = app.winning_counts
        if wc is not None:
            shade = (f" (dark = near the target .. light = {wc['max_steps']} steps to go)" if wc.get("max_steps")
                     else " (shade: share of winning cells over the other dimensions)" if wc.get("reduced_dims")
                     else "")
            rows.append(f"| winning map | green {wc['winning']} winning{shade}, beige {wc['losing']} safe but "
                        f"losing, red {wc['unsafe']} unsafe, blue target |")
        if getattr(app.run, "per_run", None) is not None and app.perrun_view["map"]:
            rows.append("| p_cert map | drawn over the winning map (Per run tab: colors, toggle) |")
        rd = app.rollout_drawn
        res = app.results.get("rollout")
        if rd is not None and res is not None:
            rows.append(f"| rollouts | {rd['drawn']} of {rd['total']} drawn; failures (red) {rd['failed']} of "
                        f"{rd['total']}, {rd['failed_drawn']} drawn |")
            rows.append("| bold | yellow: mean trajectory, black: nominal model"
                        + (", magenta: mean map" if getattr(res, "mean_map_trajectory", None) is not None else "")
                        + " |")
            T = int(res.trajectories.shape[1]) - 1
            self.time.max = max(T, 1)
            self.n_draw.max = max(int(rd["total"]), 1)
            self.rollout_index.max = int(rd["total"]) - 1
        self.legend.content = ("| layer | shows |\n|---|---|\n" + "\n".join(rows)) if rows else "*nothing drawn yet*"

    def rebuild_sliders(self) -> None:
        """(Re)create the slice controls for the current system's variables."""
        app = self.app
        for h in self.handles:
            h.remove()
        self.handles, self.sliders = [], []
        sysm = app.system
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


def build(app) -> ViewPanel:
    return ViewPanel(app)
