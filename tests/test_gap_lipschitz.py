"""The gap's own Lipschitz term (beyond the paper), per-dimension radii and inputs between grid values.

Planted gaps with known slopes on the numpy simulator: the estimate must find the planted slope,
gamma must hold at fresh points between cover points and between input values (checked against
the exact gap), and halving or dropping the term must break it. A gap with a feature thinner than
the cover spacing is invisible to any slope estimate: the audit at fresh points must flag it.
"""

import dataclasses

import numpy as np
import pytest

from simgap.certify import certify, load
from simgap.certify.audit import audit
from simgap.certify.synthetic import synthetic_dataset
from simgap.errors import SimgapError
from simgap.simulators.base import SimulatorConfig
from simgap.simulators.numpy_sim import NumpySimulator
from simgap.systems import System, input_grid

DT = 0.1


def plant(gap_v=lambda x, u: 0.0 * x[:, 0], counts=5):
    """(nominal, true simulator): x = (p, v), p+ = p + dt v, v+ = v + dt (u - 5 sin p) (+ dt gap_v(x, u)
    in the truth): both sides share the stiff spring, whose slope cancels in the gap."""
    def nominal_step(x, u, dt):
        return np.stack([x[:, 0] + dt * x[:, 1], x[:, 1] + dt * (u[:, 0] - 5.0 * np.sin(x[:, 0]))], axis=1)

    def true_step(x, u, dt):
        return nominal_step(x, u, dt) + np.stack([0.0 * x[:, 0], dt * gap_v(x, u)], axis=1)

    kw = dict(state_names=("p", "v"), input_names=("a",), x_lo=(-1.0, -1.0), x_hi=(1.0, 1.0),
              inputs=input_grid([-1.0], [1.0], [counts]), base_tau=DT)
    nominal = System(name="plant", step=nominal_step, **kw)
    truth = System(name="plant", step=true_step, **kw)
    return nominal, NumpySimulator(SimulatorConfig("numpy", "plant"), system=truth)


def exact_gap(nominal, sim, x, u):
    return np.abs(sim.mean_next(x, u) - nominal.f(x, u))


def test_planted_slope_is_found_and_far_below_the_paper_term():
    c = 0.8  # undeclared damping: gap_v = -dt c v, slope dt c in v, 0 in p
    nominal, sim = plant(lambda x, u: -c * x[:, 1])
    ds = synthetic_dataset(sim, 0.1, 1, seed=0).with_nominal(nominal)
    cert = certify(ds, method="deterministic", lipschitz_term="gap")
    L = np.array(cert.dims[1].L_gap)
    assert DT * c * 0.999 <= L[1] <= DT * c * 1.2          # the planted slope, not missed
    assert L[0] < 1e-9                                       # none in p
    assert cert.gap_terms()[1] < 0.2 * cert.paper_terms()[1]  # the sides' slopes cancel in the gap
    # radii per dimension: half the grid spacing, not one Euclidean epsilon
    h = np.diff(np.unique(ds.x[:, 0]))[0]
    assert np.allclose(cert.radii, h / 2)
    assert cert.lipschitz_term == "gap" and any("gap itself" in b for b in cert.options["beyond_paper"])


def centre_dataset(nominal, sim, spacing):
    """The exact means (noise-free simulator) on simgap's own cover: points at the cell centres,
    so X's edges lie half a cell beyond the outermost points."""
    from simgap.cover import CoverSpec, make_cover
    from simgap.dataset import Dataset
    cov = make_cover(nominal, CoverSpec(epsilon=float(np.linalg.norm(spacing)) / 2 * 1.001, spacing=tuple(spacing)))
    U = nominal.inputs
    ci, ii = np.repeat(np.arange(cov.N), len(U)), np.tile(np.arange(len(U)), cov.N)
    x, u = cov.points[ci], U[ii]
    mean = sim.mean_next(x, u)
    return Dataset(system=nominal, x=x, u=u, f_nom=nominal.f(x, u), mean=mean, var=np.zeros_like(mean), lo=mean,
                   hi=mean, cover_index=ci, input_index=ii, n_runs=1, epsilon=cov.epsilon,
                   manifest={"cover": cov.describe()})


def _edge_case(seed=0):
    """A gap linear in p seen through a constant basis: gamma = max |g| on the cover + L eps_p is
    exactly tight in the half cells at X's edges, so any smaller Lipschitz term is violated there."""
    s = 0.5
    nominal, sim = plant(lambda x, u: s * x[:, 0])
    ds = centre_dataset(nominal, sim, (0.5, 0.5))
    cert = certify(ds, method="deterministic", degree=0, lipschitz_term="gap")
    rng = np.random.default_rng(seed)
    x = rng.uniform(-1, 1, (20000, 2))
    u = nominal.inputs[rng.integers(0, len(nominal.inputs), len(x))]
    return nominal, sim, cert, x, u


def _scaled(cert, factor):
    """Mutation: the whole Lipschitz term (gap slopes and fit slopes) scaled by ``factor``."""
    dims = [dataclasses.replace(d, L_gap=[factor * v for v in d.L_gap], L2_x=[factor * v for v in d.L2_x])
            for d in cert.dims]
    return dataclasses.replace(cert, dims=dims)


def test_gamma_with_the_gap_term_holds_between_cover_points_and_a_halved_or_dropped_term_does_not():
    nominal, sim, cert, x, u = _edge_case()
    g = exact_gap(nominal, sim, x, u)
    assert np.all(cert.gamma(x, u) >= g - 1e-12)
    for factor in (0.5, 0.0):  # mutations: the term halved, the term dropped
        bad = _scaled(cert, factor)
        assert np.mean(bad.gamma(x, u)[:, 1] < g[:, 1] - 1e-9) > 0.01, factor


def test_saved_certificate_keeps_the_term_and_an_edited_row_is_refused(tmp_path):
    _, _, cert, x, u = _edge_case()
    back = load(cert.save(tmp_path / "c.json"))
    assert np.allclose(back.gamma(x[:50], u[:50]), cert.gamma(x[:50], u[:50]))
    import json
    d = json.loads((tmp_path / "c.json").read_text())
    d["dims"][1]["L_gap"] = [0.0, 0.0]
    (tmp_path / "e.json").write_text(json.dumps(d))
    with pytest.raises(SimgapError, match="modified"):
        load(tmp_path / "e.json")


def test_inputs_between_grid_values_are_covered_and_the_input_term_is_needed():
    c = 0.6  # actuator gain error: gap_v = dt c u, certified on a degree-2 fit through 5 input values
    nominal, sim = plant(lambda x, u: c * u[:, 0])
    ds = synthetic_dataset(sim, 0.3, 1, seed=1).with_nominal(nominal)
    cert = certify(ds, method="deterministic", lipschitz_term="gap", continuous_inputs=True)
    assert cert.continuous and np.allclose(cert.input_radii, 0.25)
    rng = np.random.default_rng(2)
    x = rng.uniform(-1, 1, (20000, 2))
    u = rng.uniform(-1, 1, (20000, 1))
    g = exact_gap(nominal, sim, x, u)
    assert np.all(cert.gamma(x, u, continuous=True) >= g - 1e-12)
    assert np.mean(cert.gamma(x, u)[:, 1] < g[:, 1] - 1e-9) > 0.01   # without the input term: violated
    # gamma_sup over a state box and the whole input box bounds every sample in it
    sup = cert.gamma_sup([-1, -1], [1, 1], [-1], [1])
    assert np.all(sup >= cert.gamma(x, u, continuous=True).max(axis=0) - 1e-12)
    with pytest.raises(SimgapError, match="input box"):
        cert.gamma(x[:1], [[1.5]], continuous=True)
    # the audit draws inputs between the grid values for such a certificate, and passes
    rep = audit(cert, sim, points=100, runs=2, seed=3, system=nominal)
    assert rep["passed"] and rep["inputs"] == "uniform in the input box"


def test_a_feature_thinner_than_the_cover_is_flagged_by_the_audit():
    # g_v = A sin(2 pi p / h) vanishes on every cover point (spacing h): no slope between cover
    # points shows it, so the estimate misses it; the audit at fresh points must not pass.
    nominal, _ = plant()
    ds0 = synthetic_dataset(plant()[1], 0.2, 1, seed=0)
    h = np.diff(np.unique(ds0.x[:, 0]))[0]
    lo = nominal.x_lo[0]
    nominal, sim = plant(lambda x, u: 0.5 * np.sin(2 * np.pi * (x[:, 0] - lo) / h))
    ds = synthetic_dataset(sim, 0.2, 1, seed=0).with_nominal(nominal)
    cert = certify(ds, method="deterministic", lipschitz_term="gap")
    assert cert.dims[1].L_gap[0] < 1e-6   # invisible to the estimate, by construction
    rep = audit(cert, sim, points=200, runs=2, seed=4, system=nominal)
    assert not rep["passed"]
    assert rep["per_dim"]["v"]["fraction_violated"] > 0.3


def test_data_slopes_state_their_noise_floor_and_warn_when_it_dominates():
    nominal, _ = plant()
    noisy = NumpySimulator(SimulatorConfig("numpy", "plant", noise={"process_std": 0.05}), system=plant()[1].system)
    ds = synthetic_dataset(noisy, 0.2, 20, seed=5).with_nominal(nominal)
    cert = certify(ds, lipschitz_term="gap", beta1=0.05, beta2=0.05)
    how = cert.dims[1].gap_how["v"]
    # no gap at all: every slope is noise, sd sqrt(2) sigma / (sqrt(N1hat) h) per pair
    h = np.diff(np.unique(ds.x[:, 1]))[0]
    assert how["noise_floor"] >= 0.5 * np.sqrt(2) * 0.05 / (np.sqrt(20) * h)
    assert how["noise_share"] > 0.5
    assert any("mostly the noise" in w and "simulator" in w for w in cert.options["warnings"])


NOISY_RUN = """
[system]
name = "pendulum"
[simulator]
kind = "numpy"
noise = { actuation_std = 0.05 }
[collect]
epsilon = 0.04
n_runs = 8
seed = 1
executor = "serial"
[certify]
degree = 1
lipschitz_term = "gap"
[audit]
points = 10
runs = 20
[synthesis]
spec = "invariance"
eta = [0.01, 0.025]
[rollout]
n = 10
horizon = 20
x0 = [0.05, 0.1]
"""


def test_noisy_gap_entries_make_one_warning_naming_their_count_and_the_worst(tmp_path):
    """Every entry L_gap[i, j] of a noise-only gap is mostly noise: one warning for the certificate
    (not one line per entry), naming how many and the worst; the entries, worst first, in the
    certificate (kept by save and load) and in `simgap run`'s summary.json."""
    nominal, _ = plant()
    noisy = NumpySimulator(SimulatorConfig("numpy", "plant", noise={"process_std": 0.05}), system=plant()[1].system)
    ds = synthetic_dataset(noisy, 0.2, 20, seed=5).with_nominal(nominal)
    cert = certify(ds, lipschitz_term="gap", beta1=0.05, beta2=0.05)
    gap_warnings = [w for w in cert.options["warnings"] if "L_gap" in w]
    entries = cert.options["noisy_gap_entries"]
    assert len(gap_warnings) == 1 and len(entries) >= 2
    worst = entries[0]
    assert f"{len(entries)} of 4 L_gap entries" in gap_warnings[0]
    assert f"worst L_gap[{worst['dim']}, {worst['wrt']}]" in gap_warnings[0]
    assert [e["noise_share"] for e in entries] == sorted((e["noise_share"] for e in entries), reverse=True)
    assert all(e["noise_share"] > 0.5 and e["dim"] in ("p", "v") and e["wrt"] in ("p", "v") for e in entries)
    cert.save(tmp_path / "c.json")
    assert load(tmp_path / "c.json").options["noisy_gap_entries"] == entries
    # a certificate without the gap's term has none
    assert certify(ds, beta1=0.05, beta2=0.05).options["noisy_gap_entries"] == []

    import json

    from simgap.config import load_experiment
    from simgap.pipeline import comparison_table, run_experiment
    (tmp_path / "exp.toml").write_text(NOISY_RUN)
    summary = run_experiment(load_experiment(tmp_path / "exp.toml", None), tmp_path / "run", log=lambda m: None)
    sto = json.loads((tmp_path / "run" / "summary.json").read_text())["methods"]["stochastic"]
    assert sto["noisy_gap_entries"] and sto["noisy_gap_entries"] == summary["methods"]["stochastic"]["noisy_gap_entries"]
    table = comparison_table(summary)
    assert sum("L_gap" in line for line in table.splitlines()) == 1


def test_bad_input_is_refused_by_name():
    nominal, sim = plant()
    ds = synthetic_dataset(sim, 0.2, 1, seed=0).with_nominal(nominal)
    one = centre_dataset(nominal, sim, (0.5, 2.0))  # one cell along v: no neighbours there
    with pytest.raises(SimgapError, match="neighbours along every covered dimension.*v has 1 value"):
        certify(one, method="deterministic", lipschitz_term="gap")
    with pytest.raises(SimgapError, match="lipschitz_term"):
        certify(ds, method="deterministic", lipschitz_term="tight")
    from simgap.synthesis.examples import dcdc_system
    from simgap.simulators.numpy_sim import NumpySimulator as NS
    dc = dcdc_system()
    dds = synthetic_dataset(NS(SimulatorConfig("numpy", "dcdc"), system=dc), 0.1, 1, seed=0)
    with pytest.raises(SimgapError, match="categorical"):
        certify(dds, method="deterministic", continuous_inputs=True)
    # a single input value: nothing between values to certify
    nominal1, sim1 = plant(counts=1)
    ds1 = synthetic_dataset(sim1, 0.2, 1, seed=0).with_nominal(nominal1)
    with pytest.raises(SimgapError, match="single value"):
        certify(ds1, method="deterministic", continuous_inputs=True)
    # gamma between grid values from a certificate made without continuous inputs
    cert = certify(ds, method="deterministic")
    with pytest.raises(SimgapError, match="continuous_inputs"):
        cert.gamma_sup([-1, -1], [1, 1], [-1], [1])


def test_a_cover_with_one_radius_per_dimension_from_the_experiment(tmp_path):
    from simgap.config import load_experiment
    body = '[system]\nname = "pendulum"\n[simulator]\nkind = "numpy"\n[collect]\nn_runs = 2\n'
    (tmp_path / "e.toml").write_text(body + "epsilon = [0.01, 0.02]\n")
    cov = load_experiment(tmp_path / "e.toml", profile=None).cover()
    assert np.allclose(cov.widths / 2, [0.01, 0.02]) and cov.radius <= cov.epsilon
    for bad, words in (("epsilon = [0.01, 0.0]", "epsilon[1]"), ("epsilon = [0.01, -1.0]", "epsilon[1]"),
                       ("epsilon = [0.01, 0.02]\nspacing = [0.02, 0.04]", "not both")):
        (tmp_path / "b.toml").write_text(body + bad + "\n")
        with pytest.raises(SimgapError, match=words.replace("[", r"\[").replace("]", r"\]")):
            load_experiment(tmp_path / "b.toml", profile=None)


def test_the_run_table_shows_both_terms_side_by_side():
    from simgap.pipeline import METHODS, comparison_table
    entry = lambda g, gp: {"gamma": {"max": g, "mean": g, "lipschitz_term": "gap", "max_paper_term": gp},
                           "confidence_per_dim": [None, None], "audit_pass_rate_joint": 1.0,
                           "audit_violated_joint": 0.0, "winning_cells": 5, "rollouts": {"skipped": "x"}}
    summary = {"system": {"state_names": ["p", "v"]},
               "methods": {m: entry([0.001, 0.002], [0.01, 0.02]) for m in METHODS}}
    table = comparison_table(summary)
    assert "gamma max [v] (gap's term)" in table and "gamma max [v] (paper's term)" in table
    line = next(l for l in table.splitlines() if l.strip().startswith("gamma max [v] (paper's term)"))
    assert line.split()[-1] == "0.02"


def test_slopes_the_common_draws_do_not_smooth_are_flagged_and_never_loosen_gamma():
    # a gap that flips with the actuation noise at a fine scale in p: common random numbers at two
    # nearby states do not cancel it, so the CRN slopes are noise over a short distance
    nominal, _ = plant()
    _, sim = plant(lambda x, u: 0.3 * np.sign(np.sin(400.0 * (x[:, 0] + u[:, 0]))))
    noisy = NumpySimulator(SimulatorConfig("numpy", "plant", noise={"actuation_std": 0.05}), system=sim.system)
    ds = synthetic_dataset(noisy, 0.2, 50, seed=6).with_nominal(nominal)
    cert = certify(ds, lipschitz_term="gap", lhat="simulator", lhat_pairs=200, lhat_runs=20, beta1=0.05,
                   beta2=0.05, simulator=noisy)
    how = cert.dims[1].gap_how["p"]
    assert how["noise_share"] > 0.5 and how["noise_floor"] > 0
    assert any("did not cancel" in w for w in cert.options["warnings"])
    # gamma takes the smaller term per dimension: an inflated estimate cannot loosen it past the paper's
    assert np.all(cert.lipschitz_terms() <= cert.paper_terms() + 1e-15)
    assert np.allclose(cert.lipschitz_terms(), np.minimum(cert.gap_terms(), cert.paper_terms()))


def test_common_draw_slopes_across_the_angle_seam_are_not_inflated():
    # heading+ = heading + dt (w + u) with held actuation noise: the gap is dt a in every run, the
    # same at both ends of a common-draw pair, so its slope along the heading is 0. Near +-pi the
    # runs' next headings straddle the seam; averaging the wrapped next states there is off by up
    # to pi (slopes of order 2 pi / runs / h), averaging the per-run increments is not.
    def step(x, u, dt):
        return np.stack([x[:, 0] + dt * (x[:, 1] + u[:, 0]), x[:, 1]], axis=1)

    kw = dict(state_names=("heading", "w"), input_names=("a",), x_lo=(-np.pi, -1.0), x_hi=(np.pi, 1.0),
              inputs=input_grid([-1.0], [1.0], [3]), base_tau=DT, angle_dims=(0,))
    nominal = System(name="turn", step=step, **kw)
    sim = NumpySimulator(SimulatorConfig("numpy", "turn", noise={"actuation_std": 2.0}), system=nominal)
    from simgap.certify.lipschitz import crn_pair_means, gap_slopes_crn
    rng = np.random.default_rng(3)
    sl, se = gap_slopes_crn(sim, nominal, rng, "x", 0, 0.05, 400, 20, nominal.inputs)
    assert sl[:, 0].max() < 1e-9 and se[:, 0].max() < 1e-9
    # the mean next state itself, at a pair straddling the seam, against the per-run truth
    x = np.array([[np.pi - 0.01, 0.0]])
    m1, m2 = crn_pair_means(sim, x, x, np.zeros((1, 1)), np.zeros((1, 1)), 200, np.random.default_rng(0),
                            increment=False)
    assert abs(nominal.diff(m1, nominal.f(x, np.zeros((1, 1))))[0, 0]) < 0.1   # E[dt a] = 0, SE 0.014
    ds = synthetic_dataset(sim, 0.2, 40, seed=1).with_nominal(nominal)
    cert = certify(ds, lipschitz_term="gap", lhat="simulator", lhat_pairs=200, lhat_runs=20, beta1=0.05,
                   beta2=0.05, simulator=sim)
    assert cert.dims[0].L_gap[0] < 1e-6


def test_compare_prints_its_estimate_first_one_bar_and_computes_the_gap_term_once(tmp_path, capsys, monkeypatch):
    """`simgap certify --compare` with the gap's term from the simulator: the first line is the
    estimate (with the simulator runs' count), one progress bar covers every certification, and the
    Lipschitz constants (the gap's matrix with its simulator runs, Lhat_fhat) are computed once for
    all the bound options, not once per option."""
    from simgap.certify import pipeline
    from simgap.cli import main
    cfg = {"kind": "numpy", "system": "pendulum", "noise": {"actuation_std": 0.05},
           "effects": {"linear": [[0.0, 0.0], [0.0, -0.5]]}}
    data = synthetic_dataset(cfg, epsilon=0.04, n_runs=20, seed=3).save_npz(tmp_path / "d.npz")
    calls = {"gap": 0, "fhat": 0}
    gap_compute, fhat_crn = pipeline._gap_lipschitz_compute, pipeline.fhat_slopes_crn

    def counted_gap(*a, **k):
        calls["gap"] += 1
        return gap_compute(*a, **k)

    def counted_fhat(*a, **k):
        calls["fhat"] += 1
        return fhat_crn(*a, **k)
    monkeypatch.setattr(pipeline, "_gap_lipschitz_compute", counted_gap)
    monkeypatch.setattr(pipeline, "fhat_slopes_crn", counted_fhat)
    assert main(["certify", str(data), "--compare", "--lipschitz-term", "gap", "--lhat", "simulator"]) == 0
    cap = capsys.readouterr()
    lines = cap.out.splitlines()
    assert lines[0].startswith("estimate: --compare certifies the data under 5 bound options")
    assert "simulator runs" in lines[0] and "for the gap's own Lipschitz term" in lines[0]
    assert lines[1].startswith("option") and "sub-Gaussian, uniform over K rows" in cap.out
    # one progress (off a terminal: a line per update): every line is the same "compare" progress, ending at 5 of 5
    draws = [d for d in cap.err.replace("\r", "\n").splitlines() if d.strip()]
    assert draws and all(d.startswith("compare:") for d in draws)
    assert "5/5 certifications" in draws[-1]
    assert calls == {"gap": 1, "fhat": 1}
    # the same data certified again in this process: nothing simulated again, and the same gamma
    from simgap.certify import certify
    from simgap.dataset import load_dataset
    ds = load_dataset(data)
    a = certify(ds, lipschitz_term="gap", lhat="simulator")
    b = certify(ds, lipschitz_term="gap", lhat="simulator", beta1=0.02, beta2=0.02)
    assert calls == {"gap": 2, "fhat": 2} and a.dims[1].L_gap == b.dims[1].L_gap
    # other slope draws (another seed) are not answered from the memo
    certify(ds, lipschitz_term="gap", lhat="simulator", seed=1)  # the default seed is 0
    assert calls["gap"] == 3 and calls["fhat"] == 3
    assert pipeline.simulator_rows(ds, pipeline.CertifyOptions(lipschitz_term="gap", lhat="simulator"))["rows"] == 0


def test_a_local_certificates_gap_slopes_are_drawn_in_its_region():
    """A wall at p = 0.8 (outside the region p in [-0.5, 0.5]) puts a steep gap there: pairs drawn in the
    simulator's X find it, pairs drawn in the region (``box``, what certify passes for a local or tube
    certificate: its gamma is stated there only) do not, and every simulated row lies in the region."""
    nominal, sim = plant(gap_v=lambda x, u: 50.0 * np.maximum(x[:, 0] - 0.8, 0.0))
    from simgap.certify.lipschitz import gap_slopes_crn
    seen = []
    step = sim.step_with_noise
    sim.step_with_noise = lambda x, u, noise: (seen.append(x.copy()), step(x, u, noise))[1]
    box = (np.array([-0.5, -1.0]), np.array([0.5, 1.0]))
    sl_x, _ = gap_slopes_crn(sim, nominal, np.random.default_rng(0), "x", 0, 0.1, 200, 2, nominal.inputs)
    sl_box, _ = gap_slopes_crn(sim, nominal, np.random.default_rng(0), "x", 0, 0.1, 200, 2, nominal.inputs,
                               box=box)
    assert sl_x[:, 1].max() > 1.0 and sl_box[:, 1].max() < 1e-9
    rows = seen[-1]
    assert np.all(rows >= box[0] - 1e-12) and np.all(rows <= box[1] + 1e-12)
