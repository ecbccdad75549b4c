"""The invariant-set controller: u(x) = u* + K (x - x*) on E = {x : (x - x*)^T P (x - x*) <= 1}.

It answers the grid :class:`~simgap.synthesis.controller.Controller`'s queries (``input``,
``winning``, ``check_winning``, ``size``, ``describe``, ``system``, ``spec``, ``hold``, ``x0``)
so that rollouts, the mean map and ``simgap run`` use it unchanged; ``continuous_input`` tells
them that the input is a value, not a row of ``system.inputs`` (``input_index`` is -1 outside E
and 0 inside: "the feedback law").

File format (``.npz``, no pickle, the grid controller's conventions): arrays ``K`` (m, n),
``P`` (n, n), ``x_star`` (n,), ``u_star`` (m,), and ``meta`` (a JSON string: format
``simgap-controller``, version, kind ``invariant_set``, system.describe(), spec.to_dict(), the
gap's provenance (a certificate's digest), the design and proof statistics, the margins, and
``digest`` = sha256 of the meta without it and of every array). :meth:`load` recomputes the
digest and refuses an edited file.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np

from ..errors import BAD_FILE_ERRORS, SimgapError
from ..sets import Ellipsoid
from ..systems import System
from .controller_file import check_digest, write_controller
from .spec import Spec
from .statement import DrawnSet, Row, Statement, fmt_list, gap_words, margin_words

KIND = "invariant_set"
ARRAYS = ("K", "P", "x_star", "u_star")


class EllipsoidController:
    """A linear feedback on a proved invariant ellipsoid (module docstring)."""

    continuous_input = True
    kind = KIND

    def __init__(self, x_star, u_star, K, P, system: Optional[System] = None, spec: Optional[Spec] = None,
                 meta: Optional[dict] = None, hold: int = 1):
        self.x_star = np.asarray(x_star, dtype=float).ravel()
        self.u_star = np.asarray(u_star, dtype=float).ravel()
        n, m = self.x_star.size, self.u_star.size
        self.K = np.asarray(K, dtype=float).reshape(m, n)
        self.P = np.asarray(P, dtype=float).reshape(n, n)
        if hold != 1:  # a file edited with its digest recomputed must not hold the input longer than the proof
            raise SimgapError(f"invariant-set controller: hold = {hold!r}, but its proof applies u(x) every period (hold = 1): "
                              "refused (was the file edited?)")
        self.system, self.spec, self.hold = system, spec, int(hold)
        self.meta = dict(meta or {})
        x0 = self.meta.get("x0")
        self.x0 = None if x0 is None else np.asarray(x0, dtype=float)

    # ----- the set ---------------------------------------------------------------------
    @property
    def half_widths(self) -> np.ndarray:
        """(n,) half-widths of E's bounding box: sqrt(diag P^-1)."""
        return np.sqrt(np.diag(np.linalg.inv(self.P)))

    @property
    def size(self) -> int:
        """1: one set (the grid controller counts winning cells)."""
        return 1

    size_with_target = size

    def projection(self, dims) -> tuple:
        """E's shadow on the coordinates ``dims`` (two state indices): (centre (2,), P2 (2, 2)) with
        {y : (y - c)^T P2 (y - c) <= 1} the set of (x_a, x_b) of all x in E.

        The projection of an ellipsoid is the ellipse of the matching block of the inverse:
        P2 = ((P^-1)[dims, dims])^-1 (the slice through x*, P[dims, dims], is smaller when the
        coordinates correlate with the others)."""
        d = [int(i) for i in dims]
        if len(d) != 2 or d[0] == d[1] or not all(0 <= i < self.x_star.size for i in d):
            raise SimgapError(f"projection: need two different state indices in 0..{self.x_star.size - 1}, got {dims!r}")
        Q = np.linalg.inv(self.P)[np.ix_(d, d)]
        return self.x_star[d].copy(), np.linalg.inv(0.5 * (Q + Q.T))

    def projection_outline(self, dims, points: int = 181) -> np.ndarray:
        """(points, 2) the boundary of :meth:`projection` (closed: the last point is the first):
        c + L u for u on the unit circle, L L^T = (P^-1)[dims, dims]."""
        self.projection(dims)  # the indices checked, with this class's message
        return Ellipsoid(self.x_star, self.P).outline([int(i) for i in dims], points)

    def level(self, x) -> np.ndarray:
        """(B,) (x - x*)^T P (x - x*): <= 1 inside E."""
        e = np.atleast_2d(np.asarray(x, dtype=float)) - self.x_star
        return np.einsum("bi,ij,bj->b", e, self.P, e)

    def winning(self, x) -> np.ndarray:
        """(B,) bool: x lies in E."""
        return self.level(x) <= 1.0

    def check_winning(self, x, what: str = "initial state") -> None:
        """Raise SimgapError if any x (B, n) lies outside E, naming it."""
        x = np.atleast_2d(np.asarray(x, dtype=float))
        lv = self.level(x)
        if np.any(lv > 1.0):
            i = int(np.flatnonzero(lv > 1.0)[0])
            raise SimgapError(f"{what} {x[i].tolist()} is outside the controller's invariant set E "
                              f"((x - x*)^T P (x - x*) = {lv[i]:.4g} > 1; E's half-widths "
                              f"{np.round(self.half_widths, 6).tolist()} around x* = {self.x_star.tolist()})")

    # ----- inputs ----------------------------------------------------------------------
    def input(self, x, strict: bool = True) -> np.ndarray:
        """(B, m) u* + K (x - x*). Outside E: SimgapError with ``strict``, else NaN rows."""
        x = np.atleast_2d(np.asarray(x, dtype=float))
        if strict:
            self.check_winning(x, "state")
        u = self.u_star + (x - self.x_star) @ self.K.T
        u[~self.winning(x)] = np.nan
        return u

    def input_index(self, x) -> np.ndarray:
        """(B,) 0 inside E (the feedback law applies), -1 outside (the grid controller's 'no input')."""
        return np.where(self.winning(x), 0, -1).astype(np.int64)

    # ----- description -----------------------------------------------------------------
    def describe(self) -> dict:
        return {"kind": KIND, "n": int(self.x_star.size), "m": int(self.u_star.size), "hold": self.hold,
                "x_star": self.x_star.tolist(), "u_star": self.u_star.tolist(),
                "half_widths": self.half_widths.tolist(), "margins": self.meta.get("margins")}

    def summary(self) -> str:
        st = self.meta.get("stats", {})
        return (f"invariant-set controller: u = u* + K (x - x*), K = {np.round(self.K, 4).tolist()}, "
                f"x* = {self.x_star.tolist()}, u* = {self.u_star.tolist()}; E half-widths "
                f"{np.round(self.half_widths, 6).tolist()}; {margin_words(st)}")

    def statement(self, entry: Optional[dict] = None):
        """What the ellipsoid proved, in its words (:mod:`.statement`): E invariant for the mean map;
        ``entry``: the method's record in summary.json (rollouts from states in E), optional."""
        entry = entry or {}
        st = self.meta.get("stats", {})
        nominal = (self.meta.get("gap") or {}).get("kind") == "none"
        conf = None if nominal or entry.get("confidence_proof") is None else "all rows"
        name = "invariant ellipsoid E"
        w = (st.get("verification") or {}).get("w_max")
        rows = [Row("proved", "yes: E invariant", "proof", conf),
                Row("E half-widths", fmt_list(self.half_widths), "proof", conf)]
        if w is not None:
            rows.append(Row("gap over E [max]", fmt_list(w), "proof", conf))
        rows.append(Row("margin: E invariant with gamma x", str(st.get("gap_scale_text", "-")), "proof", conf))
        if st.get("x0_inside") is not None:
            rows.append(Row("x0 in E", "yes" if st["x0_inside"] else "no", "proof", conf))
        ris = entry.get("rollouts_in_set")
        if ris:
            rows.append(Row("single runs failing from states in E", f"{ris['failures']} / {ris['n_rollouts']} "
                            f"({ris['states']} states)", "single_runs"))
        sets = [DrawnSet("ellipsoid", "invariant ellipsoid E", "ellipsoid", self.x_star[None], P=self.P)]
        return Statement(method=KIND, name=name, proved=True, set_name="E", rows=rows, sets=sets,
                         headline=f"{name}: proved invariant with {gap_words(self.meta)}, {margin_words(st)}; "
                                  "no per-run probability")

    # ----- files -----------------------------------------------------------------------
    def save(self, path) -> Path:
        """Write the controller as .npz (temp file, then rename; :mod:`.controller_file`)."""
        arrays = {"K": self.K, "P": self.P, "x_star": self.x_star, "u_star": self.u_star}
        return write_controller(path, self.meta, KIND, self.hold, self.system, self.spec, arrays)

    @classmethod
    def from_arrays(cls, path, z, meta: dict, system: Optional[System] = None) -> "EllipsoidController":
        """Build from an open .npz whose meta says kind invariant_set (called by Controller.load)."""
        try:
            arrays = {k: np.asarray(z[k], dtype=float) for k in ARRAYS}
        except (*BAD_FILE_ERRORS, KeyError) as e:
            raise SimgapError(f"controller file {str(path)!r} is not an invariant-set controller ({e})") from None
        check_digest(path, meta, arrays)
        K, P, xs, us = (arrays[k] for k in ARRAYS)
        n, m = xs.size, us.size
        if K.shape != (m, n) or P.shape != (n, n) or not all(np.all(np.isfinite(a)) for a in arrays.values()) \
                or np.any(np.linalg.eigvalsh(0.5 * (P + P.T)) <= 0):
            raise SimgapError(f"controller file {str(path)!r}: K, P, x_star, u_star do not fit together "
                              f"(shapes {list(K.shape)}, {list(P.shape)}, {n}, {m}; P must be positive definite)")
        spec = Spec.from_dict(meta["spec"]) if meta.get("spec") else None
        if system is None and meta.get("system"):
            from ..system_ref import ref_of_description, resolve_system
            try:
                system = resolve_system(ref_of_description(meta["system"]), int(meta["system"].get("steps", 1)),
                                        paths=False)
            except SimgapError:
                system = None
        return cls(xs, us, K, P, system=system, spec=spec, meta=meta, hold=meta.get("hold", 1))
