"""The compiler: a system file's expression trees -> numba kernels (the one code generator).

Input is the tuple tree of :mod:`simgap.expr` (``("const", v) | ("var", j) | ("neg", a) |
("add"|"sub"|"mul"|"div", a, b) | ("pow", a, p) | ("fn", name, a, ...) | ("cmp", op, a, b)``),
already parsed against the allow-list, with parameters folded and definitions inlined
(:func:`simgap.system_file.model_trees`). The compiler emits Python source for numba from that
tree only: every node kind is checked against an allow-list while emitting, constants are written
with ``repr(float)`` of a finite float, variables as integer array indices, function names map to
fixed code fragments of this module, and the names of the generated locals are numbers. No text a
user wrote is ever copied into the source (a tree that holds anything else is refused with
:class:`~simgap.errors.SimgapError`), so compiling a hostile file executes nothing it says.

Identical sub-trees are emitted once (hash-consing: the tree becomes a DAG of numbered nodes), so
the definitions a file shares between formulas (``det``, ``M12`` of the reacher) are computed once
per evaluation, as in the numpy path.

Three kernels:

* :func:`interval_kernel` -> ``closed_loop(xlo, xhi, ulo, uhi, K, tau, substeps, steps,
  continuous)``: the whole :meth:`simgap.synthesis.interval_map.IntervalMap.closed_loop` (every
  base period, RK4 substep and stage, value box and interval Jacobian d y / d x0 in midpoint-radius
  form) for a batch of boxes in ONE call. The right-hand side's value box and interval Jacobian are
  the forward-mode interval arithmetic of :meth:`simgap.certify.basis.Term.interval_grad`, node for
  node (the same interval formulas, the same operation order), with the derivative carried only
  for the variables a node depends on (structural zeros are skipped: the numpy path adds exact
  zeros there). Transcendental functions are the C library's (numpy's SIMD tan/exp differ in the
  last bit for ~1 % of arguments) and the interval matrix products sum in another order, so the
  results may differ from the numpy path by a few units in the last place; the enclosure's radius
  is widened by the same relative 1e-9 plus 1e-12 as the numpy path (``REL_WIDEN``, ``ABS_WIDEN``),
  far above those differences. One difference is deliberate: the numpy interval product counts
  every NaN endpoint product as 0 (meant for 0 * inf); the kernel does so only for 0 * inf, every
  interval helper keeps a NaN endpoint NaN (min and max would drop it), and a NaN anywhere (a
  formula outside its domain, inf - inf) makes the box unbounded, which is never narrower.
* :func:`values_kernel` -> ``values(ZL, ZH)``: interval values (no derivatives) of a list of
  formulas over boxes of z, :meth:`simgap.certify.basis.Term.interval` for every term of a basis at
  once (the certificate's gamma over a box, :meth:`simgap.certify.basis.Basis.value_bounds`).
* :func:`point_kernel` -> ``step(X, U, tau, nint, continuous)``: the model's step (``nint`` RK4 substeps of a
  continuous file in :func:`~simgap.runge_kutta.rk4_integrate`'s operation order, or the
  discrete map) bit for bit equal to the numpy evaluation: no fast-math, the same operations in
  the same order. Only trees whose every function gives numpy's bits in numba are compiled
  (:data:`POINT_EXACT`: + - * /, sin, cos, sqrt, abs, powers 0, 1, 2, -1, 0.5, comparisons, where,
  minimum, maximum, clip; numpy's own SIMD exp, tan, tanh, log, arctan and general powers differ
  from the C library's in the last bit, measured); :func:`point_exact` says why not otherwise.

Compiled code is cached on disk: the generated module is written to
``$SIMGAP_KERNEL_CACHE`` (default ``~/.cache/simgap/kernels``) as ``k<digest>.py``, the digest a
sha256 of the source and numba's version, and imported by path with numba's ``cache=True``, so a
second process loads the machine code instead of compiling it (measured in docs/synthesis.md,
"Speed"). Whether to compile at all follows :mod:`simgap.jit`'s modes (``SIMGAP_JIT``)
with a break-even per use (:class:`Twin`).
"""

from __future__ import annotations

import hashlib
import importlib.util
import math
import os
import sys
import tempfile
from pathlib import Path
from typing import Optional

from .errors import SimgapError

#: functions the point kernel evaluates with numpy's bits (module docstring)
POINT_EXACT = frozenset({"sin", "cos", "sqrt", "abs", "minimum", "maximum", "clip", "where"})
#: exponents for which numba's pow gives np.power's bits
POINT_EXACT_POWERS = frozenset({0.0, 1.0, 2.0, -1.0, 0.5})
#: functions with an interval extension and derivative in the interval kernel (basis.FUNCS)
INTERVAL_FUNCS = frozenset({"sin", "cos", "tan", "exp", "abs", "sqrt", "tanh", "sign"})
_ARITH = {"add": "+", "sub": "-", "mul": "*", "div": "/"}
_CMP = {"lt": "<", "le": "<=", "gt": ">", "ge": ">="}
_POINT_FN = {"sin": "math.sin", "cos": "math.cos", "sqrt": "np.sqrt", "abs": "abs",
             "minimum": "_minimum", "maximum": "_maximum", "clip": "_clip", "where": "_where"}


# ---------------------------------------------------------------------------------------------
# trees -> DAG (hash-consed, validated)
# ---------------------------------------------------------------------------------------------

def _num(v) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(float(v)):
        raise SimgapError(f"compiler: constant {v!r} is not a finite number")
    return float(v)


class _Dag:
    """Nodes numbered in evaluation order (children first), identical sub-trees once.

    ``nodes[i]`` = (kind, payload, child ids); payload: the float of a const, the column of a var,
    the exponent of a pow, the function or comparison name. ``deps[i]``: the columns (< ``nvar``)
    node i depends on, i.e. where its derivative may be non-zero."""

    def __init__(self, nvar: int, fns):
        self.nvar, self.fns = int(nvar), frozenset(fns)
        self.nodes, self.deps, self.ids, self.trees = [], [], {}, []

    def add(self, t) -> int:
        if not isinstance(t, tuple) or not t or not isinstance(t[0], str):
            raise SimgapError(f"compiler: {type(t).__name__} is not an expression node")
        k = t[0]
        if k == "const":
            key = ("const", _num(t[1]), ())
        elif k == "var":
            if isinstance(t[1], bool) or not isinstance(t[1], int) or t[1] < 0:
                raise SimgapError(f"compiler: variable index {t[1]!r} is not a column")
            key = ("var", int(t[1]), ())
        elif k == "neg":
            key = ("neg", None, (self.add(t[1]),))
        elif k in _ARITH:
            key = (k, None, (self.add(t[1]), self.add(t[2])))
        elif k == "pow":
            p = _num(t[2])
            key = ("pow", int(p) if p == int(p) else p, (self.add(t[1]),))
        elif k == "fn":
            if t[1] not in self.fns:
                raise SimgapError(f"compiler: function {t[1]!r} is not compiled here "
                                  f"(allowed: {', '.join(sorted(self.fns))})")
            key = ("fn", str(t[1]), tuple(self.add(a) for a in t[2:]))
        elif k == "cmp":
            if t[1] not in _CMP or "cmp" not in self.fns:
                raise SimgapError(f"compiler: comparison {t[1]!r} is not compiled here")
            key = ("cmp", str(t[1]), (self.add(t[2]), self.add(t[3])))
        else:
            raise SimgapError(f"compiler: node kind {k!r} is not allowed")
        if key not in self.ids:
            self.ids[key] = len(self.nodes)
            self.nodes.append(key)
            self.trees.append(t)
            d = {key[1]} if k == "var" and key[1] < self.nvar else set()
            for c in key[2]:
                d |= self.deps[c]
            self.deps.append(frozenset(d))
        return self.ids[key]


# ---------------------------------------------------------------------------------------------
# interval kernel
# ---------------------------------------------------------------------------------------------

_INTERVAL_PRELUDE = '''
import math
import numpy as np
from simgap.jit import njit

PI = math.pi
TWO_PI = 2.0 * math.pi
INF = math.inf


@njit(error_model="numpy")
def _p(a, b):
    """a * b with 0 * inf = 0 (basis._imul's convention); NaN otherwise propagates."""
    c = a * b
    if c != c and a == a and b == b:
        return 0.0
    return c


@njit(error_model="numpy")
def _imul(al, ah, bl, bh):
    c0, c1, c2, c3 = _p(al, bl), _p(al, bh), _p(ah, bl), _p(ah, bh)
    if c0 != c0 or c1 != c1 or c2 != c2 or c3 != c3:
        return math.nan, math.nan
    return min(min(c0, c1), min(c2, c3)), max(max(c0, c1), max(c2, c3))


@njit(error_model="numpy")
def _idiv(al, ah, bl, bh):
    if bl <= 0.0 and bh >= 0.0:
        return -INF, INF
    return _imul(al, ah, 1.0 / bh, 1.0 / bl)


@njit(error_model="numpy")
def _ipow(al, ah, k):
    """[a]^k for an integer k (basis._ipow)."""
    if al != al or ah != ah:  # NaN endpoints stay NaN (min/max would drop them)
        return math.nan, math.nan
    if k == 0:
        return 1.0, 1.0
    a = abs(k)
    pl, ph = al ** a, ah ** a
    if a % 2 == 0:
        pl, ph = (0.0 if (al <= 0.0 and ah >= 0.0) else min(pl, ph)), max(pl, ph)
    if k < 0:
        return _idiv(1.0, 1.0, pl, ph)
    return pl, ph


@njit(error_model="numpy")
def _contains(lo, hi, c, period):
    return np.ceil((lo - c) / period) <= np.floor((hi - c) / period)


@njit(error_model="numpy")
def _isin(lo, hi):
    if not (lo == lo and hi == hi) or math.isinf(lo) or math.isinf(hi):
        return (-1.0, 1.0) if (lo == lo and hi == hi) else (math.nan, math.nan)
    wide = (hi - lo) >= TWO_PI
    sl, sh = math.sin(lo), math.sin(hi)
    rl, rh = min(sl, sh), max(sl, sh)
    if wide or _contains(lo, hi, PI / 2, TWO_PI):
        rh = 1.0
    if wide or _contains(lo, hi, -PI / 2, TWO_PI):
        rl = -1.0
    return rl, rh


@njit(error_model="numpy")
def _icos(lo, hi):
    return _isin(lo + PI / 2, hi + PI / 2)


@njit(error_model="numpy")
def _itan(lo, hi):
    if not (lo == lo and hi == hi):
        return math.nan, math.nan
    if math.isinf(lo) or math.isinf(hi) or _contains(lo, hi, PI / 2, PI) or (hi - lo) >= PI:
        return -INF, INF
    return math.tan(lo), math.tan(hi)


@njit(error_model="numpy")
def _isign(x):
    if x > 0.0:
        return 1.0
    if x < 0.0:
        return -1.0
    return x


@njit(error_model="numpy")
def _iabs(al, ah):
    if al != al or ah != ah:
        return math.nan, math.nan
    lo = 0.0 if (al <= 0.0 and ah >= 0.0) else min(abs(al), abs(ah))
    return lo, max(abs(al), abs(ah))


@njit(error_model="numpy")
def _isqrt(al, ah):
    if al != al or ah != ah:
        return math.nan, math.nan
    return np.sqrt(max(al, 0.0)), np.sqrt(ah)


@njit(error_model="numpy")
def _dsqrt(al, ah):
    if al != al or ah != ah:
        return math.nan, math.nan
    if al > 0.0:
        return 0.5 / np.sqrt(ah), 0.5 / np.sqrt(al)
    return 0.0, INF


@njit(error_model="numpy")
def _dabs(al, ah):
    if al != al or ah != ah:
        return math.nan, math.nan
    gl, gh = _isign(al), _isign(ah)
    if al <= 0.0:
        gl = -1.0
    if ah >= 0.0:
        gh = 1.0
    return gl, gh


@njit(error_model="numpy")
def _dsign(al, ah):
    if al != al or ah != ah:
        return math.nan, math.nan
    if al <= 0.0 and ah >= 0.0:
        return -INF, INF
    return 0.0, 0.0
'''

_INTERVAL_DRIVER = '''

@njit(error_model="numpy")
def _field(yl, yh, ul, uh, dt, K, Yc, Yr, vl, vh, gl, gh, oc, orr):
    """Value box (vl, vh) and derivative [oc +- orr] = G_x [Yc +- Yr] + G_u K of the right-hand side
    (IntervalMap.closed_loop's field); False when unbounded."""
    n, m = yl.shape[0], ul.shape[0]
    _rhs(yl, yh, ul, uh, dt, vl, vh, gl, gh)
    for i in range(n):
        if not (math.isfinite(vl[i]) and math.isfinite(vh[i])):
            return False
        for j in range(n + m):
            if not (math.isfinite(gl[i, j]) and math.isfinite(gh[i, j])):
                return False
    for i in range(n):
        for j in range(n):
            c = 0.0
            r = 0.0
            for k in range(n):
                gc = 0.5 * (gl[i, k] + gh[i, k])
                gr = 0.5 * (gh[i, k] - gl[i, k])
                c += gc * Yc[k, j]
                r += abs(gc) * Yr[k, j] + gr * abs(Yc[k, j]) + gr * Yr[k, j]
            for k in range(m):
                gc = 0.5 * (gl[i, n + k] + gh[i, n + k])
                gr = 0.5 * (gh[i, n + k] - gl[i, n + k])
                c += gc * K[k, j]
                r += gr * abs(K[k, j])
            oc[i, j] = c
            orr[i, j] = r
    return True


@njit(error_model="numpy")
def closed_loop(xlo, xhi, ulo, uhi, K, tau, substeps, steps, continuous, rel_widen, abs_widen):
    """IntervalMap.closed_loop for the boxes [xlo, xhi] (B, n), inputs [ulo, uhi] (B, m), u = u* + K (x - x*):
    (lo, hi) (B, n) and (Dc, Dr) (B, n, n); an unbounded box gets lo = -inf, hi = inf, Dc = 0, Dr = inf."""
    B, n = xlo.shape
    m = ulo.shape[1]
    LO, HI = np.empty((B, n)), np.empty((B, n))
    DC, DR = np.empty((B, n, n)), np.empty((B, n, n))
    h = tau / substeps
    w = (1.0, 2.0, 2.0, 1.0)
    kl, kh = np.empty((4, n)), np.empty((4, n))
    kc, kr = np.empty((4, n, n)), np.empty((4, n, n))
    gl, gh = np.empty((n, n + m)), np.empty((n, n + m))
    lo, hi, sl, sh = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    Dc, Dr, Sc, Sr = np.empty((n, n)), np.empty((n, n)), np.empty((n, n)), np.empty((n, n))
    for b in range(B):
        ul, uh = ulo[b], uhi[b]
        lo[:] = xlo[b]
        hi[:] = xhi[b]
        Dc[:] = 0.0
        Dr[:] = 0.0
        for i in range(n):
            Dc[i, i] = 1.0
        ok = True
        for _ in range(steps):
            if not ok:
                break
            if not continuous:
                ok = _field(lo, hi, ul, uh, tau, K, Dc, Dr, kl[0], kh[0], gl, gh, kc[0], kr[0])
                lo[:] = kl[0]
                hi[:] = kh[0]
                Dc[:] = kc[0]
                Dr[:] = kr[0]
                continue
            for _s in range(substeps):
                ok = _field(lo, hi, ul, uh, tau, K, Dc, Dr, kl[0], kh[0], gl, gh, kc[0], kr[0])
                for st in range(1, 4):
                    if not ok:
                        break
                    a = h if st == 3 else h / 2
                    for i in range(n):
                        sl[i] = lo[i] + a * kl[st - 1, i]
                        sh[i] = hi[i] + a * kh[st - 1, i]
                        for j in range(n):
                            Sc[i, j] = Dc[i, j] + a * kc[st - 1, i, j]
                            Sr[i, j] = Dr[i, j] + a * kr[st - 1, i, j]
                    ok = _field(sl, sh, ul, uh, tau, K, Sc, Sr, kl[st], kh[st], gl, gh, kc[st], kr[st])
                if not ok:
                    break
                for i in range(n):
                    al, ah = 0.0, 0.0
                    for st in range(4):
                        al = al + w[st] * kl[st, i]
                        ah = ah + w[st] * kh[st, i]
                    lo[i] = lo[i] + h / 6 * al
                    hi[i] = hi[i] + h / 6 * ah
                    for j in range(n):
                        ac, ar = 0.0, 0.0
                        for st in range(4):
                            ac = ac + w[st] * kc[st, i, j]
                            ar = ar + w[st] * kr[st, i, j]
                        Dc[i, j] = Dc[i, j] + h / 6 * ac
                        Dr[i, j] = Dr[i, j] + h / 6 * ar
        for i in range(n):
            for j in range(n):
                r = Dr[i, j] + rel_widen * abs(Dc[i, j]) + abs_widen
                fin = ok and math.isfinite(Dc[i, j]) and math.isfinite(r)
                DR[b, i, j] = r if fin else INF
                DC[b, i, j] = Dc[i, j] if fin else 0.0
            if ok and math.isfinite(lo[i]) and math.isfinite(hi[i]):
                span = rel_widen * max(abs(lo[i]), abs(hi[i])) + abs_widen
                LO[b, i] = lo[i] - span
                HI[b, i] = hi[i] + span
            else:
                LO[b, i] = -INF
                HI[b, i] = INF
    return LO, HI, DC, DR
'''


#: a function's value box over its argument's box (l{a}, h{a}) (basis._ifn)
_FN_VALUE = {"sin": "_isin(l{a}, h{a})", "cos": "_icos(l{a}, h{a})", "tan": "_itan(l{a}, h{a})",
             "sqrt": "_isqrt(l{a}, h{a})", "abs": "_iabs(l{a}, h{a})", "exp": "math.exp(l{a}), math.exp(h{a})",
             "tanh": "math.tanh(l{a}), math.tanh(h{a})", "sign": "_isign(l{a}), _isign(h{a})"}
#: lines giving its derivative's box (gl, gh) from the argument's and the value's (l{i}, h{i}) (basis._ig)
_FN_SLOPE = {"sin": ["gl, gh = _icos(l{a}, h{a})"],
             "cos": ["gl, gh = _isin(l{a}, h{a})", "gl, gh = -gh, -gl"],
             "tan": ["sl, sh = _ipow(l{i}, h{i}, 2)", "gl, gh = 1.0 + sl, 1.0 + sh"],
             "exp": ["gl, gh = l{i}, h{i}"],
             "tanh": ["sl, sh = _ipow(l{i}, h{i}, 2)", "gl, gh = 1.0 - sh, 1.0 - sl"],
             "abs": ["gl, gh = _dabs(l{a}, h{a})"], "sqrt": ["gl, gh = _dsqrt(l{a}, h{a})"],
             "sign": ["gl, gh = _dsign(l{a}, h{a})"]}


class _IntervalEmitter:
    """Straight-line interval code of one right-hand side: node i -> locals ``l{i}``, ``h{i}`` (value
    box) and ``a{i}_{j}``, ``b{i}_{j}`` (derivative box along column j, only for j in deps[i])."""

    def __init__(self, dag: _Dag, n: int, m: int, flat: bool = False):
        self.dag, self.n, self.m, self.flat = dag, n, m, flat
        self.lines = []

    def emit(self, line):
        self.lines.append("    " + line)

    def node(self, i):
        kind, pay, ch = self.dag.nodes[i]
        deps = sorted(self.dag.deps[i])
        e = self.emit
        n, m = self.n, self.m
        if kind == "const":
            e(f"l{i} = h{i} = {pay!r}")
            return
        if kind == "var" and self.flat:
            e(f"l{i}, h{i} = zl[{pay}], zh[{pay}]")
            return
        if kind == "var":
            if pay < n:
                e(f"l{i}, h{i} = yl[{pay}], yh[{pay}]")
            elif pay < n + m:
                e(f"l{i}, h{i} = ul[{pay - n}], uh[{pay - n}]")
            elif pay == n + m:
                e(f"l{i} = h{i} = dt")
            else:
                raise SimgapError(f"compiler: column {pay} is not x, u or dt")
            if pay < n + m:
                e(f"a{i}_{pay} = b{i}_{pay} = 1.0")
            return
        if kind == "neg":
            a = ch[0]
            e(f"l{i}, h{i} = -h{a}, -l{a}")
            for j in deps:
                e(f"a{i}_{j}, b{i}_{j} = -b{a}_{j}, -a{a}_{j}")
            return
        if kind in ("add", "sub"):
            a, b = ch
            da, db = self.dag.deps[a], self.dag.deps[b]
            if kind == "add":
                e(f"l{i}, h{i} = l{a} + l{b}, h{a} + h{b}")
            else:
                e(f"l{i}, h{i} = l{a} - h{b}, h{a} - l{b}")
            for j in deps:
                if j in da and j in db:
                    e(f"a{i}_{j}, b{i}_{j} = a{a}_{j} + a{b}_{j}, b{a}_{j} + b{b}_{j}" if kind == "add" else
                      f"a{i}_{j}, b{i}_{j} = a{a}_{j} - b{b}_{j}, b{a}_{j} - a{b}_{j}")
                elif j in da:
                    e(f"a{i}_{j}, b{i}_{j} = a{a}_{j}, b{a}_{j}")
                else:
                    e(f"a{i}_{j}, b{i}_{j} = a{b}_{j}, b{b}_{j}" if kind == "add" else
                      f"a{i}_{j}, b{i}_{j} = -b{b}_{j}, -a{b}_{j}")
            return
        if kind in ("mul", "div"):  # (ab)' = a'b + ab';  (a/b)' = (a'b - ab') / b^2
            a, b = ch
            da, db = self.dag.deps[a], self.dag.deps[b]
            if kind == "div" and deps:
                e(f"s{i}l, s{i}h = _ipow(l{b}, h{b}, 2)")
            for j in deps:
                if j in da:
                    e(f"p1, q1 = _imul(a{a}_{j}, b{a}_{j}, l{b}, h{b})")
                if j in db:
                    e(f"p2, q2 = _imul(l{a}, h{a}, a{b}_{j}, b{b}_{j})")
                both = j in da and j in db
                if kind == "mul":
                    lo, hi = ("p1 + p2", "q1 + q2") if both else ("p1", "q1") if j in da else ("p2", "q2")
                    e(f"a{i}_{j}, b{i}_{j} = {lo}, {hi}")
                else:
                    lo, hi = ("p1 - q2", "q1 - p2") if both else ("p1", "q1") if j in da else ("-q2", "-p2")
                    e(f"a{i}_{j}, b{i}_{j} = _idiv({lo}, {hi}, s{i}l, s{i}h)")
            e(f"l{i}, h{i} = {'_imul' if kind == 'mul' else '_idiv'}(l{a}, h{a}, l{b}, h{b})")
            return
        if kind == "pow":
            a = ch[0]
            if pay != int(pay):
                raise SimgapError(f"compiler: the interval kernel needs integer powers, got {pay!r}")
            p = int(pay)
            e(f"l{i}, h{i} = _ipow(l{a}, h{a}, {p})")
            if deps and p != 0:
                e(f"cl, ch = _ipow(l{a}, h{a}, {p - 1})")
                e(f"cl, ch = _imul(cl, ch, {float(p)!r}, {float(p)!r})")
                for j in deps:
                    e(f"a{i}_{j}, b{i}_{j} = _imul(cl, ch, a{a}_{j}, b{a}_{j})")
            elif deps:
                for j in deps:
                    e(f"a{i}_{j} = b{i}_{j} = 0.0")
            return
        if kind == "fn":  # (g(a))' = g'(a) a'
            a = ch[0]
            if pay not in _FN_VALUE:
                raise SimgapError(f"compiler: function {pay!r} has no interval extension here")
            e(f"l{i}, h{i} = " + _FN_VALUE[pay].format(a=a))
            if deps:
                for line in _FN_SLOPE[pay]:
                    e(line.format(a=a, i=i))
                for j in deps:
                    e(f"a{i}_{j}, b{i}_{j} = _imul(gl, gh, a{a}_{j}, b{a}_{j})")
            return
        raise SimgapError(f"compiler: node kind {kind!r} has no interval extension")


def interval_source(trees, n: int, m: int) -> str:
    """Source of the interval module for formulas ``trees`` over z = [x (n), u (m), dt]: ``_rhs`` (value
    box and interval Jacobian over the n + m columns) and the ``closed_loop`` driver."""
    dag = _Dag(n + m, INTERVAL_FUNCS)
    roots = [dag.add(t) for t in trees]
    if len(roots) != n:
        raise SimgapError(f"compiler: {len(roots)} formulas for {n} states")
    em = _IntervalEmitter(dag, int(n), int(m))
    for i in range(len(dag.nodes)):
        em.node(i)
    for s, r in enumerate(roots):
        em.emit(f"vl[{s}], vh[{s}] = l{r}, h{r}")
        for j in range(n + m):
            em.emit(f"GL[{s}, {j}], GH[{s}, {j}] = " + (f"a{r}_{j}, b{r}_{j}" if j in dag.deps[r] else "0.0, 0.0"))
    body = "\n".join(em.lines) or "    pass"
    rhs = ('\n\n@njit(error_model="numpy")\ndef _rhs(yl, yh, ul, uh, dt, vl, vh, GL, GH):\n'
           '    """Generated: value box and interval Jacobian of the formulas (one box)."""\n' + body + "\n")
    return _INTERVAL_PRELUDE + rhs + _INTERVAL_DRIVER


_VALUES_DRIVER = '''

@njit(error_model="numpy")
def values(ZL, ZH):
    """Interval values (lo, hi) (B, T) of the T formulas over the boxes [ZL, ZH] (B, width)."""
    B = ZL.shape[0]
    LO, HI = np.empty((B, NT)), np.empty((B, NT))
    for b in range(B):
        _values(ZL[b], ZH[b], LO[b], HI[b])
    return LO, HI
'''


def values_source(trees, width: int) -> str:
    """Source of a value-interval module (no derivatives): ``values(ZL, ZH) -> (lo, hi)`` (B, T) for
    formulas over the columns of z (``width``), :meth:`simgap.certify.basis.Term.interval` for each."""
    dag = _Dag(0, INTERVAL_FUNCS)          # nvar 0: no derivative is carried
    roots = [dag.add(t) for t in trees]
    em = _IntervalEmitter(dag, 0, 0, flat=True)
    for i, (kind, pay, _) in enumerate(dag.nodes):
        if kind == "var" and pay >= width:
            raise SimgapError(f"compiler: column {pay} is outside z's {width}")
        em.node(i)
    for s, r in enumerate(roots):
        em.emit(f"lo[{s}], hi[{s}] = l{r}, h{r}")
    body = "\n".join(em.lines) or "    pass"
    fn = ('\n\n@njit(error_model="numpy")\ndef _values(zl, zh, lo, hi):\n'
          '    """Generated: interval values of the formulas (one box)."""\n' + body + "\n")
    return _INTERVAL_PRELUDE + f"\nNT = {len(roots)}\n" + fn + _VALUES_DRIVER


def values_kernel(trees, width: int):
    """The compiled ``values(ZL, ZH)`` of :func:`values_source`."""
    return load(values_source(trees, width)).values


#: numpy seconds after which a :class:`Twin` compiles its kernel (auto mode): about a first compile of
#: a 4-state closed loop on the loaded 2-core machine (the 6-state double pendulum's takes ~40 s)
AUTO_SECONDS = 5.0
#: numpy seconds after which a :class:`Twin` loads its kernel from the disk cache (a load: ~1 s)
LOAD_SECONDS = 1.0


class Twin:
    """A compiled twin of a numpy evaluation, loaded when it pays (the ``SIMGAP_JIT`` modes of
    :mod:`simgap.jit`).

    ``source(*args)`` builds the source (a module-level function and plain data: a Twin pickles,
    without its loaded kernel); ``attr`` names the kernel in it. :meth:`get` is asked before each
    evaluation of ``rows`` rows and returns the kernel or None (the caller evaluates in numpy, and
    those rows are counted): SIMGAP_JIT=1 always, 0 never; auto (numba installed) once the rows
    done in numpy plus these reach ``auto_rows`` (about what a first compile costs, seconds) or
    the job declared with :func:`simgap.jit.expected_work` does, and already from
    ``early`` rows (default ``auto_rows / 20``) or when numba is imported anyway, if the kernel is
    in the disk cache (a load costs numba's start, ~0.5 s CPU and ~100 MB).

    Rows are a poor measure of the numpy path's cost when the formulas are long: one row of the
    6-state double pendulum's closed loop costs about 100 x a 4-state row (its 3 x 3 adjugate), so the
    caller may also report the seconds its numpy evaluations took (:meth:`spent`): auto mode then
    compiles once they reach :data:`AUTO_SECONDS` (ski rental: at most about twice the better
    choice's cost) and loads a cached kernel once they reach :data:`LOAD_SECONDS`."""

    def __init__(self, source, args: tuple, attr: str, auto_rows: int, early: Optional[int] = None):
        self.source, self.args, self.attr, self.auto_rows = source, tuple(args), attr, int(auto_rows)
        self.early = int(auto_rows) // 20 if early is None else int(early)
        self.done, self.fn, self.cached, self.seconds = 0, None, None, 0.0

    def spent(self, seconds: float) -> None:
        """Count ``seconds`` of numpy evaluation (the cost the compiled twin would save)."""
        self.seconds += float(seconds)

    def __getstate__(self):  # the compiled code stays in its process (loaded again on use)
        return dict(self.__dict__, fn=None)

    def make(self) -> str:
        return self.source(*self.args)

    def get(self, rows: int = 0):
        if self.fn is not None:
            return self.fn
        from . import jit
        m = jit.mode()
        if m == "0":
            return None
        if m == "auto":
            if not jit.available():
                return None
            due = max(self.done + rows, jit._WORK.get())
            if due < self.auto_rows and self.seconds < AUTO_SECONDS:
                early = due >= self.early or "numba" in sys.modules or self.seconds >= LOAD_SECONDS
                if early and self.cached is None:
                    self.cached = is_cached(self.make())
                if not (early and self.cached):
                    self.done += rows
                    return None
        else:
            jit.use_compiled()  # SIMGAP_JIT=1 without numba: the message naming it
        self.fn = getattr(load(self.make()), self.attr)
        return self.fn


# ---------------------------------------------------------------------------------------------
# point kernel
# ---------------------------------------------------------------------------------------------

_POINT_PRELUDE = '''
import math
import numpy as np
from simgap.jit import njit


@njit(error_model="numpy")
def _minimum(a, b):
    if a != a:
        return a
    if b != b:
        return b
    return a if a <= b else b


@njit(error_model="numpy")
def _maximum(a, b):
    if a != a:
        return a
    if b != b:
        return b
    return a if a >= b else b


@njit(error_model="numpy")
def _clip(a, lo, hi):
    return _minimum(_maximum(a, lo), hi)


@njit(error_model="numpy")
def _where(c, a, b):
    return a if c != 0.0 else b
'''

_POINT_DRIVER = '''

@njit(error_model="numpy")
def step(X, U, tau, nint, continuous):
    """The model's step for every row: nint RK4 substeps of rk4_integrate's order, or the map."""
    B, n = X.shape
    out = np.empty((B, n))
    x, acc, tmp, k = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    h = tau / nint
    h2 = h / 2
    h6 = h / 6
    for b in range(B):
        u = U[b]
        x[:] = X[b]
        if not continuous:
            _rhs(x, u, tau, k)
            out[b] = k
            continue
        for _ in range(nint):
            _rhs(x, u, tau, k)
            for i in range(n):
                acc[i] = k[i]
                tmp[i] = k[i] * h2 + x[i]
            _rhs(tmp, u, tau, k)
            for i in range(n):
                acc[i] += k[i] + k[i]
                tmp[i] = k[i] * h2 + x[i]
            _rhs(tmp, u, tau, k)
            for i in range(n):
                acc[i] += k[i] + k[i]
                tmp[i] = k[i] * h + x[i]
            _rhs(tmp, u, tau, k)
            for i in range(n):
                acc[i] += k[i]
                acc[i] *= h6
                x[i] += acc[i]
        out[b] = x
    return out
'''


def point_exact(trees) -> str:
    """'' when the point kernel gives numpy's bits for these trees, else why not (a function or power
    whose numba result differs from numpy's in the last bit)."""
    from .expr import walk
    for t in trees:
        for node in walk(t):
            if node[0] == "fn" and node[1] not in POINT_EXACT:
                return f"{node[1]}() (numpy's own implementation differs from the C library's in the last bit)"
            if node[0] == "pow" and float(node[2]) not in POINT_EXACT_POWERS:
                return f"the power {node[2]} (numpy's pow differs from the C library's in the last bit)"
    return ""


#: the point formulas' syntax per target: numba's Python and C (the same nodes, the same operations)
_SYNTAX = {
    "py": {"fn": _POINT_FN, "pow": "math.pow({a}, {p})", "cmp": "1.0 if {a} {op} {b} else 0.0",
           "line": "    v{i} = {rhs}", "out": "    out[{s}] = v{r}", "hoisted": "hv[{k}]"},
    "c": {"fn": {"sin": "sin", "cos": "cos", "sqrt": "sqrt", "abs": "fabs", "minimum": "_minimum",
                 "maximum": "_maximum", "clip": "_clip", "where": "_where"},
          "pow": "pow({a}, {p})", "cmp": "(({a} {op} {b}) ? 1.0 : 0.0)",
          "line": "    const double v{i} = {rhs};", "out": "    out[{s}] = v{r};", "hoisted": "hv[{k}]"},
}


#: functions the C kernel remembers per node (argument bits -> value): RK4's middle stages, and the
#: first stage after the last, often evaluate them at the same argument (a heading held by a
#: state-free rate); the same argument gives the same bits, so this changes no result
MEMO = frozenset({"sin", "cos"})


def _point_lines(dag: _Dag, roots, n: int, m: int, target: str, hoisted: Optional[dict] = None,
                 memo: Optional[list] = None) -> list:
    """Straight-line code of the formulas ``roots`` at one point (x, u, dt) -> ``out``, in the syntax of
    ``target`` ("py" for numba, "c"); the nodes in ``hoisted`` (node id -> column) are read from ``hv``
    instead (values computed once per input by numpy, :func:`hoist`), and only the nodes the outputs
    need are emitted. The same operations in the same order in both targets (numpy's bits). With a
    list ``memo`` (C only), the :data:`MEMO` functions read and fill the slots ``mk``/``mv`` (their
    function names are appended to ``memo``, one per slot)."""
    syn, hoisted = _SYNTAX[target], hoisted or {}
    need, stack = set(), list(roots)
    while stack:  # the nodes reachable from the roots without passing a hoisted one
        i = stack.pop()
        if i not in need:
            need.add(i)
            if i not in hoisted:
                stack.extend(dag.nodes[i][2])
    lines = []
    for i in sorted(need):
        kind, pay, ch = dag.nodes[i]
        if i in hoisted:
            rhs = syn["hoisted"].format(k=hoisted[i])
        elif kind == "const":
            rhs = repr(pay)
        elif kind == "var":
            if pay < n:
                rhs = f"x[{pay}]"
            elif pay < n + m:
                rhs = f"u[{pay - n}]"
            elif pay == n + m:
                rhs = "dt"
            else:
                raise SimgapError(f"compiler: column {pay} is not x, u or dt")
        elif kind == "neg":
            rhs = f"-v{ch[0]}"
        elif kind in _ARITH:
            rhs = f"v{ch[0]} {_ARITH[kind]} v{ch[1]}"
        elif kind == "pow":  # the C library's pow: np.power's bits for POINT_EXACT_POWERS
            rhs = syn["pow"].format(a=f"v{ch[0]}", p=repr(float(pay)))
        elif kind == "fn" and memo is not None and pay in MEMO:
            j = len(memo)
            memo.append(pay)
            a = f"v{ch[0]}"
            lines.append(f"    double v{i}; {{ uint64_t b_; memcpy(&b_, &{a}, 8); if (b_ == mk[{j}]) v{i} = mv[{j}]; "
                         f"else {{ v{i} = {syn['fn'][pay]}({a}); mk[{j}] = b_; mv[{j}] = v{i}; }} }}")
            continue
        elif kind == "fn":
            rhs = f"{syn['fn'][pay]}({', '.join(f'v{c}' for c in ch)})"
        else:  # cmp
            rhs = syn["cmp"].format(a=f"v{ch[0]}", op=_CMP[pay], b=f"v{ch[1]}")
        lines.append(syn["line"].format(i=i, rhs=rhs))
    lines += [syn["out"].format(s=s, r=r) for s, r in enumerate(roots)]
    return lines


def _not_exact(dag: _Dag, ids) -> str:
    """'' when every node of ``ids`` gives numpy's bits compiled, else why not (:func:`point_exact`)."""
    for i in ids:
        kind, pay, _ = dag.nodes[i]
        if kind == "fn" and pay not in POINT_EXACT:
            return f"{pay}() (numpy's own implementation differs from the C library's in the last bit)"
        if kind == "pow" and float(pay) not in POINT_EXACT_POWERS:
            return f"the power {pay} (numpy's pow differs from the C library's in the last bit)"
    return ""


def point_source(trees, n: int, m: int) -> str:
    """Source of the point module: ``_rhs(x, u, dt, out)`` and the ``step`` driver."""
    from .expr import FUNCTIONS
    dag = _Dag(n + m, frozenset(FUNCTIONS) | {"cmp"})   # validates every node first
    roots = [dag.add(t) for t in trees]
    why = point_exact(trees)
    if why:
        raise SimgapError(f"compiler: no bit-identical point kernel for {why}")
    rhs_fn = ('\n\n@njit(error_model="numpy")\ndef _rhs(x, u, dt, out):\n'
              '    """Generated: the formulas at one point."""\n' + "\n".join(_point_lines(dag, roots, n, m, "py")) + "\n")
    return _POINT_PRELUDE + rhs_fn + _POINT_DRIVER


# ---------------------------------------------------------------------------------------------
# grid kernel (C): the abstraction's successor boxes of a system file
# ---------------------------------------------------------------------------------------------

def hoist(trees, n: int, m: int):
    """Split the formulas for the grid kernel: ``(dag, roots, hoisted)`` with ``hoisted`` the maximal
    sub-trees that read no state (inputs, dt and constants only: held over a period) as
    {node id: column}; :func:`hoisted_trees` gives their trees, which numpy evaluates once per input.
    Numpy's values are the oracle's own, so these may use any function (the vehicle's tan and arctan);
    the rest must be :data:`POINT_EXACT` (refused otherwise, naming the function)."""
    from .expr import FUNCTIONS
    dag = _Dag(n, frozenset(FUNCTIONS) | {"cmp"})  # deps: the state columns a node reads
    roots = [dag.add(t) for t in trees]
    if len(roots) != n:
        raise SimgapError(f"compiler: {len(roots)} formulas for {n} states")
    for kind, pay, _ in dag.nodes:
        if kind == "var" and pay > n + m:
            raise SimgapError(f"compiler: column {pay} is not x, u or dt")
    state_free = [not dag.deps[i] and dag.nodes[i][0] not in ("const", "var") for i in range(len(dag.nodes))]
    top = set(i for i in roots if state_free[i])
    for i, (_, _, ch) in enumerate(dag.nodes):
        if not state_free[i]:
            top.update(c for c in ch if state_free[c])
    hoisted = {i: k for k, i in enumerate(sorted(top))}
    kept, stack = set(), list(roots)
    while stack:
        i = stack.pop()
        if i not in kept and i not in hoisted:
            kept.add(i)
            stack.extend(dag.nodes[i][2])
    why = _not_exact(dag, kept)
    if why:
        raise SimgapError(f"compiler: no bit-identical grid kernel for {why} of the state")
    return dag, roots, hoisted


def hoisted_trees(dag: _Dag, hoisted: dict) -> list:
    """The trees of the hoisted nodes, in column order (for numpy's evaluation)."""
    return [dag.trees[i] for i in sorted(hoisted, key=hoisted.get)]


_GRID_PRELUDE = r"""/* Generated by simgap.compile from a system file's expression trees (no text of the file). */
#include <math.h>
#include <stdint.h>
#include <string.h>

static inline double _minimum(double a, double b) { if (a != a) return a; if (b != b) return b; return a <= b ? a : b; }
static inline double _maximum(double a, double b) { if (a != a) return a; if (b != b) return b; return a >= b ? a : b; }
static inline double _clip(double a, double lo, double hi) { return _minimum(_maximum(a, lo), hi); }
static inline double _where(double c, double a, double b) { return c != 0.0 ? a : b; }
"""

_GRID_DRIVER = r"""
/* LANES pairs at a time: each pair's RK4 is a chain of dependent operations (latency-bound); the
   lanes' chains are independent, so the processor overlaps them. Every lane computes exactly its
   own pair's operations in the same order (the same bits as one pair at a time). */

/* one base period in place for nl lanes: nint RK4 substeps in rk4_integrate's operation order, or the map */
static void _period(int nl, double *x, const double *const *u, const double *const *hv, double tau, int64_t nint,
                    int64_t continuous, uint64_t *mk, double *mv)
{
    double k[LANES * NX], acc[LANES * NX], tmp[LANES * NX];
    const int w = nl * NX;
    if (!continuous) {
        _rhs(nl, x, u, hv, tau, k, mk, mv);
        for (int i = 0; i < w; i++) x[i] = k[i];
        return;
    }
    const double h = tau / (double)nint, h2 = h / 2, h6 = h / 6;
    for (int64_t s = 0; s < nint; s++) {
        _rhs(nl, x, u, hv, tau, k, mk, mv);
        for (int i = 0; i < w; i++) { acc[i] = k[i]; tmp[i] = k[i] * h2 + x[i]; }
        _rhs(nl, tmp, u, hv, tau, k, mk, mv);
        for (int i = 0; i < w; i++) { acc[i] += k[i] + k[i]; tmp[i] = k[i] * h2 + x[i]; }
        _rhs(nl, tmp, u, hv, tau, k, mk, mv);
        for (int i = 0; i < w; i++) { acc[i] += k[i] + k[i]; tmp[i] = k[i] * h + x[i]; }
        _rhs(nl, tmp, u, hv, tau, k, mk, mv);
        for (int i = 0; i < w; i++) { acc[i] += k[i]; acc[i] *= h6; x[i] += acc[i]; }
    }
}

/* abstraction._cell_offset of one value: floor(v) - base, NaN -> 0, clipped to +-limit before and after */
static double _offset(double v, double base, double limit)
{
    v = floor(v);
    if (v != v) v = 0.0;
    v = (v < -limit ? -limit : (v > limit ? limit : v)) - base;
    return v < -limit ? -limit : (v > limit ? limit : v);
}

/* The successor boxes of the classes k0 .. k1-1 (every input each), build_abstraction's numpy loop
   per pair: centre first + i eta (i: the class's multi-index over cshape, 0 in the invariant
   dimensions), `steps` base periods of the model, the radius R[input] (the growth bound, per
   input), left = (x - r) - z, right = (x + r) + z, the offsets floor((left - first + eta/2) / eta) - i
   (and right's) into lo/hi (int8, or int16 when wide), valid = x and r finite and the box inside
   (dom_lo, dom_hi) outside the invariant dimensions. mm[0], mm[1]: the least and greatest offset. */
void grid_boxes(int64_t k0, int64_t k1, const int64_t *cshape, const double *first, const double *eta,
                int64_t M, const double *U, int64_t nh, const double *H, const double *R,
                const double *z, const double *dom_lo, const double *dom_hi, const uint8_t *inv,
                double tau, int64_t nint, int64_t steps, int64_t continuous, double limit, int64_t wide,
                void *lo_out, void *hi_out, uint8_t *ok_out, double *mm)
{
    double x[LANES * NX], vmin = limit, vmax = -limit;
    int64_t mi[LANES * NX];
    const double *ul[LANES], *hl[LANES];
    MEMO_SLOTS
    int8_t *lo8 = (int8_t *)lo_out, *hi8 = (int8_t *)hi_out;
    int16_t *lo16 = (int16_t *)lo_out, *hi16 = (int16_t *)hi_out;
    const int64_t P = (k1 - k0) * M;
    int64_t cur[NX], jn = 0, rest = k0;  /* the next pair's class multi-index and input (an odometer: no division a pair) */
    for (int d = NX - 1; d >= 0; d--) { cur[d] = rest % cshape[d]; rest /= cshape[d]; }
    for (int64_t p0 = 0; p0 < P; p0 += LANES) {
        const int nl = P - p0 < LANES ? (int)(P - p0) : LANES;
        for (int l = 0; l < nl; l++) {
            for (int d = 0; d < NX; d++) {
                mi[l * NX + d] = cur[d];
                x[l * NX + d] = first[d] + (double)cur[d] * eta[d];
            }
            ul[l] = U + jn * NU;
            hl[l] = H + jn * nh;
            if (++jn == M) {
                jn = 0;
                for (int d = NX - 1; d >= 0 && ++cur[d] == cshape[d]; d--) cur[d] = 0;
            }
        }
        for (int64_t s = 0; s < steps; s++) _period(nl, x, ul, hl, tau, nint, continuous, mk, mv);
        for (int l = 0; l < nl; l++) {
            const int64_t p = p0 + l, j = p % M;
            int good = 1, out = 0;
            for (int d = 0; d < NX; d++) {
                const double xd = x[l * NX + d], rd = R[j * NX + d];
                if (!(isfinite(xd) && isfinite(rd))) good = 0;
                const double left = xd - rd - z[d], right = xd + rd + z[d];
                if (!inv[d] && (left <= dom_lo[d] || right >= dom_hi[d])) out = 1;
                const double base = (double)mi[l * NX + d];
                const double a = _offset((left - first[d] + eta[d] / 2) / eta[d], base, limit);
                const double b = _offset((right - first[d] + eta[d] / 2) / eta[d], base, limit);
                if (a < vmin) vmin = a;
                if (b < vmin) vmin = b;
                if (a > vmax) vmax = a;
                if (b > vmax) vmax = b;
                if (wide) { lo16[p * NX + d] = (int16_t)a; hi16[p * NX + d] = (int16_t)b; }
                else { lo8[p * NX + d] = (int8_t)(a < -128 ? -128 : a > 127 ? 127 : a);
                       hi8[p * NX + d] = (int8_t)(b < -128 ? -128 : b > 127 ? 127 : b); }
            }
            ok_out[p] = (uint8_t)(good && !out);
        }
    }
    mm[0] = vmin;
    mm[1] = vmax;
}

/* The posts alone (the tests' view of the same code): row p from X[p] under input J[p], `steps` periods */
void grid_posts(int64_t P, const double *X, const int64_t *J, const double *U, int64_t nh, const double *H,
                double tau, int64_t nint, int64_t steps, int64_t continuous, double *out)
{
    double x[LANES * NX];
    const double *ul[LANES], *hl[LANES];
    MEMO_SLOTS
    for (int64_t p0 = 0; p0 < P; p0 += LANES) {
        const int nl = P - p0 < LANES ? (int)(P - p0) : LANES;
        for (int l = 0; l < nl; l++) {
            for (int d = 0; d < NX; d++) x[l * NX + d] = X[(p0 + l) * NX + d];
            ul[l] = U + J[p0 + l] * NU;
            hl[l] = H + J[p0 + l] * nh;
        }
        for (int64_t s = 0; s < steps; s++) _period(nl, x, ul, hl, tau, nint, continuous, mk, mv);
        for (int l = 0; l < nl; l++)
            for (int d = 0; d < NX; d++) out[(p0 + l) * NX + d] = x[l * NX + d];
    }
}
"""


C_FN_MEMO = {"sin": "sin", "cos": "cos"}


def grid_source(trees, n: int, m: int) -> tuple:
    """C source of the grid kernel ``grid_boxes`` for the formulas ``trees`` (one per state, over
    z = [x (n), u (m), dt]) and the hoisted sub-trees numpy evaluates per input (:func:`hoist`)."""
    dag, roots, hoisted = hoist(trees, n, m)
    memo = []
    body = _point_lines(dag, roots, n, m, "c", hoisted, memo)
    rhs = ("\n/* the formulas at nl points (lanes); x, u, hv, out, mk, mv: one lane's */\n"
           "static inline void _rhs(int nl, const double *X, const double *const *U, const double *const *HV, double dt,\n"
           "                        double *OUT, uint64_t *MK, double *MV)\n{\n"
           "    for (int l = 0; l < nl; l++) {\n"
           "    const double *x = X + l * NX, *u = U[l], *hv = HV[l];\n"
           "    double *out = OUT + l * NX;\n"
           "    uint64_t *mk = MK + l * MS;\n"
           "    double *mv = MV + l * MS;\n"
           "    (void)x; (void)u; (void)hv; (void)dt; (void)mk; (void)mv;\n" + "\n".join(body) + "\n    }\n}\n")
    # every lane's memo slots start at the argument 0.0 with the function's value there
    slots = len(memo) or 1
    init = "".join(f" mk[l * MS + {j}] = 0; mv[l * MS + {j}] = {C_FN_MEMO[f]}(0.0);" for j, f in enumerate(memo))
    # lanes (measured, 2-core x86-64, gcc 12 -O3): arithmetic only (dcdc) 4 lanes 0.114 s vs 1 lane 0.151 s
    # a pass; with sin/cos calls (the vehicle) 1 lane 1.40 s vs 4 lanes 2.1 s (the calls serialize anyway)
    defs = (f"#define NX {int(n)}\n#define NU {int(m)}\n#define MS {slots}\n#define LANES {1 if memo else 4}\n"
            f"#define MEMO_SLOTS uint64_t mk[4 * MS]; double mv[4 * MS]; (void)mk; (void)mv; "
            f"for (int l = 0; l < 4; l++) {{{init} }}\n")
    src = _GRID_PRELUDE + defs + rhs + _GRID_DRIVER
    return src, hoisted_trees(dag, hoisted)


# ---------------------------------------------------------------------------------------------
# the disk cache
# ---------------------------------------------------------------------------------------------

def cache_dir() -> Path:
    """``$SIMGAP_KERNEL_CACHE`` or ``~/.cache/simgap/kernels`` (a temporary directory when neither is writable)."""
    d = Path(os.environ.get("SIMGAP_KERNEL_CACHE") or Path.home() / ".cache" / "simgap" / "kernels")
    try:
        d.mkdir(parents=True, exist_ok=True)
        if os.access(d, os.W_OK):
            return d
    except OSError:
        pass
    d = Path(tempfile.gettempdir()) / f"simgap-kernels-{os.getuid()}"
    d.mkdir(parents=True, exist_ok=True)
    return d


_LOADED: dict = {}


_NUMBA_VERSION: list = []


def _digest(source: str) -> str:
    """sha256 of numba's version and the source (the version read once, without importing numba)."""
    if not _NUMBA_VERSION:
        from importlib.metadata import version
        _NUMBA_VERSION.append(version("numba"))
    return hashlib.sha256((_NUMBA_VERSION[0] + "\0" + source).encode()).hexdigest()[:32]


def is_cached(source: str) -> bool:
    """Whether numba's machine code for ``source`` is in the disk cache (its index file exists)."""
    digest = _digest(source)
    return digest in _LOADED or any((cache_dir() / "__pycache__").glob(f"k{digest}.*.nbi"))


def load(source: str):
    """The module of generated ``source``: written once to the cache directory as ``k<digest>.py``
    (digest: sha256 of the source and numba's version; written to a temporary name and renamed, so a
    concurrent process never imports half a file) and imported by path, so numba's ``cache=True``
    stores its machine code next to it."""
    digest = _digest(source)
    if digest in _LOADED:
        return _LOADED[digest]
    d = cache_dir()
    path = d / f"k{digest}.py"
    if not path.exists() or path.read_text() != source:
        fd, tmp = tempfile.mkstemp(dir=d, suffix=".tmp")
        with os.fdopen(fd, "w") as f:
            f.write(source)
        os.replace(tmp, path)
    name = f"simgap_kernel_{digest}"
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    _LOADED[digest] = mod
    return mod


def interval_kernel(trees, n: int, m: int):
    """The compiled ``closed_loop`` of :func:`interval_source` (compiled or loaded from the disk cache)."""
    return load(interval_source(trees, n, m)).closed_loop


def point_kernel(trees, n: int, m: int):
    """The compiled ``step(X, U, tau, nint, continuous)`` of :func:`point_source`."""
    return load(point_source(trees, n, m)).step


# ---------------------------------------------------------------------------------------------
# C kernels: compiled by the system's C compiler, cached, loaded with ctypes
# ---------------------------------------------------------------------------------------------

#: flags for numpy's bits: no fast-math, no fused multiply-add (x86-64's baseline has none; other
#: targets contract a * b + c unless told not to)
C_FLAGS = ("-O3", "-fPIC", "-shared", "-fno-fast-math", "-ffp-contract=off")
_C_LOADED: dict = {}


def c_compiler() -> Optional[str]:
    """The C compiler (``$CC``, else cc or gcc on the PATH), or None."""
    import shutil
    for name in (os.environ.get("CC"), "cc", "gcc"):
        if name:
            path = shutil.which(name)
            if path:
                return os.path.realpath(path)
    return None


def _c_digest(source: str, cc: str) -> str:
    """sha256 of the source, the flags and the compiler (its path, size and time stamp: a new
    compiler build gives a new digest)."""
    st = os.stat(cc)
    ident = f"{cc}\0{st.st_size}\0{st.st_mtime_ns}\0{' '.join(C_FLAGS)}\0"
    return hashlib.sha256((ident + source).encode()).hexdigest()[:32]


def c_cached(source: str) -> bool:
    """Whether the shared library of ``source`` is in the disk cache (no compile needed)."""
    cc = c_compiler()
    if cc is None:
        return False
    digest = _c_digest(source, cc)
    return digest in _C_LOADED or (cache_dir() / f"c{digest}.so").exists()


def load_c(source: str):
    """The ``ctypes.CDLL`` of generated C ``source`` (compiled once into the cache directory as
    ``c<digest>.so``, written under a temporary name and renamed), or None when no C compiler is
    found or it fails (the caller then takes the numpy path, which gives the same bits)."""
    cc = c_compiler()
    if cc is None:
        return None
    digest = _c_digest(source, cc)
    if digest in _C_LOADED:
        return _C_LOADED[digest]
    import ctypes
    d = cache_dir()
    lib = d / f"c{digest}.so"
    if not lib.exists():
        import subprocess
        with tempfile.TemporaryDirectory(dir=d) as tmp:
            src, out = Path(tmp) / "k.c", Path(tmp) / "k.so"
            src.write_text(source)
            r = subprocess.run([cc, *C_FLAGS, "-o", str(out), str(src), "-lm"], capture_output=True, text=True)
            if r.returncode != 0 or not out.exists():
                return None
            os.replace(out, lib)
    _C_LOADED[digest] = ctypes.CDLL(str(lib))
    return _C_LOADED[digest]
