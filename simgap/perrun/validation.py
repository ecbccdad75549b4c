"""Empirical success of a controller from many initial states, next to its certified p_cert.

R batched closed-loop runs per initial state in the simulator (fresh noise every period; with
``randomize.per = "episode"`` each run keeps its per-run parameters for the whole horizon),
each judged on the continuous states at every sampling period: invariance fails on the first
state outside the safe set / X; reach-avoid succeeds on the first state in the target and fails
on an obstacle or leaving X (a run that does neither within the horizon fails). p_emp = k / R
with its two-sided 95 % Clopper-Pearson interval and standard error sqrt(p (1 - p) / R).
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from ..errors import SimgapError
from ..synthesis.spec import Spec
from .orderstats import clopper_pearson

InputFn = Callable[[np.ndarray, int], np.ndarray]   # (states (B, n), abstract step t) -> input index (B,), -1 none


def success_counts(input_fn: InputFn, hold: int, sim, spec: Spec, x0s: np.ndarray, n_rollouts: int, horizon: int,
                   seed: int = 0, max_batch: int = 400_000, on_progress=None) -> np.ndarray:
    """(S,) successes of ``n_rollouts`` runs from each of the S initial states ``x0s`` (S, n).

    ``input_fn`` picks an input index per state at each abstract step (the input is then held
    ``hold`` periods); -1 keeps the previous input (the middle input at the start).
    ``on_progress(done, total)``: called after every simulated period, in periods over all batches.
    """
    x0s = np.atleast_2d(np.asarray(x0s, float))
    if int(horizon) < 1:
        raise SimgapError(f"horizon must be >= 1 sampling period, got {horizon}")
    s = sim.system
    U = s.inputs
    S, R = x0s.shape[0], int(n_rollouts)
    out = np.zeros(S, np.int64)
    per = max(1, max_batch // R)
    rng = np.random.default_rng([seed, 5])
    ep_rng = np.random.default_rng([seed, 6])
    H, n_batches = int(horizon), -(-S // per)
    for a in range(0, S, per):  # batches of whole initial states: bounded memory, vectorized runs
        b = min(S, a + per)
        x = np.repeat(x0s[a:b], R, axis=0)
        # randomize.per = "episode": each run keeps its per-run parameters (its own stream)
        ep = sim.draw_episode(len(x), ep_rng) if getattr(sim, "per_episode", False) else {}
        alive = np.ones(len(x), bool)       # still running (neither failed nor reached)
        ok = np.zeros(len(x), bool)
        cur = np.full(len(x), len(U) // 2)
        fail = spec.violated(x, s.x_lo, s.x_hi)
        alive &= ~fail
        if spec.kind == "reach_avoid":
            ok |= alive & spec.reached(x)
            alive &= ~ok
        t = 0
        for period in range(H):
            if on_progress:
                on_progress((a // per) * H + period, n_batches * H)
            if not alive.any():
                break
            if period % hold == 0:
                idx = np.asarray(input_fn(x[alive], t))
                cur[alive] = np.where(idx >= 0, idx, cur[alive])
                t += 1
            x[alive] = sim.step(x[alive], U[cur[alive]], rng, {k: v[alive] for k, v in ep.items()})
            bad = alive & spec.violated(x, s.x_lo, s.x_hi)
            alive &= ~bad
            if spec.kind == "reach_avoid":
                got = alive & spec.reached(x)
                ok |= got
                alive &= ~got
        if spec.kind == "invariance":
            ok |= alive
        out[a:b] = ok.reshape(b - a, R).sum(axis=1)
    if on_progress:
        on_progress(n_batches * H, n_batches * H)
    return out


def empirical(successes: np.ndarray, n_rollouts: int) -> dict:
    """p_emp, its 95 % Clopper-Pearson interval and standard error, per initial state (lists)."""
    k = np.asarray(successes, float)
    p = k / n_rollouts
    lo, hi = clopper_pearson(k, n_rollouts)
    return {"p_emp": p.tolist(), "ci95": np.stack([lo, hi], axis=1).tolist(),
            "se": np.sqrt(p * (1 - p) / n_rollouts).tolist(), "n_rollouts": int(n_rollouts)}


def sample_in_cells(grid, cells: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """``count`` states uniform in randomly chosen cells of ``cells`` (ids), (count, n); angle
    (periodic) dimensions wrapped into X."""
    if cells.size == 0:
        return np.zeros((0, grid.n))
    pick = cells[rng.integers(0, cells.size, count)]
    x = grid.points(pick) + (rng.random((count, grid.n)) - 0.5) * grid.eta
    # a periodic (angle) cell may straddle the seam: wrap into [lo, hi), or the state starts outside X
    per = np.flatnonzero(grid.periodic_mask)
    x[:, per] = grid.lo[per] + np.mod(x[:, per] - grid.lo[per], grid.hi[per] - grid.lo[per])
    return x
