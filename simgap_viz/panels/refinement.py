"""Refine tab: residuals of the data against the nominal model, the selected effects, the refined model."""

from __future__ import annotations

from .. import engine
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
        self.comparison = gui.add_markdown("")
        self.report = gui.add_markdown("")

    def show_report(self) -> None:
        res = self.app.results.get("refine")
        self.report.content = "" if res is None else engine.refine_markdown(res)
        self.compare_button.disabled = res is None
        self.use_button.disabled = res is None


def build(app) -> RefinementPanel:
    return RefinementPanel(app)
