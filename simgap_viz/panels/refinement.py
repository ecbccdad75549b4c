"""Refine tab: residuals of the data against the nominal model, the selected effects, the refined model."""

from __future__ import annotations

from .. import engine
from . import plots
from .base import Panel


class RefinementPanel(Panel):
    def __init__(self, app):
        super().__init__(app)
        gui = app.server.gui
        self.buttons["refine"] = gui.add_button("Refine")
        self.buttons["refine"].on_click(lambda _: app.refine())
        self.note = gui.add_markdown(engine.unavailable_note("refine"))
        self.compare_button = gui.add_button("Compare f and f'", disabled=True,
                                             hint="certify (and synthesize) with both models on the same data")
        self.compare_button.on_click(lambda _: app.compare_refined())
        self.use_button = gui.add_button("Use refined model", disabled=True,
                                         hint="make f' the nominal model: certify, synthesize and roll out with it")
        self.use_button.on_click(lambda _: app.guarded(app.use_refined))
        names = list(app.system.state_names)
        self.res_state = gui.add_dropdown("Residual of", options=names, initial_value=names[-1])
        self.res_var = gui.add_dropdown("against", options=names + list(app.system.input_names),
                                        initial_value=names[-1])
        self.res_state.on_update(lambda _: app.guarded(self.show_residuals))
        self.res_var.on_update(lambda _: app.guarded(self.show_residuals))
        self.plot = plots.add(gui, "residuals")
        self.comparison = gui.add_markdown("")
        self.report = gui.add_markdown("")

    def show_residuals(self) -> int:
        """Redraw the residual layer for the chosen state and variable."""
        from ..layers import scene
        s = self.app.system
        names = list(s.state_names)
        if self.res_state.value not in names:  # the system changed: new options
            self.res_state.options = names
            self.res_var.options = names + list(s.input_names)
            self.res_state.value, self.res_var.value = names[-1], names[-1]
        self.app.view["res_state"] = names.index(self.res_state.value)
        self.app.view["res_var"] = self.res_var.value
        plots.residuals(self.app, self.plot)
        return scene.draw_residuals(self.app)

    def show_report(self) -> None:
        res = self.app.results.get("refine")
        self.report.content = "" if res is None else engine.refine_markdown(res)
        plots.residuals(self.app, self.plot)
        self.compare_button.disabled = res is None
        self.use_button.disabled = res is None


def build(app) -> RefinementPanel:
    return RefinementPanel(app)
