"""Basis functions p_i(x, u) of the simulation-gap function gamma_i = L_x eps + q_i^T p_i(x,u) + delta_2i.

A basis is a list of :class:`Term` s. A term is a small expression over the state and input
variables, parsed SAFELY by the shared allow-list parser :mod:`simgap.expr` (nothing is ever
``eval``-ed):

* numbers, variables ``x1..xn``, ``u1..um`` (1-based) and the system's own state/input names
  (e.g. ``theta``, ``omega``, ``torque`` for the pendulum);
* ``+ - * /``, powers ``**`` or ``^`` with an integer exponent, unary minus;
* functions ``sin cos tan exp abs sqrt tanh sign`` of one argument.

Anything else (attribute access, other calls, comparisons, unknown names, non-integer powers)
raises :class:`~simgap.errors.SimgapError` naming the term.

Every term can be evaluated three ways, all vectorized over a batch:

* :meth:`Term.eval` on points, for the (K, P) design matrix of the scenario program;
* :meth:`Term.interval` on boxes [lo, hi] (sound interval arithmetic), for
  ``Certificate.gamma_upper_box`` used by synthesis;
* :meth:`Term.interval_grad` on boxes: forward-mode interval differentiation, giving sound
  bounds on d p / d x over a box, for the analytic Lipschitz constant L_2 of q^T p.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import List, Sequence, Tuple

import numpy as np

from ..errors import SimgapError
from ..expr import Expr, VarSpace, parse
from ..systems import System

FUNCS = ("sin", "cos", "tan", "exp", "abs", "sqrt", "tanh", "sign")
#: numpy term evaluations (one per term per value_bounds call, whatever its batch: the recursion's
#: per-call cost dominates, about 0.1 ms each) after which one Basis compiles value_bounds in auto
#: mode: about 2 s of numpy, the order of a first compile
AUTO_TERM_CALLS = 20_000
TWO_PI = 2.0 * np.pi


# ---------------------------------------------------------------------------------------
# Parsing: the shared allow-list parser (simgap.expr) with the functions that have interval
# extensions below; no constants, integer powers only, no comparisons or lags.
#   ("const", v) | ("var", j) | ("neg", a) | ("add"|"sub"|"mul"|"div", a, b) | ("pow", a, k)
#   | ("fn", name, a);  j indexes z = [x_1..x_n, u_1..u_m]
# ---------------------------------------------------------------------------------------

def variable_names(system: System) -> dict:
    """Map every accepted variable name to its column in z = [x, u]."""
    return dict(VarSpace.of_system(system).columns)


def term_dimension(key, system: System, one_based: bool, where: str) -> int:
    """The 0-based state dimension a basis term's key names, or -1 for every dimension.

    One spelling works everywhere: a state name (``omega``) or ``all``. Numbers differ by
    place: the command line (``--term 2:EXPR``, ``one_based``) counts from 1; an experiment's
    ``[certify] terms`` table counts from 0 with ``-1`` for all (older files). A number in the
    other place's convention is refused with the spelling to use."""
    k = str(key).strip()
    if k in ("all", "*"):
        return -1
    if k in system.state_names:
        return system.state_names.index(k)
    names = f"a state name ({', '.join(system.state_names)}) or all"
    try:
        v = int(k)
    except ValueError:
        raise SimgapError(f"{where}: {k!r} is not {names}") from None
    if one_based:
        if v == -1:
            raise SimgapError(f"{where}: -1 is the experiment file's key for every dimension; on the command line "
                              "write all:EXPR")
        if not 1 <= v <= system.n:
            raise SimgapError(f"{where}: dimension {v} is not 1..{system.n} (the command line counts from 1; "
                              f"the experiment's terms keys from 0), or use {names}")
        return v - 1
    if not -1 <= v < system.n:
        raise SimgapError(f"{where}: key {v} is not 0..{system.n - 1} or -1 (an experiment's terms keys count from 0, "
                          f"-1 = all; the command line from 1), or use {names}")
    return v


def terms_by_dimension(terms: dict, system: System, where: str = "[certify] terms") -> dict:
    """An experiment's ``[certify] terms`` table ({key: [EXPR, ...]}, keys as :func:`term_dimension`
    with 0-based numbers) as {0-based dimension or -1: [EXPR, ...]}."""
    out: dict = {}
    for k, v in (terms or {}).items():
        out.setdefault(term_dimension(k, system, one_based=False, where=f"{where} key {k!r}"), []).extend(list(v))
    return out


def parse_term(text: str, system: System) -> "Term":
    """Parse one basis term (see module docstring) into a :class:`Term`."""
    e = parse(text, VarSpace.of_system(system), what="basis term", functions=FUNCS, constants=False,
              integer_powers=True)
    return Term(e.text, e.tree)


# ---------------------------------------------------------------------------------------
# Interval helpers (arrays lo <= hi, elementwise; +-inf allowed)
# ---------------------------------------------------------------------------------------

def _imul(al, ah, bl, bh):
    with np.errstate(invalid="ignore", over="ignore"):
        c = [al * bl, al * bh, ah * bl, ah * bh]
    if any(np.isnan(v).any() for v in c):
        c = [np.where(np.isnan(v), 0.0, v) for v in c]  # 0 * inf endpoint products count as 0
    return np.minimum(np.minimum(c[0], c[1]), np.minimum(c[2], c[3])), \
        np.maximum(np.maximum(c[0], c[1]), np.maximum(c[2], c[3]))


def _idiv(al, ah, bl, bh):
    zero_in = (bl <= 0) & (bh >= 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        rl, rh = _imul(al, ah, 1.0 / np.where(zero_in, 1.0, bh), 1.0 / np.where(zero_in, 1.0, bl))
    return np.where(zero_in, -np.inf, rl), np.where(zero_in, np.inf, rh)


def _contains(lo, hi, c, period):
    """Whether [lo, hi] contains c + k*period for some integer k."""
    with np.errstate(invalid="ignore"):
        return np.ceil((lo - c) / period) <= np.floor((hi - c) / period)


def _isin(lo, hi):
    wide = (hi - lo) >= TWO_PI
    sl, sh = np.sin(lo), np.sin(hi)
    rl, rh = np.minimum(sl, sh), np.maximum(sl, sh)
    rh = np.where(wide | _contains(lo, hi, np.pi / 2, TWO_PI), 1.0, rh)
    rl = np.where(wide | _contains(lo, hi, -np.pi / 2, TWO_PI), -1.0, rl)
    return rl, rh


def _ipow(al, ah, k):
    if k == 0:
        return np.ones_like(al), np.ones_like(al)
    if k < 0:
        pl, ph = _ipow(al, ah, -k)
        return _idiv(np.ones_like(pl), np.ones_like(pl), pl, ph)
    with np.errstate(over="ignore"):
        pl, ph = al ** k, ah ** k
    if k % 2 == 1:
        return pl, ph
    lo = np.where((al <= 0) & (ah >= 0), 0.0, np.minimum(pl, ph))
    return lo, np.maximum(pl, ph)


def _ifn(name, al, ah):
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        if name == "sin":
            return _isin(al, ah)
        if name == "cos":
            return _isin(al + np.pi / 2, ah + np.pi / 2)
        if name == "tan":
            pole = _contains(al, ah, np.pi / 2, np.pi) | ((ah - al) >= np.pi)
            return np.where(pole, -np.inf, np.tan(al)), np.where(pole, np.inf, np.tan(ah))
        if name == "exp":
            return np.exp(al), np.exp(ah)
        if name == "tanh":
            return np.tanh(al), np.tanh(ah)
        if name == "sign":
            return np.sign(al), np.sign(ah)
        if name == "abs":
            lo = np.where((al <= 0) & (ah >= 0), 0.0, np.minimum(np.abs(al), np.abs(ah)))
            return lo, np.maximum(np.abs(al), np.abs(ah))
        if name == "sqrt":
            return np.sqrt(np.maximum(al, 0.0)), np.sqrt(ah)  # ah < 0 gives nan: domain error
    raise AssertionError(name)


# ---------------------------------------------------------------------------------------
# Terms
# ---------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Term(Expr):
    """One basis function p(z), z = [x, u] (see module docstring); points: :meth:`Expr.eval`."""

    # ----- boxes -----------------------------------------------------------------------
    def interval(self, zlo: np.ndarray, zhi: np.ndarray, cache: dict | None = None) -> Tuple[np.ndarray, np.ndarray]:
        """Sound bounds (lo, hi), each (B,), of p over the boxes [zlo, zhi] (B, n+m).

        ``cache``: a dict shared by the terms of one basis evaluated on the same boxes (common
        sub-expressions such as x1 or x1^2 are bounded once).
        """
        lo, hi = self._iv(self.tree, zlo, zhi, {} if cache is None else cache)
        B = zlo.shape[0]
        return np.broadcast_to(lo, (B,)).astype(float), np.broadcast_to(hi, (B,)).astype(float)

    def _iv(self, t, zl, zh, cache):
        if t in cache:
            return cache[t]
        out = self._iv1(t, zl, zh, cache)
        cache[t] = out
        return out

    def _iv1(self, t, zl, zh, cache):
        k = t[0]
        if k == "const":
            return np.float64(t[1]), np.float64(t[1])
        if k == "var":
            return zl[:, t[1]], zh[:, t[1]]
        if k == "neg":
            l, h = self._iv(t[1], zl, zh, cache)
            return -h, -l
        if k == "pow":
            return _ipow(*self._iv(t[1], zl, zh, cache), t[2])
        if k == "fn":
            return _ifn(t[1], *self._iv(t[2], zl, zh, cache))
        al, ah = self._iv(t[1], zl, zh, cache)
        bl, bh = self._iv(t[2], zl, zh, cache)
        if k == "add":
            return al + bl, ah + bh
        if k == "sub":
            return al - bh, ah - bl
        if k == "mul":
            return _imul(al, ah, bl, bh)
        return _idiv(al, ah, bl, bh)

    def interval_grad(self, zlo, zhi, dims: Sequence[int]):
        """Sound bounds on p and on d p / d z_j (j in ``dims``) over boxes.

        Returns (lo, hi, dlo, dhi) with lo/hi (B,) and dlo/dhi (B, len(dims)).
        """
        B = zlo.shape[0]
        lo, hi, dl, dh = self._ig(self.tree, zlo, zhi, list(dims))
        D = len(dims)
        return (np.broadcast_to(lo, (B,)).astype(float), np.broadcast_to(hi, (B,)).astype(float),
                np.broadcast_to(dl, (B, D)).astype(float), np.broadcast_to(dh, (B, D)).astype(float))

    def _ig(self, t, zl, zh, dims):
        # forward-mode: each node -> (value lo, value hi, derivative lo (B,D), derivative hi (B,D))
        k = t[0]
        D = len(dims)
        if k == "const":
            z = np.zeros((1, D))
            return np.float64(t[1]), np.float64(t[1]), z, z
        if k == "var":
            d = np.array([[1.0 if j == t[1] else 0.0 for j in dims]])
            return zl[:, t[1]], zh[:, t[1]], d, d
        if k == "neg":
            l, h, dl, dh = self._ig(t[1], zl, zh, dims)
            return -h, -l, -dh, -dl
        if k in ("add", "sub", "mul", "div"):
            al, ah, adl, adh = self._ig(t[1], zl, zh, dims)
            bl, bh, bdl, bdh = self._ig(t[2], zl, zh, dims)
            if k == "add":
                return al + bl, ah + bh, adl + bdl, adh + bdh
            if k == "sub":
                return al - bh, ah - bl, adl - bdh, adh - bdl
            A = (np.asarray(al)[..., None] if np.ndim(al) else al, np.asarray(ah)[..., None] if np.ndim(ah) else ah)
            Bv = (np.asarray(bl)[..., None] if np.ndim(bl) else bl, np.asarray(bh)[..., None] if np.ndim(bh) else bh)
            if k == "mul":  # (ab)' = a'b + ab'
                l1, h1 = _imul(adl, adh, *Bv)
                l2, h2 = _imul(*A, bdl, bdh)
                vl, vh = _imul(al, ah, bl, bh)
                return vl, vh, l1 + l2, h1 + h2
            # (a/b)' = (a'b - ab') / b^2
            l1, h1 = _imul(adl, adh, *Bv)
            l2, h2 = _imul(*A, bdl, bdh)
            sl, sh = _ipow(*Bv, 2)
            nl, nh = _idiv(l1 - h2, h1 - l2, sl, sh)
            vl, vh = _idiv(al, ah, bl, bh)
            return vl, vh, nl, nh
        if k == "pow":
            al, ah, adl, adh = self._ig(t[1], zl, zh, dims)
            p = t[2]
            vl, vh = _ipow(al, ah, p)
            if p == 0:
                z = np.zeros((1, D))
                return vl, vh, z, z
            cl, ch = _ipow(al, ah, p - 1)
            cl, ch = _imul(cl, ch, np.float64(p), np.float64(p))
            dl, dh = _imul(_col(cl), _col(ch), adl, adh)
            return vl, vh, dl, dh
        # functions: (g(a))' = g'(a) a'
        name = t[1]
        al, ah, adl, adh = self._ig(t[2], zl, zh, dims)
        vl, vh = _ifn(name, al, ah)
        with np.errstate(all="ignore"):
            if name == "sin":
                gl, gh = _ifn("cos", al, ah)
            elif name == "cos":
                gl, gh = _ifn("sin", al, ah)
                gl, gh = -gh, -gl
            elif name == "tan":
                sl, sh = _ipow(vl, vh, 2)
                gl, gh = 1.0 + sl, 1.0 + sh
            elif name == "exp":
                gl, gh = vl, vh
            elif name == "tanh":
                sl, sh = _ipow(vl, vh, 2)
                gl, gh = 1.0 - sh, 1.0 - sl
            elif name == "abs":
                gl, gh = np.sign(al) * 1.0, np.sign(ah) * 1.0
                gl = np.where(al <= 0, -1.0, gl)
                gh = np.where(ah >= 0, 1.0, gh)
            elif name == "sqrt":
                pos = np.asarray(al) > 0
                gl = np.where(pos, 0.5 / np.sqrt(np.where(pos, ah, 1.0)), 0.0)
                gh = np.where(pos, 0.5 / np.sqrt(np.where(pos, al, 1.0)), np.inf)
            else:  # sign: derivative 0 away from 0, unbounded across it
                cross = (np.asarray(al) <= 0) & (np.asarray(ah) >= 0)
                gl, gh = np.where(cross, -np.inf, 0.0), np.where(cross, np.inf, 0.0)
        dl, dh = _imul(_col(gl), _col(gh), adl, adh)
        return vl, vh, dl, dh


def _col(a):
    a = np.asarray(a, dtype=float)
    return a[..., None] if a.ndim else a


# ---------------------------------------------------------------------------------------
# Bases
# ---------------------------------------------------------------------------------------

def monomial_names(system: System, degree: int, exclude_dims: Sequence[int] = ()) -> List[str]:
    """All monomials in z = [x1..xn, u1..um] of total degree 0..``degree`` ("1", "x1", "x1*u1", "x2^2", ...).

    ``exclude_dims``: 0-based state dimensions left out (declared invariant: gamma must not depend on them).
    """
    if int(degree) != degree or degree < 0:
        raise SimgapError(f"basis degree must be an integer >= 0, got {degree!r}")
    vars_ = [f"x{i + 1}" for i in range(system.n) if i not in set(exclude_dims)] + \
        [f"u{j + 1}" for j in range(system.m)]
    out = ["1"]
    for d in range(1, int(degree) + 1):
        for combo in itertools.combinations_with_replacement(range(len(vars_)), d):
            counts = {}
            for c in combo:
                counts[c] = counts.get(c, 0) + 1
            out.append("*".join(vars_[c] if k == 1 else f"{vars_[c]}^{k}" for c, k in sorted(counts.items())))
    return out


class Basis:
    """The basis p(x, u) = [p^(1); ...; p^(z)] of one state dimension."""

    def __init__(self, system: System, terms: Sequence[str]):
        if not terms:
            raise SimgapError("basis: no terms")
        self.system = system
        self.terms = [parse_term(t, system) for t in terms]
        from ..compile import Twin, values_source
        self.twin = Twin(values_source, ([t.tree for t in self.terms], system.n + system.m), "values", AUTO_TERM_CALLS)
        seen = set()
        for t in self.terms:
            if t.text in seen:
                raise SimgapError(f"basis: term {t.text!r} appears twice")
            seen.add(t.text)

    @classmethod
    def polynomial(cls, system: System, degree: int, extra: Sequence[str] = (),
                   exclude_dims: Sequence[int] = ()) -> "Basis":
        """Monomials up to total ``degree`` in (x, u) (without ``exclude_dims``) plus user terms ``extra``."""
        return cls(system, monomial_names(system, degree, exclude_dims) + list(extra))

    def uses(self) -> set:
        """Columns of z = [x, u] that some term depends on."""
        return set().union(*(t.columns for t in self.terms))

    @property
    def names(self) -> List[str]:
        return [t.text for t in self.terms]

    def __len__(self):
        return len(self.terms)

    def _z(self, x, u):
        x = np.atleast_2d(np.asarray(x, dtype=float))
        u = np.atleast_2d(np.asarray(u, dtype=float))
        if x.shape[1] != self.system.n or u.shape[1] != self.system.m or x.shape[0] != u.shape[0]:
            raise SimgapError(f"basis: need x (B,{self.system.n}) and u (B,{self.system.m}) with equal B, "
                              f"got {x.shape} and {u.shape}")
        return np.concatenate([x, u], axis=1)

    def design(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Design matrix P (B, z) with P[r, l] = p^(l)(x_r, u_r). Raises if a term is NaN/inf."""
        z = self._z(x, u)
        P = np.empty((z.shape[0], len(self.terms)))
        for l, t in enumerate(self.terms):  # loop over the few terms, vectorized over rows
            P[:, l] = t.eval(z)
            if not np.all(np.isfinite(P[:, l])):
                raise SimgapError(f"basis term {t.text!r} is NaN or inf on {int((~np.isfinite(P[:, l])).sum())} "
                                  f"data rows (outside its domain)")
        return P

    def value_bounds(self, zlo: np.ndarray, zhi: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """Interval bounds of every term over boxes: (lo, hi), each (B, z); compiled
        (:func:`simgap.compile.values_kernel`, the same interval formulas) when it pays
        (:class:`simgap.compile.Twin`)."""
        kern = self.twin.get(len(self.terms))
        if kern is not None:
            return kern(np.ascontiguousarray(zlo, dtype=float), np.ascontiguousarray(zhi, dtype=float))
        lo = np.empty((zlo.shape[0], len(self.terms)))
        hi = np.empty_like(lo)
        cache = {}
        for l, t in enumerate(self.terms):
            lo[:, l], hi[:, l] = t.interval(zlo, zhi, cache)
        return lo, hi

    def upper_box(self, q: np.ndarray, zlo: np.ndarray, zhi: np.ndarray) -> np.ndarray:
        """Sound upper bound of q^T p over boxes [zlo, zhi] (B, n+m) -> (B,)."""
        lo, hi = self.value_bounds(zlo, zhi)
        with np.errstate(invalid="ignore"):
            c = np.where(q > 0, q * hi, np.where(q < 0, q * lo, 0.0))
        out = c.sum(axis=1)
        return np.where(np.isnan(out), np.inf, out)

    def grad_x_bound(self, q: np.ndarray, zlo: np.ndarray, zhi: np.ndarray) -> np.ndarray:
        """Sound bound on |d (q^T p) / d x_j| over boxes -> (B, n)."""
        return self.grad_bound(q, zlo, zhi, range(self.system.n))

    def grad_bound(self, q: np.ndarray, zlo: np.ndarray, zhi: np.ndarray, dims) -> np.ndarray:
        """Sound bound on |d (q^T p) / d z_j| over boxes for z = (x, u) and j in ``dims`` -> (B, len(dims))."""
        dims = list(dims)
        n = len(dims)
        dl = np.zeros((zlo.shape[0], n))
        dh = np.zeros((zlo.shape[0], n))
        for l, t in enumerate(self.terms):
            if q[l] == 0:
                continue
            _, _, gl, gh = t.interval_grad(zlo, zhi, dims)
            a, b = q[l] * gl, q[l] * gh
            dl += np.minimum(a, b)
            dh += np.maximum(a, b)
        out = np.maximum(np.abs(dl), np.abs(dh))
        return np.where(np.isnan(out), np.inf, out)
