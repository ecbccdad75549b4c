"""SIGTERM and Ctrl-C end a collection's busy workers within 5 s and say how to resume.

A real ``simgap collect`` runs in a subprocess with chunks of about half a minute each (a numpy
pendulum with 400 base periods per run); the signal arrives while both workers are inside their
first chunk. Before workers were stopped, the command waited for those chunks to finish."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

SLOW = """
description = "slow chunks for the signal tests"
[system]
name = "pendulum"
steps = 400
[simulator]
kind = "numpy"
noise = { actuation_std = 0.01 }
[collect]
epsilon = 0.01
n_runs = 50
seed = 1
executor = "local"
workers = 2
chunk_size = 8000
"""


def _descendants(pid: int) -> set:
    """Every live process below ``pid`` (the fork server and the pool's workers included), from /proc."""
    parent = {}
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                with open(f"/proc/{d}/stat", "rb") as f:
                    fields = f.read().rsplit(b")", 1)[1].split()
                if fields[0] != b"Z":
                    parent[int(d)] = int(fields[1])
            except OSError:
                pass
    out, todo = set(), [pid]
    while todo:
        p = todo.pop()
        kids = [c for c, pp in parent.items() if pp == p]
        out.update(kids)
        todo += kids
    return out


@pytest.mark.skipif(not os.path.exists("/proc/self/stat"), reason="reads process trees from /proc")
@pytest.mark.parametrize("sig, code, word", [(signal.SIGTERM, 143, "terminated"), (signal.SIGINT, 130, "interrupted")])
def test_signal_ends_busy_workers_quickly_and_says_how_to_resume(tmp_path, sig, code, word):
    toml = tmp_path / "slow.toml"
    toml.write_text(SLOW)
    env = dict(os.environ, PYTHONPATH=str(REPO))
    err = open(tmp_path / "err.txt", "w+")
    p = subprocess.Popen([sys.executable, "-m", "simgap", "collect", str(toml), "--out", str(tmp_path / "store")],
                         stdout=subprocess.PIPE, stderr=err, text=True, env=env, cwd=tmp_path)
    try:
        # wait until the collection runs (its progress bar is drawn) and the workers are busy
        t0 = time.monotonic()
        while time.monotonic() - t0 < 120:
            err.seek(0)
            # the progress is drawn (a tqdm bar on a terminal; off one, a line at once: "... 0/N pairs [") and both
            # workers run: the command's pools start them from a fork server (executors.PREFERRED_START), so 3
            # processes below it (a signal while the second worker was still being started left it outside
            # the pool's list of processes to stop)
            text = err.read()
            if ("pairs/s" in text or "pairs [" in text) and len(_descendants(p.pid)) >= 3:
                break
            assert p.poll() is None, "the collection ended before the signal"
            time.sleep(0.2)
        time.sleep(3.0)  # inside the first chunks (each about 30 s)
        workers = _descendants(p.pid)
        assert len(workers) >= 3
        t_sig = time.monotonic()
        p.send_signal(sig)
        p.wait(timeout=30)
        elapsed = time.monotonic() - t_sig
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    err.seek(0)
    text = err.read()
    assert p.returncode == code, text
    assert elapsed <= 5.0, f"took {elapsed:.1f} s to stop"
    assert f"{word}:" in text and "run the same command again to resume" in text
    assert "Traceback" not in text
    time.sleep(0.5)
    left = [w for w in workers if os.path.exists(f"/proc/{w}") and
            open(f"/proc/{w}/stat", "rb").read().rsplit(b")", 1)[1].split()[0] != b"Z"]
    assert not left, f"workers still running: {left}"


@pytest.mark.parametrize("kind, code, word", [("Terminated", 143, "terminated"), ("KeyboardInterrupt", 130, "interrupted")])
def test_interruption_inside_a_library_cleanup_is_still_the_interruption(monkeypatch, capsys, kind, code, word):
    """numpy's savez, interrupted while writing its zip, raises ValueError from its own cleanup over the
    signal's exception (seen in CI: exit 1 and a traceback instead of 143). The CLI must still see the
    signal in the exception's context and exit with its code and the resume line."""
    from simgap import cli
    from simgap.cli import plugins

    signal_exc = cli.Terminated if kind == "Terminated" else KeyboardInterrupt

    def interrupted_cleanup(args):
        try:
            raise signal_exc()
        finally:
            raise ValueError("Can't close the ZIP file while there is an open writing handle on it.")

    monkeypatch.setattr(plugins, "run", interrupted_cleanup)
    assert cli.main(["plugins"]) == code
    err = capsys.readouterr().err
    assert err.startswith(f"{word}:") and "resume" in err and "Traceback" not in err


def test_an_ordinary_error_is_not_taken_for_an_interruption(monkeypatch):
    from simgap import cli
    from simgap.cli import plugins

    def broken(args):
        raise ValueError("a real bug")

    monkeypatch.setattr(plugins, "run", broken)
    with pytest.raises(ValueError, match="a real bug"):
        cli.main(["plugins"])
