"""Idle CPU of ``simgap view`` (run by hand; the numbers go to docs/app.md and docs/getting-started.md).

    python bench/bench_view_cpu.py results/pendulum-small [--seconds 30]

Starts ``simgap view RUN`` on free ports, waits until it printed its address and a few seconds
more, then reads the CPU time (user + system, /proc/PID/stat) of ``simgap view`` and every
descendant at the start and the end of ``--seconds`` with no browser connected, and prints the
difference per process and in total, the processes it found (a browser child or a defunct one
would be listed) and what is left after SIGTERM. Linux only (/proc).
"""

from __future__ import annotations

import argparse
import os
import re
import signal
import subprocess
import sys
import time

TICK = os.sysconf("SC_CLK_TCK")


def tree(pid: int) -> dict:
    """pid -> (name, state, cpu seconds) of ``pid`` and its descendants."""
    procs = {}
    for d in filter(str.isdigit, os.listdir("/proc")):
        try:
            stat = open(f"/proc/{d}/stat").read()
        except OSError:
            continue
        name = stat[stat.index("(") + 1:stat.rindex(")")]
        f = stat[stat.rindex(")") + 2:].split()
        procs[int(d)] = (int(f[1]), name, f[0], (int(f[11]) + int(f[12])) / TICK)
    out, todo = {}, [pid]
    while todo:
        p = todo.pop()
        if p in procs:
            out[p] = procs[p][1:]
        todo += [c for c, v in procs.items() if v[0] == p]
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", help="a results folder with run.rrd, or an .rrd file")
    ap.add_argument("--seconds", type=float, default=30.0)
    ap.add_argument("--settle", type=float, default=5.0, help="seconds after the address before measuring")
    a = ap.parse_args(argv)
    p = subprocess.Popen([sys.executable, "-m", "simgap", "view", a.run, "--web-port", "0", "--grpc-port", "0"],
                         stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        for line in p.stdout:
            if re.search(r"open http://\S+ in a browser", line):
                break
        else:
            print("simgap view printed no address", file=sys.stderr)
            return 1
        time.sleep(a.settle)
        t0 = tree(p.pid)
        time.sleep(a.seconds)
        t1 = tree(p.pid)
        load = open("/proc/loadavg").read().split()[:3]
        total = 0.0
        for pid, (name, state, cpu) in sorted(t1.items()):
            d = cpu - t0.get(pid, (name, state, cpu))[2]
            total += d
            print(f"{pid:>8} {name:<16} state {state}  {d:.2f} s CPU in {a.seconds:g} s")
        print(f"total {total:.2f} s CPU in {a.seconds:g} s ({100 * total / a.seconds:.2f} % of a core); "
              f"load average {' '.join(load)}")
    finally:
        pids = list(tree(p.pid))
        p.send_signal(signal.SIGTERM)
        p.wait(30)
    time.sleep(0.5)
    left = [q for q in pids if os.path.exists(f"/proc/{q}")]
    print("left after SIGTERM: " + (", ".join(map(str, left)) if left else "none"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
