"""Integration: the small pendulum profile end to end (collect, certify x2, audit x2, synthesize x2, roll out)."""

import json

import numpy as np
import pytest

from simgap.cli import main
from simgap.errors import SimgapError


@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("pendulum-small")
    rc = main(["run", "pendulum", "--profile", "small", "--out", str(out), "--workers", "2"])
    assert rc == 0
    return out, json.loads((out / "summary.json").read_text())


def test_summary_structure_and_sanity(small_run):
    out, s = small_run
    assert not (out / ".run.lock").exists()  # the run's lock goes with the run (issue 54)
    assert s["experiment"] == "pendulum" and s["profile"] == "small"
    from simgap.pipeline import SUMMARY_STATEMENTS
    assert s["statements"] == SUMMARY_STATEMENTS  # which statement each number is, in the file itself
    det, sto = s["methods"]["deterministic"], s["methods"]["stochastic"]
    n = len(s["system"]["state_names"])
    # confidences: stochastic in (0, 1) per dimension and jointly; the deterministic baseline states none
    assert all(0.0 < c < 1.0 for c in sto["confidence_per_dim"]) and 0.0 < sto["confidence_joint"] < 1.0
    assert det["confidence_joint"] is None
    # the stochastic gap pays for noise: at least the deterministic one in every dimension
    assert all(gs >= gd for gs, gd in zip(sto["gamma"]["max"], det["gamma"]["max"]))
    for e in (det, sto):
        assert len(e["gamma"]["max"]) == n
        assert 0.0 <= e["audit_pass_rate_joint"] <= 1.0
        assert e["winning_cells"] > 0
    # a larger gap cannot give a larger winning domain on the same grid
    assert sto["winning_cells"] <= det["winning_cells"]
    # the stochastic controller: R rollouts, none failing, audit at or above the claimed confidence
    assert sto["n_rollouts"] == 1000
    assert sto["failures"] == 0
    assert sto["audit_pass_rate_joint"] >= sto["confidence_joint"]
    assert sto["mean_map_satisfies"] is True and sto["rollout_average_satisfies"] is True
    # per-run p_emp(x0): the success fraction of the same rollouts, with no p_cert stated
    for e in (det, sto):
        pe = e["per_run_empirical"]
        assert pe["successes"] == e["n_rollouts"] - e["failures"] and pe["n_rollouts"] == e["n_rollouts"]
        assert pe["p_emp"] == pytest.approx(1 - e["failures"] / e["n_rollouts"]) and pe["p_cert"] is None
    for name in ("cert_stochastic.json", "cert_deterministic.json", "controller_stochastic.npz",
                 "rollouts_stochastic.npz", "audit_stochastic.json", "run.rrd"):
        assert (out / name).stat().st_size > 0, name


def test_certificate_warnings_reach_the_table(small_run):
    """`simgap run` prints what a certificate warns about (none on the small profile), per method."""
    from simgap.pipeline import comparison_table
    _, s = small_run
    assert s["methods"]["stochastic"]["warnings"] == [] and "warning" not in comparison_table(s)
    s = json.loads(json.dumps(s))
    s["methods"]["stochastic"]["warnings"] = ["Lhat_fhat[omega] = 0.4 is mostly noise"]
    assert "warning (stochastic certificate): Lhat_fhat[omega] = 0.4 is mostly noise" in comparison_table(s)


def test_rerun_resumes_and_reproduces(small_run, tmp_path):
    out, s = small_run
    rc = main(["run", "pendulum", "--profile", "small", "--out", str(out), "--no-record", "--workers", "2"])
    assert rc == 0
    s2 = json.loads((out / "summary.json").read_text())
    # the collection is reused (resumed, nothing recomputed) and every number is reproduced
    assert s2["seconds"]["collect/stochastic"] < s["seconds"]["collect/stochastic"] or s["seconds"]["collect/stochastic"] < 1
    for m in ("deterministic", "stochastic"):
        np.testing.assert_array_equal(s2["methods"][m]["gamma"]["max"], s["methods"][m]["gamma"]["max"])
        assert s2["methods"][m]["winning_cells"] == s["methods"][m]["winning_cells"]
        assert s2["methods"][m].get("failures") == s["methods"][m].get("failures")


def test_bad_experiment_is_a_clear_error(tmp_path, capsys):
    assert main(["run", "no-such-experiment"]) == 2
    assert "error:" in capsys.readouterr().err
    bad = tmp_path / "bad.toml"
    src = (__import__("simgap.config", fromlist=["EXPERIMENTS_DIR"]).EXPERIMENTS_DIR / "pendulum.toml").read_text()
    bad.write_text(src.replace('spec = "invariance"', 'spec = "invariance"\nbogus = 1'))
    assert main(["run", str(bad), "--out", str(tmp_path / "o")]) == 2
    assert "bogus" in capsys.readouterr().err


@pytest.mark.slow  # a second whole `simgap run` (1000 rollouts per method); the small profile's run above
# keeps the chain in the default suite
def test_noisy_profile_shows_the_papers_claim(tmp_path):
    """The noisy profile as shipped: the deterministic-gap controller fails a visible share of runs,
    the stochastic-gap controller has a winning domain from x0 and does not fail. (The shipped profile
    once lost its stochastic domain to an Lhat estimate inflated by the noise of the empirical means:
    this guards the configuration and the chain behind it, not one function.)"""
    out = tmp_path / "noisy"
    assert main(["run", "pendulum", "--profile", "noisy", "--out", str(out), "--workers", "2", "--no-record"]) == 0
    s = json.loads((out / "summary.json").read_text())
    det, sto = s["methods"]["deterministic"], s["methods"]["stochastic"]
    assert sto["winning_cells"] > 0.25 * det["winning_cells"], sto["winning_cells"]
    assert det["failures"] >= 50 and det["n_rollouts"] == 1000           # 122 / 1000 measured
    assert sto["n_rollouts"] == 1000 and sto["failures"] == 0
    assert sto["audit_pass_rate_joint"] >= sto["confidence_joint"]


def test_readme_numbers_match_the_run(small_run):
    """The pages' printed `simgap run pendulum` table (README.md, docs/getting-started.md) and their
    results rows for the small profile (the README's compact row, docs/results.md's full row) are what
    this run gives (bench/readme_numbers.py writes them; a stale number fails here)."""
    import importlib.util
    from pathlib import Path
    root = Path(__file__).resolve().parents[1]
    spec = importlib.util.spec_from_file_location("readme_numbers", root / "bench" / "readme_numbers.py")
    rn = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(rn)
    _, s = small_run
    for page in rn.PAGE_PATHS[:3]:
        text = (root / page).read_text()
        new, diffs = rn.apply_page(root / page, text, [s], [])
        assert diffs == [] and new == text, "\n".join(diffs)
    # the check can fail: a changed number is reported and rewritten, in either table's form
    for page, cell in (("docs/results.md", "| 0.000253, 0.00223 |"), ("README.md", "| 36,839 / 18,124 |")):
        text = (root / page).read_text()
        bad = text.replace(cell, cell.replace("3", "4", 1), 1)
        assert bad != text
        fixed, diffs = rn.apply_page(root / page, bad, [s], [])
        assert len(diffs) == 1 and "pendulum, small" in diffs[0] and fixed == text, diffs


def test_closest_approach_over_rollouts_and_the_mean_map():
    """Per rollout the minimum clearance along the whole trajectory (not the last state), then
    min / 5 % quantile / median over rollouts; the mean map's own minimum; the table shows them."""
    from types import SimpleNamespace

    from simgap.maps import load_map
    from simgap.pipeline import closest_approach, comparison_table

    m = load_map("arena")
    x_left = m.inflated_obstacles[0][0]                     # left face of the grown wall
    dist = np.linspace(0.0, 0.6, 100)                       # rollout i passes dist[i] from the wall
    traj = np.zeros((100, 3, 3))
    traj[:, :, 1] = 0.5                                     # far from the other obstacles
    traj[:, 0, 0] = x_left - 0.5                            # start and end far from the wall ...
    traj[:, 1, 0] = x_left - dist                           # ... closest in the middle
    traj[:, 2, 0] = x_left - 0.5
    traj[0, 1, 0] = x_left + 0.05                           # rollout 0 goes 0.05 m inside
    mm = traj[50]
    ca = closest_approach(m, SimpleNamespace(trajectories=traj, mean_map_trajectory=mm))
    assert ca["min"] == pytest.approx(-0.05) and ca["mean_map"] == pytest.approx(dist[50])
    per = np.r_[-0.05, dist[1:]]
    assert ca["q05"] == pytest.approx(np.quantile(per, 0.05)) and ca["median"] == pytest.approx(np.median(per))
    e = {"gamma": {"max": [0.1] * 3}, "confidence_per_dim": [0.9] * 3, "audit_pass_rate_joint": 1.0,
         "audit_violated_joint": 0.0, "winning_cells": 1, "rollouts": {"skipped": "x0 is outside the winning domain"}}
    s = {"system": {"state_names": ["x", "y", "theta"]},
         "methods": {"deterministic": {**e, "failures": 1, "n_rollouts": 100, "closest_approach": ca},
                     "stochastic": e}}
    table = comparison_table(s)
    assert "closest approach min [m]" in table and "-0.050" in table and f"{dist[50]:.3f}" in table


def test_per_run_empirical_is_the_success_fraction_with_its_standard_error():
    """p_emp = k / R with SE sqrt(p (1 - p) / R) and a 95 % Clopper-Pearson interval, checked against
    Monte Carlo: over 4000 seeded repeats of R = 1000 Bernoulli(0.95) runs the spread of p_emp is
    the stated SE (to 5 %) and the interval covers 0.95 in at least 95 % of the repeats (3 SE)."""
    from types import SimpleNamespace

    from simgap.pipeline import comparison_table, per_run_empirical, per_run_note

    pe = per_run_empirical(SimpleNamespace(n_rollouts=1000, n_failures=44, horizon=600))
    assert pe["successes"] == 956 and pe["p_emp"] == pytest.approx(0.956)
    assert pe["se"] == pytest.approx(np.sqrt(0.956 * 0.044 / 1000))
    assert pe["ci95"][0] < 0.956 < pe["ci95"][1] and pe["p_cert"] is None and "mean map" in pe["p_cert_note"]
    rng = np.random.default_rng(5)
    fails = rng.binomial(1000, 0.05, 4000)
    once = {f: per_run_empirical(SimpleNamespace(n_rollouts=1000, n_failures=int(f), horizon=1)) for f in set(fails)}
    est = [once[f] for f in fails]
    p = np.array([e["p_emp"] for e in est])
    assert np.std(p) == pytest.approx(np.sqrt(0.95 * 0.05 / 1000), rel=0.05)
    assert np.mean([e["se"] for e in est]) == pytest.approx(np.std(p), rel=0.05)
    cover = np.mean([e["ci95"][0] <= 0.95 <= e["ci95"][1] for e in est])
    assert cover >= 0.95 - 3 * np.sqrt(0.95 * 0.05 / 4000)
    e = {"gamma": {"max": [0.1] * 3}, "confidence_per_dim": [0.9] * 3, "audit_pass_rate_joint": 1.0,
         "audit_violated_joint": 0.0, "winning_cells": 1, "rollouts": {"skipped": "x0 is outside the winning domain"}}
    s = {"system": {"state_names": ["x", "y", "theta"]},
         "methods": {"deterministic": {**e, "failures": 44, "n_rollouts": 1000, "per_run_empirical": pe},
                     "stochastic": e}}
    table = comparison_table(s)
    assert "p_emp(x0) per run +- SE" in table and "0.9560 +- 0.0065" in table and "none stated" in table
    assert "mean map" in per_run_note(s) and per_run_note({"methods": {"deterministic": e, "stochastic": e}}) is None


def test_a_second_run_reads_the_first_runs_stores(small_run, tmp_path):
    """`stores_from`: another run on the same collection (e.g. another Lipschitz term) collects nothing
    new, certifies the very same data and says where they are; a missing folder is refused first."""
    from simgap.config import load_experiment
    from simgap.pipeline import run_experiment
    out, s = small_run
    exp = load_experiment("pendulum", "small")
    with pytest.raises(SimgapError, match="stores_from"):
        run_experiment(exp, tmp_path / "refused", n_rollouts=20, stores_from=tmp_path / "nowhere", log=lambda m: None)
    assert not (tmp_path / "refused").exists()
    before = sorted(p.name for p in (out / "data" / "chunks").iterdir())
    s2 = run_experiment(exp, tmp_path / "second", n_rollouts=20, stores_from=out, log=lambda m: None)
    assert not (tmp_path / "second" / "data").exists() and not (tmp_path / "second" / "data_deterministic").exists()
    assert sorted(p.name for p in (out / "data" / "chunks").iterdir()) == before
    assert s2["stores_from"] == str(out.resolve()) and s2["collect"]["n_runs"] == exp.collect.n_runs
    assert s2["n_rollouts"] == 20 and s["n_rollouts"] == 1000 and s["stores_from"] is None
    plan = exp.plan()
    assert s["collected_runs"]["stochastic"] == plan.n_pairs * plan.n_runs  # the first run simulated them all
    assert s2["collected_runs"] == {"stochastic": 0, "deterministic": 0}  # the second none
    for m in ("deterministic", "stochastic"):
        assert s2["methods"][m]["dataset_hash"] == s["methods"][m]["dataset_hash"]
        assert s2["methods"][m]["gamma"]["max"] == s["methods"][m]["gamma"]["max"]


def test_table_says_which_statement_each_number_is():
    """A set proved (about the mean map, or for the nominal model about f alone) and 1000 / 1000
    single runs failing are two statements: the printed table puts every row under the header of
    the statement it is (certificate, proof, the mean map in the simulator, single runs), and
    summary.json names them. The case of the double pendulum's nominal set: proved, its mean map
    satisfies the spec, every single run leaves X."""
    from simgap.pipeline import SUMMARY_STATEMENTS, TABLE_GROUPS, comparison_table, per_run_empirical
    from types import SimpleNamespace
    e = {"gamma": {"max": [0.1] * 2}, "confidence_per_dim": [0.9] * 2, "audit_pass_rate_joint": 1.0,
         "audit_violated_joint": 0.0, "winning_cells": 0,
         "synthesis": {"gap_scale": 0.2, "diagnosis": "the gap is too large"}, "rollouts": {"skipped": "no set"}}
    nominal = {"gap": "none", "winning_cells": 1, "failures": 1000, "n_rollouts": 1000,
               "synthesis": {"half_widths": [0.1, 0.2], "x0_inside": True, "gap_scale_text": "any factor (no gap)"},
               "mean_map_satisfies": True, "rollout_average_satisfies": False,
               "per_run_empirical": per_run_empirical(SimpleNamespace(n_rollouts=1000, n_failures=1000, horizon=9))}
    s = {"system": {"state_names": ["a", "b"]}, "sections": {"synthesis": {"method": "invariant_set"}},
         "methods": {"deterministic": e, "stochastic": e, "nominal": nominal}}
    lines = comparison_table(s).split("\n")
    heads = {k: lines.index(v) for k, v in TABLE_GROUPS.items() if k != "proof"}  # a nominal column: its header
    heads["proof"] = heads.pop("proof_nominal")
    assert heads["certificate"] < heads["proof"] < heads["mean_map"] < heads["runs"]

    def under(label):  # the group a row is printed in
        i = next(k for k, ln in enumerate(lines) if ln.startswith("  " + label))
        return max((h, k) for k, h in heads.items() if h < i)[1]
    assert under("proved") == "proof"
    assert next(ln for ln in lines if ln.startswith("  proved ")).split()[-1] == "yes"
    # each method in its own words: an ellipsoid run's rows never speak of a tube, nor the grid's of E
    assert "invariant ellipsoid E" in next(ln for ln in lines if ln.startswith("  method (its own words)"))
    assert under("mean map satisfies the spec") == "mean_map"
    for label in ("single runs failing from x0", "p_emp(x0) per run", "rollout average satisfies"):
        assert under(label) == "runs", label
    row = next(ln for ln in lines if ln.startswith("  single runs failing from x0"))
    assert row.endswith("1000 / 1000")
    assert "MEAN MAP" in TABLE_GROUPS["proof_nominal"] and "f only" in TABLE_GROUPS["proof_nominal"]
    assert TABLE_GROUPS["proof"] in comparison_table({**s, "methods": {"deterministic": e, "stochastic": e}})
    assert "SINGLE RUNS" in TABLE_GROUPS["runs"] and "only p_cert" in TABLE_GROUPS["runs"]
    # summary.json names the same statements for its keys
    keys = ", ".join(SUMMARY_STATEMENTS)
    for k in ("winning_cells", "mean_map_satisfies", "failures", "rollout_average_satisfies"):
        assert k in keys
    assert "SINGLE RUNS" in next(v for k, v in SUMMARY_STATEMENTS.items() if "failures" in k)
    assert "MEAN MAP" in SUMMARY_STATEMENTS["winning_cells"]
