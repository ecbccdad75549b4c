"""What a synthesis method proved, in its own words: one small typed interface.

Every method (the grid's winning domain, the invariant ellipsoid E, the box tube from x0, the
per-run interval MDP) returns a :class:`Statement` from its controller's ``statement(entry)``
(``entry``: the method's record in ``summary.json`` with its rollouts, optional), or
:func:`not_proved` when nothing was proved. The CLI table, ``summary.json["methods"][m]["statement"]``,
the GUI, the recording and the figures read only this, so no method is ever described in another's
words and a new method needs no edit in them: it returns its own name, rows and sets.

Each :class:`Row` says which statement its number is (``about``):

* ``"proof"``       -- proved on the model about the MEAN MAP m+ = E fhat(m, u(m)) (for the nominal
  model: about f only), at the certificate's confidence ``confidence`` ("all rows": the simultaneous
  one the proof rests on; None: no probability, e.g. a deterministic or no gap);
* ``"mean_map"``    -- the mean map run in the simulator (one sequence, checked);
* ``"single_runs"`` -- single runs of the simulator, counted (not proved);
* ``"per_run"``     -- proved about single runs (a p_cert), see :class:`PerRunStatement`.

Each :class:`DrawnSet` is a set to draw over time: ``kind = "boxes"`` (centres and half-widths per
period, the last row holding from ``periods[-1]`` on), ``"ellipsoid"`` ({x : (x - c)^T P (x - c) <= 1})
or ``"cells"`` (a grid's winning domain, drawn from the controller's own grid).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np

#: how each method names itself when it proved nothing (the controllers name themselves otherwise)
METHOD_NAMES = {"grid": "grid abstraction (winning domain)", "invariant_set": "invariant ellipsoid E",
                "box_tube": "box tube from x0 (reach and stay)", "perrun": "per-run interval MDP"}
ABOUT = ("proof", "mean_map", "single_runs", "per_run")


@dataclass(frozen=True)
class Row:
    """One number a method states: ``label`` in the method's words, ``value`` as text, ``about`` one of
    :data:`ABOUT`, ``confidence`` "all rows" / "pointwise" / None (module docstring)."""

    label: str
    value: str
    about: str = "proof"
    confidence: Optional[str] = None

    def to_dict(self) -> dict:
        return {"label": self.label, "value": self.value, "about": self.about, "confidence": self.confidence}


@dataclass(frozen=True)
class DrawnSet:
    """A set to draw: ``role`` (tube, noise_tube, terminal, target, ellipsoid, winning_domain),
    ``label`` for legends; for ``kind = "boxes"`` ``centers`` and ``half_widths`` (k, n) in state units
    and ``periods`` (k,) the period of each box (the last box holds from its period on); for
    ``"ellipsoid"`` ``centers`` (1, n) and ``P`` (n, n); ``"cells"`` carries no arrays."""

    role: str
    label: str
    kind: str
    centers: Optional[np.ndarray] = None
    half_widths: Optional[np.ndarray] = None
    periods: Optional[np.ndarray] = None
    P: Optional[np.ndarray] = None

    def outlines(self, dims=(0, 1), every: int = 1) -> list:
        """Closed outlines (k, 2) on states ``dims``: a rectangle per box (every ``every``-th, the last
        always) or the ellipsoid's projection (its shadow, 181 points); [] for cells."""
        d = [int(i) for i in dims]
        if self.kind == "boxes":
            idx = sorted(set(range(0, len(self.centers), max(1, int(every)))) | {len(self.centers) - 1})
            c, r = self.centers[idx][:, d], self.half_widths[idx][:, d]
            corners = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1], [-1, -1]], float)
            return list(c[:, None, :] + corners[None] * r[:, None, :])
        if self.kind == "ellipsoid":
            Q = np.linalg.inv(self.P)[np.ix_(d, d)]  # the shadow's shape matrix
            t = np.linspace(0, 2 * np.pi, 181)
            L = np.linalg.cholesky(Q)
            return [self.centers[0, d] + (L @ np.stack([np.cos(t), np.sin(t)])).T]
        return []

    def band(self, dim: int, T: int):
        """(periods 0..T, lo, hi) of the set along state ``dim`` per period (boxes only; the last box
        repeated to T): the band a time-series plot draws."""
        t = np.arange(int(T) + 1)
        k = np.minimum(np.searchsorted(self.periods, t, side="right") - 1, len(self.periods) - 1)
        c, r = self.centers[k, dim], self.half_widths[k, dim]
        return t, c - r, c + r

    def to_dict(self) -> dict:
        f = lambda a: None if a is None else np.asarray(a).tolist()
        return {"role": self.role, "label": self.label, "kind": self.kind, "centers": f(self.centers),
                "half_widths": f(self.half_widths), "periods": f(self.periods), "P": f(self.P)}

    @classmethod
    def from_dict(cls, d: dict) -> "DrawnSet":
        a = lambda k, t=float: None if d.get(k) is None else np.asarray(d[k], t)
        return cls(role=str(d["role"]), label=str(d["label"]), kind=str(d["kind"]), centers=a("centers"),
                   half_widths=a("half_widths"), periods=a("periods", np.int64), P=a("P"))


@dataclass(frozen=True)
class PerRunStatement:
    """A probability proved about single runs: P(``event`` for runs of ``horizon`` periods) >= p_cert,
    resting on ``rests_on`` (assumptions and confidence)."""

    p_cert: float
    event: str
    horizon: int
    rests_on: str = ""

    def to_dict(self) -> dict:
        return {"p_cert": self.p_cert, "event": self.event, "horizon": self.horizon, "rests_on": self.rests_on}


@dataclass
class Statement:
    """What one method proved (module docstring). ``method``: its key; ``name``: its own words;
    ``set_name``: what its proved set is called ("the tube", "E", "the winning domain");
    ``headline``: one line; ``notes``: what a reader must know (why a row reads as it does)."""

    method: str
    name: str
    proved: bool
    headline: str
    set_name: str = ""
    rows: list = field(default_factory=list)
    sets: list = field(default_factory=list)
    per_run: Optional[PerRunStatement] = None
    notes: list = field(default_factory=list)

    def rows_about(self, about: str) -> list:
        return [r for r in self.rows if r.about == about]

    def set_of(self, role: str) -> Optional[DrawnSet]:
        return next((s for s in self.sets if s.role == role), None)

    def to_dict(self) -> dict:
        return {"method": self.method, "name": self.name, "proved": self.proved, "headline": self.headline,
                "set_name": self.set_name, "rows": [r.to_dict() for r in self.rows],
                "sets": [s.to_dict() for s in self.sets],
                "per_run": None if self.per_run is None else self.per_run.to_dict(), "notes": list(self.notes)}

    def to_json(self) -> dict:
        """The summary.json form: without the arrays of the sets (the controller file holds them)."""
        d = self.to_dict()
        d["sets"] = [{k: s[k] for k in ("role", "label", "kind")} for s in d["sets"]]
        return d


def not_proved(method: str, stats: Optional[dict] = None, why: str = "") -> Statement:
    """The statement of a method that proved nothing: its name and the reason (its diagnosis)."""
    why = why or (stats or {}).get("diagnosis") or "nothing proved"
    name = METHOD_NAMES.get(method, method)
    return Statement(method=method, name=name, proved=False, headline=f"{name}: not proved (the reason in its notes)",
                     rows=[Row("proved", "no", "proof")], notes=[why])


def gap_words(meta: dict) -> str:
    """What the gap of a controller's proof was, from its meta["gap"]: the words rows and titles use."""
    kind = (meta.get("gap") or {}).get("kind")
    return {"none": "nominal model f, no gap", "constant": "a constant gap",
            "certificate": "the certified gap gamma"}.get(kind, "a gap")


def margin_words(stats: dict) -> str:
    """The proof's margin as words: "margin gamma x 2.48" (the largest factor of gamma the proof holds
    with), "margin: any gap factor" (no gap), or "margin not searched" (``margin_search`` off)."""
    text = stats.get("gap_scale_text")
    if text is None or text == "not searched":
        return "margin not searched"
    return "margin: any gap factor" if text.startswith("any factor") else f"margin gamma x {text}"


def statement_of(method: str, controller=None, stats: Optional[dict] = None,
                 entry: Optional[dict] = None) -> Statement:
    """The statement of a method's result: its controller's own (``controller.statement(entry)``), or
    :func:`not_proved` when there is none (``stats``: the synthesis's, for the diagnosis)."""
    if controller is not None and hasattr(controller, "statement"):
        return controller.statement(entry)
    return not_proved(method, stats)


def fmt_list(a, digits: int = 4) -> str:
    return "[" + ", ".join(f"{v:.{digits}g}" for v in np.asarray(a, float).ravel()) + "]"


__all__ = ["ABOUT", "DrawnSet", "METHOD_NAMES", "PerRunStatement", "Row", "Statement", "fmt_list", "gap_words",
           "not_proved", "statement_of"]
