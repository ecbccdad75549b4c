"""The Silverbox (real electronic Duffing oscillator): linear nominal model -> simgap refine -> free run.

    PYTHONPATH=. python bench/refine_silverbox.py [--data DIR] [--out DIR] [--fit-nominal] [--sindy]

Record: SNLS80mV.mat (../shared/data/silverbox or $SIMGAP_SILVERBOX_DIR), offsets removed as the
benchmark's README says. Estimation: samples 40,501.. (the multisines); test: the "arrow", samples
101..40,500. Transitions with causal velocities (backward differences, no filter:
simgap.refine.trajectory.backward_transitions). Nominal: examples/silverbox/silverbox_linear.toml
(linear mass-spring-damper, semi-implicit Euler; --fit-nominal prints its least-squares k, d, b).
Prints the effects simgap refine names on the estimation record, then the benchmark's metric:
the RMS error [mV] of a free-run simulation of y over the whole arrow from its first two samples,
for the nominal model and for the refined model saved to --out and loaded back (history effects,
which a memoryless f' cannot hold, are left out of the free run and listed). --sindy: pysindy
(STLSQ, degree-3 polynomial library in (y, v, u), unit-RMS columns and target, threshold 0.05,
ridge 1e-3) on the same residual, added to the same nominal model, free run likewise.
"""
import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from simgap.refine.data import make_transitions
from simgap.refine.refined import load_system, save_refined
from simgap.refine.report import format_table, refine
from simgap.refine.trajectory import backward_transitions, read_timeseries

ROOT = Path(__file__).resolve().parents[1]
NOMINAL = ROOT / "examples" / "silverbox" / "silverbox_linear.toml"
FS = 1e7 / 2 ** 14
ARROW = slice(100, 40500)
ESTIMATION = slice(40500, None)


def find_record(folder=None) -> Path:
    for d in [folder, os.environ.get("SIMGAP_SILVERBOX_DIR"), ROOT.parent / "shared" / "data" / "silverbox",
              ROOT.parents[1] / "shared" / "data" / "silverbox"]:
        if d and (Path(d) / "SNLS80mV.mat").exists():
            return Path(d) / "SNLS80mV.mat"
    raise SystemExit("SNLS80mV.mat not found: pass --data DIR or set SIMGAP_SILVERBOX_DIR")


def load(path):
    d = read_timeseries(path, ["V1", "V2"])
    u, y = d["V1"] - d["V1"].mean(), d["V2"] - d["V2"].mean()
    return u, y, np.arange(u.size) / FS


def free_run(system, y, u, extra=None):
    """y predicted by iterating x <- f(x, u_k) from x_1 = (y_1, (y_1 - y_0) / tau); (pred, diverged at)."""
    x = np.array([[y[1], (y[1] - y[0]) * FS]])
    pred = np.full(y.size, np.nan)
    pred[:2] = y[:2]
    for k in range(1, y.size - 1):
        x = system.f(x, u[k:k + 1, None])
        if extra is not None:
            x = x + extra(x, k)
        if not np.all(np.isfinite(x)) or abs(x[0, 0]) > 10:
            return pred, k
        pred[k + 1] = x[0, 0]
    return pred, None


def rms_mv(pred, y):
    return 1000 * float(np.sqrt(np.mean((pred - y) ** 2)))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--data")
    ap.add_argument("--out", default="silverbox_out")
    ap.add_argument("--fit-nominal", action="store_true")
    ap.add_argument("--sindy", action="store_true")
    args = ap.parse_args()
    u, y, t = load(find_record(args.data))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    est = backward_transitions(t[ESTIMATION], y[ESTIMATION], u[ESTIMATION], source="SNLS80mV.mat:estimation")
    if args.fit_nominal:
        a = (est.x_next[:, 1] - est.x[:, 1]) * FS
        A = np.column_stack([est.x[:, 0], est.x[:, 1], est.u[:, 0]])
        c = np.linalg.lstsq(A, a, rcond=None)[0]
        print(f"least squares on the estimation record: k = {-c[0]:.7g}, d = {-c[1]:.6g}, b = {c[2]:.7g}")
    est.save_npz(out / "silverbox_estimation.npz")
    nominal = load_system(str(NOMINAL))
    t0 = time.perf_counter()
    res = refine(nominal, est)
    print(format_table(res.report))
    print(f"refine: {time.perf_counter() - t0:.1f} s")
    p = save_refined(res.refined, out / "silverbox_refined.json")
    refined = load_system(str(p))
    ya, ua = y[ARROW], u[ARROW]
    rows = {}
    for name, sysm in (("linear nominal (examples/silverbox/silverbox_linear.toml)", nominal),
                       (f"simgap refine, saved and loaded ({p.name})", refined)):
        t0 = time.perf_counter()
        pred, div = free_run(sysm, ya, ua)
        rows[name] = (rms_mv(pred, ya) if div is None else float("nan"), div, time.perf_counter() - t0)
    hist = [e for e in res.report["effects"] if not e["in_refined_system"]]
    if args.sindy:
        rows.update(sindy_rows(nominal, est, ya, ua))
    print("\nfree-run RMS error of y over the arrow (samples 101..40,500), mV:")
    for name, (r, div, sec) in rows.items():
        print(f"  {name:<62} {r:8.3f}" + (f"  (diverged at sample {div})" if div else "") + f"   [{sec:.1f} s]")
    if hist:
        print("history effects named but not in the saved f' (not in its free run): "
              + ", ".join(f"{e['name']}:{e['state_name']} {e['coefficient']:.4g}" for e in hist))
    (out / "silverbox_summary.json").write_text(json.dumps(
        {"effects": res.report["effects"], "free_run_rms_mV": {k: v[0] for k, v in rows.items()}}, indent=1))


def sindy_rows(nominal, est, ya, ua):
    import pysindy as ps
    Z = np.column_stack([est.x, est.u])
    r = (est.x_next - nominal.f(est.x, est.u)) * FS
    lib = ps.PolynomialLibrary(degree=3)
    Theta = np.asarray(lib.fit_transform(Z))
    sc = np.sqrt(np.mean(Theta ** 2, axis=0))
    sc[sc == 0] = 1.0
    coefs, names = [], lib.get_feature_names(["y", "v", "u"])
    for i in range(2):
        sy = float(np.sqrt(np.mean(r[:, i] ** 2))) or 1.0
        opt = ps.STLSQ(threshold=0.05, alpha=1e-3)
        opt.fit(Theta / sc, r[:, i] / sy)
        coefs.append(np.asarray(opt.coef_).reshape(-1) * sy / sc)
    C = np.stack(coefs)
    terms = [f"{'yv'[i]}:{names[j]}" for i in range(2) for j in np.flatnonzero(C[i])]
    print(f"pysindy: {len(terms)} terms: {', '.join(terms)}")

    powers = np.asarray(lib.powers_)           # monomial exponents of the library's features

    def extra(x, k):
        z = np.array([x[0, 0], x[0, 1], ua[k]])
        th = np.prod(z[None, :] ** powers, axis=1)
        return (th @ C.T)[None, :] / FS

    t0 = time.perf_counter()
    pred, div = free_run(nominal, ya, ua, extra)
    return {f"pysindy residual model ({len(terms)} terms)": (rms_mv(pred, ya) if div is None else float("nan"),
                                                             div, time.perf_counter() - t0)}


if __name__ == "__main__":
    main()
