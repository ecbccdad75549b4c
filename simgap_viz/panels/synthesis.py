"""Synthesis tab: grid eta, steps held, gap on/off; synthesize and show the winning domain's size."""

from __future__ import annotations

from .. import engine
from ..settings import parse_vector
from .base import Panel, fmt_vec


class SynthesisPanel(Panel):
    def __init__(self, app):
        super().__init__(app)
        gui = app.server.gui
        s = app.settings
        self.eta = gui.add_text("Grid eta", initial_value=fmt_vec(s.eta),
                                hint="cell widths per state dimension [state units]")
        self.hold = gui.add_number("Hold steps", initial_value=s.hold, step=1,
                                   hint="sampling periods an input is held in the abstraction")
        self.use_gap = gui.add_checkbox("Use gamma", initial_value=s.use_gap,
                                        hint="synthesize on f + [-gamma, gamma]; off: nominal f only")
        self.buttons["synthesize"] = gui.add_button("Synthesize")
        self.buttons["synthesize"].on_click(lambda _: app.synthesize())
        self.note = gui.add_markdown(engine.unavailable_note("synthesize"))
        self.stats = gui.add_markdown("")
        self.on(self.eta, lambda v: app.update_settings(eta=parse_vector(v, "grid eta", app.system.n)), debounce=0.6)
        self.on(self.hold, lambda v: app.update_settings(hold=int(v) if float(v) == int(v) else float(v)))
        self.on(self.use_gap, lambda v: app.update_settings(use_gap=bool(v)))

    def sync_from_settings(self) -> None:
        s = self.app.settings
        self.set_quiet(self.eta, fmt_vec(s.eta))
        self.set_quiet(self.hold, s.hold)
        self.set_quiet(self.use_gap, s.use_gap)

    def show_stats(self) -> None:
        res = self.app.results.get("synthesize")
        self.stats.content = "" if res is None else self.app.stale_note("synthesize") + engine.synthesis_markdown(res)


def build(app) -> SynthesisPanel:
    return SynthesisPanel(app)
