"""bench/turtlebot_separation.py without simulation: noise levels, the skip/resume rule, the table and figure."""

import importlib.util
import json
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def sep():
    spec = importlib.util.spec_from_file_location("turtlebot_separation", ROOT / "bench" / "turtlebot_separation.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_noise_levels_run_from_gazebo_to_beyond_stress(sep):
    from simgap.config import load_experiment
    gz = load_experiment(sep.EXPERIMENT, "gazebo").simulator.to_dict()
    st = load_experiment(sep.EXPERIMENT, "gazebo_stress").simulator.to_dict()
    e0 = sep.experiments(0.0, 100)
    assert e0["paper"].simulator.to_dict()["noise"] == gz["noise"]  # level 0: the gazebo profile's noise
    assert e0["paper"].collect.n_runs == 100 and e0["paper"].section("synthesis") == load_experiment(
        sep.EXPERIMENT, "gazebo").section("synthesis")
    e1 = sep.experiments(1.0, 400)
    s1 = e1["gap"].simulator.to_dict()
    assert s1["noise"] == st["noise"] and s1["randomize"] == st["randomize"]  # level 1: gazebo_stress's noise
    assert e1["gap"].collect.n_runs == 400
    assert e1["paper"].section("certify")["lipschitz_term"] == "paper"
    assert e1["gap"].section("certify")["lipschitz_term"] == "gap"
    n2, r2 = sep.noise_at(2.0, gz, st)
    assert n2["wheel_slip"] == [0.4, 1.0] and n2["actuation_jitter"] == [0.1, 0.4]
    assert n2["actuation_std"] == [0.07, 0.37] and r2 == st["randomize"]  # the per-run spread is held beyond 1
    assert sep.noise_at(9.0, gz, st)[0]["wheel_slip"][0] == 1.0  # a probability stays a probability
    with pytest.raises(ValueError):
        sep.noise_at(-0.5, gz, st)


def _config(sep, level=0.0, n1hat=100, rollouts=1000):
    return sep.point_config(level, n1hat, rollouts, sep.experiments(level, n1hat))


def _summary(cfg, term, det=(True, 44), sto=(True, 0), hashes=("hs", "hd")):
    def method(won, failures, h):
        e = {"gamma": {"max": [0.02, 0.02, 0.03]}, "winning_cells": 1000, "audit_pass_rate_joint": 1.0,
             "audit_violated_joint": 0.0, "audit_pass_rate_per_dim": {"x": 1.0, "y": 1.0, "theta": 1.0},
             "dataset_hash": h}
        if won:
            e.update(failures=failures, n_rollouts=cfg["rollouts"], rollouts={},
                     closest_approach={"min": 0.05, "q05": 0.08, "median": 0.1})
        else:
            e["rollouts"] = {"skipped": "x0 is outside the winning domain"}
        return e
    return {"run_id": "r", "simulator": cfg["simulator"],
            "sections": {"certify": cfg["certify"][term], "audit": cfg["audit"]},
            "collect": {"n_runs": cfg["n1hat"]}, "n_rollouts": cfg["rollouts"],
            "seconds": {"collect/stochastic": 120.0, "audit/stochastic": 30.0},
            "stores_from": None if term == "paper" else "x",
            "methods": {"deterministic": method(*det, hashes[1]), "stochastic": method(*sto, hashes[0])}}


def _write_point(sep, out, cfg, terms=("paper", "gap"), **kw):
    folder = out / sep.point_name(cfg["level"], cfg["n1hat"])
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "point.json").write_text(json.dumps(cfg))
    for t in terms:
        (folder / t).mkdir(exist_ok=True)
        (folder / t / "summary.json").write_text(json.dumps(_summary(cfg, t, **kw)))
    return folder


def test_a_point_is_finished_only_for_its_own_configuration(sep, tmp_path):
    cfg = _config(sep)
    folder = _write_point(sep, tmp_path, cfg)
    assert sep.finished(folder / "paper", cfg, "paper") and sep.finished(folder / "gap", cfg, "gap")
    # the paper term's summary is not the gap term's (its certify section differs)
    assert not sep.finished(folder / "paper", cfg, "gap")
    reduced = sep.point_config(0.0, 100, 1000, sep.experiments(0.0, 100, {"points": 20}))
    assert reduced["audit"]["points"] == 20 and reduced["audit"]["runs"] == cfg["audit"]["runs"]
    fewer_lhat = sep.point_config(0.0, 100, 1000, sep.experiments(0.0, 100, lhat_pairs=30))
    assert fewer_lhat["certify"]["gap"]["lhat_pairs"] == 30
    for other in (_config(sep, level=0.25), _config(sep, n1hat=400), _config(sep, rollouts=200), reduced, fewer_lhat):
        assert not sep.finished(folder / "paper", other, "paper")
    s = json.loads((folder / "gap" / "summary.json").read_text())
    # the gap term must have certified the paper term's data (one collection for both)
    s["methods"]["stochastic"]["dataset_hash"] = "another"
    (folder / "gap" / "summary.json").write_text(json.dumps(s))
    assert not sep.finished(folder / "gap", cfg, "gap")
    # a summary cut short (interrupted write) or without a method is not finished
    (folder / "paper" / "summary.json").write_text('{"methods": {"deterministic": ')
    assert not sep.finished(folder / "paper", cfg, "paper")
    s = _summary(cfg, "paper")
    del s["methods"]["stochastic"]
    (folder / "paper" / "summary.json").write_text(json.dumps(s))
    assert not sep.finished(folder / "paper", cfg, "paper")
    assert not sep.finished(tmp_path / "nowhere", cfg, "paper")


def test_rerun_skips_finished_points_and_runs_the_rest_from_one_collection(sep, tmp_path, monkeypatch, capsys):
    import simgap.pipeline as pipeline
    calls = []

    def fake_run(exp, out, *, stores_from=None, n_rollouts=None, **kw):
        calls.append((Path(out), stores_from))
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        cfg = json.loads((out.parent / "point.json").read_text())
        term = exp.section("certify")["lipschitz_term"]
        assert n_rollouts == cfg["rollouts"] and exp.collect.n_runs == cfg["n1hat"]
        (out / "summary.json").write_text(json.dumps(_summary(cfg, term, det=(True, 3))))

    monkeypatch.setattr(pipeline, "run_experiment", fake_run)
    out = tmp_path / "scan"
    cfg = _config(sep, level=0.0, rollouts=200)
    _write_point(sep, out, cfg)  # level 0 finished earlier
    half = _write_point(sep, out, _config(sep, level=1.0, rollouts=200), terms=("paper",))  # interrupted after paper
    argv = ["--out", str(out), "--levels", "0", "1", "1.5", "--rollouts", "200", "--no-figure"]
    assert sep.main(argv) == 0
    # level 0 skipped; level 1 ran only its gap term, on the paper term's stores; level 1.5 both, in order
    assert calls == [(half / "gap", half / "paper"), (out / "noise1.5_n100" / "paper", None),
                     (out / "noise1.5_n100" / "gap", out / "noise1.5_n100" / "paper")]
    printed = capsys.readouterr().out
    assert "[noise0_n100] finished earlier: skipped" in printed and "projected wall time" in printed
    table = json.loads((out / sep.TABLE).read_text())
    assert [(r["level"], r["term"]) for r in table["rows"]] == [(0.0, "paper"), (1.0, "paper"), (1.5, "paper"),
                                                                (0.0, "gap"), (1.0, "gap"), (1.5, "gap")]
    calls.clear()
    assert sep.main(argv) == 0 and calls == []  # everything finished: nothing runs again


def test_points_projected_over_the_limit_are_not_run(sep, tmp_path, monkeypatch):
    import simgap.pipeline as pipeline
    monkeypatch.setattr(pipeline, "run_experiment", lambda *a, **k: pytest.fail("a point over the limit ran"))
    out = tmp_path / "scan"
    assert sep.main(["--out", str(out), "--levels", "0.5", "--n1hat", "1000", "--max-hours", "0.001",
                     "--no-figure"]) == 0
    table = json.loads((out / sep.TABLE).read_text())
    assert table["rows"] == [] and len(table["projected_not_run"]) == 1
    p = table["projected_not_run"][0]
    assert p["level"] == 0.5 and p["n1hat"] == 1000 and p["hours"] > 0.001
    assert "not run: noise 0.5, N1hat 1000" in sep.text_table(table)



def test_project_only_runs_nothing_and_later_calls_keep_its_projections(sep, tmp_path, monkeypatch):
    """--project-only records projections without running; a later call for other points keeps them
    (fails if each call's table replaced the earlier calls' projections)."""
    import simgap.pipeline as pipeline
    monkeypatch.setattr(pipeline, "run_experiment", lambda *a, **k: pytest.fail("--project-only ran a point"))
    out = tmp_path / "scan"
    assert sep.main(["--out", str(out), "--levels", "0.5", "--n1hat", "400", "--project-only", "--no-figure",
                     "--max-hours", "1000"]) == 0  # under the limit at any load: only --project-only keeps it
    assert sep.main(["--out", str(out), "--levels", "1", "--n1hat", "1000", "--project-only", "--no-figure",
                     "--max-hours", "1000"]) == 0
    table = json.loads((out / sep.TABLE).read_text())
    assert [(p["level"], p["n1hat"]) for p in table["projected_not_run"]] == [(0.5, 400), (1.0, 1000)]
    assert all(p["project_only"] for p in table["projected_not_run"])
    assert "(--project-only;" in sep.text_table(table)
    assert sep.main(["--out", str(out), "--table-only", "--no-figure"]) == 0
    assert len(json.loads((out / sep.TABLE).read_text())["projected_not_run"]) == 2

def test_bad_arguments_are_refused_by_name(sep, tmp_path, capsys):
    assert sep.main(["--out", str(tmp_path / "o"), "--levels", "-1"]) == 2
    assert "noise levels" in capsys.readouterr().err
    assert sep.main(["--out", str(tmp_path / "o"), "--n1hat", "1"]) == 2
    assert sep.main(["--out", str(tmp_path / "o"), "--audit-points", "0"]) == 2
    assert "--audit-points 0" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()
    assert sep.main(["--out", str(tmp_path / "none"), "--table-only"]) == 2


def test_table_separation_rule_and_figure_from_a_fake_table(sep, tmp_path):
    out = tmp_path / "scan"
    # level 0: neither collides; 0.25: the stochastic controller collides once; 0.5 and 0.75: the
    # separation (44 and exactly 20 / 1000 vs 0 / 1000, x0 won); 1: 19 / 1000 is below the rule;
    # 1.5: the stochastic certificate does not win x0
    cases = {0.0: ((True, 0), (True, 0)), 0.25: ((True, 44), (True, 1)), 0.5: ((True, 44), (True, 0)),
             0.75: ((True, 20), (True, 0)), 1.0: ((True, 19), (True, 0)), 1.5: ((True, 60), (False, None))}
    for lv, (det, sto) in cases.items():
        _write_point(sep, out, _config(sep, level=lv), det=det, sto=sto)
    table = sep.build_table(out, [])
    sepa = {(r["level"], r["term"]): r["separation"] for r in table["rows"]}
    assert sepa == {(lv, t): lv in (0.5, 0.75) for lv in cases for t in sep.TERMS}
    r15 = next(r for r in table["rows"] if r["level"] == 1.5)
    assert r15["stochastic"]["x0_won"] is False and r15["stochastic"]["skipped"] == "x0 is outside the winning domain"
    text = sep.text_table(table)
    assert "44/1000" in text and "no x0" not in text.split("\n")[2]
    lines = [ln for ln in text.split("\n") if ln.strip().startswith("1.5")]
    assert len(lines) == 2 and all(" no " in ln and "60/1000" in ln for ln in lines)
    md = sep.markdown_table(table)
    assert md.count("\n") == 1 + len(table["rows"]) and "| 0.5 | 100 | paper | 44/1000 | yes | 0/1000 |" in md
    # the figure is drawn from the JSON alone: --table-only rebuilds table and figure from the folder
    assert sep.main(["--out", str(out), "--table-only"]) == 0
    assert json.loads((out / sep.TABLE).read_text())["rows"] == json.loads(json.dumps(table["rows"]))
    assert all((out / f"separation.{ext}").stat().st_size > 10_000 for ext in ("png", "pdf"))


def test_readme_numbers_puts_the_scan_table_between_the_markers(sep, tmp_path):
    spec = importlib.util.spec_from_file_location("readme_numbers", ROOT / "bench" / "readme_numbers.py")
    rn = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(rn)
    page = (ROOT / "docs" / "turtlebot-separation.md").read_text()
    assert all(page.count(m) == 1 for m in rn.SEPARATION_MARKERS)
    out = tmp_path / "scan"
    _write_point(sep, out, _config(sep, level=0.5), det=(True, 44), sto=(True, 0))
    table = sep.build_table(out, [])
    new, diffs = rn.apply_separation(page, table)
    assert len(diffs) == 1 and "| 0.5 | 100 | gap | 44/1000 | yes | 0/1000 |" in new
    assert new.replace(sep.markdown_table(table), "").count("44/1000") == 0  # the table went in once
    assert rn.apply_separation(new, table) == (new, [])  # in step: nothing to change
    # the command line: --check exits 1 while the page lags, 0 after --write
    (out / sep.TABLE).write_text(json.dumps(table))
    rd = tmp_path / "turtlebot-separation.md"
    rd.write_text(page)
    assert rn.main([str(out), "--page", str(rd), "--check"]) == 1
    assert rn.main([str(out), "--page", str(rd), "--write"]) == 0 and rd.read_text() == new
    assert rn.main([str(out), "--page", str(rd), "--check"]) == 0


def test_projection_counts_only_what_is_left(sep, tmp_path):
    store = tmp_path / "data"
    assert sep.collected(store) == 0.0  # nothing yet
    (store / "chunks").mkdir(parents=True)
    (store / "manifest.json").write_text(json.dumps({"config": {"n_chunks": 4}}))
    for i in range(3):
        (store / "chunks" / f"c{i:06d}.npz").write_bytes(b"x")
    assert sep.collected(store) == 0.75
    full = sep.project_seconds(2625, 100, 1000, 2, 1.0, 1000.0, 90.0)
    assert full == pytest.approx(262.5 + 180.0)
    assert sep.project_seconds(2625, 100, 1000, 2, 0.25, 1000.0, 90.0) == pytest.approx(262.5 / 4 + 180.0)
    assert sep.project_seconds(2625, 100, 200, 1, 0.0, 1000.0, 90.0) == pytest.approx(90.0 * (0.4 + 0.12))


def test_the_readme_table_is_the_committed_scan():
    """docs/turtlebot-separation.md's table is made from bench/results/turtlebot-separation/separation.json
    (the scan's own output, committed): a hand edit of either makes this fail."""
    spec = importlib.util.spec_from_file_location("readme_numbers", ROOT / "bench" / "readme_numbers.py")
    rn = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(rn)
    scan = ROOT / "bench" / "results" / "turtlebot-separation"
    assert rn.main([str(scan), "--page", str(ROOT / "docs" / "turtlebot-separation.md"), "--check"]) == 0
    table = json.loads((scan / "separation.json").read_text())
    assert table["rows"] and all(r["stochastic"]["audit_pass_joint"] == 1.0 for r in table["rows"])


def _cert(gap, delta, lip_paper, lip_gap, n_runs=100, eps=0.03):
    """A stochastic certificate file's fields the budget reads (delta split as delta_1 = delta_2)."""
    return {"n_runs": n_runs, "epsilon": eps,
            "dims": [{"gap_max": g, "delta1": d / 2, "delta2": d / 2, "Mhat": 0.1, "L_x": lp / eps,
                      "scp": {"lipschitz_terms": {"paper": lp, "gap": lg}}}
                     for g, d, lp, lg in zip(gap, delta, lip_paper, lip_gap)]}


def test_gamma_budget_and_the_n1hat_a_win_needs(sep, tmp_path):
    # hand computation: N0 (gap + delta)^2 / (target - Lipschitz)^2 per dimension, the largest
    b = {"n1hat": 100, "gap_max": [0.02, 0.02, 0.1], "delta": [0.02, 0.02, 0.1], "lipschitz": [0.001, 0.001, 0.0]}
    assert sep.n1hat_needed(b, [(0.011, 0.011, 0.2)]) == pytest.approx(100 * (0.04 / 0.01) ** 2)  # x binds: 1600
    assert sep.n1hat_needed(b, [(0.011, 0.011, 0.2), (0.041, 0.041, 0.1)]) == pytest.approx(400)  # the best target
    assert sep.n1hat_needed(b, [(0.001, 0.5, 0.5)]) == float("inf")  # under the Lipschitz term: never
    # the best-case path passes through the certificate at its own N1hat and meets the need
    assert sep.best_case_gamma(b, [100])[0] == pytest.approx([0.041, 0.041, 0.2])
    assert sep.best_case_gamma(b, [1600])[0][0] == pytest.approx(0.011)
    # from files: gamma = gap + delta + the Lipschitz term the certificate used (the smaller with the gap's)
    out = tmp_path / "scan"
    folder = _write_point(sep, out, _config(sep, level=0.5), det=(True, 44), sto=(False, None))
    c = _cert([0.02, 0.03, 0.1], [0.02, 0.02, 0.5], [0.018, 0.018, 0.007], [0.002, 0.002, 3.4])
    for t in sep.TERMS:
        (folder / t / "cert_stochastic.json").write_text(json.dumps(c))
    table = sep.build_table(out, [])
    rows = {r["term"]: r for r in table["rows"]}
    assert rows["paper"]["budget"]["lipschitz"] == pytest.approx([0.018, 0.018, 0.007])
    assert rows["gap"]["budget"]["lipschitz"] == pytest.approx([0.002, 0.002, 0.007])
    # without a frontier the two known winning gaps; with one, its rows (a different answer)
    assert table["win_gammas"] == [list(g) for g in sep.WIN_GAMMAS]
    need_two = rows["gap"]["n1hat_needed"]
    assert need_two == pytest.approx(min(max(100 * ((0.03 + 0.02) / (0.0122 - 0.002)) ** 2, 100 * (0.6 / 0.193) ** 2),
                                         100 * (0.6 / 0.093) ** 2))
    (out / sep.FRONTIER).write_text(json.dumps({"profile": "gazebo", "syntheses": 9, "tolerance": 0.0005,
                                                "seconds": 60.0, "rows": [{"gamma_theta": 0.3, "gamma_xy_max": 0.04},
                                                                           {"gamma_theta": 0.5, "gamma_xy_max": None}]}))
    table = sep.build_table(out, [])
    rows = {r["term"]: r for r in table["rows"]}
    assert rows["gap"]["n1hat_needed"] == pytest.approx(max(100 * (0.05 / 0.038) ** 2, 100 * (0.6 / 0.293) ** 2))
    md = sep.markdown_table(table)
    assert "| 0.5 | 100 | gap | 0.052 / 0.607 | 0.03 / 0.1 | 0.02 / 0.5 | 0.002 / 0.007 | 0.1 / 0.1 | 420 |" in md
    assert "| 0.3 | 0.0400 |" in md and "| 0.5 | none (lost at 0) |" in md
    # a what-if against another nominal model is tabulated with its file's digest and its own need
    b2 = sep.budget(_cert([0.01, 0.01, 0.1], [0.01, 0.01, 0.1], [0.018, 0.018, 0.007], [0.001, 0.001, 0.003], 400),
                    "gap")
    (out / sep.WHATIF).write_text(json.dumps({"rows": [{"level": 0.5, "n1hat": 400, "system_file": "r.json",
                                                        "system_sha256": "ab" * 32, "budget": b2, "x0_won": False}]}))
    md = sep.markdown_table(sep.build_table(out, []))
    assert ("| 0.5 | 400 | r.json (abababababab) | 0.021 / 0.203 | 0.01 / 0.1 | 0.01 / 0.1 | 0.001 / 0.003 | no | "
            f"{sep._round2(400 * (0.2 / 0.297) ** 2):,} |") in md
    assert sep.main(["--out", str(out), "--table-only"]) == 0
    assert (out / "separation_gamma.png").stat().st_size > 10_000
    assert sep.main(["--out", str(out), "--nominal", str(tmp_path / "missing.json")]) == 2
    (tmp_path / "r.json").write_text("{}")
    assert sep.main(["--out", str(out), "--levels", "0.3", "--nominal", str(tmp_path / "r.json")]) == 2  # not run
    assert json.loads((out / sep.WHATIF).read_text())["rows"][0]["n1hat"] == 400  # refused: nothing rewritten


def test_the_win_frontier_bisects_each_heading_gap(sep, monkeypatch):
    # a fake synthesis that wins x0 iff gamma_xy + 0.1 gamma_theta <= 0.03: the frontier is 0.03 - 0.1 gamma_theta
    import simgap.synthesis.controller as sc

    class Res:
        def __init__(self, won):
            self.empty = not won
            self.controller = type("C", (), {"winning": lambda _s, x: [won]})()
    calls = []

    def fake(system, spec, eta, gap=None, hold=1, x0=None, **kw):
        calls.append(gap)
        return Res(gap[0] + 0.1 * gap[2] <= 0.03 and gap[0] == gap[1])
    monkeypatch.setattr(sc, "synthesize", fake)
    fr = sep.win_frontier(thetas=(0.1, 0.2, 0.5), tol=1e-4, log=lambda m: None)
    got = {r["gamma_theta"]: r["gamma_xy_max"] for r in fr["rows"]}
    assert got[0.1] == pytest.approx(0.02, abs=1e-4) and got[0.1] <= 0.02
    assert got[0.2] == pytest.approx(0.01, abs=1e-4) and got[0.2] <= 0.01
    assert got[0.5] is None and fr["syntheses"] == len(calls)
