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
        self.report = gui.add_markdown("")

    def show_report(self) -> None:
        res = self.app.results.get("refine")
        self.report.content = "" if res is None else engine.refine_markdown(res)


def build(app) -> RefinementPanel:
    return RefinementPanel(app)
