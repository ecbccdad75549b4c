"""certify(dataset, options) -> Certificate: the paper's Sections III-IV end to end.

Per state dimension i:
  1. basis p_i (monomials up to ``degree`` + user terms), design matrix P_i (K, z_i);
  2. observed gap g_i = |mean - f_nom| (wrapped for angles);
  3. stochastic: Mhat_i (variance.py), then delta_1i, delta_2i <-> beta_1i, beta_2i (bounds.py);
     deterministic baseline: delta = 0, no confidence;
  4. SCP-N1hat (scp.py) -> q_i;
  5. L_f, Lhat_fhat, L_2 (lipschitz.py);
  6. gamma_i = (L_f + Lhat_fhat + L_2) eps + q_i^T p_i + delta_2i (+ repair_i), or with
     ``lipschitz_term = "gap"`` (beyond the paper) sum_j (L_ij + L_2,ij) eps_j in place of the first
     term: L_ij the gap's own slope in x_j, eps_j the cover's radius per dimension (_gap_lipschitz).
"""

from __future__ import annotations

import dataclasses
import platform
import time
from collections import OrderedDict
from dataclasses import asdict, dataclass, field
from typing import Dict, List, Optional, Sequence, Union

import numpy as np

from ..dataset import invariant_dims
from ..errors import SimgapError
from ..system_ref import embedded_ref, system_digest
from .basis import Basis
from .bounds import BoundOptions, beta_from_delta, delta_from_beta, required_runs
from .certificate import Certificate, DimCertificate
from .lipschitz import (LHAT_PAIRS, LHAT_RUNS, load_fitting_modules, axis_grid, check_crn_cost, check_pair_distance, crn_cost,
                        fhat_slopes_crn, gap_slopes_crn, gap_slopes_data, l2_analytic, l2_partials, neighbour_pairs,
                        slopes_of, wood_zhang)
from .scp import DependentTerms, solve_scp
from .variance import variance_bound

PerDim = Union[None, float, Sequence[float]]


@dataclass
class CertifyOptions:
    """Options of :func:`certify`. Defaults are the paper's method.

    method : "stochastic" (paper) or "deterministic" (predecessor baseline: delta = 0, no beta).
    degree : total degree of the monomial basis, an int or one per dimension.
    terms : extra basis terms per dimension, {i (0-based): ["cos(x3)", ...]}; key -1 = all dims.
    delta1, delta2 : margins (state units), scalar or per dimension -> betas are computed.
    beta1, beta2 : target failure probabilities -> the smallest deltas are computed. If both a
        delta and a beta are given, the data must have enough runs (else SimgapError).
        Neither given: beta1 = beta2 = 0.01, or what ``confidence`` asks for.
    confidence : the joint confidence the certificate must state (the all-rows reading with
        ``bounds.uniform``, else the pointwise one), in (0, 1): beta1 = beta2 = (1 - confidence -
        sum_i beta_v,i) / (2 n) in every dimension, so that 1 - sum_i (beta1 + beta2 + beta_v) equals it.
        Refused beside beta1/beta2 (two keys setting the same thing) and for the deterministic baseline.
    variance : "empirical" (paper: safety * max sample variance) or "maurer_pontil" (certified).
    safety : the paper's safety factor on the empirical variance (default 10).
    value_range : known range b of fhat_i (for maurer_pontil and bernstein).
    beta_v : failure probability spent on the Maurer-Pontil bound per dimension.
    bounds : BoundOptions (concentration, lemma2_factor, uniform).
    lipschitz_mode : "increment" (default) or "state" (see lipschitz.py).
    l2 : "analytic" (sound interval bound, default) or "estimated" (Wood-Zhang on the fit).
    lhat : "data" (default: slopes between the data set's empirical means over neighbouring
        cover points) or "simulator" (common random numbers, see lipschitz.fhat_slopes_crn;
        rebuilds the simulator from the manifest unless ``simulator`` is passed to certify).
    lhat_pairs, lhat_runs : pairs and runs per pair of the "simulator" estimate.
    lipschitz_term : "paper" (default: (L_f + Lhat_fhat + L_2) eps, one Euclidean radius) or "gap"
        (beyond the paper: sum_j (L_ij + L_2,ij) eps_j with L_ij the Lipschitz constant of the gap
        g_i = E fhat_i - f_i itself in x_j and eps_j the cover's radius per dimension; estimated
        from slopes of g between axis neighbours of the cover, or with common random numbers when
        lhat = "simulator"). Both terms are computed and shown; this picks the one gamma uses.
    continuous_inputs : also certify gamma between the input grid's values (beyond the paper): a
        term sum_k (L^u_ik + L^u_2,ik) eps^u_k (gap and fit slopes in u_k, half the input spacing)
        that callers add for inputs anywhere in the grid's box (Certificate.gamma(..., continuous=True)).
    scp_method, solver, secondary : see scp.solve_scp.
    seed : seeds the Lipschitz batches and the constraint-generation start set.
    round : 0 (one look at the data), or k >= 1: the k-th of the rounds of :mod:`simgap.rounds`; beta1,
        beta2 and beta_v are then spent as beta / 2^k (sum over every round k >= 1: beta), so that the
        certificates of all the rounds hold together with the confidence the base betas state. The
        deltas must then come from betas (delta1 / delta2 refused).
    """

    method: str = "stochastic"
    degree: Union[int, Sequence[int]] = 2
    terms: Dict[int, List[str]] = field(default_factory=dict)
    delta1: PerDim = None
    delta2: PerDim = None
    beta1: PerDim = None
    beta2: PerDim = None
    confidence: Optional[float] = None
    variance: str = "empirical"
    safety: float = 10.0
    value_range: Optional[float] = None
    beta_v: float = 0.001
    bounds: BoundOptions = field(default_factory=BoundOptions)
    lipschitz_mode: str = "increment"
    l2: str = "analytic"
    lhat: str = "data"
    lhat_pairs: int = LHAT_PAIRS
    lhat_runs: int = LHAT_RUNS
    lipschitz_term: str = "paper"
    continuous_inputs: bool = False
    scp_method: str = "cg"
    solver: str = "CLARABEL"
    secondary: bool = True
    seed: int = 0
    round: int = 0

    def to_dict(self) -> dict:
        d = asdict(self)
        if not d["round"]:  # one look at the data: the options (and so the certificates) as before rounds
            del d["round"]
        d["terms"] = {str(k): list(v) for k, v in self.terms.items()}
        for k in ("delta1", "delta2", "beta1", "beta2", "degree"):
            if d[k] is not None and not np.isscalar(d[k]):
                d[k] = [float(v) for v in d[k]]
        return d


def round_split(o: CertifyOptions) -> float:
    """The share 2^-k of the base betas round k >= 1 spends (1 without rounds)."""
    k = o.round
    if isinstance(k, bool) or int(k) != k or k < 0:
        raise SimgapError(f"round must be an integer >= 0, got {k!r}")
    return 1.0 if k == 0 else 0.5 ** int(k)


def _per_dim(v, n, name):
    if v is None:
        return None
    a = np.asarray(v, dtype=float)
    if a.ndim == 0:
        a = np.full(n, float(a))
    if a.shape != (n,):
        raise SimgapError(f"{name}: need one value or {n} values (one per state dimension), got {v!r}")
    if not np.all(np.isfinite(a)):
        raise SimgapError(f"{name}: NaN or inf in {v!r}")
    return a


def confidence_betas(confidence, n: int, beta_v: float, betas_given: bool = False) -> float:
    """beta1 = beta2 per dimension for a joint ``confidence`` over n dimensions: (1 - confidence - n beta_v) / (2 n)
    (CertifyOptions.confidence)."""
    if betas_given:
        raise SimgapError("confidence and beta1/beta2 both set the betas: give one of them")
    c = float(confidence)
    if not (np.isfinite(c) and 0.0 < c < 1.0):
        raise SimgapError(f"confidence must be a probability in (0, 1), got {confidence!r}")
    b = (1.0 - c - n * beta_v) / (2 * n)
    if b <= 0:
        raise SimgapError(f"confidence = {c:g} leaves nothing for beta1/beta2 after the variance bound's "
                          f"{n} x beta_v = {n * beta_v:g}")
    return b


def _versions() -> dict:
    import cvxpy
    import scipy

    from .. import __version__
    return {"simgap": __version__, "numpy": np.__version__, "scipy": scipy.__version__,
            "cvxpy": cvxpy.__version__, "python": platform.python_version()}


def dataset_region(dataset) -> Optional[tuple]:
    """(lo, hi) of the region the collection covered (manifest "cover" "region", a sub-box of X), or
    None when it covered X."""
    boxes = dataset_region_boxes(dataset)
    if boxes is not None:  # a cover along a tube: the estimates are made over the boxes' hull
        return boxes[0].min(axis=0), boxes[1].max(axis=0)
    reg = (dataset.manifest.get("cover") or {}).get("region")
    if not reg:
        return None
    from ..cover import region_box
    return region_box(dataset.system, reg)


def dataset_region_boxes(dataset) -> Optional[tuple]:
    """((B, n), (B, n)) the boxes a cover along a tube covered (manifest "cover" "boxes"; declared-invariant
    dimensions at X's bounds), or None for a grid cover."""
    boxes = (dataset.manifest.get("cover") or {}).get("boxes")
    if not boxes:
        return None
    from ..tube_cover import check_boxes
    lo, hi = check_boxes(dataset.system, boxes)
    inv = invariant_dims(dataset)
    lo[:, inv], hi[:, inv] = dataset.system.x_lo[inv], dataset.system.x_hi[inv]
    return lo, hi


_REGION_DS: "OrderedDict[int, tuple]" = OrderedDict()


def _region_dataset(ds):
    """``ds`` with its system's box X narrowed to the region its collection covered (a local
    certificate's data), or ``ds`` itself when it covered X (or is already narrowed). One object per
    dataset, so that the estimates memoized by the dataset's identity are found again."""
    region = dataset_region(ds)
    if region is None or (np.array_equal(ds.system.x_lo, region[0]) and np.array_equal(ds.system.x_hi, region[1])):
        return ds
    hit = _REGION_DS.get(id(ds))
    if hit is not None and hit[0] is ds:  # the original is held, so its id is not reused meanwhile
        return hit[1]
    out = dataclasses.replace(ds, system=dataclasses.replace(ds.system, x_lo=region[0], x_hi=region[1]))
    _REGION_DS[id(ds)] = (ds, out)
    while len(_REGION_DS) > 4:
        _REGION_DS.popitem(last=False)
    return out


def bases_for(system, degree, terms: Dict[int, List[str]], exclude_dims: Sequence[int] = ()) -> List[Basis]:
    """One Basis per state dimension from a degree (or per-dim degrees) and extra terms.

    ``exclude_dims``: declared-invariant state dimensions; no term may depend on them (the data
    do not vary along them, and the declared invariance says gamma does not either).
    """
    n = system.n
    degs = [degree] * n if np.isscalar(degree) else list(degree)
    if len(degs) != n:
        raise SimgapError(f"degree: need one value or {n} values, got {degree!r}")
    for k in terms:
        if k != -1 and not (0 <= int(k) < n):
            raise SimgapError(f"basis terms given for state dimension {int(k) + 1}, but the system has {n}")
    out = []
    for i in range(n):
        extra = list(terms.get(-1, [])) + list(terms.get(i, []))
        if degs[i] is None or degs[i] < 0:  # only the user's terms
            out.append(Basis(system, extra))
        else:
            out.append(Basis.polynomial(system, degs[i], extra, exclude_dims))
        bad = out[-1].uses() & set(exclude_dims)
        if bad:
            names = ", ".join(system.state_names[j] for j in sorted(bad))
            raise SimgapError(f"basis terms of dimension {system.state_names[i]} use {names}, declared invariant "
                              f"by the collection (the data do not vary along it)")
    return out


def dependent_terms_message(err, system, i: int, degree, terms: Dict[int, List[str]], names: List[str]) -> str:
    """What to drop when the basis of dimension ``i`` is linearly dependent on the data (``err``: a
    :class:`~simgap.certify.scp.DependentTerms`), in the command line's and the TOML's spellings."""
    n, dim = system.n, system.state_names[i]
    degs = [degree] * n if np.isscalar(degree) else list(degree)
    t_all, t_i = list(terms.get(-1, [])), list(terms.get(i, []))
    n_mono = len(names) - len(t_all) - len(t_i)
    bad = names[err.column]
    why = (f"'{bad}' is zero on the data" if not err.on else
           f"'{bad}' is a linear combination of {', '.join(repr(names[j]) for j in err.on)} on the data")
    head = (f"certify: the basis terms of {dim} are linearly dependent on the data, so q would not be unique: "
            f"{why}. Drop it")
    if err.column >= n_mono + len(t_all):  # a term the user gave for this dimension
        return (f"{head}: on the command line leave out --term {dim}:'{bad}'; in the experiment's [certify] "
                f"remove \"{bad}\" from terms.{dim}")
    if err.column >= n_mono:  # a term given for every dimension
        return (f"{head}: it is given for all dimensions (--term all:'{bad}', TOML terms.all); give it only for the "
                f"dimensions that need it (--term NAME:'{bad}', TOML terms.NAME)")
    keep = [t for j, t in enumerate(names[:n_mono]) if j != err.column] + t_i  # the monomials stay, listed
    d_i, degs[i] = int(degs[i]), -1
    cli = f"--degree {','.join(str(int(d)) for d in degs)} " + " ".join(f"--term {dim}:'{t}'" for t in keep)
    toml = (f"degree = [{', '.join(str(int(d)) for d in degs)}] and terms.{dim} = "
            f"[{', '.join(chr(34) + t + chr(34) for t in keep)}]")
    return (f"{head} (a monomial of the degree-{d_i} basis: with degree -1 for {dim} "
            f"the terms are listed instead): on the command line {cli}"
            + (" (keeping the --term all: terms)" if t_all else "") + f"; in the experiment's [certify] {toml}")


def check_dataset(ds) -> None:
    """Reject data the program would silently get wrong."""
    ds.check_finite()
    if ds.K == 0:
        raise SimgapError("dataset: no rows")
    if not (np.isfinite(ds.epsilon) and ds.epsilon > 0):
        raise SimgapError(f"dataset: epsilon must be > 0, got {ds.epsilon}")
    if np.any(ds.var < 0):
        raise SimgapError("dataset: negative sample variances")
    check_recorded(ds)


def check_recorded(ds) -> None:
    """Refuse a data set whose rows or recorded numbers contradict its own configuration: every
    cover point x_r inside X (a point outside changes the Lipschitz and basis terms the
    certificate rests on), the cover and input indices in range, and N1hat, epsilon and the pair
    count equal to the collection configuration the manifest records."""
    s = ds.system
    s.check_states(ds.x, "dataset: cover points x_r")
    M = len(s.inputs)
    if ds.input_index.shape != (ds.K,) or np.any(ds.input_index < 0) or np.any(ds.input_index >= M):
        raise SimgapError(f"dataset: input_index must hold one index in 0..{M - 1} per row (the system's {M} inputs)")
    if np.any(ds.cover_index < 0):
        raise SimgapError("dataset: cover_index holds negative indices")
    m = ds.manifest or {}
    for key, have in (("n_runs", int(ds.n_runs)), ("epsilon", float(ds.epsilon)), ("n_pairs", int(ds.K))):
        want = m.get(key)
        if want is None:
            continue
        if isinstance(want, bool) or not isinstance(want, (int, float)) or not np.isclose(float(want), have,
                                                                                        rtol=1e-12, atol=0):
            what = "rows (x_r, u) pairs" if key == "n_pairs" else key
            raise SimgapError(f"dataset: {what} is {have:g} but its manifest's collection configuration says "
                              f"{key} = {want!r} (the data set was edited; refused)")


def certify(dataset, options: Optional[CertifyOptions] = None, simulator=None, on_progress=None,
            **kw) -> Certificate:
    """Compute the stochastic simulation-gap certificate of ``dataset`` (see module docstring).

    ``options`` or keyword arguments of :class:`CertifyOptions`. ``simulator`` (a Simulator)
    is only used by ``lhat="simulator"``; by default it is rebuilt from the data manifest.
    ``on_progress(rows_done, rows)``: progress of the ``lhat="simulator"`` runs (the same numbers).
    """
    t0 = time.perf_counter()
    o = options or CertifyOptions(**kw)
    if options is not None and kw:
        raise SimgapError("certify: give either options or keyword arguments, not both")
    X_lo, X_hi = dataset.system.x_lo.copy(), dataset.system.x_hi.copy()
    region = dataset_region(dataset)
    # a local certificate: its data cover the region only, so every estimate (Lipschitz pairs, the
    # analytic L_2 sweep, the cover radii) is over the region; gamma is stated there only
    ds = _region_dataset(dataset)
    if region is not None:
        if o.method == "stochastic" and not o.bounds.uniform:
            # gamma's sup over the region (what every consumer takes) is a statement about all its rows
            # at once: the uniform (union-bounded) deltas, so that the confidence stated is that one
            o = dataclasses.replace(o, bounds=dataclasses.replace(o.bounds, uniform=True))
    s = ds.system
    n = s.n
    check_dataset(ds)
    if o.method not in ("stochastic", "deterministic"):
        raise SimgapError(f"unknown method {o.method!r}; choose 'stochastic' or 'deterministic'")
    if o.method == "stochastic" and int(ds.n_runs) < 2:
        raise SimgapError(f"dataset: the stochastic certificate needs N1hat >= 2 runs per pair (sample variances), got "
                          f"{ds.n_runs}; the deterministic baseline (--method deterministic) takes one run")
    if o.lipschitz_mode not in ("increment", "state"):
        raise SimgapError(f"lipschitz_mode must be 'increment' or 'state', got {o.lipschitz_mode!r}")
    if o.l2 not in ("analytic", "estimated"):
        raise SimgapError(f"l2 must be 'analytic' or 'estimated', got {o.l2!r}")
    if o.lhat not in ("data", "simulator"):
        raise SimgapError(f"lhat must be 'data' or 'simulator', got {o.lhat!r}")
    if o.lipschitz_term not in ("paper", "gap"):
        raise SimgapError(f"lipschitz_term must be 'paper' or 'gap', got {o.lipschitz_term!r}")
    o.bounds.validate()
    inv = invariant_dims(ds)
    bases = bases_for(s, o.degree, o.terms, inv)
    g = ds.gap()
    K, N = ds.K, int(ds.n_runs)
    notes = []
    if inv:
        notes.append("declared invariant (not covered, not in the basis): "
                     + ", ".join(s.state_names[j] for j in inv))
    if region is not None:
        notes.append("local certificate: data, estimates and gamma over the region "
                     + " x ".join(f"{s.state_names[i]} [{region[0][i]:g}, {region[1][i]:g}]" for i in range(n)
                                  if region[0][i] > X_lo[i] or region[1][i] < X_hi[i])
                     + (" with the uniform (all-rows) confidence a sup over it needs" if o.method == "stochastic"
                        else ""))

    # ----- margins and confidences -----------------------------------------------------
    if o.method == "stochastic":
        split = round_split(o)  # 1, or 2^-k in round k of the anytime-valid rounds
        vb = variance_bound(ds.var, N, o.variance, o.safety, o.value_range, o.beta_v * split)
        M = vb.M
        d1, d2 = _per_dim(o.delta1, n, "delta1"), _per_dim(o.delta2, n, "delta2")
        b1, b2 = _per_dim(o.beta1, n, "beta1"), _per_dim(o.beta2, n, "beta2")
        if (d1 is None) != (d2 is None):
            d1 = d2 if d1 is None else d1
            d2 = d1 if d2 is None else d2
        if (b1 is None) != (b2 is None):
            b1 = b2 if b1 is None else b1
            b2 = b1 if b2 is None else b2
        if d1 is not None and (np.any(d1 <= 0) or np.any(d2 <= 0)):
            raise SimgapError(f"delta must be > 0 (delta1={d1.tolist()}, delta2={d2.tolist()})")
        if d1 is not None:
            # a margin a million times the size of the states certifies nothing and overflows the
            # bounds' arithmetic downstream (the LP's coefficients, then L_2): refuse it here, by name
            scale = np.maximum(np.abs(ds.x).max(axis=0), 1.0)
            for name, d in (("delta1", d1), ("delta2", d2)):
                big = d > 1e6 * scale
                if np.any(big):
                    i = int(np.argmax(big))
                    raise SimgapError(f"{name} = {d[i]:g} for {s.state_names[i]} is over 1e6 times the size of "
                                      f"the states (|x| up to {scale[i]:g}): a margin that large certifies nothing")
        if o.confidence is not None:
            b1 = b2 = np.full(n, confidence_betas(o.confidence, n, float(vb.beta_v), b1 is not None or
                                                  o.beta2 is not None))
        if d1 is None and b1 is None:
            b1 = b2 = np.full(n, 0.01)
        if split != 1.0:
            if d1 is not None:
                raise SimgapError(f"round {o.round}: the rounds split the betas (beta / 2^k), so the deltas must "
                                  "come from them: give beta1 / beta2, not delta1 / delta2")
            b1, b2 = b1 * split, b2 * split
        if d1 is None:
            d1, d2 = delta_from_beta(M, b1, b2, N, K, o.bounds)
            beta1, beta2 = beta_from_delta(M, d1, d2, N, K, o.bounds)
        else:
            beta1, beta2 = beta_from_delta(M, d1, d2, N, K, o.bounds)
            if b1 is not None and (np.any(beta1 > b1 * (1 + 1e-9)) or np.any(beta2 > b2 * (1 + 1e-9))):
                need = required_runs(M, d1, d2, b1, b2, K, o.bounds)
                raise SimgapError(f"N1hat = {N} runs per (x_r,u) is too small for beta1={b1.tolist()}, "
                                  f"beta2={b2.tolist()} at delta1={d1.tolist()}, delta2={d2.tolist()}: "
                                  f"these deltas give beta1={beta1.tolist()}, beta2={beta2.tolist()}; "
                                  f"need N1hat >= {need}")
        bv = np.full(n, vb.beta_v)
        total = beta1 + beta2 + bv
        if np.any(total >= 1):
            i = int(np.argmax(total))
            raise SimgapError(f"N1hat = {N} runs is too small for delta1={d1[i]:g}, delta2={d2[i]:g} in dimension "
                              f"{s.state_names[i]}: beta1 + beta2 = {total[i]:.3g} >= 1 (no confidence); "
                              f"use larger deltas or more runs")
        if 1.0 - total.sum() <= 0:
            notes.append("joint confidence <= 0: per-dimension statements only")
        variance_info = vb.to_dict()
    else:
        given = [k for k in ("delta1", "delta2", "beta1", "beta2", "confidence") if getattr(o, k) is not None]
        if given:
            raise SimgapError(f"the deterministic baseline has no delta or beta terms; remove {', '.join(given)} "
                              f"(or use --method stochastic)")
        M = None
        d1 = d2 = np.zeros(n)
        beta1 = beta2 = None
        bv = np.zeros(n)
        variance_info = None
        if N > 1:
            notes.append(f"deterministic baseline on a data set with N1hat = {N}: the gap uses the mean of "
                         f"{N} runs (the predecessor work used one run)")

    # ----- Lipschitz constants from the data (no dependence on delta or the basis) --------
    # The gap's term and the paper's are estimated independently: gamma takes the smaller per dimension,
    # so a noise-inflated estimate of one is caught by the other (sharing the runs would inflate both).
    rows = simulator_rows(ds, o)
    gap_progress = fhat_progress = None
    if on_progress is not None and rows["rows"]:  # one count over both parts: the gap's axes, then Lhat_fhat's pairs
        total = int(rows["rows"])
        gap_progress = lambda a, done, _: on_progress(a * rows["gap_axis_rows"] + done, total)  # noqa: E731
        fhat_progress = lambda done, _: on_progress(int(rows["gap_rows"]) + done, total)  # noqa: E731
    gl = _gap_lipschitz(ds, o, simulator, gap_progress) if (o.lipschitz_term == "gap" or o.continuous_inputs) else None
    pairs, lip, U_data = _data_lipschitz(ds, o, simulator, fhat_progress)  # U_data: the inputs gamma is certified for
    warnings = []  # notes that likely cost the user: also shown by `simgap run`
    for i, (_, _, L_fhat, how_fhat) in enumerate(lip):
        share = how_fhat.get("noise_share", 0.0)
        if o.method == "stochastic" and share > NOISE_SHARE_NOTE:
            warnings.append(f"Lhat_fhat[{s.state_names[i]}] = {L_fhat:.4g} is mostly the noise of the empirical means: "
                         f"noise alone gives {share:.0%} of the largest slope (N1hat = {N}); lhat = \"simulator\" "
                         f"(--lhat simulator) estimates it with common random numbers, usually far smaller")
    noisy_gap = noisy_gap_entries(gl, s) if gl is not None else []
    if noisy_gap:  # one warning for all of them (a wall of one line per entry hid the rest of the output)
        where = (f"the noise of the empirical means (N1hat = {N}); lhat = \"simulator\" (--lhat simulator) "
                 f"estimates the slopes with common random numbers" if o.lhat == "data" else
                 f"noise the common random numbers did not cancel ({o.lhat_runs} runs per pair end; contacts or "
                 f"slip events respond unevenly to the same draws): more lhat_runs")
        worst = noisy_gap[0]
        total = sum(len(h) for h in gl["how"])  # every estimated entry: n x the covered state and input axes
        warnings.append(f"{len(noisy_gap)} of {total} L_gap entries are mostly {where} (worst "
                        f"L_gap[{worst['dim']}, {worst['wrt']}]: noise alone gives {worst['noise_share']:.0%} of "
                        f"the largest slope; all of them in the certificate's noisy_gap_entries); gamma takes the "
                        f"smaller of the gap's and the paper's term per dimension")
    rng = np.random.default_rng(o.seed)  # only for l2 = "estimated"

    dims = []
    for i in range(n):
        P = bases[i].design(ds.x, ds.u)
        try:
            res = solve_scp(P, g[:, i], float(d1[i]), method=o.scp_method, solver=o.solver,
                            secondary=o.secondary, seed=o.seed)
        except DependentTerms as e:
            raise SimgapError(dependent_terms_message(e, s, i, o.degree, o.terms, bases[i].names)) from None
        L_f, how_f, L_fhat, how_fhat = lip[i]
        how = {"L_f": how_f, "L_fhat": how_fhat}
        partials = None
        if gl is not None:  # one interval sweep gives the paper's L_2 and the per-dimension partials
            partials = l2_partials(bases[i], res.q, s, U_data, u_box=gl["input_box"] if o.continuous_inputs else None)
        if o.l2 == "analytic":
            L_2 = partials[0] if partials is not None else l2_analytic(bases[i], res.q, s, inputs=U_data)
            how["L_2"] = "analytic: interval bound of ||grad_x q^T p||_2 over sub-boxes of X, all u in U (sound)"
        else:
            wz = wood_zhang(slopes_of((P @ res.q)[:, None].repeat(n, axis=1), pairs, s, angle_diff=False)[:, 0], rng)
            L_2 = wz.estimate
            how["L_2"] = {"how": "Wood-Zhang estimate on slopes of q^T p over neighbouring cover points",
                          **wz.to_dict()}
        if not np.isfinite(L_2):
            raise SimgapError(f"L_2 of dimension {s.state_names[i]} is unbounded on X (a basis term has an "
                              f"unbounded derivative there, e.g. sqrt or sign at 0); use l2='estimated' or change terms")
        fit = P @ res.q
        scp = res.to_dict()
        paper_term = (L_f + L_fhat + L_2) * ds.epsilon
        gapd = {}
        if gl is not None:
            _, L2x, L2u = partials
            gapd = dict(L_gap=gl["L"][i].tolist(), L2_x=L2x.tolist(), L_gap_u=gl["Lu"][i].tolist(),
                        L2_u=L2u.tolist() if o.continuous_inputs else None, gap_how=gl["how"][i])
            gap_term = float(np.dot(gl["L"][i] + L2x, gl["radii"]))
            scp["lipschitz_terms"] = {"paper": paper_term, "gap": gap_term}
        # both terms bound the same |g(x) - g(x_r)| (each an estimate); the gap's never needs to be larger
        term = min(gap_term, paper_term) if o.lipschitz_term == "gap" else paper_term
        const = term + float(d2[i]) + res.repair
        scp["gamma_range_on_data"] = [float(fit.min() + const), float(fit.max() + const)]
        dims.append(DimCertificate(
            terms=bases[i].names, q=res.q, delta1=float(d1[i]), delta2=float(d2[i]),
            beta1=None if beta1 is None else float(beta1[i]), beta2=None if beta2 is None else float(beta2[i]),
            beta_v=float(bv[i]), Mhat=None if M is None else float(M[i]), L_f=L_f, L_fhat=L_fhat, L_2=L_2,
            lipschitz_how=how, repair=res.repair, eta=res.eta, gap_max=float(g[:, i].max()), scp=scp,
            basis=bases[i], **gapd))

    opts = o.to_dict()
    opts["beyond_paper"] = beyond_paper(o)
    opts["variance_bound"] = variance_info
    opts["notes"] = notes + warnings
    opts["warnings"] = warnings
    opts["noisy_gap_entries"] = noisy_gap
    prov = {"dataset_hash": ds.hash, "dataset_config_hash": ds.config_hash, "versions": _versions(), "seed": o.seed,
            "dataset_seed": ds.manifest.get("seed"), "simulator": ds.manifest.get("simulator"),
            "created_unix": time.time(), "seconds": time.perf_counter() - t0}
    return Certificate(system_name=s.name, steps=int(s.steps), state_names=tuple(s.state_names),
                       input_names=tuple(s.input_names), x_lo=X_lo, x_hi=X_hi, region=region,
                       region_boxes=dataset_region_boxes(dataset),
                       angle_dims=tuple(s.angle_dims), epsilon=float(ds.epsilon), n_runs=N, K=K,
                       method=o.method, options=opts, dims=dims, provenance=prov, inputs=U_data,
                       system_digest=system_digest(s), system_ref=embedded_ref(s),
                       lipschitz_term=o.lipschitz_term, radii=None if gl is None else gl["radii"],
                       input_radii=gl["input_radii"] if o.continuous_inputs else None,
                       input_box=gl["input_box"] if o.continuous_inputs else None)



def noisy_gap_entries(gl: dict, system) -> list:
    """The gap's Lipschitz entries L_gap[i, j] whose estimate is mostly noise (share of the largest
    slope explained by noise alone above NOISE_SHARE_NOTE), worst first: [{dim, wrt, noise_share}]
    with the state name of g_i and the state or input name of the slope's direction."""
    n = system.n
    out = [{"dim": system.state_names[i], "wrt": system.state_names[j] if j < n else system.input_names[j - n],
            "noise_share": float(share)}
           for i in range(n) for j, share in sorted(gl["noise_share"][i].items()) if share > NOISE_SHARE_NOTE]
    return sorted(out, key=lambda e: -e["noise_share"])


#: above this share of the largest data slope explained by the empirical means' noise, the
#: certificate notes that Lhat_fhat is mostly noise and names the remedy
NOISE_SHARE_NOTE = 0.5


def mean_noise_share(ds, pairs, i: int, slopes: np.ndarray, rng: np.random.Generator) -> float:
    """Share of the largest slope of the empirical means along dimension i that their noise alone gives.

    The means of two rows carry independent noise of variance (s_a^2 + s_b^2) / N1hat (sample
    variances s^2), so a pair at distance d has a pure-noise slope |Z| sqrt(s_a^2 + s_b^2) / (sqrt(N1hat) d),
    Z ~ N(0, 1). Drawing Z once per pair gives the largest slope noise alone would show; a share near
    1 means Lhat_fhat estimates the sampling noise of the means, not the simulator."""
    ra, rb, dist = pairs
    if ra.size == 0 or not np.max(slopes, initial=0.0) > 0:
        return 0.0
    sd = np.sqrt((ds.var[ra, i] + ds.var[rb, i]) / ds.n_runs) / dist
    return float(min(1.0, np.max(np.abs(rng.standard_normal(ra.size)) * sd) / np.max(slopes)))


def beyond_paper(o: CertifyOptions) -> List[str]:
    """Labels of every choice in ``o`` that the paper does not make (stored in the certificate)."""
    out = []
    if o.lipschitz_term == "gap":
        out.append("Lipschitz term from the gap itself: sum_j L_ij eps_j with L_ij the slope of g_i = E fhat_i - f_i "
                   "in x_j and eps_j the cover's radius per dimension (the paper: (L_f + Lhat_fhat + L_2) eps)")
    if o.continuous_inputs:
        out.append("gamma certified between the input grid's values: + sum_k L^u_ik eps^u_k for continuous inputs")
    if o.method != "stochastic":
        return out
    out += list(o.bounds.beyond_paper())
    if o.variance == "empirical" and o.safety != 10.0:
        out.append(f"variance safety factor {o.safety:g} (the paper takes 10 x the largest sample variance)")
    if o.variance != "empirical":
        out.append(f"variance={o.variance}: Mhat holds with confidence 1 - beta_v at the K cover rows, "
                   f"not over all of X (between rows the variance is assumed no larger)")
    if o.lhat == "simulator":
        out.append("Lhat_fhat from the simulator with common random numbers along the covered dimensions")
    return out


_LIP_CACHE: "OrderedDict[tuple, tuple]" = OrderedDict()


def _lip_key(ds, o: CertifyOptions, own_simulator: bool) -> tuple:
    return (id(ds), ds.config_hash, ds.K, tuple(invariant_dims(ds)), o.lipschitz_mode, o.lhat, o.lhat_pairs,
            o.lhat_runs, o.seed, own_simulator)


def _paper_pairs_simulated(ds, o: CertifyOptions) -> bool:
    """Whether Lhat_fhat (the paper's Lipschitz term) comes from the simulator's pairs ||x - x'|| = eps.

    With lhat = "simulator" it does, unless the pairs do not fit in the region the data covered (a cover
    along a tube: its boxes' hull can be narrower than 2 eps along a covered dimension) while gamma uses
    the gap's own term (lipschitz_term = "gap", from the simulator's pairs along each axis, which need no
    such room): the paper's term is then estimated from the data's slopes, as lhat = "data" does, and gamma
    keeps the smaller of the two terms (with noisy data slopes, the gap's). Refused otherwise (the paper's
    term is gamma's only one)."""
    if o.lhat != "simulator":
        return False
    cov = [j for j in range(ds.system.n) if j not in invariant_dims(ds)]
    try:
        check_pair_distance(ds.system, ds.epsilon, cov)
    except SimgapError:
        if o.lipschitz_term != "gap" or not (ds.manifest.get("cover") or {}).get("boxes"):
            raise
        return False
    return True


def _data_lipschitz(ds, o: CertifyOptions, simulator=None, on_progress=None):
    """(neighbour pairs, [(L_f, how, Lhat_fhat, how)] per dimension, the data's inputs) of a dataset.

    These depend only on the data and the Lipschitz options, not on delta or the basis, so the
    result is memoized per dataset (a delta or basis change re-solves only the programs). Each
    estimate has its own seeded generator, so the values do not depend on the call order.
    """
    key = _lip_key(ds, o, simulator is None)
    if key in _LIP_CACHE:
        _LIP_CACHE.move_to_end(key)
        return _LIP_CACHE[key]
    s = ds.system
    pairs = neighbour_pairs(ds)
    if o.lipschitz_mode == "increment":
        sl_fhat = slopes_of(s.diff(ds.mean, ds.x), pairs, s)  # mean fhat - x (wrapped): the increment
        sl_f = slopes_of(s.diff(ds.f_nom, ds.x), pairs, s)
        Lf_analytic = None
    else:
        sl_fhat = slopes_of(ds.mean, pairs, s)
        sl_f = slopes_of(ds.f_nom, pairs, s)
        Lf_analytic = s.lipschitz_f()
    crn_fhat = _paper_pairs_simulated(ds, o)
    if crn_fhat:
        from ..simulators import make_simulator
        cov = [j for j in range(s.n) if j not in invariant_dims(ds)]  # pairs along covered dims only
        crn = dict(h=ds.epsilon, n_pairs=o.lhat_pairs, runs=o.lhat_runs, increment=o.lipschitz_mode == "increment",
                   dims=cov, inputs=np.unique(ds.u, axis=0), on_progress=on_progress)
        if simulator is None:
            cfg = ds.manifest.get("simulator")
            if not cfg:
                raise SimgapError("lhat='simulator' needs the data manifest's simulator config or a simulator")
            with make_simulator(cfg, system=s) as sim:
                sl_fhat = fhat_slopes_crn(sim, np.random.default_rng([o.seed, 1]), **crn)
        else:
            sl_fhat = fhat_slopes_crn(simulator, np.random.default_rng([o.seed, 1]), **crn)
    src = (" over neighbouring cover points (independent draws per row)" + (
        "" if o.lhat == "data" else f"; the simulator's pairs eps = {ds.epsilon:g} apart do not fit in the region the "
        "data covered, gamma uses the gap's own term (simulator)") if not crn_fhat else
           f" at {o.lhat_pairs} random pairs ||x - x'|| = eps along the covered dimensions, {o.lhat_runs} runs "
           f"each with common random numbers (simulator)")
    incr = o.lipschitz_mode == "increment"
    out = []
    for i in range(s.n):
        if Lf_analytic is not None:
            L_f = float(Lf_analytic[i])
            how_f = ("estimated: System.lipschitz_f from a Jacobian bound estimated by central differences on "
                     "256 states of X per input (a system file without [bounds]; not a proof)"
                     if s.params.get("_jacobian") == "estimated" else
                     "analytic: System.lipschitz_f (Jacobian bound, Euclidean row norm, max over U)")
        else:
            wz = wood_zhang(sl_f[:, i], np.random.default_rng([o.seed, 2, i]))
            L_f = wz.estimate
            how_f = {"how": f"Wood-Zhang estimate on slopes of f_{i + 1}" + (" - x" if incr else "")
                     + " over neighbouring cover points", **wz.to_dict()}
        wz = wood_zhang(sl_fhat[:, i], np.random.default_rng([o.seed, 3, i]))
        how_fhat = {"how": "Wood-Zhang estimate on slopes of the empirical mean"
                    + (" increment (mean - x)" if incr else "") + src, **wz.to_dict()}
        if not crn_fhat and ds.n_runs > 1:
            how_fhat["noise_share"] = mean_noise_share(ds, pairs, i, sl_fhat[:, i], np.random.default_rng([o.seed, 4, i]))
        out.append((L_f, how_f, wz.estimate, how_fhat))
    _LIP_CACHE[key] = (pairs, out, np.unique(ds.u, axis=0))
    while len(_LIP_CACHE) > 4:
        _LIP_CACHE.popitem(last=False)
    return _LIP_CACHE[key]

def input_grid_of(system, U: np.ndarray) -> tuple:
    """(lo, hi) of the input box when U is a full grid of >= 2 values per input, else SimgapError."""
    if (system.params or {}).get("inputs") == "categorical":
        raise SimgapError(f"continuous inputs: the inputs of {system.name!r} are categorical (e.g. switch modes "
                          f"{np.unique(U, axis=0).ravel().tolist()[:6]}): there is nothing between their values "
                          f"to certify; drop continuous_inputs")
    vals = [np.unique(U[:, k]) for k in range(U.shape[1])]
    few = [system.input_names[k] for k, v in enumerate(vals) if len(v) < 2]
    if few or len(np.unique(U, axis=0)) != int(np.prod([len(v) for v in vals])):
        why = (f"input {', '.join(few)} takes a single value" if few else
               "the input set is not the full grid of its per-input values")
        raise SimgapError(f"continuous inputs need the data's inputs on a grid (input_grid): {why}")
    return np.array([v[0] for v in vals]), np.array([v[-1] for v in vals])


def simulator_rows(ds, o: CertifyOptions) -> dict:
    """Simulator runs ``certify`` makes with ``lhat = "simulator"`` (all 0 with lhat = "data").

    ``fhat_rows`` = 2 lhat_pairs lhat_runs (:func:`fhat_slopes_crn`, both ends of every pair);
    ``gap_rows`` = axes x 2 per_axis lhat_runs for the gap's own Lipschitz matrix (lipschitz_term =
    "gap" or continuous inputs: one batch per covered state axis and per input axis), per_axis =
    max(100, lhat_pairs // axes); ``rows`` their sum. Known from the data's shape alone, so the
    commands print it before any run (:func:`simgap.certify.lipschitz.crn_cost`)."""
    zero = {"fhat_rows": 0, "gap_rows": 0, "gap_axis_rows": 0, "axes": 0, "rows": 0}
    if o.lhat != "simulator":
        return zero
    s = ds.system
    ds = _region_dataset(ds)  # the dataset certify estimates over (the keys below are its)
    fhat = 2 * int(o.lhat_pairs) * int(o.lhat_runs) if _paper_pairs_simulated(ds, o) else 0
    gap = axis_rows = axes = 0
    if o.lipschitz_term == "gap" or o.continuous_inputs:
        axes = s.n - len(invariant_dims(ds)) + (s.m if o.continuous_inputs else 0)
        per_axis = max(100, int(o.lhat_pairs) // max(1, axes))
        axis_rows = 2 * per_axis * int(o.lhat_runs)
        gap = axes * axis_rows
    cached = _lip_key(ds, o, True) in _LIP_CACHE or _lip_key(ds, o, False) in _LIP_CACHE
    if cached:  # an earlier call with these data and options: Lhat_fhat is not simulated again
        fhat = 0
    if gap and (_gap_key(ds, o, True) in _GAP_CACHE or _gap_key(ds, o, False) in _GAP_CACHE):
        gap = 0  # nor the gap's own Lipschitz matrix
    return {"fhat_rows": fhat, "gap_rows": gap, "gap_axis_rows": axis_rows, "axes": axes, "rows": fhat + gap}


def lhat_cost(ds, o: CertifyOptions, simulator) -> Optional[dict]:
    """:func:`simgap.certify.lipschitz.crn_cost` of every simulator run ``certify(ds, o)`` will make,
    at ``simulator``'s rate measured here (0.05-0.3 s); None when it makes none. Checks the pair
    distance first (a refusal costs no run) and refuses work over the memory or time limits."""
    from ..cover import calibrate_rate
    rows = simulator_rows(ds, o)
    if not rows["rows"]:
        return None
    load_fitting_modules()
    if rows["fhat_rows"]:
        _paper_pairs_simulated(_region_dataset(ds), o)
    pairs = o.lhat_pairs if rows["fhat_rows"] else 0
    work = crn_cost(pairs, o.lhat_runs, ds.system, gap_rows=rows["gap_rows"])["rows"]
    cost = crn_cost(pairs, o.lhat_runs, ds.system,
                    calibrate_rate(simulator, budget=0.3, repeat=int(o.lhat_runs), work=work),  # rows repeated as the runs step them
                    gap_rows=rows["gap_rows"])
    check_crn_cost(cost)
    return cost


_GAP_CACHE: "OrderedDict[tuple, dict]" = OrderedDict()


def _gap_key(ds, o: CertifyOptions, own_simulator: bool) -> tuple:
    """What the gap's Lipschitz matrix depends on: the data (and the box its estimates are over), the
    slope source and its sizes, the seed and whether the inputs' axes are included."""
    return _lip_key(ds, o, own_simulator) + (tuple(ds.system.x_lo), tuple(ds.system.x_hi), o.continuous_inputs,
                                             id(ds.system))


def _gap_lipschitz(ds, o: CertifyOptions, simulator=None, on_progress=None) -> dict:
    """:func:`_gap_lipschitz_compute`, memoized per dataset like :func:`_data_lipschitz`: it depends on
    neither delta, beta nor the basis, so certifying the same data again (``--compare``'s bound
    options, a GUI knob) reuses it instead of repeating its simulator runs."""
    key = _gap_key(ds, o, simulator is None)
    if key in _GAP_CACHE:
        _GAP_CACHE.move_to_end(key)
        return _GAP_CACHE[key]
    out = _gap_lipschitz_compute(ds, o, simulator, on_progress)
    _GAP_CACHE[key] = out
    while len(_GAP_CACHE) > 4:
        _GAP_CACHE.popitem(last=False)
    return out


def _gap_lipschitz_compute(ds, o: CertifyOptions, simulator=None, on_progress=None) -> dict:
    """The gap's own Lipschitz matrix L (n, n) in x and Lu (n, m) in u, with the radii (beyond the paper).

    L_ij: Wood-Zhang on slopes |g_i(a) - g_i(b)| / h between rows that differ only in x_j by one
    grid step (lhat = "data"), or on common-random-number pairs along x_j at log-uniform distances
    up to 2 eps_j (lhat = "simulator"); 0 along declared-invariant dimensions (not covered: x is
    moved along them onto the cover, and the gap is declared independent of them). Lu likewise
    along u_k (continuous inputs). With data slopes, the noise floor per (i, j) is stated: the
    means of two rows carry independent noise, sd sqrt(s_a^2 + s_b^2) / (sqrt(N1hat) h) per slope,
    which inflates the estimate (conservative); its share of the estimate is recorded and a share
    above one half is warned about."""
    s = ds.system
    n, m = s.n, s.m
    cov = [j for j in range(n) if j not in invariant_dims(ds)]
    ubox = input_grid_of(s, np.unique(ds.u, axis=0)) if o.continuous_inputs else None
    cv = ds.manifest.get("cover") or {}
    # a cover along a tube with simulator slopes needs no neighbours nor two values per state (its radii are
    # its cells', its slopes the simulator's); the inputs' radii still come from the input grid's values
    free = bool(cv.get("boxes")) and o.lhat == "simulator"
    inputs = range(m) if o.continuous_inputs else ()
    grid = axis_grid(ds, cov, inputs, by_point=free)  # along a tube its points are no grid over the states
    if cv.get("boxes"):  # a cover along a tube: each box has its own grid, so the values along x_j of all
        # boxes together say nothing of a cell's width; eps_j = half the widest cell over the boxes
        w = np.zeros(n)
        w[cov] = 0.5 * np.asarray(cv["widths"], float)
        grid = dataclasses.replace(grid, radii=np.maximum(grid.radii, w))
    for j in grid.dims:
        if not (free and j < n) and (grid.neighbours[j][0].size == 0 or len(grid.values[j]) < 2):
            nm = s.state_names[j] if j < n else s.input_names[j - n]
            raise SimgapError(f"the gap's Lipschitz term needs cover points with neighbours along every covered "
                              f"dimension, but {nm} has {len(grid.values[j])} value(s) in the data: use a finer "
                              f"spacing along {nm} (or lipschitz_term = \"paper\")")
    L, Lu = np.zeros((n, n)), np.zeros((n, m))
    how = [dict() for _ in range(n)]
    share = [dict() for _ in range(n)]
    sim_ctx = None
    if o.lhat == "simulator":
        from ..simulators import make_simulator
        cfg = ds.manifest.get("simulator")
        if simulator is None and not cfg:
            raise SimgapError("lhat='simulator' needs the data manifest's simulator config or a simulator")
        sim_ctx = simulator if simulator is not None else make_simulator(cfg, system=s)
        per_axis = max(100, o.lhat_pairs // max(1, len(grid.dims)))
    try:
        for a, j in enumerate(grid.dims):
            rng = np.random.default_rng([o.seed, 5, j])
            eps_j = grid.radii[j] if j < n else grid.input_radii[j - n]
            if sim_ctx is None:
                sl, noise = gap_slopes_data(ds, grid, j)
                src = "slopes of the observed gap between axis neighbours of the cover (independent draws per row)"
            else:
                direction, k = ("x", j) if j < n else ("u", j - n)
                lo, hi = (ubox if ubox is not None else (None, None))
                sl, noise = gap_slopes_crn(sim_ctx, s, rng, direction, k, 2.0 * eps_j, per_axis,
                                           o.lhat_runs, np.unique(ds.u, axis=0), lo, hi,
                                           None if on_progress is None else
                                           (lambda done, rows, a=a: on_progress(a, done, rows)),
                                           box=(s.x_lo, s.x_hi))  # the region's X (ds is narrowed to it)
                src = (f"{per_axis} common-random-number pairs along it at distances log-uniform in "
                       f"[{eps_j / 4:.3g}, {2 * eps_j:.3g}], {o.lhat_runs} runs each (simulator)")
            for i in range(n):
                wz = wood_zhang(sl[:, i], np.random.default_rng([o.seed, 6, i, j]))
                nm = s.state_names[j] if j < n else s.input_names[j - n]
                entry = {"how": "Wood-Zhang estimate on " + src, "radius": float(eps_j), **wz.to_dict()}
                if wz.estimate > 0:
                    floor = float(np.max(np.abs(rng.standard_normal(len(noise))) * noise[:, i]))
                    entry["noise_floor"] = floor
                    entry["noise_share"] = min(1.0, floor / wz.estimate)
                    share[i][j] = entry["noise_share"]
                how[i][nm] = entry
                (L if j < n else Lu)[i, j if j < n else j - n] = wz.estimate
    finally:
        if sim_ctx is not None and simulator is None:
            sim_ctx.close()
    return {"L": L, "Lu": Lu, "radii": grid.radii, "input_radii": grid.input_radii,
            "input_box": ubox, "how": how, "noise_share": share}


def compare_variants(base: CertifyOptions) -> list:
    """[(name, BoundOptions)] that :func:`compare_options` certifies under, in its rows' order."""
    variants = [("paper (chebyshev, 2 Mhat, pointwise)", BoundOptions()),
                ("chebyshev, 4 Mhat (general Lemma 2)", BoundOptions(lemma2_factor=4.0)),
                ("chebyshev, uniform over K rows", BoundOptions(uniform=True)),
                ("sub-Gaussian", BoundOptions(concentration="subgaussian")),
                ("sub-Gaussian, uniform over K rows", BoundOptions(concentration="subgaussian", uniform=True))]
    if base.value_range:
        variants += [("bernstein (range b)", BoundOptions(concentration="bernstein", value_range=base.value_range)),
                     ("bernstein (range b), uniform", BoundOptions(concentration="bernstein", uniform=True,
                                                                   value_range=base.value_range))]
    return variants


def compare_options(dataset, base: Optional[CertifyOptions] = None, simulator=None, on_progress=None) -> list:
    """Certify ``dataset`` under the paper's bounds and each option beyond it, at the same betas.

    Returns rows {option, delta1, delta2, beta1, beta2, gamma_min, gamma_max, joint} (per-dimension
    lists). Deltas are derived from the base options' betas (default 0.01 each), so the rows show
    what each option does to delta and to gamma at equal confidence.

    The Lipschitz constants (the paper's and, with lipschitz_term = "gap", the gap's own, with their
    simulator runs under lhat = "simulator") depend on no bound option: the first certification
    computes them, the others reuse them. ``simulator`` serves those runs (default: rebuilt from the
    data's manifest). ``on_progress(done, total)`` counts certifications (total = the variants);
    during the first one's simulator runs ``done`` is their finished fraction, below 1.
    """
    base = base or CertifyOptions()
    if base.method != "stochastic":
        raise SimgapError("--compare needs the stochastic method")
    b1 = base.beta1 if base.beta1 is not None else 0.01
    b2 = base.beta2 if base.beta2 is not None else b1
    common = dict(delta1=None, delta2=None, beta1=b1, beta2=b2)
    variants = compare_variants(base)
    total = len(variants)
    runs = None if on_progress is None else (lambda done, rows: on_progress(min(done / rows, 0.999), total)
                                             if rows else None)
    rows = []
    for k, (name, bo) in enumerate(variants):
        c = certify(dataset, dataclasses.replace(base, bounds=bo, **common), simulator=simulator,
                    on_progress=runs if k == 0 else None)
        rows.append({"option": name, "delta1": [d.delta1 for d in c.dims], "delta2": [d.delta2 for d in c.dims],
                     "beta1": [d.beta1 for d in c.dims], "beta2": [d.beta2 for d in c.dims],
                     "gamma_min": [d.scp["gamma_range_on_data"][0] for d in c.dims],
                     "gamma_max": [d.scp["gamma_range_on_data"][1] for d in c.dims],
                     "joint": c.joint_confidence})
        if on_progress is not None:
            on_progress(k + 1, total)
    return rows


def compare_estimate_text(dataset, base: CertifyOptions, cost: Optional[dict]) -> str:
    """The line ``simgap certify --compare`` prints before any work: how many certifications, what
    is computed once, and the simulator runs' time (``cost``: :func:`lhat_cost`, None without runs)."""
    from .lipschitz import crn_cost_text
    v = len(compare_variants(base))
    n = dataset.system.n
    once = ("the Lipschitz constants once, from the data (no simulator runs)" if cost is None else
            "the Lipschitz constants once, in the first: " + crn_cost_text(cost)[len("estimate: "):])
    return (f"estimate: --compare certifies the data under {v} bound options: {v} x {n} linear programs over "
            f"{dataset.K:,} (x_r,u) rows, each certification timed by the bar after the first; {once}")


def comparison_table(rows: list, state_names) -> str:
    """Text table of :func:`compare_options` rows."""
    hdr = f"{'option':<40}{'dim':<8}{'delta1':>11}{'delta2':>11}{'beta1':>9}{'beta2':>9}{'gamma min':>11}" \
          f"{'gamma max':>11}{'joint':>8}"
    lines = [hdr, "-" * len(hdr)]
    for r in rows:
        for i, nm in enumerate(state_names):
            lines.append(f"{r['option'] if i == 0 else '':<40}{nm:<8}{r['delta1'][i]:>11.4g}{r['delta2'][i]:>11.4g}"
                         f"{r['beta1'][i]:>9.3g}{r['beta2'][i]:>9.3g}{r['gamma_min'][i]:>11.4g}"
                         f"{r['gamma_max'][i]:>11.4g}{(format(r['joint'], '.4f') if i == 0 else ''):>8}")
    return "\n".join(lines)
