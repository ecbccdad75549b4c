"""Soundness at tight margins: tests that a wrong abstraction or certificate would fail.

Each test here is aimed at one wrong implementation (``bench/mutations.py`` applies them and
checks that these tests catch every one): gamma bounded at cell centres or halved, the angle
seam ignored, synthesis over inputs the certificate did not certify, and gamma's constant
terms (delta_2, L_x * epsilon) dropped.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from simgap.synthesis.examples import integrator_system
from simgap.certify.basis import Basis
from simgap.certify.certificate import Certificate, DimCertificate
from simgap.errors import SimgapError
from simgap.synthesis.abstraction import build_abstraction, gamma_upper_wrapped
from simgap.synthesis.grid import UniformGrid
from simgap.systems import System, get_system, input_grid


def poly_certificate(system: System, terms, q, *, epsilon=0.0, L=(0.0, 0.0, 0.0), delta2=0.0, inputs=None):
    """A certificate with gamma_i = (L_f + Lhat + L_2) eps + q_i^T p_i(x, u) + delta_2 (hand-made)."""
    dims = []
    for t, c in zip(terms, q):
        basis = Basis(system, list(t))
        dims.append(DimCertificate(
            terms=list(t), q=np.asarray(c, float), delta1=0.0, delta2=float(delta2), beta1=0.01, beta2=0.01,
            beta_v=0.0, Mhat=1.0, L_f=float(L[0]), L_fhat=float(L[1]), L_2=float(L[2]), lipschitz_how={},
            repair=0.0, eta=0.0, gap_max=0.0, scp={}, basis=basis))
    return Certificate(system_name=system.name, steps=system.steps, state_names=system.state_names,
                       input_names=system.input_names, x_lo=system.x_lo, x_hi=system.x_hi,
                       angle_dims=system.angle_dims, epsilon=float(epsilon), n_runs=100, K=1, method="stochastic",
                       options={}, dims=dims, provenance={},
                       inputs=system.inputs if inputs is None else np.asarray(inputs, float))


def corners(n):
    return np.array(list(itertools.product((-1.0, 1.0), repeat=n)))


def assert_abstraction_sound(system, ab, gamma, x, js):
    """Every extreme successor f(x,u) + s * gamma(x,u), s in {-1,1}^n, of every usable pair
    (cell of x, input j) lies in the pair's successor box. Returns the number of pairs checked."""
    X = np.repeat(x, len(js), axis=0)
    J = np.tile(js, len(x))
    U = system.inputs[J]
    _, _, ok = ab.successor_box(X, J)
    X, J, U = X[ok], J[ok], U[ok]
    fx, g = system.f(X, U), gamma(X, U)
    bad = 0
    for s in corners(system.n):
        nxt = system.wrap(fx + s * g)
        inside = ab.contains(X, J, nxt)
        bad += int(np.count_nonzero(~inside))
    assert bad == 0, f"{bad} extreme successors outside their successor boxes"
    return int(ok.sum())


# ---------------------------------------------------------------------------------------
# 1. the angle seam
# ---------------------------------------------------------------------------------------

def _seam_setup():
    tb = get_system("turtlebot")
    sysm = System(**{**tb.__dict__, "inputs": input_grid([-1, -1], [1, 1], [5, 5])})
    cert = poly_certificate(sysm, [["1"], ["1"], ["1", "theta"]], [[0.01], [0.01], [0.16, 0.05]])
    grid = UniformGrid(sysm.x_lo, sysm.x_hi, (0.2, 0.2, 2 * np.pi / 32), periodic=(2,))
    ab = build_abstraction(sysm, grid, gap=cert, invariant_dims=(0, 1))
    return sysm, cert, grid, ab


def test_seam_counterexample_from_the_review():
    """TurtleBot, 32 heading cells, gamma_theta = 0.16 + 0.05 theta, x = (1, 1, pi - 0.01), u = 0."""
    sysm, cert, grid, ab = _seam_setup()
    x = np.array([[1.0, 1.0, np.pi - 0.01]])
    j = np.array([int(np.flatnonzero(np.all(sysm.inputs == 0, axis=1))[0])])
    g = cert.gamma(x, sysm.inputs[j])[0]
    assert g[2] == pytest.approx(0.16 + 0.05 * (np.pi - 0.01))  # 0.317
    # the cell's gamma bound covers gamma at every point of the cell, both sides of the seam
    c = grid.x_to_multi(x)[0]
    centre = grid.multi_to_points(c)
    lo, hi = centre - grid.eta / 2, centre + grid.eta / 2
    assert gamma_upper_wrapped(cert, lo, hi, sysm.inputs[j], grid)[0, 2] >= g[2]
    # and the certified extreme successor lies in the successor box
    nxt = sysm.wrap(sysm.f(x, sysm.inputs[j]) + np.array([0.0, 0.0, 1.0]) * g)
    assert ab.contains(x, j, nxt)[0]
    assert_abstraction_sound(sysm, ab, cert.gamma, x, j)


def test_seam_states_sampled_near_pi(rng):
    """States on both sides of the seam (theta near +-pi), every input, every extreme successor."""
    sysm, cert, grid, ab = _seam_setup()
    B = 300
    x = np.column_stack([rng.uniform(0.5, 3.5, B), rng.uniform(0.5, 3.5, B),
                         np.where(rng.random(B) < 0.5, np.pi - rng.uniform(0, grid.eta[2] / 2, B),
                                  -np.pi + rng.uniform(0, grid.eta[2] / 2, B))])
    n = assert_abstraction_sound(sysm, ab, cert.gamma, x, np.arange(len(sysm.inputs)))
    assert n > 1000


# ---------------------------------------------------------------------------------------
# gamma that varies inside a cell (centre evaluation, halving)
# ---------------------------------------------------------------------------------------

def integrator(tau=0.07):
    return integrator_system(tau, hi=2.0)


def test_state_dependent_gamma_bounded_over_the_whole_cell(rng):
    """gamma_p = 0.003 + 0.3 p varies by 0.3 eta inside a cell (far more than the 1e-10 guard):
    states at the cells' corners and inside, every extreme successor in its box."""
    sysm = integrator()
    cert = poly_certificate(sysm, [["1", "p"], ["1", "q"]], [[0.003, 0.3], [0.002, 0.2]])
    grid = UniformGrid(sysm.x_lo, sysm.x_hi, 0.05)
    ab = build_abstraction(sysm, grid, gap=cert)
    ids = rng.choice(grid.size, 400)
    c = grid.points(ids)
    x = np.concatenate([c + 0.49999 * grid.eta, c + (rng.random(c.shape) - 0.5) * grid.eta * 0.999])
    n = assert_abstraction_sound(sysm, ab, cert.gamma, x, np.arange(len(sysm.inputs)))
    assert n > 3000


# ---------------------------------------------------------------------------------------
# 2. synthesis uses only the inputs the certificate certified
# ---------------------------------------------------------------------------------------

def test_synthesis_restricted_to_certified_inputs():
    from simgap.synthesis.controller import synthesize
    from simgap.synthesis.spec import Box, Spec
    pend = get_system("pendulum")                      # 21 inputs in [-1, 1]
    cert = poly_certificate(pend, [["1"], ["1"]], [[1e-4], [1e-3]], inputs=[[-1.0], [0.0], [1.0]])
    spec = Spec(kind="invariance", safe=Box([0.0, -0.5], [0.2, 0.5]))
    res = synthesize(pend, spec, (0.004, 0.01), gap=cert)
    ctrl = res.controller
    assert ctrl.n_inputs == 3 and np.array_equal(ctrl.inputs, [[-1.0], [0.0], [1.0]])
    assert ctrl.system.inputs.shape == (3, 1) and "restricted to the 3 inputs" in res.summary()
    assert res.stats["winning"] > 0
    used = ctrl.inputs[ctrl.input_index(ctrl.grid.points(np.flatnonzero(ctrl.winning_mask)))]
    assert np.all(np.isin(used, [-1.0, 0.0, 1.0]))
    # the abstraction itself refuses uncertified inputs, naming them
    grid = UniformGrid(pend.x_lo, pend.x_hi, (0.004, 0.01))
    with pytest.raises(SimgapError, match=r"18 of the 21 inputs .* not certified .*torque = \[-0.9\]"):
        build_abstraction(pend, grid, gap=cert)
    # no certified input at all: refused
    other = poly_certificate(pend, [["1"], ["1"]], [[1e-4], [1e-3]], inputs=[[0.05]])
    with pytest.raises(SimgapError, match="none is left"):
        synthesize(pend, spec, (0.004, 0.01), gap=other)


def test_cli_synthesize_turtlebot_with_a_small_certificate(tmp_path, capsys):
    """`simgap synthesize --system turtlebot --cert <25-input certificate>`: 25 inputs, not 441."""
    from simgap.cli import main
    from simgap.synthesis.controller import Controller
    tb = get_system("turtlebot", 30)
    small = input_grid([-1, -1], [1, 1], [5, 5])
    cert = poly_certificate(tb, [["1"], ["1"], ["1"]], [[0.005], [0.005], [0.01]], inputs=small)
    p = cert.save(tmp_path / "cert.json")
    out = tmp_path / "c.npz"
    rc = main(["synthesize", "--system", "turtlebot", "--cert", str(p), "--spec", "arena",
               "--eta", "0.2,0.2,0.4", "--out", str(out)])
    text = capsys.readouterr().out
    assert "inputs        25 (restricted to the 25 inputs the certificate covers (the system has 441" in text
    # exit 3: the controller is written, but the arena's x0 lies outside this small certificate's domain
    assert rc == 3 and Controller.load(out).n_inputs == 25


# ---------------------------------------------------------------------------------------
# 3. holding an input k periods does not silently compose a one-period certificate
# ---------------------------------------------------------------------------------------

def cos_system(tau=0.1):
    """f = (x1 + tau cos x2, x2): the review's counterexample, fhat adds w ~ N(0, s^2) to x2."""
    def step(x, u, dt):
        return np.stack([x[:, 0] + dt * np.cos(x[:, 1]), x[:, 1] + 0.0 * u[:, 0]], axis=1)

    def jac(u):
        J = np.zeros((u.shape[0], 2, 2))
        J[:, 0, 0] = J[:, 1, 1] = 1.0
        J[:, 0, 1] = tau
        return J

    return System(name="cosine", state_names=("p", "h"), input_names=("u",), x_lo=(0, -1.5), x_hi=(3, 1.5),
                  inputs=np.array([[0.0]]), base_tau=tau, step=step, jacobian_bound=jac)


def test_two_step_mean_is_not_the_composed_one_step_mean():
    """The one-step gap of fhat = (x1 + tau cos x2, x2 + w) is exactly 0, but the two-step mean
    differs from f(f(x)) by tau cos(x2) (exp(-s^2/2) - 1) (Monte Carlo, 6 standard errors)."""
    sysm, s, R = cos_system(), 0.5, 200_000
    rng = np.random.default_rng(5)
    x0 = np.array([1.0, 0.3])
    u = np.zeros((R, 1))
    X = np.repeat(x0[None], R, axis=0)
    one = sysm.f(X, u) + np.column_stack([np.zeros(R), s * rng.standard_normal(R)])
    assert np.abs(one.mean(axis=0) - sysm.f(x0[None], u[:1])[0]).max() < 6 * s / np.sqrt(R)  # gap 0
    two = sysm.f(one, u) + np.column_stack([np.zeros(R), s * rng.standard_normal(R)])
    ff = sysm.f(sysm.f(x0[None], u[:1]), u[:1])[0]
    want = sysm.base_tau * np.cos(x0[1]) * (np.exp(-s ** 2 / 2) - 1)     # -0.0112
    se = two[:, 0].std() / np.sqrt(R)
    assert abs(two[:, 0].mean() - ff[0] - want) < 6 * se and abs(want) > 20 * se


def test_hold_with_a_gap_needs_an_explicit_labelled_composition(tmp_path, capsys):
    from simgap.cli import main
    from simgap.synthesis.controller import Controller, synthesize
    from simgap.synthesis.spec import Box, Spec
    sysm = integrator()
    spec = Spec(kind="reach_avoid", target=Box([1.4, 1.4], [1.8, 1.8]))
    cert = poly_certificate(sysm, [["1"], ["1"]], [[0.002], [0.002]])
    with pytest.raises(SimgapError, match="compose a one-period gap 3 times"):
        synthesize(sysm, spec, 0.05, gap=cert, hold=3)
    with pytest.raises(SimgapError, match="compose_hold"):
        build_abstraction(sysm, UniformGrid(sysm.x_lo, sysm.x_hi, 0.05), gap=[0.002, 0.002], hold=3)
    res = synthesize(sysm, spec, 0.05, gap=cert, hold=3, compose_hold=True)
    assert res.stats["hold_mode"].startswith("composed") and "composed" in res.summary()
    assert synthesize(sysm, spec, 0.05, gap=cert).stats["hold_mode"].startswith("certified at the abstraction step")
    assert synthesize(sysm, spec, 0.05, hold=3).stats["hold_mode"].startswith("none")  # nominal: exact
    res.controller.save(tmp_path / "c.npz")
    assert Controller.load(tmp_path / "c.npz").meta["stats"]["hold_mode"].startswith("composed")
    # the CLI: refused with a message, accepted and labelled with --compose-hold
    args = ["synthesize", "--system", "pendulum", "--gamma", "1e-5,1e-4", "--safe", "0,0.2,-0.5,0.5",
            "--eta", "0.004,0.01", "--hold", "2", "--out", str(tmp_path / "p.npz")]
    assert main(args) == 2 and "--compose-hold" in capsys.readouterr().err
    assert main(args + ["--compose-hold"]) == 0
    assert "gap per step  composed" in capsys.readouterr().out
