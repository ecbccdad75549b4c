"""A collection killed with SIGKILL mid-run resumes, and the result is bit-identical to an uninterrupted run."""

import os
import signal
import subprocess
import sys
import time

import numpy as np

from simgap.collect import load_store, store_status
from simgap.config import load_experiment
from simgap.collect import collect

TOML = """
[system]
name = "pendulum"
[simulator]
kind = "numpy"
noise = {{ actuation_std = 0.05, process_std = 0.0001 }}
effects = {{ linear = [[0.0, 0.0], [0.0, -0.5]] }}
[collect]
epsilon = 0.01
n_runs = 300
seed = 11
chunk_size = 400
out = "{out}"
"""


def test_sigkill_then_resume_is_bit_identical(tmp_path):
    killed = tmp_path / "killed"
    toml = tmp_path / "exp.toml"
    toml.write_text(TOML.format(out="killed"))  # collect.out is relative to the experiment file
    # 2,059 cover points x 21 inputs = 43,239 pairs in 109 chunks; ~13M runs take a few seconds
    cmd = [sys.executable, "-m", "simgap", "collect", str(toml), "--profile", "base", "--executor", "local",
           "--workers", "2", "--no-progress"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)
    chunks = killed / "chunks"
    deadline = time.time() + 120
    try:
        while time.time() < deadline:
            if chunks.is_dir() and len(list(chunks.glob("c*.npz"))) >= 10:
                break
            if proc.poll() is not None:
                raise AssertionError(f"collection ended before it could be killed: {proc.stderr.read().decode()}")
            time.sleep(0.005)
    finally:
        os.killpg(proc.pid, signal.SIGKILL)  # the CLI process and its pool workers
        proc.wait()
    st = store_status(killed)
    print("killed after", st["done"], "of", st["n_chunks"], "chunks")
    assert 10 <= st["done"] < st["n_chunks"], st["done"]
    exp = load_experiment(toml, profile=None)
    plan = exp.plan()
    assert st["hash"] == plan.hash()

    res = collect(plan, killed, executor="local", workers=2)
    assert res.resumed_from == st["done"] and res.complete
    assert not any(p.name.endswith(".tmp") for p in chunks.iterdir())
    collect(plan, tmp_path / "ref", executor="local", workers=2)
    a, b = load_store(killed), load_store(tmp_path / "ref")
    for k in ("x", "u", "f_nom", "mean", "var", "lo", "hi", "cover_index", "input_index"):
        assert np.array_equal(getattr(a, k), getattr(b, k)), k
    assert a.hash == b.hash
