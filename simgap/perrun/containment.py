"""Containment check of a built interval MDP: does the Lipschitz widening hold off the sampled points?

The interval MDP's rows rest on an ASSUMPTION that no finite sample proves: per noise draw w,
the run from ANY x in a cell stays inside the widened box around the reference run the row was
counted from (the run from the cell center, or with ``share`` the anchor's run shifted by the
nominal model; :mod:`simgap.perrun.imdp`). The constants are Wood-Zhang estimates from secants
at sampled pairs, which can miss a narrow feature (a hole a fraction of a cell wide, a ripple).

This check draws ``n_states`` fresh states uniformly inside the cell of every checked row (cell
c, input a), not at cover points, and simulates each for the k periods of a hold together with
the row's reference run under the SAME noise (common random numbers). Per fresh run it records

* ``outside_box``: at some period t the fresh state left y_ref,t +- rho (the assumption itself
  failed for this realization: a sound row may survive it, a counterexample to the widening);
* ``unaccounted``: the reference run is not a sink run of the row (every widened box safe, its
  end box inside the row's support T(c, a) and live/target cells), yet the fresh run is unsafe
  at some period or ends in a cell its reference's end box does not touch. Such a realization is
  counted by the row as a success it is not: the row's intervals are wrong for this x. Given the
  same box test, unaccounted runs are a subset of outside_box runs.

Rows checked: every live (cell, input) row of a per-cell or shared build; for a translation
build (one reference class of cells per heading) one random live cell per class, every input,
with the cell center's own run as reference (this checks the widening, not the translation
invariance itself). A row fails when any of its fresh runs is unaccounted or outside its box;
the report lists failures per cell and the certificate is marked (``passed`` false).

What it cannot catch (docs/per-run.md): a feature hit with probability well below 1 / (rows x
n_states) per row (a hole narrower than eta / n_states in a single cell is found with
probability about 1 - (1 - w / eta)^(n_states x inputs)); a violation only in noise draws rarer
than 1 / n_states; and, for a translation build, a failure of the translation invariance.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from ..errors import SimgapError
from ..synthesis.spec import Spec
from .imdp import IMDP, _hits, block_anchors, box_unsafe, shared_box

#: at most this many failing rows are listed one by one in the report (all are counted)
MAX_LISTED = 50


@dataclass
class ContainmentReport:
    """Outcome of :func:`check_containment` (module docstring); JSON-able via :meth:`to_dict`."""

    construction: str            # "per cell", "shared", "translation"
    states_per_row: int
    rows_checked: int
    runs: int                    # fresh runs (each with its reference run): rows_checked x states_per_row
    outside_box: int             # fresh runs that left the widened box around the reference run
    unaccounted: int             # fresh runs the row's counts do not account for
    cells_failed: int            # cells with a failing row
    failures: list = field(default_factory=list)   # up to MAX_LISTED rows: cell, center, input, counts
    seconds: float = 0.0

    @property
    def passed(self) -> bool:
        return self.outside_box == 0 and self.unaccounted == 0

    def to_dict(self) -> dict:
        return dict(asdict(self), passed=self.passed,
                    what="fresh states uniform in every checked cell, k periods with the reference run's noise: "
                         "outside_box = left the widened box (the Lipschitz assumption failed for that draw), "
                         "unaccounted = unsafe or ending outside the reference's end box while the reference run "
                         "is not a sink run (the row's intervals are wrong there)")

    def summary(self) -> str:
        if self.passed:
            return (f"containment check passed: {self.runs} fresh runs in {self.rows_checked} rows "
                    f"({self.construction}), none left its widened box")
        return (f"WARNING: containment check FAILED in {self.cells_failed} cell(s): {self.outside_box} of {self.runs} "
                f"fresh runs left the widened box, {self.unaccounted} are not accounted for by their row; p_cert "
                f"rests on Lipschitz constants these runs contradict")


def check_containment(sim, spec: Spec, imdp: IMDP, n_states: int = 64, seed: int = 0,
                      batch_runs: int = 1 << 18) -> ContainmentReport:
    """Check ``imdp`` against fresh runs of ``sim`` (module docstring).

    ``n_states`` fresh states per checked row, uniform in the row's cell; the draws come from
    the seeded generator ``[seed, 11]``, independent of the build's."""
    import time
    t0 = time.perf_counter()
    if int(n_states) < 1:
        raise SimgapError(f"containment check: n_states must be >= 1, got {n_states}")
    n_states = int(n_states)
    s, grid, meta = sim.system, imdp.grid, imdp.meta
    C, M, k = imdp.C, imdp.M, imdp.hold
    ad = tuple(s.angle_dims)
    half = grid.eta / 2
    rng = np.random.default_rng([int(seed), 11])
    live = np.flatnonzero(imdp.live)
    if meta.get("invariant"):
        construction = "translation"
        # one live cell per class (same index along the non-invariant dimensions)
        names = list(s.state_names)
        other = [d for d in range(s.n) if names[d] not in meta["invariant"]]
        mi = grid.ids_to_multi(live)
        cls = np.ravel_multi_index(mi[:, other].T, np.asarray(grid.shape)[other]) if other else np.zeros(live.size, int)
        perm = rng.permutation(live.size)
        _, first = np.unique(cls[perm], return_index=True)
        cells = np.sort(live[perm[first]])
    else:
        construction = "shared" if "share" in meta else "per cell"
        cells = live
    share = np.asarray(meta["share"], np.int64) if construction == "shared" else None
    if share is not None:
        Ln, Lr = (np.asarray(meta["lipschitz"][key], float) for key in ("nominal", "residual"))
    else:
        rho0 = np.asarray(meta["rho"], float)
    rows = (cells[:, None] * M + np.arange(M)[None, :]).ravel()
    # the support of every row as sorted keys row * (C + 1) + col (the sink column excluded)
    nnz_row = np.repeat(np.arange(imdp.row_ptr.size - 1), np.diff(imdp.row_ptr))
    succ = imdp.col != C
    support = np.sort(nnz_row[succ].astype(np.int64) * (C + 1) + imdp.col[succ])
    good = imdp.live | imdp.target

    outside_row = np.zeros(rows.size, np.int64)
    unacc_row = np.zeros(rows.size, np.int64)
    per = max(1, int(batch_runs) // n_states)
    for a0 in range(0, rows.size, per):
        rr = rows[a0:a0 + per]
        B = rr.size * n_states
        r_of = np.repeat(rr, n_states)
        c_of, u_of = r_of // M, s.inputs[r_of % M]
        xc = grid.points(c_of)
        xf = s.wrap(xc + (rng.random((B, s.n)) - 0.5) * grid.eta)      # fresh: uniform in the cell
        if share is None:
            xr, shift, rho = xc, np.zeros((B, k, s.n)), np.broadcast_to(rho0, (B, s.n))
        else:
            xs = grid.points(block_anchors(grid, c_of, share))
            shift, rho = shared_box(s, xc, xs, u_of, k, Ln, Lr, half)
            xr = xs
        X = np.concatenate([xf, xr])
        U = np.concatenate([u_of, u_of])
        out_box = np.zeros(B, bool)
        ref_bad = np.zeros(B, bool)
        fresh_bad = np.zeros(B, bool)
        for t in range(k):
            noise = {key: np.concatenate([v, v]) for key, v in sim.draw_noise(B, rng).items()}
            X = sim.step_with_noise(X, U, noise)
            yf, yr = X[:B], s.wrap(X[B:] + shift[:, t])
            out_box |= np.any(np.abs(s.diff(yf, yr)) > rho * (1 + 1e-9) + 1e-12, axis=1)
            ref_bad |= box_unsafe(spec, yr - rho, yr + rho, s.x_lo, s.x_hi, ad)
            fresh_bad |= box_unsafe(spec, yf, yf, s.x_lo, s.x_hi, ad)
        # the reference run's end box: touched cells must be in the row's support and live/target
        b, ids, _ = _hits(grid, yr, rho)
        key = r_of[b] * (C + 1) + np.maximum(ids, 0)
        pos = np.minimum(np.searchsorted(support, key), max(support.size - 1, 0))
        ok = (ids >= 0) & good[np.maximum(ids, 0)] & (support[pos] == key if support.size else False)
        ref_bad[b[~ok]] = True
        # the fresh run's end cell must be one the reference's end box touches
        lo_mi = np.floor((yr - rho - grid.first) / grid.eta + 0.5).astype(np.int64)
        hi_mi = np.floor((yr + rho - grid.first) / grid.eta + 0.5).astype(np.int64)
        f_mi = np.floor((yf - grid.first) / grid.eta + 0.5).astype(np.int64)
        shape = np.asarray(grid.shape)
        rel = f_mi - lo_mi
        rel = np.where(grid.periodic_mask, np.mod(rel, shape), rel)
        touched = np.all((rel >= 0) & (rel <= hi_mi - lo_mi), axis=1)
        unacc = ~ref_bad & (fresh_bad | ~touched)
        idx = np.repeat(np.arange(a0, a0 + rr.size), n_states)
        np.add.at(outside_row, idx, out_box)
        np.add.at(unacc_row, idx, unacc)
    fail = np.flatnonzero((outside_row > 0) | (unacc_row > 0))
    worst = fail[np.argsort(-(unacc_row[fail] * (n_states + 1) + outside_row[fail]), kind="stable")][:MAX_LISTED]
    failures = [{"cell": int(rows[i] // M), "center": np.round(grid.points(np.array([rows[i] // M]))[0], 9).tolist(),
                 "input": int(rows[i] % M), "outside_box": int(outside_row[i]), "unaccounted": int(unacc_row[i])}
                for i in worst]
    return ContainmentReport(construction=construction, states_per_row=n_states, rows_checked=int(rows.size),
                             runs=int(rows.size * n_states), outside_box=int(outside_row.sum()),
                             unaccounted=int(unacc_row.sum()), cells_failed=int(np.unique(rows[fail] // M).size),
                             failures=failures, seconds=round(time.perf_counter() - t0, 3))
