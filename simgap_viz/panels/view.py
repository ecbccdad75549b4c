"""View tab: which layers are visible, and the gamma-surface slice (dimension, two variables,
the others fixed by sliders)."""

from __future__ import annotations

import numpy as np

from ..layers.geometry import variable_names, variable_ranges
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
        self.folder = gui.add_folder("Gamma surface")
        self.sliders = []
        self.handles = []
        self.rebuild_sliders()

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
