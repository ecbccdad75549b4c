"""simgap refine next to pysindy (STLSQ) on the generated cases and on the EMPS record.

Both explain the same target, the residual rate y = (x_next - f(x, u)) / tau of the nominal
model, on the same train / held-out split (simgap's: random rows, or contiguous time segments
for time series). pysindy gets a degree-3 polynomial library in (x, u) (angles as sin/cos) and
STLSQ with normalized columns, as a new user would set it up; simgap its physically named library.
Printed per case: what each found, held-out RMS of the remaining residual (sum over states,
relative to the nominal model's) and wall time.

    pip install pysindy          # optional: a bench dependency, not a test dependency
    PYTHONPATH=. python bench/refine_vs_sindy.py [K]
"""
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from simgap.refine.cases import CASES, make_case, verdict
from simgap.refine.report import refine
from simgap.systems import get_system

EMPS = Path(__file__).resolve().parents[2] / "shared" / "data" / "emps" / "DATA_EMPS.mat"


def sindy(system, data, held, threshold=0.1):
    import pysindy as ps

    s = get_system(system) if isinstance(system, str) else system
    cols = []
    for j in range(s.n):
        cols += [np.sin(data.x[:, j]), np.cos(data.x[:, j])] if s.angle_mask[j] else [data.x[:, j]]
    Z = np.column_stack(cols + [data.u])
    y = s.diff(data.x_next, s.f(data.x, data.u)) / data.tau
    lib = ps.PolynomialLibrary(degree=3)
    t0 = time.perf_counter()
    Theta = np.asarray(lib.fit_transform(Z[~held]))
    names = lib.get_feature_names()
    found, rem = [], np.zeros_like(y[held])
    Th = np.asarray(lib.transform(Z[held]))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for i in range(s.n):
            opt = ps.STLSQ(threshold=threshold, normalize_columns=True)
            opt.fit(Theta, y[~held, i])
            c = np.asarray(opt.coef_).reshape(-1)
            found += [f"{s.state_names[i]}:{names[k]}" for k in np.flatnonzero(c)]
            rem[:, i] = y[held, i] - Th @ c
    dt = time.perf_counter() - t0
    return found, float(np.sqrt(np.sum(rem ** 2)) / np.sqrt(np.sum(y[held] ** 2))), dt


def row(name, system, data, expect_ok=None):
    t0 = time.perf_counter()
    res = refine(system, data)
    dt = time.perf_counter() - t0
    rep = res.report
    y = res.before.r[res.heldout]
    rel = float(np.sqrt(np.sum(res.after.r[res.heldout] ** 2)) / np.sqrt(np.sum(y ** 2)))
    desc = verdict(expect_ok, rep)[1] if expect_ok is not None else \
        ", ".join(f"{e['name']}:{e['state_name']}" for e in rep["effects"])
    ok = ("yes" if verdict(expect_ok, rep)[0] else "NO") if expect_ok is not None else "-"
    sf, srel, sdt = sindy(res.system, res.data, res.heldout)
    print(f"| {name} | {desc} | {ok} | {rel:.3f} | {dt:.2f} | {len(sf)} terms"
          f"{': ' + ', '.join(sf[:3]) + (' ...' if len(sf) > 3 else '') if sf else ''} | {srel:.3f} | {sdt:.2f} |")


def main(K=20000):
    print("| case | simgap found | right? | simgap held-out RMS (rel.) | simgap s | pysindy found | "
          "pysindy held-out RMS (rel.) | pysindy s |")
    print("|---|---|---|---|---|---|---|---|")
    for name in CASES:
        c = make_case(name, K)
        row(f"{name} ({c.shape})".replace("|", "\\|"), c.system, c.data, c)
    if EMPS.exists():
        from simgap.refine.trajectory import from_trajectory_file
        row("EMPS record", "emps", from_trajectory_file(EMPS, preset="emps"))


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 20000)
