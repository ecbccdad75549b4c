"""The results folder's run lock (simgap.results_folder.run_lock): one run writes into a folder at a
time, and the lock file does not outlive the run."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

from simgap.errors import SimgapError

ROOT = Path(__file__).resolve().parents[1]
def test_run_lock_is_removed_and_still_excludes(tmp_path):
    """results_folder.run_lock: held, a second process is refused; released, no .run.lock stays (a
    finished folder holds the run's files only); a lock held on a file removed under it is refused."""
    from simgap import results_folder

    holder = ("import sys, time; from pathlib import Path; from simgap.results_folder import run_lock\n"
              "with run_lock(Path(sys.argv[1])):\n    print('held', flush=True); time.sleep(30)\n")
    p = subprocess.Popen([sys.executable, "-c", holder, str(tmp_path)], stdout=subprocess.PIPE, text=True,
                         env={**os.environ, "PYTHONPATH": str(ROOT)})
    try:
        assert p.stdout.readline().strip() == "held"
        assert (tmp_path / results_folder.LOCK).exists()
        with pytest.raises(SimgapError, match="another simgap run is writing into"):
            with results_folder.run_lock(tmp_path):
                pass
    finally:
        p.kill()
        p.wait()
    # the holder was killed: its file stays, but no lock is held on it, so the next run takes it
    with results_folder.run_lock(tmp_path):
        assert (tmp_path / results_folder.LOCK).exists()
    assert not (tmp_path / results_folder.LOCK).exists()
    with pytest.raises(RuntimeError):  # a failing run removes it too
        with results_folder.run_lock(tmp_path):
            raise RuntimeError("stage failed")
    assert not (tmp_path / results_folder.LOCK).exists()


def test_a_lock_on_a_removed_file_is_taken_again(tmp_path, monkeypatch):
    """The run before removed .run.lock between our open and our lock: the descriptor locks a file no
    longer at the path, which would let a third run lock a new file beside us. run_lock sees the path
    gone (or another file there) and locks the file now at the path instead."""
    import os

    from simgap import results_folder

    real_stat, calls = os.stat, []

    def stat(p, *a, **k):
        if str(p).endswith(results_folder.LOCK):
            calls.append(p)
            if len(calls) == 1:  # the first look: the path was removed under us
                os.unlink(p)
        return real_stat(p, *a, **k)

    monkeypatch.setattr(os, "stat", stat)
    with results_folder.run_lock(tmp_path):
        assert len(calls) == 2                      # taken again, on the file now at the path
        st = real_stat(tmp_path / results_folder.LOCK)
        assert st.st_size == 0
    assert not (tmp_path / results_folder.LOCK).exists()
