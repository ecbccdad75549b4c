"""The box tube's per-run statement (simgap/synthesis/noise_tube.py) against Monte Carlo.

The cubic pendulum of tests/test_box_tube.py with a constant gap and Gaussian noise of known variance
added every period: the fraction of runs that leave the noise tube within T periods must stay below
the stated beta_noise(T) (plus 3 standard errors). Wrong versions are run too and must be caught:
the noise's response dropped or under-estimated (a tube as thin as the mean's), and the remainder's
noise term dropped."""

from types import SimpleNamespace

import numpy as np
import pytest

from simgap.synthesis import box_tube as bt
from simgap.synthesis import noise_tube as ntm
from simgap.synthesis.controller import Controller

from test_box_tube import GAP, X0, _spec, cubic  # noqa: F401  (the fixture)

SIGMA = np.array([2.4e-3, 8e-3])    # per-period noise std (th, w): beta_noise 0.05 over 2 T0 + 1 periods
LOUD = 2 * SIGMA                    # a statement that is vacuous (lam 2.1) and runs that leave the tube (5.7 %)
EXTRA = 60                          # periods after T0 in the statement


class NoisyGap(np.ndarray):
    """A constant gap (what gap_bound reads) with what a certificate tells the per-run statement:
    Mhat per state, a sub-Gaussian tail, per-period noise, a simultaneous confidence of 1."""

    @classmethod
    def make(cls, gap, mhat, concentration="subgaussian", randomize=None, conf=1.0):
        g = np.asarray(gap, float).view(cls)
        g.dims = [SimpleNamespace(Mhat=float(m)) for m in mhat]
        g.options = {"bounds": {"concentration": concentration}}
        g.provenance = {"simulator": {"randomize": randomize or {}}}
        g.conf = conf
        return g

    def sup_confidence(self):
        return self.conf


def _design(system, gap, horizon=None):
    return bt.synthesize_box_tube(system, _spec(system), gap, x0=X0, x_star=[0, 0], u_star=[0], margin_search=False,
                                  horizon=horizon)


def _escape_rate(ctrl, system, T, R=4000, seed=0, sigma=SIGMA):
    """Runs of x+ = f(x, u_t(x)) + w + n, n ~ N(0, SIGMA^2) each period, w at the gap's greedy outward
    vertex (half the runs) or a random vertex: the fraction that leaves the noise tube by period T."""
    rng = np.random.default_rng(seed)
    x = np.repeat(ctrl.x0[None], R, axis=0)
    traj = [x]
    with np.errstate(all="ignore"):
        for t in range(T):
            u = ctrl.input(x, strict=False, t=t)
            w = GAP * rng.choice([-1.0, 1.0], size=x.shape)
            w[: R // 2] = GAP * np.where(x[: R // 2] - ctrl.box_at(t).c >= 0, 1.0, -1.0)
            x = system.f(x, u) + w + sigma * rng.standard_normal(x.shape)
            traj.append(x)
    return 1.0 - float(ctrl.inside(np.stack(traj, axis=1), noise=True).mean())


@pytest.fixture(scope="module")
def noisy(cubic):  # noqa: F811
    res = _design(cubic, NoisyGap.make(GAP, SIGMA ** 2), horizon=None)
    T = 2 * res.controller.T0 + 1
    return res, T


def test_statement_is_stated_and_holds_against_monte_carlo(cubic, noisy):  # noqa: F811
    res, T = noisy
    nt = res.controller.noise_tube
    assert nt is not None, res.stats.get("noise_tube")
    assert nt.horizon == T and nt.lam > 3.0
    beta = nt.beta_noise(T)
    assert 0 < beta < 0.2                                  # a statement with content
    assert np.all(nt.radii >= res.controller.radii - 1e-12) and np.all(nt.H >= 0)
    rate = _escape_rate(res.controller, cubic, T)
    se = np.sqrt(max(beta, 1e-4) * (1 - beta) / 4000)
    assert rate <= beta + 3 * se, (rate, beta)
    assert nt.p_run(T) == pytest.approx(1 - beta)         # conf 1: beta_cert 0


def test_the_mean_tube_alone_is_left_by_noisy_runs(cubic, noisy):  # noqa: F811
    """Without the noise term the tube is the mean's: the same runs leave it far more often than the
    per-run statement allows (what dropping the noise would claim)."""
    res, T = noisy
    c = res.controller
    thin = Controller.__new__(type(c))
    thin.__dict__.update(c.__dict__)
    thin.noise_tube = ntm.NoiseTube(lam=c.noise_tube.lam, sigma=c.noise_tube.sigma, radii=c.radii, H=c.H,
                                    beta_cert=0.0, horizon=T)
    assert _escape_rate(thin, cubic, T) > 0.3


@pytest.mark.parametrize("factor", [0.3, 0.45])
def test_mutation_noise_response_underestimated_is_caught(cubic, monkeypatch, factor):  # noqa: F811
    """The search finds the largest lam the proof tolerates, so an under-estimated response proxy gives
    the same tube with a larger lam: a claim of fewer escapes than the runs show (at noise LOUD,
    where the true statement is vacuous and 5.7 % of the runs leave the tube)."""
    res = _design(cubic, NoisyGap.make(GAP, LOUD ** 2))
    T = 2 * res.controller.T0 + 1
    rate = _escape_rate(res.controller, cubic, T, sigma=LOUD)
    assert rate > 0.03 and res.controller.noise_tube.beta_noise(T) >= rate     # the right version holds
    orig = bt.noise_proxy
    monkeypatch.setattr(bt, "noise_proxy", lambda A, s, f=factor: f * orig(A, s))
    res = _design(cubic, NoisyGap.make(GAP, LOUD ** 2))
    claimed = res.controller.noise_tube.beta_noise(T)
    rate = _escape_rate(res.controller, cubic, T, sigma=LOUD)
    assert rate > claimed + 3 * np.sqrt(rate * (1 - rate) / 4000), (rate, claimed)


def test_noise_proxy_matches_the_linear_response_variance():
    """For z+ = A z + n with independent N(0, sigma^2) components, the proxy is at least the true std
    of z_t (equal for a diagonal A) and the empirical tail respects 2 exp(-lam^2 / 2)."""
    A = np.array([[0.9, 0.1], [-0.2, 0.7]])
    sigma = np.array([0.5, 2.0])
    T = 40
    proxy = ntm.noise_proxy(np.repeat(A[None], T, axis=0), sigma)
    rng = np.random.default_rng(1)
    z = np.zeros((20000, 2))
    for _ in range(T):
        z = z @ A.T + sigma * rng.standard_normal(z.shape)
    std = z.std(axis=0)
    assert np.all(proxy[T] >= std * 0.98)
    lam = 2.5
    assert np.all(np.mean(np.abs(z) > lam * proxy[T], axis=0) <= 2 * np.exp(-lam ** 2 / 2))
    D = np.diag([0.8, 0.5])
    pd = ntm.noise_proxy(np.repeat(D[None], T, axis=0), sigma)[T]
    exact = sigma * np.sqrt((1 - np.diag(D) ** (2 * T)) / (1 - np.diag(D) ** 2))
    assert np.allclose(pd, exact, rtol=1e-12)


@pytest.mark.parametrize("kw, why", [
    ({"mhat": None}, "no noise variance"),
    ({"concentration": "chebyshev"}, "Chebyshev"),
    ({"randomize": {"mass": 0.02}}, "once per run"),
])
def test_no_statement_without_its_assumptions(kw, why):
    mhat = kw.pop("mhat", SIGMA ** 2)
    g = NoisyGap.make(GAP, [0, 0] if mhat is None else mhat, **kw)
    if mhat is None:
        g.dims = [SimpleNamespace(Mhat=None)] * 2
    assert why in ntm.why_no_statement(g)
    assert "constant" in ntm.why_no_statement(GAP)


def test_randomization_switched_off_is_no_randomization():
    assert ntm.why_no_statement(NoisyGap.make(GAP, SIGMA ** 2, randomize={"mass": 0.0, "damping": 0.0})) is None


def test_controller_file_keeps_the_statement(noisy, tmp_path):
    res, T = noisy
    p = res.controller.save(tmp_path / "c.npz")
    c = Controller.load(p)
    assert c.noise_tube is not None and c.noise_tube.lam == res.controller.noise_tube.lam
    assert np.array_equal(c.noise_tube.radii, res.controller.noise_tube.radii)
    assert c.noise_tube.p_run(T) == res.controller.noise_tube.p_run(T)
    with pytest.raises(ValueError, match="up to"):
        c.noise_tube.beta_noise(T + 1)


def test_recording_draws_the_noise_tube(cubic, noisy, tmp_path):  # noqa: F811
    from simgap_viz.record import record_run
    res, _ = noisy
    info = record_run(tmp_path / "nt.rrd", cubic, spec=_spec(cubic),
                      methods={"stochastic": {"invariant_set": res.controller, "rollouts": None}})
    assert any(e.endswith("/noise_tube") for e in info["entities"]) and (tmp_path / "nt.rrd").is_file()
