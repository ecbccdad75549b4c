"""Judging states and paths against a specification (shared by rollouts and the mean map).

Codes: ``OUTCOMES`` (success, violation, timeout, left_domain) and ``VIOLATION_KINDS`` (none,
obstacle, outside_X, unsafe), stored as small integers in the result arrays.
"""

from __future__ import annotations

import numpy as np

from ..synthesis.spec import Spec

#: outcome codes (index = code stored in ``RolloutResult.outcome``)
OUTCOMES = ("success", "violation", "timeout", "left_domain")
SUCCESS, VIOLATION, TIMEOUT, LEFT_DOMAIN = range(4)
#: violation kinds (index = code stored in ``RolloutResult.violation_kind``)
VIOLATION_KINDS = ("none", "obstacle", "outside_X", "unsafe")


def classify(spec: Spec, x: np.ndarray, x_lo: np.ndarray, x_hi: np.ndarray) -> np.ndarray:
    """(B,) violation kind code of states x (B,n): 0 none, 1 obstacle, 2 outside X, 3 unsafe."""
    kind = np.zeros(x.shape[0], dtype=np.int8)
    if spec.kind == "invariance":
        kind[~spec.safe.contains(x)] = 3
    kind[np.any((x < x_lo) | (x > x_hi), axis=-1)] = 2
    kind[spec.in_obstacle(x)] = 1
    return kind


def circular_mean(traj: np.ndarray, angle_dims, axis: int = 0) -> np.ndarray:
    """Mean over ``axis`` of states (..., n); angle dimensions use atan2(E sin, E cos)."""
    mean = traj.mean(axis=axis)
    for d in angle_dims:
        mean[..., d] = np.arctan2(np.sin(traj[..., d]).mean(axis=axis), np.cos(traj[..., d]).mean(axis=axis))
    return mean


def judge_path(spec: Spec, path: np.ndarray, x_lo, x_hi) -> dict:
    """Spec verdict of one given path (T+1, n): first violation / first reach time, satisfied."""
    kind = classify(spec, path, x_lo, x_hi)
    bad = np.flatnonzero(kind > 0)
    tv = int(bad[0]) if bad.size else -1
    if spec.kind == "reach_avoid":
        hit = np.flatnonzero(spec.reached(path) & (kind == 0))
        tr = int(hit[0]) if hit.size else -1
        ok = tr >= 0 and (tv < 0 or tr < tv)
    else:
        tr, ok = -1, tv < 0
    return {"satisfied": bool(ok), "violation_time": tv, "reach_time": tr,
            "violation_kind": VIOLATION_KINDS[int(kind[tv])] if tv >= 0 else "none"}

