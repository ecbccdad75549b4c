"""Side by side with SCOTS v0.2 (C++): whole-process CPU and peak memory, interleaved, one run.

    python bench/bench_vs_scots.py [--scots ../shared/reference/scots-v0.2] [--build /tmp/scots-build]
                                   [--pairs 3] [--only dcdc_file,dcdc1601_file,vehicle_file,dcdc,...] [--jit auto,0]

SCOTS is built from its sources with their ``build.sh`` (g++ -O3) into ``--build`` (outside the
repository) when its binaries are missing; the 1601^2 DC-DC case is SCOTS's dcdc example with
eta halved (2/4e3 -> 1/4e3), compiled there from a copy of its source (nothing of SCOTS is
stored in this repository).

Cases through the command line as a user runs it: SCOTS's examples written as system files
(``simgap/synthesis/scots/``, ``examples/scots/`` for the vehicle's spec), ``python -m simgap
synthesize --system FILE ...`` as a subprocess:

* ``dcdc_file``, ``dcdc1601_file``: ``dcdc.toml``, invariance, at SCOTS's eta and at eta / 2;
* ``vehicle_file``: ``vehicle.toml`` with ``vehicle_spec.json`` (reach-avoid, every cell integrated).

Cases through the Python API with the built-in examples (``simgap.synthesis.examples``, a user's
Python step), every (cell, input) pair integrated as SCOTS does:

* ``dcdc``: the boost DC-DC converter, invariance; SCOTS's grid 800 x 799 points, simgap's 801 x
  801 cells over the same box (both 593,089 winning cells);
* ``dcdc1601``: the same at eta / 2 (SCOTS 1600 x 1599, simgap 1601 x 1601; 2,384,526 winning);
* ``vehicle_cells``: SCOTS's vehicle example (reach-avoid, 91,035 cells, 49 inputs), simgap
  with ``invariant_dims=()`` (no shared boxes): 48,018 winning cells, 35,772,302 transitions.

Per case, ``--pairs`` rounds of (SCOTS, simgap for every ``--jit`` mode, ``python -c "import numpy"``:
the floor any simgap process pays) in fresh processes, one
after the other, so every round sees the same load; CPU is user + system time of the child
(``wait4``: interpreter start, imports and file writes included), memory its peak RSS, after one
uncounted warm-up run per program (simgap's bytecode cached as a regular install has it, numba's
kernel cache filled, the files in the page cache). Reported:
every run, the median per program, and the ratios simgap / SCOTS per round and their median. The
machine's load average is printed before and after: on a shared machine the absolute times
inflate, the ratios of one interleaved run are what to compare.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)

SCRIPTS = {
    "dcdc": (593089, None, """
from simgap.synthesis import synthesize
from simgap.synthesis import examples as ex
r = synthesize(ex.dcdc_system(), ex.dcdc_spec(), ex.DCDC_ETA, growth=ex.dcdc_growth(), invariant_dims=())
print("winning", r.stats["winning"], "transitions", r.stats["transitions"])
"""),
    "dcdc1601": (2384526, None, """
from simgap.synthesis import synthesize
from simgap.synthesis import examples as ex
eta = (ex.DCDC_ETA[0] / 2, ex.DCDC_ETA[1] / 2)
r = synthesize(ex.dcdc_system(), ex.dcdc_spec(), eta, growth=ex.dcdc_growth(), invariant_dims=())
print("winning", r.stats["winning"], "transitions", r.stats["transitions"])
"""),
    "vehicle_cells": (48018, 35772302, """
from simgap.synthesis import synthesize
from simgap.synthesis import examples as ex
r = synthesize(ex.vehicle_system(), ex.vehicle_spec(), ex.VEHICLE_ETA, growth=ex.vehicle_growth,
               strict_domain=False, invariant_dims=())
print("winning", r.stats["winning"], "transitions", r.stats["transitions"])
"""),
}
SCOTS_BIN = {"dcdc": "dcdc/dcdc", "dcdc1601": "dcdc1601/dcdc1601", "vehicle_cells": "vehicle/vehicle"}
# SCOTS's examples as system files (examples/scots/), through the command line as a user runs it
FILES = os.path.join(ROOT, "simgap", "synthesis", "scots")  # the files the built-in examples are built from
SPECS = os.path.join(ROOT, "examples", "scots")
_DCDC_CMD = ["synthesize", "--system", os.path.join(FILES, "dcdc.toml"), "--no-gap", "--safe", "1.15,1.55,5.45,5.85",
             "--out", "c.npz", "--eta"]
COMMANDS = {
    "dcdc_file": ("dcdc", 593089, None, _DCDC_CMD + ["0.0005,0.0005"]),
    "dcdc1601_file": ("dcdc1601", 2384526, None, _DCDC_CMD + ["0.00025,0.00025"]),
    "vehicle_file": ("vehicle_cells", 48018, 35772302,
                     ["synthesize", "--system", os.path.join(FILES, "vehicle.toml"), "--no-gap", "--spec",
                      os.path.join(SPECS, "vehicle_spec.json"), "--eta", "0.2", "--no-strict-domain", "--out", "c.npz"]),
}
#: the interpreter and numpy alone: what any simgap process pays before it does anything
FLOOR = "import numpy"


def build_scots(src: str, out: str) -> None:
    """SCOTS's own build.sh, then the eta/2 dcdc from a copy of its example (in ``out``)."""
    if not all(os.path.exists(os.path.join(out, b)) for b in ("dcdc/dcdc", "vehicle/vehicle")):
        subprocess.run(["bash", os.path.join(src, "build.sh"), out], check=True)
    b = os.path.join(out, "dcdc1601", "dcdc1601")
    if not os.path.exists(b):
        os.makedirs(os.path.dirname(b), exist_ok=True)
        with open(os.path.join(src, "examples", "dcdc", "dcdc.cc")) as f:
            code = f.read()
        old = "state_type eta={{2.0/4e3,2.0/4e3}};"
        if old not in code:
            raise SystemExit(f"bench: {old!r} not found in SCOTS's dcdc.cc; cannot derive the 1601^2 case")
        with open(b + ".cc", "w") as f:
            f.write(code.replace(old, "state_type eta={{1.0/4e3,1.0/4e3}};"))
        subprocess.run(["g++", "-std=c++11", "-O3", "-DNDEBUG", "-include", "limits", "-I" + os.path.join(src, "src"),
                        "-I" + os.path.join(src, "utils"), b + ".cc", "-o", b], check=True)


def run_child(argv: list, env: dict) -> tuple[float, float, str]:
    """Run ``argv`` to completion and return its own CPU time, peak RSS and output."""
    with tempfile.TemporaryDirectory() as cwd:
        r, w = os.pipe()
        pid = os.fork()
        if pid == 0:  # the child: output into the pipe, then exec
            os.chdir(cwd)
            os.dup2(w, 1)
            os.dup2(w, 2)
            os.close(r)
            os.execve(argv[0], argv, env)
        os.close(w)
        chunks = []
        with os.fdopen(r) as f:
            chunks.append(f.read())
        _, status, ru = os.wait4(pid, 0)
    return ru.ru_utime + ru.ru_stime, ru.ru_maxrss / 1024, "".join(chunks)


def _med(v):
    v = sorted(v)
    return v[len(v) // 2]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scots", default=next((p for p in (os.path.join(ROOT, *[".."] * k, "shared", "reference", "scots-v0.2")
                                                         for k in (1, 2)) if os.path.isdir(p)), None),
                    help="SCOTS v0.2 sources with build.sh")
    ap.add_argument("--build", default=os.path.join(tempfile.gettempdir(), "scots-build"),
                    help="where SCOTS is built (outside the repository)")
    ap.add_argument("--pairs", type=int, default=3)
    ap.add_argument("--only", default="dcdc_file,dcdc1601_file,vehicle_file,dcdc,dcdc1601,vehicle_cells")
    ap.add_argument("--jit", default="auto,0", help="SIMGAP_JIT modes to run for simgap (auto: compiled "
                    "kernels when a job is large enough; 0: numpy only)")
    a = ap.parse_args()
    cases = [c for c in a.only.split(",") if c]
    bad = [c for c in cases if c not in SCRIPTS and c not in COMMANDS]
    if bad:
        print(f"bench: --only {','.join(bad)} unknown; choose from {', '.join(list(COMMANDS) + list(SCRIPTS))}",
              file=sys.stderr)
        return 2
    modes = [m for m in a.jit.split(",") if m]
    if any(m not in ("auto", "0", "1") for m in modes):
        print(f"bench: --jit {a.jit!r}: modes are auto, 0, 1", file=sys.stderr)
        return 2
    if not a.scots or not os.path.exists(os.path.join(a.scots, "build.sh")):
        print(f"bench: --scots {a.scots!r} has no build.sh (SCOTS v0.2 sources)", file=sys.stderr)
        return 2
    build_scots(os.path.abspath(a.scots), os.path.abspath(a.build))
    # compiled bytecode cached as after a regular install (pip writes it; a warm-up run per
    # program writes it here, and numba's kernel cache): without it every process compiles
    # simgap's modules again (this machine sets PYTHONDONTWRITEBYTECODE=1)
    env0 = {k: v for k, v in os.environ.items() if k not in ("SIMGAP_JIT", "PYTHONDONTWRITEBYTECODE")}
    env0["PYTHONPATH"] = ROOT + os.pathsep + env0.get("PYTHONPATH", "")
    load0 = os.getloadavg()
    print(f"load average before: {load0[0]:.2f} {load0[1]:.2f} {load0[2]:.2f} ({os.cpu_count()} cores); "
          f"python {sys.version.split()[0]}")
    ok = True
    summary = []
    for case in cases:
        if case in COMMANDS:
            scots, win, trans, argv = COMMANDS[case]
            argv = [sys.executable, "-m", "simgap"] + argv
        else:
            scots, (win, trans, script) = case, SCRIPTS[case]
            argv = [sys.executable, "-c", script]
        progs = [("SCOTS", [os.path.join(os.path.abspath(a.build), SCOTS_BIN[scots])], env0)]
        progs += [(f"simgap jit={m}", argv, {**env0, "SIMGAP_JIT": m}) for m in modes]
        progs.append(("python+numpy", [sys.executable, "-c", FLOOR], env0))
        res = {name: [] for name, _, _ in progs}
        for name, argv, env in progs:
            run_child(argv, env)  # warm-up (not counted): bytecode and kernel caches, file cache
        print(f"\n== {case}")
        print(f"{'round':>5} {'program':<16} {'CPU s':>7} {'peak RSS MB':>12}  result")
        for i in range(a.pairs):
            for name, argv, env in progs:
                cpu, rss, out = run_child(argv, env)
                if name == "SCOTS":
                    w = re.search(r"Winning domain size: (\d+)", out)
                    t = re.search(r"Number of transitions: (\d+)", out)
                    got = (int(w.group(1)) if w else -1, int(t.group(1)) if t else -1)
                elif name == "python+numpy":
                    got = (win, trans if trans is not None else -1)
                else:  # a script's line, or the command's summary ("winning   48,018 cells ...")
                    w = re.search(r"winning\s+([\d,]+)", out)
                    t = re.search(r"transitions\s+([\d,]+)", out)
                    got = tuple(int(x.group(1).replace(",", "")) if x else -1 for x in (w, t))
                good = got[0] == win and (trans is None or got[1] == trans)
                ok &= good
                res[name].append((cpu, rss))
                print(f"{i:>5} {name:<16} {cpu:>7.3f} {rss:>12.1f}  winning {got[0]:,}, transitions {got[1]:,}"
                      f"{'' if good else '  MISMATCH: ' + out[-300:]}")
        s_cpu = [c for c, _ in res["SCOTS"]]
        s_rss = [r for _, r in res["SCOTS"]]
        for name, _, _ in progs[1:]:
            rc = [c / s for (c, _), s in zip(res[name], s_cpu)]
            rm = [r / s for (_, r), s in zip(res[name], s_rss)]
            line = (f"{case}: {name}: CPU {_med([c for c, _ in res[name]]):.3f} s vs SCOTS {_med(s_cpu):.3f} s, "
                    f"ratio per round {', '.join(f'{x:.2f}' for x in rc)} (median {_med(rc):.2f}x); "
                    f"peak RSS {_med([r for _, r in res[name]]):.1f} MB vs {_med(s_rss):.1f} MB, "
                    f"ratio {', '.join(f'{x:.2f}' for x in rm)} (median {_med(rm):.2f}x)")
            summary.append(line)
            print(line)
    load1 = os.getloadavg()
    print(f"\nload average after: {load1[0]:.2f} {load1[1]:.2f} {load1[2]:.2f}")
    print("\n".join(["summary:"] + summary))
    print(f"parity (winning cells, and transitions for the vehicle) in every run: {'yes' if ok else 'NO'}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
