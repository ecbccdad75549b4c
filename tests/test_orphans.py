"""Worker processes leave with the process that started them: a killed `simgap` leaves nothing running.

Without simgap.executors.exit_with_parent, a pool worker of a killed parent finishes its task and
then blocks for ever on a result pipe it holds both ends of (measured: every worker was left)."""

import os
import signal
import subprocess
import sys
import textwrap
import time
import uuid
from pathlib import Path

import pytest

CHILD = textwrap.dedent("""
    import sys, time
    import numpy as np
    from simgap.executors import LocalExecutor
    from simgap.simulators.base import make_simulator
    from simgap.simulators.parallel import ParallelSimulator

    def slow(job, c):
        time.sleep(120)
        return c

    if __name__ == "__main__":
        if sys.argv[1] == "pool":
            LocalExecutor(2, start_method=sys.argv[2]).map_chunks(slow, None, range(4), lambda c, r: None)
        else:
            sim = ParallelSimulator(make_simulator({"kind": "numpy", "system": "pendulum"}), 2)
            x, u = np.zeros((2_000_000, 2)), np.zeros((2_000_000, 1))
            rng = np.random.default_rng(0)
            while True:
                sim.step(x, u, rng)
""")


def _tagged(token: str) -> list:
    """Processes whose environment carries the token (the child and everything it started)."""
    out = []
    for p in Path("/proc").iterdir():
        if p.name.isdigit():
            try:
                if f"SIMGAP_TEST_TOKEN={token}".encode() in (p / "environ").read_bytes():
                    state = (p / "stat").read_bytes().rsplit(b")", 1)[1].split()[0]
                    if state != b"Z":
                        out.append(int(p.name))
            except OSError:
                pass
    return out


@pytest.mark.skipif(not Path("/proc/self/environ").exists(), reason="needs /proc (Linux) to find the processes")
@pytest.mark.parametrize("args", [("pool", "fork"), ("pool", "forkserver"), ("simulator", "")])
def test_killed_parent_leaves_no_worker(tmp_path, args):
    script = tmp_path / "child.py"
    script.write_text(CHILD)
    token = uuid.uuid4().hex
    env = dict(os.environ, SIMGAP_TEST_TOKEN=token)
    child = subprocess.Popen([sys.executable, str(script), *args], env=env)
    try:
        deadline = time.time() + 60
        while len(_tagged(token)) < 2 and time.time() < deadline:   # the child and at least one worker
            time.sleep(0.2)
        assert len(_tagged(token)) >= 2, "the workers did not start"
        time.sleep(1.0)
        child.send_signal(signal.SIGKILL)
        child.wait()
        deadline = time.time() + 10
        while _tagged(token) and time.time() < deadline:
            time.sleep(0.2)
        left = _tagged(token)
        assert not left, f"{len(left)} worker processes outlived their killed parent"
    finally:
        for pid in _tagged(token):
            os.kill(pid, signal.SIGKILL)
        if child.poll() is None:
            child.kill()


@pytest.mark.parametrize("proc", [True, False])
def test_watch_exits_only_after_the_parent(monkeypatch, proc):
    """The watcher with /proc (start time) and without it (os.kill, as on macOS): it must not fire while
    the watched process lives (a worker that left at once would break every pool), and must fire after."""
    import simgap.executors as ex
    if not proc:
        real = os.path.exists
        monkeypatch.setattr(ex.os.path, "exists", lambda p: False if p == "/proc/self/stat" else real(p))
        assert ex._process_token(os.getpid()) is None
    elif not Path("/proc/self/stat").exists():
        pytest.skip("needs /proc")
    exited = []
    monkeypatch.setattr(ex.os, "_exit", lambda code: exited.append(code))
    # exit_with_parent ignores SIGINT (as a worker must); in this process that would outlive the test
    # and every later subprocess would inherit SIG_IGN (a Ctrl-C test then saw its SIGINT ignored)
    monkeypatch.setattr(ex.signal, "signal", lambda *a: None)
    parent = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(2)"])
    ex.exit_with_parent(parent.pid, period=0.1)
    time.sleep(1.0)
    assert not exited, "the watcher fired while the process was alive"
    parent.wait()
    deadline = time.time() + 5
    while not exited and time.time() < deadline:
        time.sleep(0.1)
    assert exited == [1]


def _blocked_at_start(job, c):
    """What the worker's signal mask held when it was forked (read before anything unblocks it)."""
    return signal.SIGINT in signal.pthread_sigmask(signal.SIG_BLOCK, [])


def test_workers_start_with_sigint_blocked():
    """A terminal's Ctrl-C reaches the whole process group; a worker forked in that moment, before its
    initializer ignores SIGINT, died and left the pool broken while the parent shut it down (a
    collect that did not end within 60 s of Ctrl-C under load). Workers are forked with SIGINT
    blocked; the parent's mask is restored after each submit. (With forkserver the mask is the fork
    server's, blocked too when a simgap pool started it; not asserted: an earlier pool may have.)"""
    from simgap.executors import LocalExecutor

    out = {}
    LocalExecutor(2, start_method="fork").map_chunks(_blocked_at_start, None, range(4),
                                                     lambda c, r: out.__setitem__(c, r))
    assert out == {c: True for c in range(4)}
    assert signal.SIGINT not in signal.pthread_sigmask(signal.SIG_BLOCK, [])
