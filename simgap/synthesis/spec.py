"""Specifications over the state space: reach-avoid and invariance, built from axis-aligned boxes.

A :class:`Box` bounds some or all state dimensions (use -inf/inf for unconstrained ones, e.g. the
TurtleBot heading). A :class:`Spec` is either

* ``reach_avoid``: reach ``target`` while never entering an ``obstacles`` box and staying in X;
* ``invariance``: stay in ``safe`` (a subset of X) forever.

Synthesis uses the boxes to label grid cells; rollouts use :meth:`Spec.violated` and
:meth:`Spec.reached` on continuous states.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Tuple

import numpy as np

from ..errors import SimgapError


@dataclass(frozen=True, eq=False)
class Box:
    """Closed box [lo, hi] in R^n (infinite bounds allowed)."""

    lo: np.ndarray
    hi: np.ndarray

    def __post_init__(self):
        lo = np.asarray(self.lo, dtype=float).ravel()
        hi = np.asarray(self.hi, dtype=float).ravel()
        if lo.shape != hi.shape or np.any(np.isnan(lo)) or np.any(np.isnan(hi)) or np.any(lo > hi):
            raise SimgapError(f"box: need lo <= hi of equal length, got lo={lo.tolist()} hi={hi.tolist()}")
        object.__setattr__(self, "lo", lo)
        object.__setattr__(self, "hi", hi)

    def contains(self, x: np.ndarray) -> np.ndarray:
        """(B,) bool: x (B,n) inside the closed box."""
        x = np.atleast_2d(x)
        return np.all((x >= self.lo) & (x <= self.hi), axis=-1)

    def to_dict(self) -> dict:
        return {"lo": [float(v) for v in self.lo], "hi": [float(v) for v in self.hi]}

    @classmethod
    def from_dict(cls, d: dict) -> "Box":
        return cls(np.asarray(d["lo"], dtype=float), np.asarray(d["hi"], dtype=float))


@dataclass(frozen=True, eq=False)
class Spec:
    """A reach-avoid or invariance specification (see module docstring)."""

    kind: str
    target: Box | None = None
    obstacles: Tuple[Box, ...] = field(default_factory=tuple)
    safe: Box | None = None

    def __post_init__(self):
        object.__setattr__(self, "obstacles", tuple(self.obstacles))
        if self.kind == "reach_avoid":
            if self.target is None:
                raise SimgapError("reach_avoid spec: needs a target box")
        elif self.kind == "invariance":
            if self.safe is None:
                raise SimgapError("invariance spec: needs a safe box")
        else:
            raise SimgapError(f"unknown spec kind {self.kind!r}; use 'reach_avoid' or 'invariance'")

    def in_obstacle(self, x: np.ndarray) -> np.ndarray:
        x = np.atleast_2d(x)
        hit = np.zeros(x.shape[0], dtype=bool)
        for b in self.obstacles:  # a handful of boxes, vectorized over states
            hit |= b.contains(x)
        return hit

    def violated(self, x: np.ndarray, x_lo: np.ndarray, x_hi: np.ndarray) -> np.ndarray:
        """(B,) bool: x leaves X, enters an obstacle, or (invariance) leaves the safe set."""
        x = np.atleast_2d(x)
        out = np.any((x < x_lo) | (x > x_hi), axis=-1) | self.in_obstacle(x)
        if self.kind == "invariance":
            out |= ~self.safe.contains(x)
        return out

    def reached(self, x: np.ndarray) -> np.ndarray:
        """(B,) bool: x in the target (always False for invariance)."""
        if self.kind != "reach_avoid":
            return np.zeros(np.atleast_2d(x).shape[0], dtype=bool)
        return self.target.contains(x)

    def to_dict(self) -> dict:
        return {"kind": self.kind,
                "target": self.target.to_dict() if self.target is not None else None,
                "obstacles": [b.to_dict() for b in self.obstacles],
                "safe": self.safe.to_dict() if self.safe is not None else None}

    @classmethod
    def from_dict(cls, d: dict) -> "Spec":
        return cls(kind=d["kind"],
                   target=Box.from_dict(d["target"]) if d.get("target") else None,
                   obstacles=tuple(Box.from_dict(b) for b in d.get("obstacles", [])),
                   safe=Box.from_dict(d["safe"]) if d.get("safe") else None)
