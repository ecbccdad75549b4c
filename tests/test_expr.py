"""The one allow-list parser for user expressions (simgap.expr): hostile input never runs."""

import json

import numpy as np
import pytest

from simgap.certify.basis import parse_term
from simgap.cli import main
from simgap.errors import SimgapError
from simgap.expr import FUNCTIONS, VarSpace, parse, walk
from simgap.refine.effects import user_effect
from simgap.systems import get_system

PEND = get_system("pendulum")
MARK = "simgap_expr_pwned"

# each would run code, reach a builtin or an object's internals, or hang if evaluated as Python
HOSTILE = [
    "(lambda: ().__class__.__base__.__subclasses__())()",
    f"(lambda: __import__('os').system('touch {MARK}'))()",
    "[c for c in ().__class__.__base__.__subclasses__()][0]",
    "{c for c in (1, 2)}", "{c: 1 for c in (1,)}", "sum(c for c in (1, 2))",
    "theta.__class__", "sin.__self__", "theta.real", "().__class__", "omega.__array_interface__",
    "__import__('os')", "__builtins__", "__builtins__['eval']('1')", "eval('1')", "exec('1')",
    "open('/etc/passwd')", "getattr(theta, '__class__')", "globals()", "np.sin(theta)", "numpy.sin(theta)",
    "sin(theta=1)", "sin(*[theta])", "sin(**{})",
    "(x := 3)", "theta if omega else 1", "theta and omega", "not theta", "~theta", "theta | omega",
    "theta << 2", "theta % 2", "theta // 2", "theta @ omega", "'a'", "b'a'", "None", "True", "...",
    "[theta]", "(theta, omega)", "{theta}", "{1: theta}", "f'{theta}'", "theta[0]", "theta[k+1]",
    "theta[k-1.5]", "sin[k-1]", "sin(theta)(omega)", "yield theta", "await theta",
    "omega ** 10 ** 10", "2 ** 9999999999", "omega ** 1e10", "9" * 400, "1e999", "omega ** theta",
    "(" * 300 + "theta" + ")" * 300, "theta " * 200, "sin(" * 120 + "theta" + ")" * 120,
]


@pytest.mark.parametrize("text", HOSTILE)
def test_hostile_user_effect_is_refused(text, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SimgapError, match="user effect 'g'"):
        user_effect(PEND, "g", "omega", text)
    assert not (tmp_path / MARK).exists()


@pytest.mark.parametrize("text", HOSTILE)
def test_hostile_basis_term_is_refused(text):
    with pytest.raises(SimgapError, match="basis term"):
        parse_term(text, PEND)


def test_random_token_soup_yields_only_allow_listed_nodes():
    """Fuzz: whatever parses holds only allowed node kinds, known functions and existing columns."""
    tokens = ["theta", "omega", "torque", "x1", "u1", "pi", "sin", "where", "clip", "(", ")", ",", "+", "-", "*",
              "/", "**", "^", "<", ">=", "1", "2.5", "[k-1]", ".", "__class__", "lambda", ":", "for", "in", "[", "]",
              "__import__", "'os'", "open", "==", "if", "else"]
    rng = np.random.default_rng(0)
    space = VarSpace.of_system(PEND, max_lag=1)
    accepted = 0
    z = rng.normal(size=(5, 6))
    for _ in range(4000):
        text = " ".join(rng.choice(tokens, rng.integers(1, 9)))
        try:
            e = parse(text, space, comparisons=True)
        except SimgapError:
            continue
        accepted += 1
        for node in walk(e.tree):
            assert node[0] in ("const", "var", "neg", "add", "sub", "mul", "div", "pow", "fn", "cmp")
            if node[0] == "fn":
                assert node[1] in FUNCTIONS
            if node[0] == "var":
                assert 0 <= node[1] < 6
        assert e.eval(z).shape == (5,)
    assert accepted > 100      # the soup does produce valid expressions, so the loop tests something


def test_accepted_expressions_evaluate_like_numpy():
    x = np.array([[0.3, -1.2], [-0.7, 0.4]])
    u = np.array([[0.5], [-2.0]])
    cases = {"sin(2*pi*theta/0.01)": np.sin(2 * np.pi * x[:, 0] / 0.01),
             "where(omega > 0, omega^2, -torque)": np.where(x[:, 1] > 0, x[:, 1] ** 2, -u[:, 0]),
             "clip(x2, -0.5, 0.5) * u1": np.clip(x[:, 1], -0.5, 0.5) * u[:, 0],
             "arctan2(theta, omega) + abs(omega)**1.5": np.arctan2(x[:, 0], x[:, 1]) + np.abs(x[:, 1]) ** 1.5,
             "-theta^-2": -x[:, 0] ** -2.0, "3": np.full(2, 3.0),
             "-" * 200 + "theta": x[:, 0]}      # deep but short: parsed without a recursion error
    for text, want in cases.items():
        g = user_effect(PEND, "g", "omega", text)
        np.testing.assert_allclose(g(x, u), want, rtol=1e-12)
    assert not user_effect(PEND, "g", "omega", "where(omega > 0, 1, 0)").smooth
    assert user_effect(PEND, "g", "omega", "sin(theta)").smooth
    # basis terms keep their narrower language: integer powers, their functions, no constants
    for text, match in [("theta^0.5", "integer"), ("clip(theta, 0, 1)", "function 'clip'"),
                        ("pi*theta", "unknown variable 'pi'"), ("theta > 0", "Compare")]:
        with pytest.raises(SimgapError, match=match):
            parse_term(text, PEND)


def test_lagged_values_read_history():
    g = user_effect(PEND, "g", "omega", "torque[k-1] - torque", max_lag=2)
    assert g.lag == 1
    x, u = np.zeros((3, 2)), np.array([[1.0], [2.0], [3.0]])
    hist = np.array([[0, 0, 0.5], [0, 0, 1.0], [0, 0, 2.0]])      # [x_{k-1}, u_{k-1}]
    np.testing.assert_allclose(g(x, u, hist), [-0.5, -1.0, -1.0])
    with pytest.raises(SimgapError, match="deeper than the 2"):
        user_effect(PEND, "g", "omega", "torque[k-3]", max_lag=2)
    with pytest.raises(SimgapError, match="time-ordered"):
        user_effect(PEND, "g", "omega", "torque[k-1]")


def _refined_json(tmp_path, expr):
    d = {"format": "simgap-refined-system", "version": 1, "name": "evil", "base": "pendulum", "steps": 1,
         "effects": [{"name": "evil", "state": 1, "variable": None, "coefficient": 1.0,
                      "params": {"expr": expr}}]}
    p = tmp_path / "evil.json"
    p.write_text(json.dumps(d))
    return p


def test_cli_refuses_code_in_refined_system_and_term(tmp_path, monkeypatch, capsys):
    """The reported exploit: a lambda in a refined-system JSON or a --term ran a shell command."""
    monkeypatch.chdir(tmp_path)
    rng = np.random.default_rng(0)
    x = rng.uniform(-0.5, 0.5, (300, 2))
    u = rng.uniform(-1, 1, (300, 1))
    data = tmp_path / "d.npz"
    np.savez(data, x=x, u=u, x_next=PEND.f(x, u), tau=PEND.tau)
    payload = f"(lambda: [c for c in ().__class__.__base__.__subclasses__() if c.__name__ == 'Popen'][0]" \
              f"('touch {MARK}', shell=True))()"
    sysf = _refined_json(tmp_path, payload)
    for argv in (["refine", "--system", str(sysf), "--data", str(data)],
                 ["refine", "--system", "pendulum", "--data", str(data), "--term", f"evil:omega:{payload}"]):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert "user effect 'evil'" in err and "not allowed" in err and "Traceback" not in err
    assert not (tmp_path / MARK).exists()
