"""The certificate: gamma_i(x, u) = L_x^(i) eps + q_i^T p_i(x, u) + delta_2i (+ repair_i), saved as JSON.

``gamma`` is what synthesis and rollouts consume: |E_w fhat_i(x,u,w) - f_i(x,u)| <= gamma_i(x,u)
with per-dimension confidence 1 - beta_1i - beta_2i (- beta_v,i) and joint confidence
1 - sum_i (...) (paper, Theorems 1-2). For the deterministic baseline delta = 0 and no
confidence is stated.

What the confidence is about (``scope``). By default (the paper's Lemmas) the confidence is
POINTWISE: it holds for one query point (x, u) at a time. Synthesis reads gamma at every cell at
once, which needs a SIMULTANEOUS statement; both readings of the same certificate are reported
(``pointwise_joint_confidence``, ``simultaneous_joint_confidence`` = union bound over the K
cover rows). ``uniform`` mode (bounds.py) sizes the deltas for the simultaneous one.

Integrity: the JSON carries ``digest`` = sha256 of its canonical content without the digest;
:func:`load` recomputes it and refuses an edited file, naming what no longer fits.

JSON layout (version 2): system (name, steps, names, X, angle dims), epsilon, n_runs, K, method,
options, per-dimension entries (basis terms, q, delta_1, delta_2, beta_1, beta_2, beta_v, Mhat,
L_f / Lhat_fhat / L_2 with how each was obtained, L_x, repair, eta, gap_max, solver info,
confidence), joint_confidence, provenance (dataset hash, package versions, seed, time).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Optional

import numpy as np

from .. import fileio
from ..errors import SimgapError
from .basis import Basis
from .bounds import scope_confidences

FORMAT = "simgap-certificate"
VERSION = 2


class _Names:
    """The few System attributes a Basis needs, so certificates load without the System object."""

    def __init__(self, n, m, state_names, input_names):
        self.n, self.m = int(n), int(m)
        self.state_names, self.input_names = tuple(state_names), tuple(input_names)



def _kind(v) -> str:
    """The JSON kind of a value, for messages."""
    return {dict: "an object", list: "a list", str: "a string", bool: "a boolean", type(None): "null"}.get(
        type(v), "a number" if isinstance(v, (int, float)) else type(v).__name__)


def _field(obj: dict, key: str, kind: type, where: str):
    """obj[key] if present and of JSON kind ``kind``, else SimgapError naming the field."""
    if key not in obj:
        raise SimgapError(f"{where} is malformed: missing field {key!r}")
    v = obj[key]
    if not isinstance(v, kind):
        raise SimgapError(f"{where} is malformed: field {key!r} must be {_kind(kind())}, got {_kind(v)}")
    return v

@dataclass
class DimCertificate:
    """Everything about gamma_i for one state dimension i."""

    terms: List[str]
    q: np.ndarray
    delta1: float
    delta2: float
    beta1: Optional[float]
    beta2: Optional[float]
    beta_v: float
    Mhat: Optional[float]
    L_f: float
    L_fhat: float
    L_2: float
    lipschitz_how: dict
    repair: float
    eta: float
    gap_max: float
    scp: dict
    basis: Basis = field(repr=False, default=None)
    # beyond the paper (None when not computed): the gap's own Lipschitz row L_gap[j] = sup |d g_i/d x_j|,
    # the fit's partials L2_x[j] = sup |d q^T p/d x_j|, and in u (continuous inputs) L_gap_u, L2_u
    L_gap: Optional[List[float]] = None
    L2_x: Optional[List[float]] = None
    L_gap_u: Optional[List[float]] = None
    L2_u: Optional[List[float]] = None
    gap_how: Optional[dict] = None

    @property
    def L_x(self) -> float:
        return self.L_f + self.L_fhat + self.L_2

    @property
    def confidence(self) -> Optional[float]:
        if self.beta1 is None:
            return None
        return 1.0 - self.beta1 - self.beta2 - self.beta_v

    def to_dict(self) -> dict:
        return {"terms": list(self.terms), "q": self.q.tolist(), "delta1": self.delta1, "delta2": self.delta2,
                "beta1": self.beta1, "beta2": self.beta2, "beta_v": self.beta_v, "Mhat": self.Mhat,
                "L_f": self.L_f, "L_fhat": self.L_fhat, "L_2": self.L_2, "L_x": self.L_x,
                "lipschitz_how": self.lipschitz_how, "repair": self.repair, "eta": self.eta,
                "gap_max": self.gap_max, "scp": self.scp, "confidence": self.confidence,
                **({} if self.L_gap is None else {"L_gap": self.L_gap, "L2_x": self.L2_x, "L_gap_u": self.L_gap_u,
                                                  "L2_u": self.L2_u, "gap_how": self.gap_how})}


@dataclass
class Certificate:
    system_name: str
    steps: int
    state_names: tuple
    input_names: tuple
    x_lo: np.ndarray
    x_hi: np.ndarray
    angle_dims: tuple
    epsilon: float
    n_runs: int
    K: int
    method: str
    options: dict
    dims: List[DimCertificate]
    provenance: dict
    inputs: Optional[np.ndarray] = None   # (M, m) the inputs the data covered: gamma is certified for these
    system_digest: Optional[str] = None   # simgap.system_ref.system_digest of the nominal model
    system_ref: Optional[dict] = None     # embedded system file / refined system (simgap.system_ref.system_ref)
    lipschitz_term: str = "paper"         # "paper": L_x eps; "gap": sum_j (L_gap_ij + L2_x,ij) radii_j
    radii: Optional[np.ndarray] = None    # (n,) the cover's radius per dimension eps_j (0: not covered)
    input_radii: Optional[np.ndarray] = None  # (m,) half the input grid's spacing (continuous inputs)
    input_box: Optional[tuple] = None     # ((m,), (m,)) the input box gamma holds on (continuous inputs)
    region: Optional[tuple] = None        # ((n,), (n,)) the sub-box of X the data covered: gamma holds there only
    # ((B, n), (B, n)) a cover along a tube (simgap.tube_cover): gamma holds in the union of these boxes only;
    # ``region`` is then their hull (the box every estimate was made over)
    region_boxes: Optional[tuple] = None

    # ----- shape -----------------------------------------------------------------------
    @property
    def n(self) -> int:
        return len(self.state_names)

    @property
    def m(self) -> int:
        return len(self.input_names)

    @property
    def per_dim_confidence(self) -> List[Optional[float]]:
        return [d.confidence for d in self.dims]

    @property
    def joint_confidence(self) -> Optional[float]:
        """Theorem 2's joint confidence in this certificate's ``scope``."""
        if any(c is None for c in self.per_dim_confidence):
            return None
        return 1.0 - sum(1.0 - c for c in self.per_dim_confidence)

    @property
    def uniform(self) -> bool:
        """True when the betas are spent over all K cover rows at once (uniform mode; run-level certificates)."""
        return self.method == "run" or bool((self.options.get("bounds") or {}).get("uniform", False))

    @property
    def scope(self) -> str:
        """"simultaneous" (uniform mode: one statement for all K cover rows) or "pointwise" (per (x, u))."""
        return "simultaneous" if self.uniform else "pointwise"

    def scope_confidences(self) -> dict:
        """{"pointwise", "simultaneous"} joint confidences of this certificate (None without betas)."""
        if self.joint_confidence is None:
            return {"pointwise": None, "simultaneous": None}
        return scope_confidences([d.beta1 for d in self.dims], [d.beta2 for d in self.dims],
                                 [d.beta_v for d in self.dims], self.K, self.uniform)

    def statement(self) -> str:
        """In words, what the confidence covers (never a negative number: "vacuous", explained)."""
        if self.joint_confidence is None:
            return "no probability is stated (deterministic baseline)"
        c = self.scope_confidences()
        where = "" if self.region is None else f" over the region {self.region_text()}"
        rounds = "" if not self.round else (
            f"; round {self.round} of anytime-valid rounds (betas / 2^{self.round}): every round's certificate "
            f"at once {confidence_text(self.all_rounds_confidence(), self.K)}, what a proof may state")
        return (f"scope {self.scope}; joint confidence pointwise (one query (x,u) at a time) "
                f"{confidence_text(c['pointwise'])}, simultaneous (all K = {self.K} cover rows at once, union "
                f"bound: what a sup of gamma over a set relies on: synthesis, invariant sets, tubes){where} "
                f"{confidence_text(c['simultaneous'], self.K)}{rounds}")

    @property
    def round(self) -> int:
        """0, or k >= 1: the k-th round of data (:mod:`simgap.rounds`), its betas the base ones / 2^k."""
        return int(self.options.get("round") or 0)

    def all_rounds_confidence(self) -> Optional[float]:
        """The simultaneous confidence of the certificates of EVERY round k >= 1 at once (round k spends
        beta / 2^k, so their failures sum to at most 2^k times this round's): 1 - 2^k (1 - simultaneous).
        What a proof with the certificate of the round where the rounds stopped may state, the stopping
        having looked at the data. The simultaneous confidence itself without rounds."""
        c = self.scope_confidences()["simultaneous"]
        if c is None or not self.round:
            return c
        return 1.0 - 2.0 ** self.round * (1.0 - c)

    def sup_confidence(self) -> Optional[float]:
        """The confidence of any statement that takes gamma's sup over a set (a synthesis over cells,
        an invariant set, a tube): the SIMULTANEOUS reading (all K rows at once), never the pointwise
        one (which is about one query (x, u)); over all the rounds when the certificate is one of the
        anytime-valid rounds (:meth:`all_rounds_confidence`). None: deterministic baseline, or vacuous (<= 0)."""
        c = self.all_rounds_confidence()
        return None if c is None or c <= 0 else float(c)

    def proof_confidence_text(self) -> str:
        """What a proof built on gamma's sup over a set (cells, an ellipsoid, a tube) may claim, with
        its kind named: "all rows" (:meth:`sup_confidence`), or why there is none (the pointwise
        number, about one query (x, u) at a time, is shown beside it and never stands in for it)."""
        c = self.scope_confidences()
        if c["pointwise"] is None:
            return "none stated (deterministic baseline)"
        if self.sup_confidence() is not None:
            return f"all rows {self.sup_confidence():.4g} (the all-rows reading a sup of gamma over a set needs)"
        return (f"none: the all-rows reading over K = {self.K} rows is vacuous; the pointwise {c['pointwise']:.4g} "
                f"is about one (x, u) at a time, not this proof (certify with uniform = true, --uniform)")

    # ----- region ------------------------------------------------------------------------
    def region_text(self, lo=None, hi=None) -> str:
        """The region (or a given box) as "name [lo, hi] x ...", only the dimensions it narrows from X
        (all of them for a given box)."""
        if lo is None:
            lo, hi = self.region if self.region is not None else (self.x_lo, self.x_hi)
            dims = [i for i in range(self.n) if lo[i] > self.x_lo[i] or hi[i] < self.x_hi[i]] or list(range(self.n))
        else:
            dims = list(range(self.n))
        return " x ".join(f"{self.state_names[i]} [{lo[i]:.6g}, {hi[i]:.6g}]" for i in dims)

    def outside(self, lo, hi, what: str) -> str:
        """'' when every box [lo, hi] (rows of (B, n) arrays, or one box) lies in the region the data
        covered, else why not, naming the set (``what``), the box and the dimensions. A cover along a
        tube (``region_boxes``): each box must lie inside ONE of the region's boxes (a box between them,
        or straddling two, is outside: gamma was certified on their union only, and containment in one
        box is what is checked, soundly)."""
        if self.region is None:
            return ""
        lo, hi = np.atleast_2d(np.asarray(lo, float)), np.atleast_2d(np.asarray(hi, float))
        rlo, rhi = self.region
        tol = 1e-9 * np.maximum(1.0, np.abs(rhi - rlo))
        out = (lo < rlo - tol) | (hi > rhi + tol)
        if np.any(out):
            b = int(np.argmax(out.any(axis=1)))
            dims = ", ".join(self.state_names[i] for i in np.flatnonzero(out[b]))
            return (f"{what} [{self.region_text(lo[b], hi[b])}] leaves the certificate's region "
                    f"[{self.region_text()}] in {dims}: gamma holds on that region only (its data were "
                    "collected there, [collect] region); keep the set inside it or collect over a "
                    "larger region")
        if self.region_boxes is None:
            return ""
        blo, bhi = (np.asarray(a, float) for a in self.region_boxes)
        inside = np.zeros(lo.shape[0], dtype=bool)
        step = max(1, 2_000_000 // max(1, blo.size))  # (queries x boxes x n) booleans per slice
        for a in range(0, lo.shape[0], step):
            q_lo, q_hi = lo[a:a + step, None, :], hi[a:a + step, None, :]
            inside[a:a + step] = np.any(np.all((q_lo >= blo[None] - tol) & (q_hi <= bhi[None] + tol), axis=2),
                                        axis=1)
        if inside.all():
            return ""
        b = int(np.flatnonzero(~inside)[0])
        return (f"{what} [{self.region_text(lo[b], hi[b])}] lies in none of the {len(blo)} boxes the certificate's "
                "data covered (a cover along a tube: gamma holds in their union only, and a set must lie inside "
                "one of them); keep the set along the tube or collect with a larger [collect] tube_margin")

    def require_inside(self, lo, hi, what: str) -> None:
        """Refuse taking gamma over the box [lo, hi] ("what" names the set) unless it lies in the region
        the data covered (:meth:`outside`; no-op for a certificate over all of X). Every consumer that
        takes gamma's sup over a set calls it with its set's name; :meth:`gamma_upper_box` and
        :meth:`gamma_sup` check the boxes they are given too."""
        msg = self.outside(lo, hi, what)
        if msg:
            raise SimgapError(msg)

    def restrict(self, system):
        """``system`` with X narrowed to the region (the system itself without one)."""
        if self.region is None:
            return system
        import dataclasses
        return dataclasses.replace(system, x_lo=np.asarray(self.region[0], float).copy(),
                                   x_hi=np.asarray(self.region[1], float).copy())

    def paper_terms(self) -> np.ndarray:
        """The paper's Lipschitz term (L_f + Lhat_fhat + L_2) eps per dimension, (n,)."""
        return np.array([d.L_x * self.epsilon for d in self.dims])

    def gap_terms(self) -> Optional[np.ndarray]:
        """The gap's own term sum_j (L_gap_ij + L2_x,ij) eps_j per dimension, (n,); None if not computed."""
        if self.radii is None or any(d.L_gap is None for d in self.dims):
            return None
        return np.array([float(np.dot(np.add(d.L_gap, d.L2_x), self.radii)) for d in self.dims])

    def lipschitz_terms(self) -> np.ndarray:
        """The Lipschitz term gamma uses, (n,): the paper's, or with ``lipschitz_term = "gap"`` the smaller
        of the gap's own and the paper's per dimension (both bound |g_i(x) - g_i(x_r)| on a cell; the
        gap's is the smaller in exact arithmetic, so a larger estimate is noise)."""
        if self.lipschitz_term == "gap":
            return np.minimum(self.gap_terms(), self.paper_terms())
        return self.paper_terms()

    @property
    def continuous(self) -> bool:
        """True when gamma is also certified between the input grid's values (``input_box``)."""
        return self.input_box is not None

    def input_terms(self) -> np.ndarray:
        """sum_k (L_gap_u,ik + L2_u,ik) eps^u_k per dimension, (n,): what an input between grid values adds."""
        if not self.continuous:
            raise SimgapError("this certificate holds only at the inputs its data covered; certify with "
                              "continuous_inputs = true (--continuous-inputs) for inputs between them")
        return np.array([float(np.dot(np.add(d.L_gap_u, d.L2_u), self.input_radii)) for d in self.dims])

    def constant(self) -> np.ndarray:
        """The x-independent part of gamma per dimension: Lipschitz term + delta_2 + repair, (n,)."""
        return self.lipschitz_terms() + np.array([d.delta2 + d.repair for d in self.dims])

    # ----- evaluation ------------------------------------------------------------------
    def _check_xu(self, x, u, what="x"):
        x = np.atleast_2d(np.asarray(x, dtype=float))
        u = np.atleast_2d(np.asarray(u, dtype=float))
        if x.shape[1] != self.n or u.shape[1] != self.m:
            raise SimgapError(f"certificate: need {what} (B,{self.n}) and u (B,{self.m}), got {x.shape} and {u.shape}")
        if u.shape[0] == 1 and x.shape[0] > 1:
            u = np.broadcast_to(u, (x.shape[0], self.m))
        if x.shape[0] != u.shape[0]:
            raise SimgapError(f"certificate: {x.shape[0]} states but {u.shape[0]} inputs")
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(u))):
            raise SimgapError("certificate: NaN or inf in x or u")
        return x, u

    def fit(self, x, u) -> np.ndarray:
        """q_i^T p_i(x, u) per dimension, (B, n)."""
        x, u = self._check_xu(x, u)
        return np.stack([d.basis.design(x, u) @ d.q for d in self.dims], axis=1)

    def _check_box_inputs(self, u_lo, u_hi):
        lo, hi = self.input_box
        if np.any(u_lo < np.asarray(lo) - 1e-12) or np.any(u_hi > np.asarray(hi) + 1e-12):
            raise SimgapError(f"inputs outside the certified input box [{np.asarray(lo).tolist()}, "
                              f"{np.asarray(hi).tolist()}]")

    def gamma(self, x, u, continuous: bool = False) -> np.ndarray:
        """gamma_i(x, u) = Lipschitz term + q_i^T p_i(x, u) + delta_2i (+ repair_i); x (B,n), u (B,m) -> (B,n).

        ``continuous``: u anywhere in the input box (adds :meth:`input_terms`); otherwise gamma is
        certified only at the data's inputs."""
        g = self.fit(x, u) + self.constant()
        if continuous:
            self._check_box_inputs(*(2 * [np.atleast_2d(u)]))
            g = g + self.input_terms()
        return g

    def gamma_upper_box(self, lo, hi, u, continuous: bool = False) -> np.ndarray:
        """Sound upper bound of gamma_i over the box [lo, hi] x {u}: lo, hi (B,n), u (B,m) -> (B,n).

        Interval arithmetic per basis term (monomials and the whitelisted functions), then
        q_l * [p_l lo, p_l hi] summed with the sign of q_l. +inf where a term is unbounded.
        ``continuous`` as in :meth:`gamma`.
        """
        lo, u = self._check_xu(lo, u, "lo")
        hi, _ = self._check_xu(hi, u, "hi")
        return self._upper(lo, hi, u, u, continuous)

    def gamma_sup(self, x_lo, x_hi, u_lo, u_hi) -> np.ndarray:
        """Sound sup of gamma_i over the state box [x_lo, x_hi] and the input box [u_lo, u_hi] (continuous
        inputs, :meth:`input_terms` included): (n,) or (B, n) for (B, n) / (B, m) boxes."""
        x_lo, u_lo = self._check_xu(x_lo, u_lo, "x_lo")
        x_hi, u_hi = self._check_xu(x_hi, u_hi, "x_hi")
        out = self._upper(x_lo, x_hi, u_lo, u_hi, True)
        return out[0] if out.shape[0] == 1 else out

    def _upper(self, lo, hi, ulo, uhi, continuous):
        if lo.shape != hi.shape or np.any(lo > hi) or np.any(ulo > uhi):
            raise SimgapError("gamma bound over a box: need lo <= hi with equal shapes")
        self.require_inside(lo, hi, "a box gamma is bounded over")  # a consumer should have named its set first
        extra = 0.0
        if continuous:
            extra = self.input_terms()
            self._check_box_inputs(ulo, uhi)
        zlo = np.concatenate([lo, ulo], axis=1)
        zhi = np.concatenate([hi, uhi], axis=1)
        out = np.stack([d.basis.upper_box(d.q, zlo, zhi) for d in self.dims], axis=1)
        return out + self.constant() + extra

    # ----- compatibility ---------------------------------------------------------------
    def check_system(self, system) -> None:
        """Raise unless the certificate was made for ``system`` (name, steps, dimensions)."""
        from ..system_ref import system_digest
        if system.name != self.system_name or system.steps != self.steps or system.n != self.n \
                or system.m != self.m:
            raise SimgapError(f"certificate is for system {self.system_name!r} (steps={self.steps}, n={self.n}, "
                              f"m={self.m}), not {system.name!r} (steps={system.steps}, n={system.n}, m={system.m})")
        have = system_digest(system)
        if self.system_digest is not None and have != self.system_digest:
            raise SimgapError(f"certificate is for a different model named {self.system_name!r}: its model digest "
                              f"is {self.system_digest[:16]}..., this system's is {str(have)[:16]}... (a refined "
                              f"system with other effects or coefficients?)")

    def nominal_system(self):
        """The nominal model the certificate was made for, rebuilt from what it records (a built-in
        or plugin name, or the embedded system file / refined system; never a file path), checked
        against the recorded digest; None for a system defined in Python only."""
        from ..systems import is_named
        from ..system_ref import resolve_system
        ref = self.system_ref if self.system_ref is not None else self.system_name
        if not (isinstance(ref, dict) or is_named(ref)):
            return None
        s = resolve_system(ref, self.steps, paths=False)
        if self.inputs is not None and self.inputs.shape[1] == s.m:
            import dataclasses
            s = dataclasses.replace(s, inputs=self.inputs)
        self.check_system(s)
        return s

    # ----- JSON ------------------------------------------------------------------------
    def to_dict(self) -> dict:
        """The JSON content, ``digest`` included."""
        sc = self.scope_confidences()
        d = {
            "format": FORMAT, "version": VERSION,
            "system": {"name": self.system_name, "steps": self.steps, "state_names": list(self.state_names),
                       "input_names": list(self.input_names), "x_lo": self.x_lo.tolist(),
                       "x_hi": self.x_hi.tolist(), "angle_dims": list(self.angle_dims),
                       "inputs": None if self.inputs is None else self.inputs.tolist(),
                       **({} if self.system_digest is None else {"digest": self.system_digest}),
                       **({} if self.system_ref is None else {"ref": self.system_ref})},
            "epsilon": self.epsilon, "n_runs": self.n_runs, "K": self.K, "method": self.method,
            "options": self.options, "dims": [d.to_dict() for d in self.dims],
            "per_dim_confidence": self.per_dim_confidence, "joint_confidence": self.joint_confidence,
            "confidence_scope": self.scope, "pointwise_joint_confidence": sc["pointwise"],
            "simultaneous_joint_confidence": sc["simultaneous"], "statement": self.statement(),
            "gamma_constant": self.constant().tolist(), "provenance": self.provenance,
            "lipschitz_term": self.lipschitz_term,
        }
        if self.radii is not None:
            d["radii"] = np.asarray(self.radii, float).tolist()
        if self.region is not None:  # only when present: certificates over X keep their content
            d["region"] = [np.asarray(b, float).tolist() for b in self.region]
        if self.region_boxes is not None:  # likewise
            d["region_boxes"] = [np.asarray(b, float).tolist() for b in self.region_boxes]
        if self.continuous:
            d["input_box"] = [np.asarray(b, float).tolist() for b in self.input_box]
            d["input_radii"] = np.asarray(self.input_radii, float).tolist()
            d["input_terms"] = self.input_terms().tolist()
        d["digest"] = fileio.content_digest(d)
        return d

    @property
    def digest(self) -> str:
        """sha256 of the certificate's content (what its file records as ``digest``)."""
        return self.to_dict()["digest"]

    def save(self, path, sign_key: Optional[str] = None) -> Path:
        """Write JSON atomically (temp file in the same folder, then rename); signed over its digest
        with ``sign_key`` or $SIMGAP_SIGNING_KEY when one is given (:mod:`simgap.signing`)."""
        from .. import signing

        d = self.to_dict()
        key = signing.signing_key(sign_key)
        if key:
            d["signature"] = signing.sign(d["digest"], key)
        return fileio.write_json(path, d)

    @classmethod
    def from_dict(cls, d: dict, source: str = "certificate") -> "Certificate":
        """Rebuild a certificate from its JSON content, verifying its digest (see :func:`verify`)."""
        if not isinstance(d, dict) or d.get("format") != FORMAT:
            raise SimgapError(f"{source}: not a simgap certificate (missing format tag)")
        if d.get("version") != VERSION:
            raise SimgapError(f"{source}: certificate version {d.get('version')} is not supported (need {VERSION}: "
                              f"files without a content digest are refused; certify the data again)")
        cert = cls._from_dict(d)
        verify(d, cert, source)
        from .. import signing
        signing.check(d, source)  # a signature by a trusted key, when $SIMGAP_TRUSTED_KEYS is set
        return cert

    @classmethod
    def _from_dict(cls, d: dict) -> "Certificate":
        s = _field(d, "system", dict, "certificate")
        for key in ("state_names", "input_names", "x_lo", "x_hi", "angle_dims"):
            _field(s, key, list, "certificate system")
        entries = _field(d, "dims", list, "certificate")
        for i, e in enumerate(entries):
            if not isinstance(e, dict):
                raise SimgapError(f"certificate is malformed: dims[{i}] must be an object, got {_kind(e)}")
            _field(e, "terms", list, f"certificate dims[{i}]")
        try:
            names = _Names(len(s["state_names"]), len(s["input_names"]), s["state_names"], s["input_names"])
            dims = []
            for e in entries:
                basis = Basis(names, e["terms"])
                q = np.asarray(e["q"], dtype=float)
                if q.shape != (len(basis),) or not np.all(np.isfinite(q)):
                    raise SimgapError("certificate: q does not match its basis or is not finite")
                dims.append(DimCertificate(
                    terms=list(e["terms"]), q=q, delta1=float(e["delta1"]), delta2=float(e["delta2"]),
                    beta1=None if e["beta1"] is None else float(e["beta1"]),
                    beta2=None if e["beta2"] is None else float(e["beta2"]), beta_v=float(e["beta_v"]),
                    Mhat=None if e["Mhat"] is None else float(e["Mhat"]), L_f=float(e["L_f"]),
                    L_fhat=float(e["L_fhat"]), L_2=float(e["L_2"]), lipschitz_how=e["lipschitz_how"],
                    repair=float(e["repair"]), eta=float(e["eta"]), gap_max=float(e["gap_max"]), scp=e["scp"],
                    basis=basis, **_gap_fields(e, names)))
            if len(dims) != names.n:
                raise SimgapError(f"certificate: {len(dims)} dimension entries for {names.n} states")
            return cls(system_name=s["name"], steps=int(s["steps"]), state_names=tuple(s["state_names"]),
                       input_names=tuple(s["input_names"]), x_lo=np.asarray(s["x_lo"], float),
                       x_hi=np.asarray(s["x_hi"], float), angle_dims=tuple(s["angle_dims"]),
                       epsilon=float(d["epsilon"]), n_runs=int(d["n_runs"]), K=int(d["K"]), method=d["method"],
                       options=d["options"], dims=dims, provenance=d["provenance"],
                       inputs=None if s.get("inputs") is None else np.asarray(s["inputs"], float).reshape(-1, names.m),
                       system_digest=s.get("digest"),
                       system_ref=s.get("ref") if isinstance(s.get("ref"), dict) else None,
                       **_term_fields(d, names))
        except SimgapError:
            raise
        except KeyError as e:
            raise SimgapError(f"certificate is malformed: missing field {e}") from None
        except (TypeError, ValueError) as e:
            raise SimgapError(f"certificate is malformed: a field has the wrong type ({e})") from None

    # ----- text ------------------------------------------------------------------------
    def summary(self) -> str:
        """A readable table of the certificate."""
        lines = [f"certificate: system {self.system_name} (steps={self.steps}), method {self.method}, "
                 f"eps={self.epsilon:g}, N1hat={self.n_runs}, K={self.K} (x_r,u) pairs",
                 f"data hash {self.provenance.get('dataset_hash', '?')}"]
        beyond = self.options.get("beyond_paper") or []
        if beyond:
            lines.append("options beyond the paper: " + "; ".join(beyond))
        for note in self.options.get("notes") or []:
            lines.append("note: " + note)
        cols = ["dim", "max gap", "delta1", "delta2", "beta1", "beta2", "Mhat", "L_f", "Lhat_fhat", "L_2",
                "Lx*eps", "gamma min", "gamma max", "conf"]
        if self.lipschitz_term == "gap":
            cols[10] = "L term"
        w = [10] + [11] * (len(cols) - 1)
        fmt = lambda v: "-" if v is None else (v if isinstance(v, str) else f"{v:.4g}")
        row = lambda vals: "".join(f"{fmt(v):<{w[0]}}" if k == 0 else f"{fmt(v):>{w[k]}}" for k, v in enumerate(vals))
        hdr = row(cols)
        lines += [hdr, "-" * len(hdr)]
        lt = self.lipschitz_terms()
        for i, (name, d) in enumerate(zip(self.state_names, self.dims)):
            lo, hi = d.scp.get("gamma_range_on_data", [float("nan")] * 2)
            lines.append(row([name, d.gap_max, d.delta1, d.delta2, d.beta1, d.beta2, d.Mhat, d.L_f, d.L_fhat, d.L_2,
                              lt[i], lo, hi, d.confidence]))
        gt = self.gap_terms()
        if gt is not None:
            used = self.lipschitz_term
            lines.append("")
            which = "the smaller per dimension" if used == "gap" else "the paper's"
            lines.append(f"Lipschitz term side by side (gamma uses {which}; the gap's own term is beyond the paper): "
                         f"paper (L_f + Lhat_fhat + L_2) eps with eps = {self.epsilon:g}; gap sum_j (L_ij + L_2,ij) eps_j with eps_j = "
                         + ", ".join(f"{nm} {r:.4g}" for nm, r in zip(self.state_names, self.radii)))
            cols2 = ["dim", "paper term", "gap term", "gamma max", "gamma max"] + [f"L[{nm}]" for nm in self.state_names]
            sub = ["", "", "", "(paper)", "(gap)"] + [""] * self.n
            w2 = [10] + [12] * (len(cols2) - 1)
            row2 = lambda vals: "".join(f"{fmt(v):<{w2[0]}}" if k == 0 else f"{fmt(v):>{w2[k]}}"
                                        for k, v in enumerate(vals))
            lines += [row2(cols2), row2(sub), "-" * sum(w2)]
            pt, lt = self.paper_terms(), self.lipschitz_terms()
            for i, (name, d) in enumerate(zip(self.state_names, self.dims)):
                hi = d.scp.get("gamma_range_on_data", [float("nan")] * 2)[1] - lt[i]
                paper_hi, gap_hi = hi + pt[i], hi + min(gt[i], pt[i])
                lines.append(row2([name, pt[i], gt[i], paper_hi, gap_hi, *d.L_gap]))
            if self.continuous:
                lines.append("continuous inputs (beyond the paper): u anywhere in ["
                             + ", ".join(f"{a:g}..{b:g}" for a, b in zip(*self.input_box)) + "] adds "
                             + ", ".join(f"{nm} {v:.4g}" for nm, v in zip(self.state_names, self.input_terms())))
        jc = self.joint_confidence
        lines.append("joint confidence (Theorem 2): " + ("not stated (deterministic baseline)" if jc is None
                                                         else f"{jc:.4f} ({100 * jc:.2f} %), {self.scope}" if jc > 0
                                                         else f"{confidence_text(jc)}, {self.scope}"))
        if self.region is not None:
            lines.append(f"region (local certificate): gamma holds on {self.region_text()} only (the data's "
                         "[collect] region); a set leaving it is refused")
        if self.region_boxes is not None:
            lines.append(f"  ... and there in the union of {len(self.region_boxes[0])} boxes along a tube only (a cover "
                         "along the tube); a set inside none of them is refused")
        lines.append(self.statement())
        const = self.constant()
        for i, (name, d) in enumerate(zip(self.state_names, self.dims)):
            terms = " ".join(f"{c:+.4g}*{t}" if t != "1" else f"{c:+.4g}" for c, t in zip(d.q, d.terms) if c != 0)
            lines.append(f"gamma_{name}(x,u) = {const[i]:.4g} + [{terms}]")
        return "\n".join(lines)


def confidence_text(c: Optional[float], K: Optional[int] = None) -> str:
    """A confidence for people: the number when it is > 0, else "vacuous" with why (never a negative
    number: a union bound above 1 states nothing, it is not a negative probability)."""
    if c is None:
        return "not stated"
    if c > 0:
        return f"{c:.4f}"
    rows = f" over K = {K} rows" if K else ""
    return (f"vacuous (the union bound{rows} sums the failure probabilities to more than 1: it states nothing; "
            "certify with uniform = true (--uniform) for a statement over all rows at once)")


def _finite_list(v, size: int, what: str) -> List[float]:
    a = np.asarray(v, dtype=float)
    if a.shape != (size,) or not np.all(np.isfinite(a)) or np.any(a < 0):
        raise SimgapError(f"certificate is malformed: {what} must be {size} finite numbers >= 0")
    return a.tolist()


def _gap_fields(e: dict, names) -> dict:
    """The per-dimension entries of the gap's own Lipschitz term, checked (absent in paper-only files)."""
    if e.get("L_gap") is None:
        return {}
    out = {"L_gap": _finite_list(e["L_gap"], names.n, "L_gap"), "L2_x": _finite_list(e["L2_x"], names.n, "L2_x"),
           "L_gap_u": _finite_list(e["L_gap_u"], names.m, "L_gap_u"), "gap_how": e.get("gap_how")}
    out["L2_u"] = None if e.get("L2_u") is None else _finite_list(e["L2_u"], names.m, "L2_u")
    return out


def _term_fields(d: dict, names) -> dict:
    term = d.get("lipschitz_term", "paper")
    if term not in ("paper", "gap"):
        raise SimgapError(f"certificate is malformed: lipschitz_term {term!r}")
    out = {"lipschitz_term": term}
    if d.get("radii") is not None:
        out["radii"] = np.asarray(_finite_list(d["radii"], names.n, "radii"))
    if d.get("input_box") is not None:
        box = d["input_box"]
        if not (isinstance(box, list) and len(box) == 2):
            raise SimgapError("certificate is malformed: input_box must be [lo, hi]")
        lo, hi = (np.asarray(b, float) for b in box)
        if lo.shape != (names.m,) or hi.shape != (names.m,) or not np.all(np.isfinite(lo + hi)) or np.any(lo > hi):
            raise SimgapError("certificate is malformed: input_box needs finite lo <= hi per input")
        out["input_box"] = (lo, hi)
        out["input_radii"] = np.asarray(_finite_list(d.get("input_radii"), names.m, "input_radii"))
    if d.get("region") is not None:
        box = d["region"]
        if not (isinstance(box, list) and len(box) == 2):
            raise SimgapError("certificate is malformed: region must be [lo, hi]")
        lo, hi = (np.asarray(b, float) for b in box)
        if lo.shape != (names.n,) or hi.shape != (names.n,) or not np.all(np.isfinite(lo + hi)) or np.any(lo >= hi):
            raise SimgapError("certificate is malformed: region needs finite lo < hi per state")
        out["region"] = (lo, hi)
    if d.get("region_boxes") is not None:
        box = d["region_boxes"]
        if "region" not in out or not (isinstance(box, list) and len(box) == 2):
            raise SimgapError("certificate is malformed: region_boxes must be [lo, hi] beside a region")
        try:
            lo, hi = (np.asarray(b, float) for b in box)
        except (TypeError, ValueError):
            raise SimgapError("certificate is malformed: region_boxes must hold numbers") from None
        if lo.ndim != 2 or lo.shape != hi.shape or lo.shape[1] != names.n or not np.all(np.isfinite(lo + hi)) \
                or np.any(lo >= hi):
            raise SimgapError("certificate is malformed: region_boxes needs (B, n) finite lo < hi")
        rlo, rhi = out["region"]
        if not (np.allclose(lo.min(axis=0), rlo) and np.allclose(hi.max(axis=0), rhi)):
            raise SimgapError("certificate is malformed: region is not the hull of region_boxes")
        out["region_boxes"] = (lo, hi)
    if term == "gap" and "radii" not in out:
        raise SimgapError("certificate is malformed: lipschitz_term 'gap' without radii")
    return out


def verify(d: dict, cert: Certificate, source: str = "certificate") -> None:
    """Refuse a certificate whose content no longer matches its digest, naming what does not fit.

    Derived fields (confidences, gamma's constant part) are recomputed from the parts and
    compared first, so a typical edit is named; any other change shows as a digest mismatch.
    """
    derived = cert.to_dict()
    bad = []
    for k in ("per_dim_confidence", "joint_confidence", "pointwise_joint_confidence",
              "simultaneous_joint_confidence", "gamma_constant", "input_terms"):
        if not _same(d.get(k), derived.get(k)):
            bad.append(f"{k} is {d.get(k)!r} in the file but {derived.get(k)!r} from its parts")
    want = d.get("digest")
    have = fileio.content_digest({k: v for k, v in d.items() if k not in ("digest", "signature")})
    if not isinstance(want, str):
        bad.append("it has no content digest")
    elif want != have:
        bad.append(f"its content digest is {have[:16]}... but the file records {want[:16]}...")
    if bad:
        raise SimgapError(f"{source} was modified after it was written (refused): " + "; ".join(bad))


def _same(a, b) -> bool:
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, (int, float)) and isinstance(b, (int, float)) and not isinstance(a, bool):
        return bool(np.isclose(a, b, rtol=1e-12, atol=1e-15))
    return a == b


def load(path, dataset=None) -> Certificate:
    """Load a certificate JSON, verifying its digest; with ``dataset``, check its content hash matches."""
    from ..file_guard import read_json
    path = Path(path)
    d = read_json(path, "certificate")
    cert = Certificate.from_dict(d, source=f"certificate {str(path)!r}")
    if dataset is not None:
        want = cert.provenance.get("dataset_hash", "")
        have = dataset.hash
        if want != have:
            raise SimgapError(f"certificate {str(path)!r} was made from data set {want!r}, "
                              f"but the given data set has hash {have!r}")
        check_region_matches(cert, dataset, f"certificate {str(path)!r}")
    return cert


def check_region_matches(cert: Certificate, dataset, what: str) -> None:
    """Refuse a certificate whose region is not the one its data set's collection covered (the
    manifest's cover region, X without one): the data's hash does not cover the certificate's own
    region, so a file whose region was widened and its digest recomputed would otherwise claim gamma
    where no data were collected."""
    from .pipeline import dataset_region
    data = dataset_region(dataset)
    if data is None and cert.region is None:
        return
    same = data is not None and cert.region is not None and all(
        np.allclose(np.asarray(h, float), np.asarray(w, float), rtol=0, atol=1e-12) for h, w in zip(cert.region, data))
    if not same:
        names = dataset.system.state_names
        fmt = lambda b: "X (no region)" if b is None else " x ".join(  # noqa: E731
            f"{nm} [{lo:g}, {hi:g}]" for nm, lo, hi in zip(names, *b))
        raise SimgapError(f"{what} claims gamma over {fmt(cert.region)}, but its data set was collected over "
                          f"{fmt(data)}: refused (the certificate was edited, or belongs to other data)")
