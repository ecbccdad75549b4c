"""Certificate tab: delta per dimension or a target confidence, the basis, the concentration bound;
certify from the cached data and show the summary table (gamma per dimension, betas, confidences)."""

from __future__ import annotations

from .. import engine
from ..settings import CONCENTRATIONS, parse_vector
from . import plots
from .base import Panel, fmt_vec

MODES = ("target confidence", "per dimension")


class CertificatePanel(Panel):
    def __init__(self, app):
        super().__init__(app)
        gui = app.server.gui
        s = app.settings
        self.mode = gui.add_dropdown("delta from", options=MODES,
                                     initial_value=MODES[0] if s.delta1 is None else MODES[1])
        self.confidence = gui.add_number("Confidence", initial_value=s.confidence or 0.9, step=0.001,
                                         hint="target joint confidence 1 - sum_i (beta_1i + beta_2i)")
        self.delta1 = gui.add_text("delta_1", initial_value=fmt_vec(s.delta1) or "0.05",
                                   hint="per dimension, comma separated [state units]")
        self.delta2 = gui.add_text("delta_2", initial_value=fmt_vec(s.delta2) or "0.05")
        self.degree = gui.add_slider("Basis degree", min=0, max=4, step=1, initial_value=s.degree)
        self.terms = gui.add_text("Extra terms", initial_value=s.terms, hint="e.g. sin(x1), x2*u1")
        self.concentration = gui.add_dropdown("Concentration", options=CONCENTRATIONS,
                                              initial_value=s.concentration)
        self.value_range = gui.add_number("Range b", initial_value=s.value_range or 0.0, step=0.001,
                                          hint="known range of a simulator next state (bernstein); 0 = unknown")
        self.auto = gui.add_checkbox("Re-certify on change", initial_value=app.auto_certify)
        self.buttons["certify"] = gui.add_button("Certify")
        self.buttons["certify"].on_click(lambda _: app.certify())
        self.summary = gui.add_markdown("*no certificate yet*")
        self.slice_plot = plots.add(gui, "gamma slice")
        self.audit_plot = plots.add(gui, "audit margins")
        on = self.on
        on(self.mode, lambda v: self.switch_mode())
        on(self.confidence, lambda v: self.apply_deltas(), ready=lambda v: v is not None and 0.0 < float(v) < 1.0)
        on(self.delta1, lambda v: self.apply_deltas(), debounce=0.6)
        on(self.delta2, lambda v: self.apply_deltas(), debounce=0.6)
        on(self.degree, lambda v: app.update_settings(degree=int(v)))
        on(self.terms, lambda v: app.update_settings(terms=engine.check_terms(app.system, v)), debounce=0.6)
        on(self.concentration, lambda v: app.update_settings(concentration=v))
        on(self.value_range, lambda v: app.update_settings(value_range=float(v) if float(v) != 0.0 else None))
        self.auto.on_update(lambda _: setattr(app, "auto_certify", bool(self.auto.value)))
        self._show_mode()

    def switch_mode(self) -> None:
        """Switch how the deltas are given, pre-filled with what the current certificate used
        (its deltas, or its joint confidence), so a mode switch alone never changes gamma."""
        cert = self.app.results.get("certify")
        if cert is not None:
            if self.mode.value == MODES[1]:
                self.set_quiet(self.delta1, ", ".join(repr(float(d.delta1)) for d in cert.dims))
                self.set_quiet(self.delta2, ", ".join(repr(float(d.delta2)) for d in cert.dims))
            elif cert.joint_confidence is not None and 0.0 < cert.joint_confidence < 1.0:
                self.set_quiet(self.confidence, float(f"{cert.joint_confidence:.6g}"))
        self._show_mode()
        self.apply_deltas()

    def _show_mode(self) -> None:
        per_dim = self.mode.value == MODES[1]
        self.confidence.disabled = per_dim
        self.delta1.disabled = self.delta2.disabled = not per_dim

    def apply_deltas(self) -> None:
        n = self.app.system.n
        if self.mode.value == MODES[0]:
            self.app.update_settings(confidence=float(self.confidence.value), delta1=None, delta2=None)
        else:
            d1 = parse_vector(self.delta1.value, "delta_1", n)
            d2 = parse_vector(self.delta2.value, "delta_2", n)
            self.app.update_settings(delta1=d1, delta2=d2, confidence=None)

    def sync_from_settings(self) -> None:
        s = self.app.settings
        self.set_quiet(self.degree, s.degree)
        self.set_quiet(self.terms, s.terms)
        self.set_quiet(self.concentration, s.concentration)
        if s.delta1 is not None:
            self.set_quiet(self.mode, MODES[1])
            self.set_quiet(self.delta1, fmt_vec(s.delta1))
            self.set_quiet(self.delta2, fmt_vec(s.delta2))
        elif s.confidence is not None:
            self.set_quiet(self.mode, MODES[0])
            self.set_quiet(self.confidence, s.confidence)
        self._show_mode()

    def show_summary(self) -> None:
        cert = self.app.results.get("certify")
        self.summary.content = "*no certificate yet*" if cert is None else engine.certificate_markdown(cert)
        self.show_plots()
        if cert is not None and self.mode.value == MODES[0]:  # show the deltas the confidence gave
            self.set_quiet(self.delta1, fmt_vec([float(f"{d.delta1:.4g}") for d in cert.dims]))
            self.set_quiet(self.delta2, fmt_vec([float(f"{d.delta2:.4g}") for d in cert.dims]))


    def show_plots(self) -> None:
        plots.gamma_slice(self.app, self.slice_plot)
        plots.audit_margins(self.app, self.audit_plot)


def build(app) -> CertificatePanel:
    return CertificatePanel(app)
