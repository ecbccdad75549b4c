"""Mutation check: every known wrong implementation of the certificate or the abstraction must
make the tight-margin tests fail.

    python bench/mutations.py [--group abstraction|perrun|gap|all] [--tests TEST ...]
                              [--only NAME ...] [--all-failures] [--json out.json]

Group ``abstraction`` (the default) runs tests/test_soundness_margins.py and
tests/test_certificate_margins.py per mutation; group ``perrun`` mutates the per-run stage
(simgap/perrun/) and runs each mutation's own test file (the interval-MDP mutations
tests/test_perrun_soundness.py, the realization-gap ones tests/test_perrun_realization.py);
group ``gap`` mutates the gap's own Lipschitz term and the input term (beyond the paper) and runs
tests/test_gap_lipschitz.py; ``--tests`` overrides the files for every mutation.

The repository this script lives in is copied to a temporary directory (never edited in place).
The chosen tests are run once unmutated (they must pass), then once per mutation with the
mutation applied to the copy (and reverted afterwards), with ``PYTHONPATH`` pointing at the copy
so subprocesses (``python -m simgap``) run the mutated code too. A mutation is *caught* when
pytest fails. Exit status 0 when every mutation is caught, 1 otherwise, 2 when a mutation no
longer applies (the code it targets changed: update the anchor below).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DEFAULT_TESTS = ["tests/test_soundness_margins.py", "tests/test_certificate_margins.py"]
#: the test file each per-run mutation is checked with (by the file it mutates)
PERRUN_TESTS = {"simgap/perrun/realization.py": ["tests/test_perrun_realization.py"]}
PERRUN_DEFAULT = ["tests/test_perrun_soundness.py"]
GAP_TESTS = ["tests/test_gap_lipschitz.py"]


def tests_for(rel: str, group: str, override=None) -> list:
    """The tests a mutation of ``rel`` in ``group`` is checked with (``override``: --tests)."""
    if override:
        return list(override)
    if group == "gap":
        return GAP_TESTS
    return DEFAULT_TESTS if group == "abstraction" else PERRUN_TESTS.get(rel, PERRUN_DEFAULT)


def _in_function(name: str, old: str, new: str):
    """Replace ``old`` by ``new`` once inside the body of ``def name`` (up to the next def)."""
    def apply(text: str) -> str:
        m = re.search(rf"^( *)def {name}\(", text, flags=re.M)
        if not m:
            raise LookupError(f"def {name} not found")
        end = re.compile(rf"^{m.group(1)}(def |class |@)|^\S", flags=re.M).search(text, m.end())
        stop = end.start() if end else len(text)
        body = text[m.start():stop]
        if body.count(old) != 1:
            raise LookupError(f"{old!r} occurs {body.count(old)} times in def {name}")
        return text[:m.start()] + body.replace(old, new) + text[stop:]
    return apply


def _chain(*transforms):
    """Apply several transforms in order (a mutation that changes more than one line)."""
    def apply(text: str) -> str:
        for f in transforms:
            text = f(text)
        return text
    return apply


#: (name, file, transform, what the wrong implementation does, group)
MUTATIONS = [
    ("gamma at cell centres", "simgap/synthesis/abstraction.py",
     _in_function("build_abstraction", "blo, bhi = x - r, x + r", "blo, bhi = x.copy(), x.copy()"),
     "the abstraction bounds gamma at the cell centre instead of over the cell", "abstraction"),
    ("gamma halved", "simgap/synthesis/abstraction.py",
     _in_function("build_abstraction", "g = gamma_upper_wrapped(", "g = 0.5 * gamma_upper_wrapped("),
     "the abstraction uses gamma / 2", "abstraction"),
    ("seam ignored", "simgap/synthesis/abstraction.py",
     _in_function("gamma_upper_wrapped", "if not grid.periodic:", "if True:"),
     "gamma bounded over the raw interval [-pi - eta/2, -pi + eta/2] of the seam cell", "abstraction"),
    ("certificate's inputs ignored", "simgap/synthesis/abstraction.py",
     _in_function("certified_input_mask", "M = system.inputs.shape[0]\n",
                  "M = system.inputs.shape[0]\n    return np.ones(M, dtype=bool)\n"),
     "synthesis over every input of the system, certified or not", "abstraction"),
    ("delta_2 dropped", "simgap/certify/certificate.py",
     _in_function("constant", "d.delta2 + d.repair", "d.repair"),
     "gamma = L_x eps + q^T p (+ repair), without delta_2", "abstraction"),
    ("L*epsilon term dropped", "simgap/certify/certificate.py",
     _in_function("constant", "return self.lipschitz_terms() + ", "return "),
     "gamma = q^T p + delta_2 (+ repair), without the Lipschitz term", "abstraction"),
    # ----- the gap's own Lipschitz term and inputs between grid values (tests/test_gap_lipschitz.py) -----
    ("gap term halved", "simgap/certify/certificate.py",
     _in_function("gap_terms", "np.dot(np.add(d.L_gap, d.L2_x), self.radii)",
                  "np.dot(0.5 * np.add(d.L_gap, d.L2_x), self.radii)"),
     "gamma with half the gap's own Lipschitz term", "gap"),
    ("gap term dropped", "simgap/certify/certificate.py",
     _in_function("gap_terms", "np.dot(np.add(d.L_gap, d.L2_x), self.radii)", "0.0 * self.radii[0]"),
     "gamma with the gap's term but no Lipschitz extension at all", "gap"),
    ("gap radii: full cells", "simgap/certify/lipschitz.py",
     _in_function("axis_grid", "radii[j] = max(0.5 * gaps.max(initial=0.0), v[0] - s.x_lo[j], s.x_hi[j] - v[-1])",
                  "radii[j] = max(0.25 * gaps.max(initial=0.0), v[0] - s.x_lo[j], s.x_hi[j] - v[-1])"),
     "the per-dimension radius taken as a quarter of the spacing", "gap"),
    ("input term dropped", "simgap/certify/certificate.py",
     _in_function("gamma", "g = g + self.input_terms()", "g = g"),
     "gamma at inputs between grid values without the input Lipschitz term", "gap"),
    ("CRN increments unwrapped", "simgap/certify/lipschitz.py",
     _in_function("crn_pair_means", "base = s.diff(nxt, X).reshape(2, P, runs, s.n)",
                  "base = (nxt - X).reshape(2, P, runs, s.n)"),
     "common-draw means across the angle seam: increments not wrapped run by run", "gap"),
    ("delta_1 dropped", "simgap/certify/pipeline.py",
     _in_function("certify", "solve_scp(P, g[:, i], float(d1[i]),", "solve_scp(P, g[:, i], 0.0,"),
     "the scenario program without delta_1 in its constraints", "abstraction"),
    # ----- per-run stage (issue 22: "Tests that can fail"; tests/test_perrun_soundness.py) -----
    ("perrun: support from main runs", "simgap/perrun/imdp.py",
     _chain(_in_function("count_pairs", "N0 = int(o.hold), int(o.n_runs), int(o.pilot_runs)",
                         "N0 = int(o.hold), int(o.n_runs), int(o.n_runs)"),
            _in_function("count_pairs", "run_pairs(q, N0, rng_pilot)",
                         "run_pairs(q, N0, np.random.default_rng([o.seed, 9, int(q[0])]))"),
            _in_function("count_pairs", "run_pairs(q, N, rng_main)",
                         "run_pairs(q, N, np.random.default_rng([o.seed, 9, int(q[0])]))")),
     "support T(c, a) and the split chosen on the main runs themselves (the pilot is the main runs)", "perrun"),
    ("perrun: sink test on end box only", "simgap/perrun/imdp.py",
     _in_function("_simulate", "        bad |= box_unsafe(spec, y - rho, y + rho, x_lo, x_hi, angle_dims)\n",
                  "    bad |= box_unsafe(spec, y - rho, y + rho, x_lo, x_hi, angle_dims)\n"),
     "only the widened box at the end of the hold is tested against X / the safe set / obstacles", "perrun"),
    ("perrun: unsafe boxes not sink runs", "simgap/perrun/imdp.py",
     _in_function("count_pairs", "sink_run = bad.copy()", "sink_run = np.zeros_like(bad)"),
     "runs whose widened box was unsafe along the hold are not counted as sink runs", "perrun"),
    ("perrun: invariance horizon down", "simgap/perrun/value_iteration.py",
     _in_function("abstract_steps", 'return -(-int(horizon) // int(hold)) if kind == "invariance" else',
                  'return int(horizon) // int(hold) if kind == "invariance" else'),
     "invariance over floor(H / k) holds (certifies fewer periods than H)", "perrun"),
    ("perrun: reach-avoid horizon up", "simgap/perrun/value_iteration.py",
     _in_function("abstract_steps", 'else int(horizon) // int(hold)', 'else -(-int(horizon) // int(hold))'),
     "reach-avoid over ceil(H / k) holds (credits reaching the target after period H; issue 22 item 1)", "perrun"),
    ("perrun: narrow target accepted", "simgap/perrun/imdp.py",
     _in_function("cell_labels", "if not target.any():", "if False:"),
     "a reach-avoid target holding no whole cell is not refused at the build (issue 22 item 2)", "perrun"),
    ("perrun: lower bound every hit", "simgap/perrun/imdp.py",
     _in_function("count_pairs", "inn = ok & single[b] & ~sink_run[b]", "inn = ok & ~sink_run[b]"),
     "n_in(j) counts runs whose end box touches j (j in S) instead of S = {j}", "perrun"),
    ("perrun: lower bound sink runs", "simgap/perrun/imdp.py",
     _in_function("count_pairs", "inn = ok & single[b] & ~sink_run[b]", "inn = ok & single[b]"),
     "n_in(j) counts sink runs too", "perrun"),
    ("perrun: policy read in reverse", "simgap/perrun/value_iteration.py",
     _in_function("input_index", "h = self.steps - 1 - min(int(t), self.steps - 1)", "h = min(int(t), self.steps - 1)"),
     "the time-varying policy used from its last step (policy_t at abstract step t instead of policy_{Ha-1-t})", "perrun"),
    ("perrun: Lipschitz last period", "simgap/perrun/imdp.py",
     _in_function("secant_slopes", "slope = np.maximum(slope, np.abs(s.diff(X[:B], X[B:])) / d[:, None])",
                  "slope = np.abs(s.diff(X[:B], X[B:])) / d[:, None]"),
     "the trajectory's Lipschitz slope taken from the last period of the hold only", "perrun"),
    ("perrun: translation other dims", "simgap/perrun/translation.py",
     _in_function("build_imdp_translation", "> 0) | out[:, None]", "> 0)"),
     "the translation construction checks the hold's boxes only along the invariant dimensions (item 3)", "perrun"),
    ("perrun: angle seam", "simgap/perrun/imdp.py",
     _in_function("along", "return np.where(ang, _circle(lo, hi, a, b, period, meet), flat)", "return flat"),
     "box_unsafe compares unwrapped angle intervals with obstacles and the safe set (item 4)", "perrun"),
    ("perrun: support unsorted", "simgap/perrun/imdp.py",
     _in_function("count_pairs", "support = np.sort(np.concatenate(sup))", "support = np.concatenate(sup)"),
     "the pilot's support left in batch order with shared runs (real successors become sink runs; item 6)", "perrun"),
    ("perrun: gamma^alpha Bonferroni K", "simgap/perrun/realization.py",
     _in_function("per_pair_beta", "return float(beta) / (int(K) * int(n))", "return float(beta) / int(K)"),
     "gamma^alpha's order statistic at beta / K instead of beta / (n K)", "perrun"),
    ("perrun: order statistic too low", "simgap/perrun/realization.py",
     _in_function("quantile_bounds", "dataset.absdev_top[:, j_used, :]", "dataset.absdev_top[:, j_used + 1, :]"),
     "gamma^alpha from D_(N - j - 1) instead of D_(N - j)", "perrun"),
    ("perrun: gamma^alpha no extension", "simgap/perrun/realization.py",
     _in_function("certify_run", "L_f=wf.estimate, L_fhat=wh.estimate, L_2=L_2,", "L_f=0.0, L_fhat=0.0, L_2=0.0,"),
     "gamma^alpha without the Lipschitz extension (L_f + Lhat + L_2) eps", "perrun"),
]


def copy_repo(dst: Path) -> Path:
    """Copy the repository's working tree (no .git, caches or results) to ``dst``."""
    ignore = shutil.ignore_patterns(".git", "__pycache__", ".pytest_cache", "*.egg-info", "results", "*.rrd")
    shutil.copytree(REPO, dst, ignore=ignore, symlinks=True)
    return dst


def run_tests(root: Path, tests, timeout: int, stop_first: bool = True) -> tuple[bool, str, float]:
    """(passed, failing tests or '', seconds) of pytest on ``tests`` in ``root``."""
    env = dict(os.environ, PYTHONPATH=str(root), PYTHONDONTWRITEBYTECODE="1")
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, "-m", "pytest", *(["-x"] if stop_first else []), "-q",
                        "-p", "no:cacheprovider", *tests],
                       cwd=root, env=env, capture_output=True, text=True, timeout=timeout)
    secs = time.perf_counter() - t0
    failed = re.findall(r"^(?:FAILED|ERROR) (\S+)", p.stdout, flags=re.M)
    return p.returncode == 0, (", ".join(failed) if failed else ("" if p.returncode == 0 else p.stdout[-300:])), secs


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--group", choices=["abstraction", "perrun", "gap", "all"], default="abstraction",
                    help="which mutations (default: the abstraction's)")
    ap.add_argument("--tests", nargs="+", default=None, help="test files/ids to run per mutation (default: by group)")
    ap.add_argument("--only", nargs="+", default=None, help="run only these mutations (names)")
    ap.add_argument("--timeout", type=int, default=1800, help="seconds per pytest run")
    ap.add_argument("--all-failures", action="store_true",
                    help="run every test per mutation (default: stop at the first failure, pytest -x)")
    ap.add_argument("--json", default=None, help="also write the results as JSON here")
    a = ap.parse_args(argv)
    chosen = [m for m in MUTATIONS if (a.only is None or m[0] in a.only) and (a.group == "all" or m[4] == a.group)]
    if not chosen:
        ap.error(f"--only: no such mutation in group {a.group}; known: {', '.join(m[0] for m in MUTATIONS)}")
    rows = []
    with tempfile.TemporaryDirectory(prefix="simgap-mutations-") as tmp:
        root = copy_repo(Path(tmp) / "repo")
        for tests in {tuple(tests_for(m[1], m[4], a.tests)) for m in chosen}:   # each test set passes unmutated
            ok, first, secs = run_tests(root, list(tests), a.timeout)
            print(f"unmutated: {' '.join(tests)} {'pass' if ok else 'FAIL'} ({secs:.0f} s) {first}")
            if not ok:
                print("the tests must pass on the unmutated code first")
                return 1
        for name, rel, transform, what, group in chosen:
            tests = tests_for(rel, group, a.tests)
            path = root / rel
            orig = path.read_text()
            try:
                path.write_text(transform(orig))
            except LookupError as e:
                rows.append({"mutation": name, "file": rel, "caught": None, "detail": f"not applied: {e}"})
                print(f"{name:<34} NOT APPLIED ({e})")
                continue
            try:
                passed, first, secs = run_tests(root, tests, a.timeout, not a.all_failures)
            finally:
                path.write_text(orig)
            rows.append({"mutation": name, "file": rel, "what": what, "tests": tests, "caught": not passed,
                         "first_failure": first, "seconds": round(secs, 1)})
            print(f"{name:<34} {'caught' if not passed else 'NOT CAUGHT':<10} {secs:6.0f} s  {first}", flush=True)
    print()
    print("| mutation | what the wrong code does | caught by |")
    print("|---|---|---|")
    for r in rows:
        by = r.get("first_failure") if r["caught"] else ("NOT CAUGHT" if r["caught"] is False else r["detail"])
        print(f"| {r['mutation']} | {r.get('what', '')} | {'`' + by + '`' if r['caught'] else by} |")
    if a.json:
        Path(a.json).write_text(json.dumps({"group": a.group, "results": rows}, indent=1))
    if any(r["caught"] is None for r in rows):
        return 2
    return 0 if all(r["caught"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
