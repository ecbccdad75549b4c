"""Basis terms: one spelling on the command line and in experiment files, and a linearly
dependent basis named with the fix in both spellings."""

import shutil
import sys

import numpy as np
import pytest

from cli_helpers import REPO, refused, simgap

sys.path.insert(0, str(REPO))

from simgap.certify.basis import Basis, monomial_names, term_dimension  # noqa: E402
from simgap.certify.pipeline import dependent_terms_message  # noqa: E402
from simgap.certify.scp import DependentTerms, dependent_column, solve_scp  # noqa: E402
from simgap.cli.certify import parse_terms  # noqa: E402
from simgap.errors import SimgapError  # noqa: E402
from simgap.pipeline import certify_options  # noqa: E402
from simgap.system_file import system_from_spec  # noqa: E402

TWO_INPUTS = {  # a cart driven by two inputs that a drive always sets alike (u2 = u1 in the data)
    "name": "cart2", "states": ["p", "v"], "inputs": ["a", "b"], "x_lo": [-1, -1], "x_hi": [1, 1], "tau": 0.1,
    "input_set": [[-1, -1], [0, 0], [1, 1]],
    "dynamics": {"kind": "discrete", "p": "p + dt*v", "v": "v + dt*(a + b)/2"}}


def test_the_dependent_column_and_what_it_combines():
    rng = np.random.default_rng(0)
    x = rng.random((500, 3))
    P = np.c_[np.ones(500), x[:, 0], x[:, 1], 2 * x[:, 0] - x[:, 1], x[:, 2]]
    assert dependent_column(P) == (3, [1, 2])
    with pytest.raises(DependentTerms) as e:
        solve_scp(P, rng.random(500), 0.01)
    assert (e.value.column, e.value.on) == (3, [1, 2])


def test_a_dependent_monomial_is_named_and_the_printed_fix_works():
    s = system_from_spec(dict(TWO_INPUTS), "cart2")
    rng = np.random.default_rng(1)
    x = s.x_lo + rng.random((400, 2)) * (s.x_hi - s.x_lo)
    u = s.inputs[rng.integers(0, 3, 400)]
    names = monomial_names(s, 1)                # 1, x1, x2, u1, u2: u2 = u1 on the data
    P = Basis(s, names).design(x, u)
    col, on = dependent_column(P / np.abs(P).max(axis=0))
    assert names[col] == "u2" and [names[j] for j in on] == ["u1"]
    msg = dependent_terms_message(DependentTerms(col, on), s, 1, 1, {}, names)
    assert "'u2' is a linear combination of 'u1'" in msg and "the basis terms of v" in msg
    cli = msg.split("on the command line ")[1].split(";")[0]
    assert cli.startswith("--degree 1,-1 ") and "--term v:'u2'" not in cli and "--term v:'u1'" in cli
    assert "degree = [1, -1] and terms.v = [\"1\", \"x1\", \"x2\", \"u1\"]" in msg
    # the printed command-line spelling gives a basis of full rank on the same data
    items = [t.strip("'").replace("'", "") for t in cli.split("--term ")[1:]]
    terms = parse_terms([t.strip() for t in items], s)
    P2 = Basis(s, terms[1]).design(x, u)
    assert np.linalg.matrix_rank(P2) == P2.shape[1] == 4


def test_user_terms_dependent_on_the_data_are_refused_by_name(tmp_path):
    d = tmp_path / "duffing"
    shutil.copytree(REPO / "examples" / "duffing", d)
    r = simgap("collect", "experiment.toml", "--out", "data", "--n-runs", "4", "--no-progress", cwd=d)
    assert r.returncode == 0, r.stderr
    r = simgap("certify", "data", "--degree", "1", "--term", "v:2*x1", "--out", "c.json", cwd=d)
    refused(r, "the basis terms of v are linearly dependent", "'2*x1' is a linear combination of 'x1'",
            "leave out --term v:'2*x1'", "remove \"2*x1\" from terms.v")
    assert not (d / "c.json").exists()
    # the same term from the experiment file, by state name, through simgap run's check and certify
    text = (d / "experiment.toml").read_text().replace("[certify]\ndegree = 1", "[certify]\ndegree = 1\n"
                                                       "terms = { v = [\"2*x1\"] }")
    assert "terms = { v" in text
    (d / "experiment.toml").write_text(text)
    r = simgap("run", "experiment.toml", "--out", "res", "--no-record", cwd=d, timeout=300)
    refused(r, "'2*x1' is a linear combination of 'x1'", "terms.v")


def test_one_spelling_of_term_keys_with_numbers_per_place():
    s = system_from_spec(dict(TWO_INPUTS), "cart2")
    assert parse_terms(["v:x1", "all:u1", "1:x2"], s) == {1: ["x1"], -1: ["u1"], 0: ["x2"]}
    o = certify_options({"terms": {"v": ["x1"], "all": ["u1"], "0": ["x2"], "-1": ["u2"]}}, "stochastic", s)
    assert o.terms == {1: ["x1"], -1: ["u1", "u2"], 0: ["x2"]}
    for item, words in (("0:x1", "counts from 1"), ("3:x1", "not 1..2"), ("w:x1", r"state name \(p, v\) or all")):
        with pytest.raises(SimgapError, match=words):
            parse_terms([item], s)
    with pytest.raises(SimgapError, match="on the command line write all:EXPR"):
        term_dimension("-1", s, one_based=True, where="--term")
    with pytest.raises(SimgapError, match="count from 0"):
        certify_options({"terms": {"2": ["x1"]}}, "stochastic", s)
