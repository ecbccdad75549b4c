"""Safe user expressions: the ONE parser for every formula a user or a file hands to simgap.

Certificate basis terms (``--term DIM:EXPR``, experiment TOML), user effects of the refinement
loop (``--term NAME:STATE:EXPR``) and the effects stored in refined-system JSON files are all
parsed here. The text is parsed with :func:`ast.parse` and converted node by node against an
allow-list into a tree of plain tuples; nothing is ever ``eval``-ed or ``compile``-d, so no name,
attribute or builtin outside the list can be reached (a lambda, a comprehension, ``x.__class__``,
``__import__`` or a subscript other than a lag are rejected while converting).

Accepted:

* finite numbers; the variables of a :class:`VarSpace` (``x1..xn``, ``u1..um`` and the system's
  state/input names) and constants ``pi``, ``e`` where enabled;
* ``+ - * /``, unary minus, powers ``**`` (or ``^``) with a constant exponent of magnitude at most
  :data:`MAX_EXPONENT` (an integer where ``integer_powers``);
* calls of allow-listed functions by name with their fixed number of arguments;
* where enabled, comparisons ``a < b`` (also ``<= > >=``) giving 1.0 or 0.0, for ``where``;
* where enabled, lagged values ``name[k-1]`` .. ``name[k-L]`` of time-ordered data (the value one
  .. L sampling periods earlier).

Tree nodes: ``("const", v) | ("var", j) | ("neg", a) | ("add"|"sub"|"mul"|"div", a, b) |
("pow", a, p) | ("fn", name, a, ...) | ("cmp", op, a, b)``; ``j`` indexes the columns of
z = [x_k, u_k, x_{k-1}, u_{k-1}, ...] (n + m columns per lag).
"""

from __future__ import annotations

import ast
from dataclasses import dataclass
from typing import Iterable, Mapping, Optional

import numpy as np

from .errors import SimgapError

#: every function any expression may call: name -> (numpy function, number of arguments)
FUNCTIONS = {
    "sin": (np.sin, 1), "cos": (np.cos, 1), "tan": (np.tan, 1), "tanh": (np.tanh, 1),
    "sinh": (np.sinh, 1), "cosh": (np.cosh, 1), "exp": (np.exp, 1), "log": (np.log, 1),
    "sqrt": (np.sqrt, 1), "abs": (np.abs, 1), "sign": (np.sign, 1), "arctan": (np.arctan, 1),
    "arctan2": (np.arctan2, 2), "minimum": (np.minimum, 2), "maximum": (np.maximum, 2),
    "clip": (np.clip, 3), "where": (np.where, 3),
}
CONSTANTS = {"pi": np.pi, "e": np.e}
#: functions (and comparisons) that make an expression non-Lipschitz in general
NONSMOOTH = frozenset({"sign", "abs", "clip", "where", "minimum", "maximum", "cmp"})
MAX_EXPONENT = 100
MAX_LENGTH = 500

_BINOPS = {ast.Add: "add", ast.Sub: "sub", ast.Mult: "mul", ast.Div: "div"}
_CMPOPS = {ast.Lt: "lt", ast.LtE: "le", ast.Gt: "gt", ast.GtE: "ge"}
_CMPFN = {"lt": np.less, "le": np.less_equal, "gt": np.greater, "ge": np.greater_equal}
_ARITH = {"add": np.add, "sub": np.subtract, "mul": np.multiply, "div": np.divide}


@dataclass(frozen=True)
class VarSpace:
    """The variables an expression may use: name -> column of z_k = [x_k, u_k] and lag depth.

    ``max_lag`` L > 0 accepts ``name[k-l]`` for l <= L (column + l * width of z =
    [z_k, z_{k-1}, ..., z_{k-L}]); 0 refuses lagged values with a message saying why.
    """

    columns: Mapping[str, int]
    width: int
    max_lag: int = 0

    @classmethod
    def of_system(cls, system, max_lag: int = 0) -> "VarSpace":
        """``x1..xn``, ``u1..um`` (1-based) and the system's own state/input names."""
        n, m = system.n, system.m
        cols = {f"x{i + 1}": i for i in range(n)}
        cols.update({f"u{j + 1}": n + j for j in range(m)})
        for i, s in enumerate(system.state_names):
            cols.setdefault(s, i)
        for j, s in enumerate(system.input_names):
            cols.setdefault(s, n + j)
        return cls(cols, n + m, int(max_lag))


@dataclass(frozen=True)
class Expr:
    """A parsed expression: its text and its tuple tree (see module docstring)."""

    text: str
    tree: tuple

    def __str__(self):
        return self.text

    def eval(self, z: np.ndarray) -> np.ndarray:
        """Values (B,) on the rows of z (B, width * (1 + lags))."""
        with np.errstate(all="ignore"):
            out = evaluate(self.tree, z)
        return np.broadcast_to(np.asarray(out, dtype=float), (z.shape[0],)).astype(float)

    @property
    def functions(self) -> set:
        """Names of the functions called (``"cmp"`` for a comparison)."""
        return {t[1] if t[0] == "fn" else "cmp" for t in walk(self.tree) if t[0] in ("fn", "cmp")}

    @property
    def columns(self) -> set:
        """Columns of z the expression reads."""
        return {t[1] for t in walk(self.tree) if t[0] == "var"}

    @property
    def smooth(self) -> bool:
        """False when a sign/abs/clip/where/min/max or comparison may break Lipschitz continuity."""
        return not (self.functions & NONSMOOTH)


def walk(tree: tuple) -> Iterable[tuple]:
    """All nodes of a tree, depth first."""
    stack = [tree]
    while stack:
        t = stack.pop()
        yield t
        stack.extend(c for c in t[1:] if isinstance(c, tuple))


def parse(text, variables: VarSpace, *, what: str = "expression", functions: Optional[Iterable[str]] = None,
          constants: bool = True, integer_powers: bool = False, comparisons: bool = False) -> Expr:
    """Parse ``text`` against the allow-list (module docstring) into an :class:`Expr`.

    ``functions`` restricts :data:`FUNCTIONS` (default: all). Every refusal is a
    :class:`~simgap.errors.SimgapError` that starts with ``what`` and the text.
    """
    if not isinstance(text, str) or not text.strip():
        raise SimgapError(f"{what} {text!r}: empty")
    if len(text) > MAX_LENGTH:
        raise SimgapError(f"{what} {text[:40]!r}...: longer than {MAX_LENGTH} characters")
    funcs = tuple(FUNCTIONS) if functions is None else tuple(functions)
    try:
        # '^' means power (Python's xor binds looser than '*', so rewrite it textually)
        tree = ast.parse(text.strip().replace("^", "**"), mode="eval")
    except SyntaxError as e:
        raise SimgapError(f"{what} {text!r} does not parse: {e.msg}") from None
    except (ValueError, MemoryError, RecursionError) as e:
        raise SimgapError(f"{what} {text!r} does not parse: {type(e).__name__}") from None
    conv = _Converter(text, what, variables, funcs, constants, integer_powers, comparisons)
    try:
        return Expr(text.strip(), conv(tree.body))
    except RecursionError:
        raise SimgapError(f"{what} {text!r}: nested too deeply") from None


class _Converter:
    def __init__(self, text, what, variables, funcs, constants, integer_powers, comparisons):
        self.text, self.what, self.vars, self.funcs = text, what, variables, funcs
        self.constants, self.integer_powers, self.comparisons = constants, integer_powers, comparisons

    def bad(self, why):
        raise SimgapError(f"{self.what} {self.text!r}: {why}")

    def known(self) -> str:
        names = sorted(self.vars.columns) + (sorted(CONSTANTS) if self.constants else [])
        return ", ".join(names)

    def __call__(self, node) -> tuple:
        if isinstance(node, ast.Constant):
            v = node.value
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                self.bad(f"constant {v!r} is not a number")
            if isinstance(v, int) and abs(v) > 1e300:
                self.bad("constant is too large")
            if not np.isfinite(v):
                self.bad("constant is not finite")
            return ("const", float(v))
        if isinstance(node, ast.Name):
            if node.id in self.vars.columns:
                return ("var", self.vars.columns[node.id])
            if self.constants and node.id in CONSTANTS:
                return ("const", float(CONSTANTS[node.id]))
            self.bad(f"unknown variable {node.id!r}; known: {self.known()}")
        if isinstance(node, ast.Subscript):
            return self.lagged(node)
        if isinstance(node, ast.UnaryOp):
            a = self(node.operand)
            if isinstance(node.op, ast.USub):
                return ("const", -a[1]) if a[0] == "const" else ("neg", a)
            if isinstance(node.op, ast.UAdd):
                return a
            self.bad(f"operator {type(node.op).__name__} is not allowed")
        if isinstance(node, ast.BinOp):
            op = type(node.op)
            if op is ast.Pow:
                return self.power(node)
            if op not in _BINOPS:
                self.bad(f"operator {op.__name__} is not allowed")
            return (_BINOPS[op], self(node.left), self(node.right))
        if isinstance(node, ast.Call):
            if not isinstance(node.func, ast.Name):
                self.bad(f"calling an expression ({type(node.func).__name__}) is not allowed; call functions by name: "
                         f"{', '.join(self.funcs)}")
            if node.func.id not in self.funcs:
                self.bad(f"function {node.func.id!r} is not allowed; allowed: {', '.join(self.funcs)}")
            name = node.func.id
            nargs = FUNCTIONS[name][1]
            if len(node.args) != nargs or node.keywords:
                self.bad(f"{name} takes exactly {'one argument' if nargs == 1 else f'{nargs} arguments'}")
            return ("fn", name) + tuple(self(a) for a in node.args)
        if isinstance(node, ast.Compare) and self.comparisons:
            if len(node.ops) != 1 or type(node.ops[0]) not in _CMPOPS:
                self.bad("only single comparisons < <= > >= are allowed")
            return ("cmp", _CMPOPS[type(node.ops[0])], self(node.left), self(node.comparators[0]))
        self.bad(f"{type(node).__name__} is not allowed")

    def power(self, node) -> tuple:
        a, b = self(node.left), self(node.right)
        if b[0] != "const":
            self.bad("exponents must be constant numbers" + (" (integers; use sqrt for square roots)"
                                                              if self.integer_powers else ""))
        p = b[1]
        if self.integer_powers and p != int(p):
            self.bad("exponents must be integer numbers (use sqrt for square roots)")
        if abs(p) > MAX_EXPONENT:
            self.bad(f"exponent {p:g} is larger than {MAX_EXPONENT} in magnitude")
        return ("pow", a, int(p) if p == int(p) else p)

    def lagged(self, node) -> tuple:
        """``name[k-l]``: the value l sampling periods earlier."""
        form = "lagged values are written name[k-1], name[k-2], ..."
        if not isinstance(node.value, ast.Name) or node.value.id not in self.vars.columns:
            self.bad(f"Subscript is not allowed ({form})")
        s = node.slice
        if isinstance(s, ast.Name) and s.id == "k":
            lag = 0
        elif (isinstance(s, ast.BinOp) and isinstance(s.op, ast.Sub) and isinstance(s.left, ast.Name)
              and s.left.id == "k" and isinstance(s.right, ast.Constant) and type(s.right.value) is int
              and s.right.value >= 0):
            lag = s.right.value
        else:
            self.bad(f"Subscript is not allowed ({form})")
        if lag > self.vars.max_lag:
            if self.vars.max_lag == 0:
                self.bad("lagged values need time-ordered data (transitions with time stamps t)")
            self.bad(f"lag {lag} is deeper than the {self.vars.max_lag} allowed")
        return ("var", self.vars.columns[node.value.id] + lag * self.vars.width)


def evaluate(tree: tuple, z: np.ndarray):
    """Value of a tree on the rows of z (broadcasting scalars)."""
    k = tree[0]
    if k == "const":
        return np.float64(tree[1])
    if k == "var":
        return z[:, tree[1]]
    if k == "neg":
        return -evaluate(tree[1], z)
    if k == "pow":
        return np.power(evaluate(tree[1], z), float(tree[2]))
    if k == "fn":
        return FUNCTIONS[tree[1]][0](*(evaluate(a, z) for a in tree[2:]))
    if k == "cmp":
        return _CMPFN[tree[1]](evaluate(tree[2], z), evaluate(tree[3], z)).astype(float)
    return _ARITH[k](evaluate(tree[1], z), evaluate(tree[2], z))
