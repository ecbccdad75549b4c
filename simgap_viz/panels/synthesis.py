"""Synthesis tab: the loaded run's own method. A grid: eta, steps held, gap on/off, the winning domain's
size. A set method (ellipsoid, box tube): its [synthesis] keys and what it proved, in its own words
(the method's :class:`~simgap.synthesis.statement.Statement`: for a tube T0, the terminal box H, the
margin, how K was chosen, the noise tube and p_cert); Synthesize re-runs that method."""

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
        self.method = gui.add_markdown("")
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
        app = self.app
        method = app.set_method() if hasattr(app, "set_method") else None
        for h in (self.eta, self.hold, self.use_gap):
            h.visible = method is None
        if method is not None:
            st = statement_markdown(app)
            self.method.content, self.stats.content = st
            self.method.visible = True
            self.buttons["synthesize"].label = "Synthesize again (" + method.replace("_", " ") + ")"
            return
        self.method.visible = False
        self.buttons["synthesize"].label = "Synthesize"
        res = app.results.get("synthesize")
        self.stats.content = "" if res is None else app.stale_note("synthesize") + engine.synthesis_markdown(res)


def statement_markdown(app) -> tuple:
    """(the method and its keys, what it proved) of the loaded set-method run, as markdown."""
    from ..results import run_method
    run, m = app.run, app.run_method
    syn = run.summary.get("sections", {}).get("synthesis") or {}
    keys = ", ".join(f"`{k} = {v}`" for k, v in syn.items() if k not in ("method",))
    r = run.nominal if m == "nominal" else run.methods.get(m)
    st = getattr(r, "statement", None)
    head = (f"**Method**: {st.name if st is not None else run_method(run.summary)} "
            f"(`[synthesis] method = \"{run_method(run.summary)}\"`, {m} "
            + ("model, no gap" if m == "nominal" else "certificate") + f")  \n**keys**: {keys or '-'}")
    if st is None:
        return head, ""
    rows = "\n".join(f"| {r_.label} | {r_.value} | {ABOUT_WORDS.get(r_.about, r_.about)} |" for r_ in st.rows)
    per = ("" if st.per_run is None else
           f"\n\n**p_cert = {st.per_run.p_cert:.4f}**: P({st.per_run.event}) >= p_cert; rests on {st.per_run.rests_on}")
    notes = "".join(f"\n\n*{n}*" for n in st.notes)
    return head, (f"**{st.headline}**\n\n| what | value | about |\n|---|---|---|\n{rows}{per}{notes}")


#: the statement rows' ``about`` in the tab's words
ABOUT_WORDS = {"proof": "proved (mean map)", "mean_map": "mean map, checked", "single_runs": "single runs, counted",
               "per_run": "proved (single runs)"}


def build(app) -> SynthesisPanel:
    return SynthesisPanel(app)
