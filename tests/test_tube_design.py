"""The box tube's design chosen by the tool (simgap.synthesis.tube_design): the pace search, its lines,
the levers table's N1hat and eps from the certificate's own formulas, and ``[certify] confidence``."""

import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest

from simgap.certify import BoundOptions, certify, delta_from_beta
from simgap.certify.pipeline import CertifyOptions
from simgap.certify.synthetic import synthetic_dataset
from simgap.errors import SimgapError
from simgap.progress import StageLog
from simgap.synthesis import box_tube as bt
from simgap.synthesis import tube_design as td

from test_box_tube import GAP, X0, _spec, cubic  # noqa: F401  (the fixture)
from test_certify import PEND_CFG


# ----- the pace --------------------------------------------------------------------------

@pytest.fixture(scope="module")
def searched(cubic):  # noqa: F811
    lines = []
    res = bt.synthesize_box_tube(cubic, _spec(cubic), GAP, x0=X0, x_star=[0, 0], u_star=[0], per_run=False,
                                 log=lines.append)
    return res, lines


def test_the_pace_then_the_gain_are_searched_and_each_choice_is_printed(searched):
    res, lines = searched
    designs = res.stats["designs"]
    first = designs[0]["gain"]  # the heuristic's gain: every pace tried with it first, fastest first
    paces = [d["pace"] for d in designs if d["gain"] == first]
    assert paces == list(td.PACES[:len(paces)]) and len(paces) >= 2
    gains = [d for d in designs[len(paces):]]  # then the other gains at the chosen pace
    assert len(gains) >= 1 and all(d["pace"] == res.stats["plan_input_weight"] for d in gains)
    assert len({d["gain"] for d in gains} | {first}) == len(gains) + 1
    text = "\n".join(lines)
    for d in designs:  # every design tried is named with what it gave
        assert f"pace x{d['pace']:g}, K 10^{d['gain']:g}:" in text
    assert "feedback K:" in text and "pace: x" in text and "margin:" in text and "estimate:" in text
    assert "pace x" in res.summary() and res.stats["pace_how"]


def test_the_chosen_pace_is_the_best_ranked(searched):
    res, _ = searched
    cands = [td.Candidate(**{k: v for k, v in p.items() if k != "seconds"}) for p in res.stats["designs"]]
    for c in cands:
        c.margin = np.inf if c.margin is None and c.proved else c.margin
    best = td.best_candidate(cands, 2, 0)
    assert res.stats["plan_input_weight"] == best.pace
    assert f"10^{best.gain:g}" in res.stats["K_how"]
    assert not res.empty  # a pace proves at this gap, so the chosen one does


def test_a_given_pace_is_not_searched_and_matches_the_search(cubic, searched):  # noqa: F811
    res, _ = searched
    fixed = bt.synthesize_box_tube(cubic, _spec(cubic), GAP, x0=X0, x_star=[0, 0], u_star=[0], per_run=False,
                                   plan_input_weight=res.stats["plan_input_weight"])
    assert {d["pace"] for d in fixed.stats["designs"]} == {res.stats["plan_input_weight"]}
    assert fixed.stats["pace_how"].startswith("given") and fixed.stats["K"] == res.stats["K"]
    assert fixed.stats["T0"] == res.stats["T0"]
    assert fixed.stats["gap_scale"] == pytest.approx(res.stats["gap_scale"])


def test_ranking_prefers_proof_then_per_run_bound_then_margin():
    a = td.Candidate(pace=1, T0=10, proved=False, margin=0.9)
    b = td.Candidate(pace=10, T0=20, proved=True, margin=1.1, lam=3.0)
    c = td.Candidate(pace=100, T0=40, proved=True, margin=1.05, lam=5.0)
    d = td.Candidate(pace=1000, T0=80, proved=True, margin=2.0, lam=30.0)
    e = td.Candidate(pace=1e4, error="leaves X")
    assert td.best_candidate([a, b, e], 4, 100) is b          # a proof beats a larger margin without one
    assert td.best_candidate([a, b, c], 4, 100) is c          # a larger per-run bound beats a larger margin
    cap = np.sqrt(2 * np.log(2 * 4 * 100 / td.NOISE_TERM))
    c.lam = cap + 1                                            # both past the cap: the margin decides
    assert td.best_candidate([c, d], 4, 100) is d
    assert td.best_candidate([e], 4, 100) is e and "no plan" in e.row()


def test_no_pace_proves_gives_the_levers_table(cubic):  # noqa: F811
    res = bt.synthesize_box_tube(cubic, _spec(cubic), 8 * GAP, x0=X0, x_star=[0, 0], u_star=[0], per_run=False)
    assert res.empty
    assert "levers" in res.stats and len(res.stats["levers"]["states"]) == 2
    s = res.stats["gap_scale"]
    for row, w in zip(res.stats["levers"]["states"], res.stats["verification"]["w_max"]):
        assert row["tolerable"] == pytest.approx(s * w) and row["reduce_by"] == pytest.approx((1 - s) * w)
    assert "levers" in res.summary() and "shorter period: not computed" in res.summary()


# ----- the levers' numbers ----------------------------------------------------------------

def _fake_cert(uniform=True, K=5000, N=100):
    dims = [SimpleNamespace(delta1=0.03, delta2=0.02, beta1=0.01, beta2=0.01, Mhat=0.004, gap_max=0.01),
            SimpleNamespace(delta1=0.05, delta2=0.04, beta1=0.01, beta2=0.01, Mhat=0.02, gap_max=0.2)]
    return SimpleNamespace(dims=dims, K=K, n_runs=N, method="stochastic", radii=np.array([0.1, 0.1]),
                           options={"bounds": {"concentration": "subgaussian", "uniform": uniform}},
                           lipschitz_terms=lambda: np.array([0.02, 0.05]))


@pytest.mark.parametrize("uniform", [True, False])
def test_levers_n1hat_is_the_smallest_that_removes_the_reduction(uniform):
    cert = _fake_cert(uniform)
    system = SimpleNamespace(n=2, state_names=("a", "b"))
    w, s = np.array([0.1, 0.3]), 0.8
    lv = td.levers(cert, system, w, s, [])
    opts = BoundOptions(concentration="subgaussian", uniform=uniform)
    for i, row in enumerate(lv["states"]):
        need = (1 - s) * w[i]
        N = row["n1hat"]
        assert N is not None and N > cert.n_runs

        def total(n):  # the deltas at the certificate's own betas, K rows and Mhat
            d1, d2 = delta_from_beta(np.array([cert.dims[i].Mhat]), np.array([0.01]), np.array([0.01]), n, cert.K,
                                     opts)
            return float(d1[0] + d2[0])
        dsum = cert.dims[i].delta1 + cert.dims[i].delta2
        assert total(N) <= dsum - need < total(N - 1)
        L = cert.lipschitz_terms()[i]
        assert row["eps_factor"] == pytest.approx((L - need) / L) if L > need else row["eps_factor"] is None
    assert "enough" in lv["states"][1]["text"] and "not enough" in lv["states"][0]["text"]


def test_levers_say_when_no_n1hat_suffices():
    cert = _fake_cert()
    lv = td.levers(cert, SimpleNamespace(n=2, state_names=("a", "b")), np.array([1.0, 1.0]), 0.5, [])
    assert all(r["n1hat"] is None and "no N1hat" in r["text"] for r in lv["states"])


def test_levers_on_a_noise_free_state_name_no_n1hat():
    """A state the runs do not scatter (Mhat 0, its betas 0: test_rounds' linear system) gets no N1hat
    lever and no error (delta_from_beta refuses beta 0: the table raised on it)."""
    cert = _fake_cert()
    cert.dims[0] = SimpleNamespace(delta1=0.03, delta2=0.02, beta1=0.0, beta2=0.0, Mhat=0.0, gap_max=0.01)
    lv = td.levers(cert, SimpleNamespace(n=2, state_names=("a", "b")), np.array([0.1, 0.3]), 0.8, [])
    a, b = lv["states"]
    assert a["n1hat"] is None and "no noise" in a["text"] and b["n1hat"] is not None


# ----- [certify] confidence ---------------------------------------------------------------

@pytest.fixture(scope="module")
def pend_ds():
    return synthetic_dataset(PEND_CFG, epsilon=0.05, n_runs=100, seed=3)


@pytest.mark.parametrize("variance, uniform", [("empirical", True), ("empirical", False), ("maurer_pontil", False)])
def test_confidence_sets_the_betas_for_the_joint_statement(pend_ds, variance, uniform):
    opts = CertifyOptions(confidence=0.995, variance=variance, value_range=1.0 if variance == "maurer_pontil" else None,
                          bounds=BoundOptions(concentration="subgaussian", uniform=uniform))
    c = certify(pend_ds, opts)
    sc = c.scope_confidences()
    assert (sc["simultaneous"] if uniform else sc["pointwise"]) == pytest.approx(0.995, abs=1e-9)
    b = [d.beta1 for d in c.dims]
    assert b == pytest.approx([(1 - 0.995 - 2 * c.dims[0].beta_v) / 4] * 2, rel=1e-9)


def test_confidence_refused_beside_betas_and_out_of_range(pend_ds):
    with pytest.raises(SimgapError, match="confidence and beta1/beta2"):
        certify(pend_ds, CertifyOptions(confidence=0.99, beta1=0.01))
    with pytest.raises(SimgapError, match="confidence must be a probability"):
        certify(pend_ds, CertifyOptions(confidence=1.5))
    with pytest.raises(SimgapError, match="deterministic baseline has no delta or beta terms; remove confidence"):
        certify(pend_ds, CertifyOptions(method="deterministic", confidence=0.99))


# ----- StageLog ----------------------------------------------------------------------------

def test_stage_log_never_leaves_a_silence_longer_than_every():
    stamps = []
    with StageLog("[x] ", lambda t: stamps.append((time.monotonic(), t)), every=0.2) as log:
        log("start")
        log.doing("waiting")
        time.sleep(0.9)
        log("end")
    gaps = np.diff([s for s, _ in stamps])
    assert len(stamps) >= 4 and gaps.max() < 0.2 + 0.35  # a heartbeat every 0.2 s (polling at 0.05 s)
    assert any("waiting" in t for _, t in stamps) and all(t.startswith("[x] ") for _, t in stamps)
    assert not any(th.name == "simgap-stage-log" for th in threading.enumerate())  # stopped on exit


def test_stage_log_without_a_writer_is_silent_and_starts_no_thread():
    with StageLog("", None, every=0.01) as log:
        log("nothing")
        assert not any(th.name == "simgap-stage-log" for th in threading.enumerate())


def test_the_ellipsoid_design_prints_its_rounds_and_an_estimate(cubic):  # noqa: F811
    from simgap.synthesis.invariant_set import synthesize_invariant_set
    lines = []
    synthesize_invariant_set(cubic, _spec(cubic), GAP, x_star=[0, 0], u_star=[0], log=lines.append)
    assert any(t.startswith("rate ") and "margin" in t for t in lines)
    assert sum(t.startswith("estimate:") for t in lines) == 1


def test_a_gap_far_below_what_the_tube_tolerates_is_not_ranked(cubic):  # noqa: F811
    lines = []
    res = bt.synthesize_box_tube(cubic, _spec(cubic), 1e-6 * GAP, x0=X0, x_star=[0, 0], u_star=[0], per_run=False,
                                 log=lines.append)
    assert not res.empty and len(res.stats["designs"]) == 1 and res.stats["plan_input_weight"] == td.PACES[0]
    assert any("designs not ranked" in t for t in lines)
