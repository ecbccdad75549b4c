"""A cover along a tube (issue 52 item 5): cover points only in the boxes a box tube reads gamma
over; the certificate holds in their union, and every consumer refuses a set inside none of them
(a set in the boxes' hull but between them included)."""

import json

import numpy as np
import pytest

from simgap.certify import BoundOptions, certify, load
from simgap.certify.audit import audit
from simgap.collect import CollectionPlan, collect, load_store
from simgap.cover import CoverSpec, make_cover
from simgap.errors import SimgapError
from simgap.simulators import make_simulator
from simgap.simulators.base import SimulatorConfig
from simgap.synthesis.box_tube import _check_region
from simgap.synthesis.invariant_set import gap_bound
from simgap.systems import get_system
from simgap.tube_cover import grid_size, tube_boxes

PEND_CFG = {"kind": "numpy", "system": "pendulum", "noise": {"process_std": 0.002},
            "effects": {"linear": [[0.0, 0.0], [0.0, -0.5]]}}


def _plan(T=30):
    """An L-shaped plan in the pendulum's X: theta from -0.15 to 0.15 at omega = -0.3, then omega up to 0.3."""
    a = np.linspace(-0.15, 0.15, T)
    leg1 = np.stack([a, np.full(T, -0.3)], axis=1)
    leg2 = np.stack([np.full(T, 0.15), np.linspace(-0.3, 0.3, T)], axis=1)
    return np.concatenate([leg1, leg2[1:]])


def _spec(eps=0.03, margin=0.01, T=12):
    s = get_system("pendulum")
    lo, hi = tube_boxes(s.x_lo, s.x_hi, _plan(T), margin=margin)
    return s, CoverSpec(epsilon=eps, boxes=tuple(zip(lo.tolist(), hi.tolist()))), (lo, hi)


def test_every_point_of_the_union_is_within_epsilon():
    """The cover property on the union of the boxes: 20,000 random points of the union (a random box,
    then uniform in it) are each within epsilon of a cover point, and the achieved radius is attained
    nearly (a cover with fewer points would fail it: dropping every second point does)."""
    s, spec, (lo, hi) = _spec()
    c = make_cover(s, spec)
    rng = np.random.default_rng(0)
    b = rng.integers(0, len(lo), 20000)
    x = lo[b] + rng.random((20000, 2)) * (hi[b] - lo[b])
    from scipy.spatial import cKDTree
    d, _ = cKDTree(c.points).query(x)
    assert d.max() <= c.radius <= c.epsilon
    assert d.max() > 0.7 * c.radius
    d_half, _ = cKDTree(c.points[::2]).query(x)
    assert d_half.max() > c.epsilon
    # the points lie in the boxes, none in the hull's empty corner (theta > 0, omega < 0.2 away from the legs)
    assert np.all(np.any(np.all((c.points[:, None] >= lo[None]) & (c.points[:, None] <= hi[None]), axis=2), axis=1))
    assert not np.any((c.points[:, 0] < 0.08) & (c.points[:, 1] > -0.2))


def test_wide_boxes_take_the_hulls_grid():
    """Boxes wider than the spacing that overlap from period to period: the grid over their hull has
    fewer points than their grids together, and is taken (it covers the union too)."""
    s, spec, (lo, hi) = _spec(margin=0.03, T=30)
    c = make_cover(s, spec)
    from simgap.tube_cover import box_grid_points, default_spacing
    h = default_spacing(0.03, 2)
    per_box = sum(int(np.prod(np.ceil((b - a) / h * (1 - 1e-12)))) for a, b in zip(lo, hi))
    assert c.N == grid_size(hi.max(0) - lo.min(0), h) < per_box
    rng = np.random.default_rng(1)
    b = rng.integers(0, len(lo), 5000)
    x = lo[b] + rng.random((5000, 2)) * (hi[b] - lo[b])
    from scipy.spatial import cKDTree
    assert cKDTree(c.points).query(x)[0].max() <= c.radius <= c.epsilon


def test_size_grows_with_the_horizon_not_the_dimension():
    """A tube narrower than the spacing costs one point per period: at 4, 6 and 14 states the same plan
    length gives the same count, while the grid over X grows exponentially."""
    counts = {}
    for n in (4, 6, 14):
        T = 50
        x_lo, x_hi = -np.ones(n), np.ones(n)
        xn = np.linspace(-0.8, 0.8, T)[:, None] * np.ones(n)
        eps = 0.2
        margin = 0.9 * eps / np.sqrt(n)  # the box's half-diagonal below epsilon: one cell per dimension
        lo, hi = tube_boxes(x_lo, x_hi, xn, margin=margin)
        from simgap.tube_cover import box_grid_points, default_spacing
        pts, _ = box_grid_points(lo, hi, range(n), default_spacing(eps, n))
        counts[n] = len(pts)
        assert grid_size(x_hi - x_lo, default_spacing(eps, n)) > 10 ** (n // 2)
    assert counts == {4: 50, 6: 50, 14: 50}


def test_bad_boxes_are_refused():
    s = get_system("pendulum")
    with pytest.raises(SimgapError, match="box 0 leaves X in omega"):
        make_cover(s, CoverSpec(epsilon=0.05, boxes=(([-0.1, -0.6], [0.1, 0.1]),)))
    with pytest.raises(SimgapError, match="lo < hi"):
        make_cover(s, CoverSpec(epsilon=0.05, boxes=(([0.1, 0.0], [0.1, 0.1]),)))
    with pytest.raises(SimgapError, match="region or boxes"):
        make_cover(s, CoverSpec(epsilon=0.05, boxes=(([-0.1, 0.0], [0.1, 0.1]),), region={"theta": [-0.1, 0.1]}))
    with pytest.raises(SimgapError, match="margin is 0"):
        tube_boxes(s.x_lo, s.x_hi, _plan(), margin=0.0)
    with pytest.raises(SimgapError, match="margin must be finite"):
        tube_boxes(s.x_lo, s.x_hi, _plan(), margin=-1.0)


@pytest.fixture(scope="module")
def tube_cert(tmp_path_factory):
    s, spec, boxes = _spec()
    plan = CollectionPlan(system=s, simulator=SimulatorConfig.from_dict(PEND_CFG), cover=make_cover(s, spec),
                          n_runs=20, seed=3, chunk_size=200)
    store = tmp_path_factory.mktemp("tube") / "data"
    collect(plan, store, executor="serial")
    ds = load_store(store)
    return ds, certify(ds, degree=1, bounds=BoundOptions(concentration="subgaussian"),
                       lipschitz_term="gap"), boxes


def test_certificate_holds_in_the_union_only(tube_cert, tmp_path):
    """The certificate records the boxes (their hull as its region) and is uniform; a box inside one of
    them is accepted by every consumer, a box inside the HULL but between the legs is refused by each
    (a certificate checking the hull alone would accept it), and so is a box straddling two boxes that do
    not contain it together. The boxes survive a JSON round trip and cannot be edited."""
    ds, cert, (lo, hi) = tube_cert
    assert cert.region_boxes is not None and len(cert.region_boxes[0]) == len(lo)
    assert np.allclose(cert.region[0], lo.min(axis=0)) and np.allclose(cert.region[1], hi.max(axis=0))
    assert cert.scope == "simultaneous"
    u = cert.inputs[:1]
    inside = (np.array([-0.1, -0.31]), np.array([-0.09, -0.29]))       # on the first leg
    between = (np.array([-0.1, 0.1]), np.array([-0.09, 0.12]))         # in the hull, off both legs
    assert np.all(np.isfinite(cert.gamma_upper_box(inside[0][None], inside[1][None], u)))
    assert _check_region(cert, *inside, "a box") == ""
    gap_bound(cert, 2, *inside, u[0], u[0])
    for fn in (lambda: cert.gamma_upper_box(between[0][None], between[1][None], u),
               lambda: gap_bound(cert, 2, *between, u[0], u[0]),
               lambda: cert.require_inside(*between, "a box")):
        with pytest.raises(SimgapError, match="lies in none of the"):
            fn()
    assert "lies in none of the" in _check_region(cert, *between, "the tube at period 3")
    cert.save(tmp_path / "c.json")
    back = load(tmp_path / "c.json")
    assert np.array_equal(back.region_boxes[0], cert.region_boxes[0])
    with pytest.raises(SimgapError, match="lies in none"):
        back.require_inside(*between, "a box")
    d = json.loads((tmp_path / "c.json").read_text())
    d["region_boxes"] = [[[-0.2, -0.5]], [[0.2, 0.5]]]  # one box over the hull: refused
    (tmp_path / "c.json").write_text(json.dumps(d))
    with pytest.raises(SimgapError, match="modified|malformed"):
        load(tmp_path / "c.json")


def test_gap_term_radius_is_the_widest_cell(tube_cert):
    """The gap's own Lipschitz term uses eps_j >= half the widest cell over the boxes, not only half the
    distance between neighbouring values of the union (which the boxes' shifted grids can make small)."""
    ds, cert, _ = tube_cert
    w = np.asarray(ds.manifest["cover"]["widths"])
    assert np.all(cert.radii >= 0.5 * w - 1e-12)
    from simgap.certify.lipschitz import axis_grid
    from simgap.certify.pipeline import _region_dataset
    naive = axis_grid(_region_dataset(ds), [0, 1]).radii  # half the gaps between the union's values
    assert np.allclose(cert.radii, np.maximum(naive, 0.5 * w))


def test_audit_draws_in_the_boxes(tube_cert):
    """The audit's fresh points lie in the boxes (not in the hull between them), and gamma holds there."""
    from simgap.certify.audit import draw_points
    ds, cert, (lo, hi) = tube_cert
    x, _ = draw_points(get_system("pendulum"), 500, np.random.default_rng(0), boxes=cert.region_boxes)
    assert np.all(np.any(np.all((x[:, None] >= lo[None]) & (x[:, None] <= hi[None]), axis=2), axis=1))
    with make_simulator(PEND_CFG) as sim:
        rep = audit(cert, sim, points=20, runs=50, seed=1, dataset=ds)
    assert rep["joint"]["fraction_holds"] >= 0.9


def test_tube_margin_refusals(tmp_path):
    """[collect] tube_margin without a box tube, with a region, or of the wrong size is refused by name
    before any synthesis or data; a negative margin when the file is loaded."""
    from simgap.config import load_experiment
    from simgap.tube_collect import along_tube
    from test_rounds import EXPERIMENT, LIN
    (tmp_path / "lin.toml").write_text(LIN)

    def exp(text):
        (tmp_path / "e.toml").write_text(text)
        return load_experiment(tmp_path / "e.toml")

    with pytest.raises(SimgapError, match='needs \\[synthesis\\] method = "box_tube"'):
        along_tube(exp(EXPERIMENT.replace('method = "box_tube"', 'method = "invariant_set"')))
    with pytest.raises(SimgapError, match="one value or 2"):
        along_tube(exp(EXPERIMENT.replace("tube_margin = 0.3", "tube_margin = [0.1, 0.2, 0.3]")))
    with pytest.raises(SimgapError, match="a region or a tube_margin"):
        along_tube(exp(EXPERIMENT.replace("tube_margin = 0.3", "tube_margin = 0.3\nregion = { a = [-0.5, 0.5] }")))
    with pytest.raises(SimgapError, match="tube_margin"):
        exp(EXPERIMENT.replace("tube_margin = 0.3", "tube_margin = -0.3"))


def test_simulator_slopes_on_a_tube_narrower_than_the_pairs(tmp_path):
    """lhat = "simulator" on a tube whose boxes' hull is narrower than the paper's pairs (2 eps) along theta:
    with lipschitz_term = "gap" the certificate is made, gamma's Lipschitz term is the gap's own from the
    simulator's axis pairs (no neighbours needed), the paper's Lhat_fhat comes from the data's slopes and
    says so, and no run is spent on the paper's pairs; with the paper's term alone it is refused, naming
    the pair distance (the paper's term would have no estimate)."""
    from simgap.certify.pipeline import CertifyOptions, simulator_rows
    s = get_system("pendulum")
    leg = np.stack([np.full(12, 0.15), np.linspace(-0.3, 0.3, 12)], axis=1)   # along omega, theta fixed
    lo, hi = tube_boxes(s.x_lo, s.x_hi, leg, margin=0.01)
    assert np.ptp(np.r_[lo[:, 0], hi[:, 0]]) < 2 * 0.03
    spec = CoverSpec(epsilon=0.03, boxes=tuple(zip(lo.tolist(), hi.tolist())))
    plan = CollectionPlan(system=s, simulator=SimulatorConfig.from_dict(PEND_CFG), cover=make_cover(s, spec),
                          n_runs=20, seed=3, chunk_size=200)
    collect(plan, tmp_path / "data", executor="serial")
    ds = load_store(tmp_path / "data")
    kw = dict(degree=0, bounds=BoundOptions(concentration="subgaussian"), lhat="simulator", lhat_pairs=200,
              lhat_runs=20)
    rows = simulator_rows(ds, CertifyOptions(lipschitz_term="gap", **kw))
    assert rows["fhat_rows"] == 0 and rows["gap_rows"] > 0
    cert = certify(ds, lipschitz_term="gap", **kw)
    how = cert.dims[1].lipschitz_how["L_fhat"]["how"]
    assert "do not fit in the region the data covered" in how
    assert np.all(np.isfinite(cert.lipschitz_terms())) and np.all(cert.lipschitz_terms() <= cert.paper_terms())
    with pytest.raises(SimgapError, match="pair distance"):
        certify(ds, lipschitz_term="paper", **kw)


def _lin_experiment(tmp_path, collect_extra="", synthesis_extra=""):
    """test_rounds' linear system with the actuation noise 0.001 (a narrow tube under the gap) and no design
    keys beyond ``synthesis_extra``; the margins 0.05, 0.02 are narrower than the plans' spread in b across paces."""
    from simgap.config import load_experiment
    from test_rounds import EXPERIMENT, LIN
    (tmp_path / "lin.toml").write_text(LIN)
    text = (EXPERIMENT.replace("K = [[-0.434763, -1.257824]]\n", "").replace("plan_input_weight = 1.0\n", synthesis_extra)
            .replace("actuation_std = 0.05", "actuation_std = 0.001").replace("tube_margin = 0.3", "tube_margin = [0.05, 0.02]")
            .replace("n_runs = 4", "n_runs = 8" + collect_extra).replace("epsilon = 0.1", "epsilon = 0.04"))
    (tmp_path / "e.toml").write_text(text)
    return load_experiment(tmp_path / "e.toml")


def _nominal(exp, pace):
    from simgap.experiment_spec import experiment_spec
    from simgap.synthesis import set_synthesis
    syn = dict(exp.section("synthesis"), terminal="smallest", margin_search=False, per_run=False,
               plan_input_weight=pace)
    return set_synthesis.synthesize(exp.system, experiment_spec(exp)[0], None, syn,
                                    x0=np.asarray(exp.section("rollout")["x0"], float)).controller


def _in_some_box(lo, hi, blo, bhi, tol=1e-9):
    """Per row of (lo, hi): does it lie inside one of the boxes (blo, bhi)? (the test's own check, not the
    certificate's)."""
    lo, hi = np.atleast_2d(lo), np.atleast_2d(hi)
    return np.any(np.all((lo[:, None] >= blo[None] - tol) & (hi[:, None] <= bhi[None] + tol), axis=2), axis=1)


def _tube_in_boxes(ctrl, boxes) -> bool:
    """Every box the proof read gamma over lies in one of the data's boxes: the mean's tube x_nom(t) +- h_t,
    its terminal box x* +- H, and the per-run noise tube's boxes when there is one."""
    blo, bhi = boxes
    sets = [(ctrl.x_nom - ctrl.radii, ctrl.x_nom + ctrl.radii), (ctrl.x_star - ctrl.H, ctrl.x_star + ctrl.H)]
    nt = ctrl.noise_tube
    if nt is not None:
        sets += [(ctrl.x_nom - nt.radii, ctrl.x_nom + nt.radii), (ctrl.x_star - nt.H, ctrl.x_star + nt.H)]
    return all(_in_some_box(lo, hi, blo, bhi).all() for lo, hi in sets)


def test_the_cover_holds_every_pace_the_search_may_choose(tmp_path):
    """With no pace given, the cover along the tube holds the nominal plan of EVERY pace the design search
    ranks (the stochastic synthesis chooses among them after the data are in), each period's box with its
    margin inside one of the cover's boxes; with a pace given, that pace's boxes only; a plan outlasting
    the rollouts' horizon is left out (the search ranks it as unproved)."""
    from simgap.synthesis.tube_design import PACES
    from simgap.tube_collect import along_tube
    exp = _lin_experiment(tmp_path)
    lines = []
    boxes = [np.array(b) for b in zip(*along_tube(exp, lines.append).collect.boxes)]
    T0 = {}
    for pace in PACES:
        c = _nominal(exp, pace)
        T0[pace] = c.T0
        mg = np.array([0.05, 0.02])
        lo = np.maximum(c.x_nom - mg, exp.system.x_lo)
        hi = np.minimum(c.x_nom + mg, exp.system.x_hi)
        assert _in_some_box(lo, hi, *boxes).all(), pace
    assert len(set(T0.values())) > 1  # the paces' plans differ
    one = [np.array(b) for b in zip(*along_tube(_lin_experiment(tmp_path, synthesis_extra="plan_input_weight = 1000.0\n"),
                                                lines.append).collect.boxes)]
    assert len(one[0]) < len(boxes[0]) and "pace x1000 (" in lines[-1] and "pace x1 (" not in lines[-1]
    import dataclasses
    exp_h = dataclasses.replace(exp, sections={**exp.sections, "rollout": dict(exp.section("rollout"),
                                                                              horizon=T0[1.0] + 1)})
    along_tube(exp_h, lines.append)
    assert f"its plan's {T0[100.0]} periods outlast the runs' horizon {T0[1.0] + 1}" in lines[-1]


@pytest.fixture(scope="module")
def pace1_cert(tmp_path_factory):
    """Data along the tube of pace x1 only (the pace given at collection), certified uniformly."""
    from simgap.certify.pipeline import certify as certify_ds
    from simgap.collect import collect as collect_plan
    from simgap.pipeline import certify_options
    from simgap.tube_collect import along_tube
    tmp = tmp_path_factory.mktemp("pace1")
    exp = along_tube(_lin_experiment(tmp, synthesis_extra="plan_input_weight = 1.0\n"), log=lambda m: None)
    collect_plan(exp.plan(), tmp / "data", executor="serial")
    ds = load_store(tmp / "data", system=exp.system)
    cert = certify_ds(ds, certify_options(exp.section("certify"), "stochastic", exp.system))
    return exp, cert


def test_no_proof_is_accepted_on_a_tube_that_leaves_the_datas_boxes(pace1_cert):
    """Data along pace x1's tube only. The covered pace proves and its tube (mean, terminal box, per-run
    noise tube) lies in the data's boxes by the test's own containment check; pace x1000's plan runs
    between the boxes (inside their hull: a certificate checking the hull would accept it) and is refused
    by the proof's region condition; the design search, free to choose any pace, returns a proof whose
    every box lies in the data's boxes."""
    from simgap.experiment_spec import experiment_spec
    from simgap.synthesis import set_synthesis
    exp, cert = pace1_cert
    spec, x0 = experiment_spec(exp)[0], np.asarray(exp.section("rollout")["x0"], float)
    syn = exp.section("synthesis")
    boxes = cert.region_boxes
    quick = dict(syn, margin_search=False, per_run=False)
    ok = set_synthesis.synthesize(exp.system, spec, cert, dict(quick, plan_input_weight=1.0), x0=x0)
    assert not ok.empty and _tube_in_boxes(ok.controller, boxes)
    slow = _nominal(exp, 1000.0)
    assert not _in_some_box(slow.x_nom, slow.x_nom, *boxes).all()                  # between the boxes ...
    assert np.all(slow.x_nom >= cert.region[0]) and np.all(slow.x_nom <= cert.region[1])  # ... in their hull
    bad = set_synthesis.synthesize(exp.system, spec, cert, dict(quick, plan_input_weight=1000.0), x0=x0)
    assert bad.empty and "boxes inside the certificate's region fails" in bad.stats["diagnosis"]
    free = {k: v for k, v in syn.items() if k != "plan_input_weight"}
    chosen = set_synthesis.synthesize(exp.system, spec, cert, free, x0=x0, horizon=100)
    assert not chosen.empty and chosen.controller.noise_tube is not None  # the per-run tube is checked too
    assert _tube_in_boxes(chosen.controller, boxes)
    designs = chosen.stats["designs"]
    assert any(not d["proved"] for d in designs if d["pace"] >= 100)  # the uncovered paces were tried and refused


class _Scaled:
    """A certificate whose gamma is k times the real one's (everything else delegated): a gap the tube
    cannot hold inside the data's boxes at its certified size."""

    def __init__(self, cert, k):
        self._cert, self._k = cert, k

    def __getattr__(self, name):
        return getattr(self._cert, name)

    def gamma_sup(self, *a):
        return self._k * np.asarray(self._cert.gamma_sup(*a))


def test_levers_when_the_tube_leaves_the_datas_boxes(pace1_cert):
    """The levers table when the tube at the certified gap leaves the data's boxes (gamma 40 x the
    certificate's on pace x1's data): its gamma column is the gap over the tube at the tolerable factor
    (finite, not the inf of the boxes without data), and it names the boxes and the margin; on a plan that
    runs between the boxes at every factor (pace x1000) each state says no reduction of gamma helps."""
    from simgap.experiment_spec import experiment_spec
    from simgap.synthesis import set_synthesis
    exp, cert = pace1_cert
    spec, x0 = experiment_spec(exp)[0], np.asarray(exp.section("rollout")["x0"], float)
    syn = dict(exp.section("synthesis"), per_run=False)
    wide = set_synthesis.synthesize(exp.system, spec, _Scaled(cert, 40.0), dict(syn, plan_input_weight=1.0), x0=x0)
    assert wide.empty and 0 < wide.stats["gap_scale"] < 1
    rows = wide.stats["levers"]["states"]
    assert all(np.isfinite(r["gamma"]) and r["tolerable"] == pytest.approx(wide.stats["gap_scale"] * r["gamma"])
               for r in rows)
    assert any("leaves the data's boxes" in ln and "tube_margin" in ln for ln in wide.stats["levers_text"])
    off = set_synthesis.synthesize(exp.system, spec, cert, dict(syn, plan_input_weight=1000.0), x0=x0)
    assert off.empty and off.stats["gap_scale"] == 0
    assert all(r["tolerable"] is None and "no reduction of gamma helps" in r["text"]
               for r in off.stats["levers"]["states"])
def test_inputs_by_point_match_the_dense_grid(tube_cert):
    """The input grid per cover point (``by_point``, used along a tube with simulator slopes: its points are
    no grid over the states, whose dense grid has prod_j (values along j) cells, 234^14 for the KUKA's tube)
    gives the dense grid's radii and the same input neighbours; its states get radii and no neighbours."""
    from simgap.certify.lipschitz import axis_grid
    from simgap.certify.pipeline import _region_dataset
    ds = _region_dataset(tube_cert[0])
    dense, by = axis_grid(ds, [0, 1], [0]), axis_grid(ds, [0, 1], [0], by_point=True)
    assert by.dims == dense.dims and np.array_equal(by.radii, dense.radii)
    assert np.array_equal(by.input_radii, dense.input_radii)
    n = ds.system.n
    pairs = (lambda g: sorted(zip(g.neighbours[n][0].tolist(), g.neighbours[n][1].tolist())))
    assert pairs(by) == pairs(dense) and len(pairs(by)) > 0
    assert all(by.neighbours[j][0].size == 0 for j in (0, 1))
