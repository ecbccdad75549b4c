"""`simgap refine --effects affine_ct` on the cart-pole (issue 42 item 4): the damping the textbook
model lacks, acting through the mass matrix, found from one-step MuJoCo transitions as affine
continuous-time terms on v and omega, written as a system file, and carried into certify."""

import json

import numpy as np
import pytest

mujoco = pytest.importorskip("mujoco")

from simgap.config import load_experiment  # noqa: E402
from simgap.refine.data import Transitions  # noqa: E402
from simgap.simulators import make_simulator  # noqa: E402
from simgap.system_file import load_system_file  # noqa: E402
from tests.cli_helpers import refused, simgap  # noqa: E402


def _noise_free(exp, x, u):
    """MuJoCo's next states with no actuation noise and the nominal masses and damping."""
    with make_simulator(exp.simulator, exp.system) as sim:
        noise = sim.draw_noise(len(x), np.random.default_rng(0))
        quiet = {k: (np.ones_like(v) if k in ("mass", "damping") else np.zeros_like(v)) for k, v in noise.items()}
        return sim.step_with_noise(x, u, quiet)


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("ct")
    exp = load_experiment("cartpole", profile=None)
    s = exp.system
    rng = np.random.default_rng(1)
    B = 3000
    x = rng.uniform(s.x_lo, s.x_hi, (B, 4))
    u = s.inputs[rng.integers(0, len(s.inputs), B)]
    np.savez(tmp / "t.npz", x=x, u=u, x_next=_noise_free(exp, x, u), tau=s.tau)
    sysfile = exp.path.parent / exp.sections["system"]["name"]
    r = simgap("refine", "--system", sysfile, "--data", tmp / "t.npz", "--effects", "affine_ct",
               "--save-system", tmp / "ct.toml", "--out", tmp / "r.json", "--name", "cartpole_ct", cwd=tmp, timeout=600)
    assert r.returncode == 0, r.stderr
    return exp, tmp, json.loads((tmp / "r.json").read_text()), r.stdout


def test_noise_free_gap_falls_over_x(fitted):
    """10 terms (v, omega over 1, theta, v, omega, u); the held-out noise-free omega gap falls from about
    0.065 to below 2 % of it (measured 0.0658 -> 0.00049), v's likewise, and on fresh states with inputs
    between the grid values too."""
    exp, tmp, rep, out = fitted
    assert len(rep["effects"]) == 10 and rep["velocity_states"] == ["v", "omega"]
    assert rep["variables"] == ["1", "theta", "v", "omega", "u"]
    assert rep["max_before"][3] > 0.04 and rep["max_after"][3] < 0.02 * rep["max_before"][3]
    assert rep["max_after"][2] < 0.05 * rep["max_before"][2]
    assert "95 % interval" in out and "held-out" in out
    s = exp.system
    ct = load_system_file(tmp / "ct.toml")
    rng = np.random.default_rng(9)
    x = rng.uniform(s.x_lo, s.x_hi, (2000, 4))
    u = rng.uniform(-3, 3, (2000, 1))
    y = _noise_free(exp, x, u)
    before = np.abs(y - s.f(x, u)).max(axis=0)
    after = np.abs(y - ct.f(x, u)).max(axis=0)
    assert after[3] < 0.02 * before[3] and after[2] < 0.05 * before[2], (before, after)


def test_coefficients_are_the_damping_through_the_mass_matrix(fitted):
    """The fitted velocity terms are -M^-1 diag(c_slider, c_hinge) (v, omega) at theta = 0 with the
    MJCF's c = 1 for both joints: v <- v -(I + m l^2)/D, v <- omega m l/D, omega <- v m l/D,
    omega <- omega -(M + m)/D, D = (M + m)(I + m l^2) - (m l)^2 (within 3 %); each within its 95 %
    interval's reach of the expected value or 3 %. Fails if the cross terms are missed."""
    exp, tmp, rep, _ = fitted
    p = exp.system.params
    M, m, l, I = p["M"], p["m"], p["l"], p["I"]
    D = (M + m) * (I + m * l ** 2) - (m * l) ** 2
    want = {("v", "v"): -(I + m * l ** 2) / D, ("v", "omega"): m * l / D,
            ("omega", "v"): m * l / D, ("omega", "omega"): -(M + m) / D}
    got = {(e["state_name"], e["variable"]): e for e in rep["effects"]}
    for k, w in want.items():
        e = got[k]
        assert e["coefficient"] == pytest.approx(w, rel=0.03), (k, e["coefficient"], w)
        assert e["stderr"] > 0 and e["ci95"][0] < e["coefficient"] < e["ci95"][1]


def test_system_file_is_parsed_and_certify_reads_it(fitted, tmp_path):
    """Round trip: the written file is a system file (formulas through the allow-list; params ct_*),
    and `simgap certify DATA --system ct.toml` on MuJoCo data collected for the textbook model states a
    smaller observed gap and a smaller gamma in omega than the textbook model on the same runs."""
    from simgap.collect import CollectionPlan, collect
    from simgap.cover import CoverSpec, make_cover

    exp, tmp, rep, _ = fitted
    text = (tmp / "ct.toml").read_text()
    assert "ct_omega_omega" in text and "[definitions]" in text and "simgap refine --effects affine_ct" in text
    ct = load_system_file(tmp / "ct.toml")
    assert ct.name == "cartpole_ct" and ct.params["ct_omega_omega"] < -1.9
    from simgap.synthesis.interval_map import IntervalMap
    IntervalMap(ct)   # the invariant-set proof differentiates its formulas (refuses a model it cannot)
    # the growth bound is carried over: omega on omega now includes the fitted damping c_ii < 0
    G = ct.params["_system_file"]["bounds"]["growth"]
    assert G[3][3] == pytest.approx(0.06 + ct.params["ct_omega_omega"]) and G[2][3] > 0.03
    s = exp.system
    cover = make_cover(s, CoverSpec(epsilon=0.2, spacing=[0.05, 0.25, 0.25], invariant_dims=("p",), fixed={"p": 0.0}))
    plan = CollectionPlan(system=s, simulator=exp.simulator, cover=cover, n_runs=20, seed=3, chunk_size=2000)
    collect(plan, tmp_path / "data", executor="serial")
    certs = {}
    for tag, extra in (("textbook", []), ("ct", ["--system", tmp / "ct.toml"])):
        r = simgap("certify", tmp_path / "data", *extra, "--degree", "1", "--out", tmp_path / f"{tag}.json",
                   "--no-progress", cwd=tmp_path, timeout=600)
        assert r.returncode == 0, r.stderr
        certs[tag] = json.loads((tmp_path / f"{tag}.json").read_text())
    gap = {t: c["dims"][3]["gap_max"] for t, c in certs.items()}
    gmax = {t: c["dims"][3]["scp"]["gamma_range_on_data"][1] for t, c in certs.items()}
    assert certs["ct"]["system"]["name"] == "cartpole_ct"
    assert gap["ct"] < 0.5 * gap["textbook"], gap
    assert gmax["ct"] < gmax["textbook"], gmax


def test_bad_use_is_refused(fitted, tmp_path):
    """affine_ct with other effects, a .json target, a built-in system: refused by name, nothing written."""
    exp, tmp, _, _ = fitted
    sysfile = exp.path.parent / exp.sections["system"]["name"]
    r = simgap("refine", "--system", sysfile, "--data", tmp / "t.npz", "--effects", "affine_ct,bias", cwd=tmp_path)
    refused(r, "affine_ct is fitted on its own")
    r = simgap("refine", "--system", sysfile, "--data", tmp / "t.npz", "--effects", "affine_ct",
               "--save-system", tmp_path / "x.json", cwd=tmp_path)
    refused(r, "ending in .toml")
    r = simgap("refine", "--system", "pendulum", "--data", tmp / "t.npz", "--effects", "affine_ct", cwd=tmp_path)
    assert r.returncode != 0 and "Traceback" not in r.stderr
    assert not (tmp_path / "x.json").exists()
