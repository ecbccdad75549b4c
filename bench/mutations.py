"""Mutation check: every known wrong implementation of the certificate or the abstraction must
make the tight-margin tests fail.

    python bench/mutations.py [--tests tests/test_soundness_margins.py tests/test_certificate_margins.py]
                              [--only NAME ...] [--all-failures] [--json out.json]

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


#: (name, file, transform, what the wrong implementation does)
MUTATIONS = [
    ("gamma at cell centres", "simgap/synthesis/abstraction.py",
     _in_function("build_abstraction", "blo, bhi = x - r, x + r", "blo, bhi = x.copy(), x.copy()"),
     "the abstraction bounds gamma at the cell centre instead of over the cell"),
    ("gamma halved", "simgap/synthesis/abstraction.py",
     _in_function("build_abstraction", "g = gamma_upper_wrapped(", "g = 0.5 * gamma_upper_wrapped("),
     "the abstraction uses gamma / 2"),
    ("seam ignored", "simgap/synthesis/abstraction.py",
     _in_function("gamma_upper_wrapped", "if not grid.periodic:", "if True:"),
     "gamma bounded over the raw interval [-pi - eta/2, -pi + eta/2] of the seam cell"),
    ("certificate's inputs ignored", "simgap/synthesis/abstraction.py",
     _in_function("certified_input_mask", "M = system.inputs.shape[0]\n",
                  "M = system.inputs.shape[0]\n    return np.ones(M, dtype=bool)\n"),
     "synthesis over every input of the system, certified or not"),
    ("delta_2 dropped", "simgap/certify/certificate.py",
     _in_function("constant", " + d.delta2", ""),
     "gamma = L_x eps + q^T p (+ repair), without delta_2"),
    ("L*epsilon term dropped", "simgap/certify/certificate.py",
     _in_function("constant", "d.L_x * self.epsilon + ", ""),
     "gamma = q^T p + delta_2 (+ repair), without the Lipschitz term"),
    ("delta_1 dropped", "simgap/certify/pipeline.py",
     _in_function("certify", "solve_scp(P, g[:, i], float(d1[i]),", "solve_scp(P, g[:, i], 0.0,"),
     "the scenario program without delta_1 in its constraints"),
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
    ap.add_argument("--tests", nargs="+", default=DEFAULT_TESTS, help="test files/ids to run per mutation")
    ap.add_argument("--only", nargs="+", default=None, help="run only these mutations (names)")
    ap.add_argument("--timeout", type=int, default=1800, help="seconds per pytest run")
    ap.add_argument("--all-failures", action="store_true",
                    help="run every test per mutation (default: stop at the first failure, pytest -x)")
    ap.add_argument("--json", default=None, help="also write the results as JSON here")
    a = ap.parse_args(argv)
    chosen = [m for m in MUTATIONS if a.only is None or m[0] in a.only]
    if not chosen:
        ap.error(f"--only: no such mutation; known: {', '.join(m[0] for m in MUTATIONS)}")
    rows = []
    with tempfile.TemporaryDirectory(prefix="simgap-mutations-") as tmp:
        root = copy_repo(Path(tmp) / "repo")
        ok, first, secs = run_tests(root, a.tests, a.timeout)
        print(f"unmutated: tests {'pass' if ok else 'FAIL'} ({secs:.0f} s) {first}")
        if not ok:
            print("the tests must pass on the unmutated code first")
            return 1
        for name, rel, transform, what in chosen:
            path = root / rel
            orig = path.read_text()
            try:
                path.write_text(transform(orig))
            except LookupError as e:
                rows.append({"mutation": name, "file": rel, "caught": None, "detail": f"not applied: {e}"})
                print(f"{name:<30} NOT APPLIED ({e})")
                continue
            try:
                passed, first, secs = run_tests(root, a.tests, a.timeout, not a.all_failures)
            finally:
                path.write_text(orig)
            rows.append({"mutation": name, "file": rel, "what": what, "caught": not passed,
                         "first_failure": first, "seconds": round(secs, 1)})
            print(f"{name:<30} {'caught' if not passed else 'NOT CAUGHT':<10} {secs:6.0f} s  {first}")
    print()
    print("| mutation | what the wrong code does | caught by |")
    print("|---|---|---|")
    for r in rows:
        by = r.get("first_failure") if r["caught"] else ("NOT CAUGHT" if r["caught"] is False else r["detail"])
        print(f"| {r['mutation']} | {r.get('what', '')} | {'`' + by + '`' if r['caught'] else by} |")
    if a.json:
        Path(a.json).write_text(json.dumps({"tests": a.tests, "results": rows}, indent=1))
    if any(r["caught"] is None for r in rows):
        return 2
    return 0 if all(r["caught"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
