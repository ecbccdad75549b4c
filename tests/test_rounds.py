"""Anytime-valid rounds (issue 52 item 4): round k certifies with beta / 2^k, a proof states the
confidence of every round at once (1 - sum of the base betas), and the stopping rule "go on until the
proof holds" keeps its false-proof rate below beta (Monte Carlo), which one beta reused per round
does not."""

import numpy as np
import pytest
from scipy.stats import norm

from simgap import rounds
from simgap.certify import BoundOptions, certify
from simgap.collect import CollectionPlan, collect, load_store
from simgap.cover import CoverSpec, make_cover
from simgap.errors import SimgapError
from simgap.rounds import Attempt, Budget, n_runs_of_round, run_rounds
from simgap.simulators.base import SimulatorConfig
from simgap.systems import get_system

PEND_CFG = {"kind": "numpy", "system": "pendulum", "noise": {"process_std": 0.002}}


@pytest.fixture(scope="module")
def ds(tmp_path_factory):
    s = get_system("pendulum")
    cover = make_cover(s, CoverSpec(epsilon=0.05, region={"theta": [-0.1, 0.1], "omega": [-0.2, 0.2]}))
    plan = CollectionPlan(system=s, simulator=SimulatorConfig.from_dict(PEND_CFG), cover=cover, n_runs=40, seed=2,
                          chunk_size=500)
    store = tmp_path_factory.mktemp("rounds") / "data"
    collect(plan, store, executor="serial")
    return load_store(store)


def test_round_k_spends_beta_over_2k(ds):
    """The certificate of round k carries beta1 = beta2 = 0.01 / 2^k per dimension (and beta_v / 2^k),
    wider deltas than round 0's, and states for the proof the confidence of all rounds at once,
    1 - sum of the base betas, the same in every round (a round reusing beta would state 1 - 0.04 / 2^k
    ... or carry 0.01)."""
    opts = dict(degree=1, bounds=BoundOptions(concentration="subgaussian"), variance="maurer_pontil",
                value_range=2.0, beta_v=0.002)
    c0 = certify(ds, **opts)
    base = c0.scope_confidences()["simultaneous"]
    assert base == pytest.approx(1 - 2 * (0.01 + 0.01 + 0.002))
    prev = c0
    for k in (1, 2, 3):
        ck = certify(ds, round=k, **opts)
        assert ck.round == k
        for d in ck.dims:
            assert d.beta1 == pytest.approx(0.01 / 2 ** k) and d.beta2 == pytest.approx(0.01 / 2 ** k)
            assert d.beta_v == pytest.approx(0.002 / 2 ** k)
        assert all(a.delta2 > b.delta2 for a, b in zip(ck.dims, prev.dims))  # less failure, wider margins
        own = ck.scope_confidences()["simultaneous"]
        assert own == pytest.approx(1 - (1 - base) / 2 ** k)
        assert ck.all_rounds_confidence() == pytest.approx(base)
        assert ck.sup_confidence() == pytest.approx(base)
        assert f"round {k} of anytime-valid rounds" in ck.statement()
        prev = ck
    with pytest.raises(SimgapError, match="give beta1 / beta2, not delta1"):
        certify(ds, round=1, delta1=0.01, delta2=0.01, degree=1)


class _Cert:
    """What round_row reads of a certificate."""

    def __init__(self, k, beta):
        self.k, self.beta = k, beta

    def scope_confidences(self):
        return {"simultaneous": 1 - self.beta * rounds.beta_share(self.k)}

    def all_rounds_confidence(self):
        return 1 - self.beta


def test_policy_doubles_and_stops():
    """N1hat doubles per round; the rounds stop at the first proof, when the factor stops growing, and
    before a round the budget cannot pay (its runs known in advance)."""
    assert [n_runs_of_round(100, k) for k in (1, 2, 3, 4)] == [100, 200, 400, 800]
    seen = []

    def attempt(k, n):
        seen.append(n)
        return Attempt(proved=k == 3, scale=0.5 + 0.1 * k, cert=_Cert(k, 0.02), runs=10 * n, seconds=1.0)

    r = run_rounds(100, 10, Budget(runs=10 ** 6), attempt, log=lambda s: None)
    assert seen == [100, 200, 400] and r.last.proved and r.stopped == "proved in round 3"
    assert [row["beta_share"] for row in r.rows] == [0.5, 0.25, 0.125]
    assert all(row["confidence_all_rounds"] == pytest.approx(0.98) for row in r.rows)
    # the budget: rounds 2 (2,000 runs) and 3 (4,000) fit in 6,000, round 4 (8,000 more) does not
    never = lambda k, n: Attempt(False, 0.3 * k, _Cert(k, 0.02), 10 * n, 1.0)
    r = run_rounds(100, 10, Budget(runs=6000), never, log=lambda s: None)
    assert len(r.rows) == 3 and r.stopped.startswith("budget:") and "budget_runs = 6,000" in r.stopped
    # projected: x2 per round from 0.2 needs 3 more rounds (4,000 + 8,000 + 16,000 runs), over the budget
    slow = lambda k, n: Attempt(0.1 * 2 ** (k - 1) >= 1, 0.1 * 2 ** (k - 1), _Cert(k, 0.02), 10 * n, 1.0)
    r = run_rounds(100, 10, Budget(runs=6000), slow, log=lambda s: None)
    assert len(r.rows) == 2 and "about 3 more rounds" in r.stopped and "28,000 more runs" in r.stopped
    r = run_rounds(100, 10, Budget(runs=10 ** 6), slow, log=lambda s: None)
    assert len(r.rows) == 5 and r.last.proved  # within the budget the rounds go on
    flat = lambda k, n: Attempt(False, 0.4, _Cert(k, 0.02), 10 * n, 1.0)  # not proved at 1.6 x: no proof
    r = run_rounds(100, 10, Budget(runs=10 ** 9), flat, log=lambda s: None)
    assert len(r.rows) == 2 and "did not grow" in r.stopped
    with pytest.raises(SimgapError, match="budget_runs"):
        Budget(runs=0)


def _false_proof_rate(trials, beta, share, rng, max_rounds=6):
    """The rounds on a Gaussian mean mu = 0 with known sd 1: round k's upper bound U_k = mean + z_(1 - beta
    share(k)) / sqrt(N_k) (exact level), the proof "mu < c" with c = 0 holds when U_k < 0, a FALSE
    statement. Rounds go on (the factor grows) until the proof holds or max_rounds."""
    false = 0
    z = {k: norm.ppf(1 - beta * share(k)) for k in range(1, max_rounds + 1)}
    for _ in range(trials):
        def attempt(k, n):
            m = rng.standard_normal(n).mean()
            U = m + z[k] / np.sqrt(n)
            return Attempt(proved=bool(U < 0), scale=float(k), cert=None, runs=n, seconds=0.0)
        r = run_rounds(4, 1, Budget(runs=10 ** 9), attempt, log=lambda s: None, max_rounds=max_rounds)
        false += r.last.proved
    return false / trials


def test_stopping_at_the_proof_keeps_beta_monte_carlo():
    """Monte Carlo, 4000 trials of up to 6 rounds: with beta / 2^k the rate of false proofs is at most
    beta = 0.1 (within 3 SE); with one beta reused every round it is near 1 - 0.9^6 = 0.47."""
    rng = np.random.default_rng(0)
    T, beta = 4000, 0.1
    split = _false_proof_rate(T, beta, rounds.beta_share, rng)
    reuse = _false_proof_rate(T, beta, lambda k: 1.0, rng)
    se = np.sqrt(beta * (1 - beta) / T)
    assert split <= beta + 3 * se
    assert reuse > beta + 10 * se


LIN = """
format = "simgap-system"
name = "lin2"
states = ["a", "b"]
inputs = ["u"]
x_lo = [-1.0, -1.0]
x_hi = [1.0, 1.0]
tau = 0.1
input_grid = {lo = [-1.0], hi = [1.0], counts = [3]}
[dynamics]
kind = "discrete"
a = "0.9*a + 0.1*b"
b = "0.9*b + 0.2*u"
"""

EXPERIMENT = """
system = "lin.toml"
[simulator]
kind = "numpy"
noise = { actuation_std = 0.05 }
[collect]
epsilon = 0.1
n_runs = 4
seed = 1
tube_margin = 0.3
budget_runs = 2000000
executor = "serial"
[certify]
degree = 1
concentration = "subgaussian"
safety = 1.0
lhat = "simulator"
lipschitz_term = "gap"
continuous_inputs = true
[audit]
points = 20
runs = 20
[synthesis]
spec = "invariance"
method = "box_tube"
x_star = [0.0, 0.0]
u_star = [0.0]
nominal = false
# the design pinned (the linear estimate's gain, the fastest pace): the test is about the rounds, and the
# design search finds a gain (10^-2 x that input weight) that proves at N1hat 4 already
K = [[-0.434763, -1.257824]]
plan_input_weight = 1.0
[rollout]
n = 50
x0 = [0.5, 0.0]
"""


@pytest.mark.slow
def test_run_collects_along_the_tube_in_rounds_until_proved(tmp_path):
    """simgap run with [collect] tube_margin and budget_runs on a linear system whose proof lacks data
    at N1hat = 4 (round 1: gamma tolerable up to 0.83 x its bound) and holds at 8 (round 2): the data
    cover the nominal tube's boxes only, round 2 collects its own store, the stochastic certificate is
    round 2's (b's betas 0.01 / 4), the proof and the per-run statement state every round's confidence at
    once (0.98, beta_cert 0.02), the results folder loads with the last round's data, and the same command
    again resumes every store (no new run). About 20 s on the 2-core machine at load 20."""
    from simgap.certify import load
    from simgap.config import load_experiment
    from simgap.pipeline import run_experiment
    from simgap_viz.results import load_run
    (tmp_path / "lin.toml").write_text(LIN)
    (tmp_path / "exp.toml").write_text(EXPERIMENT)
    out = tmp_path / "run"
    summary = run_experiment(load_experiment(tmp_path / "exp.toml"), out, log=lambda m: None)
    rr = summary["rounds"]
    assert [r["proved"] for r in rr["rounds"]] == [False, True] and rr["stopped"] == "proved in round 2"
    assert [r["n_runs"] for r in rr["rounds"]] == [4, 8]
    cert = load(out / "cert_stochastic.json")
    assert cert.round == 2 and cert.n_runs == 8 and cert.region_boxes is not None
    b = cert.dims[1]  # a is noise-free (Mhat 0: beta 0 there)
    assert b.beta1 == pytest.approx(0.0025) and b.beta2 == pytest.approx(0.0025)
    e = summary["methods"]["stochastic"]
    assert e["data_dir"] == "data_round2" and e["confidence_proof"] == pytest.approx(0.98)
    from simgap.pipeline import comparison_table
    assert "proof confidence (sup over the set)" in comparison_table(summary)
    assert [ln for ln in comparison_table(summary).splitlines() if "proof confidence" in ln][0].split()[-1] == "0.98"
    assert e["failures"] == 0 and e["per_run_empirical"]["p_cert"] is not None
    assert e["synthesis"]["noise_tube"]["beta_cert"] == pytest.approx(0.02)
    ds = load_store(out / "data")
    assert np.all(np.abs(ds.x[:, 1]) <= 0.45)  # along the tube (b near 0), not over X's [-1, 1]
    assert load_run(out).summary["methods"]["stochastic"]["data_dir"] == "data_round2"
    again = run_experiment(load_experiment(tmp_path / "exp.toml"), out, log=lambda m: None)
    assert sum(again["collected_runs"].values()) == 0 and again["rounds"]["stopped"] == "proved in round 2"
