"""`time simgap ...` counts the pool workers' CPU (issue 54): workers started through multiprocessing's
forkserver are its children, so the command waits for the forkserver before it returns."""

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

SCRIPT = """
import resource, sys, time
from concurrent.futures import ProcessPoolExecutor
import multiprocessing

def burn(seconds):
    t = time.process_time()
    while time.process_time() - t < seconds:
        pass
    return seconds

if __name__ == "__main__":
    from simgap.cli import _reap_forkserver
    with ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("forkserver")) as pool:
        assert sum(pool.map(burn, [0.25, 0.25])) == 0.5
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    if sys.argv[1] == "reap":
        _reap_forkserver()
        _reap_forkserver()  # a second call (no server left) is harmless
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    print(after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime)
"""


def _children_cpu(tmp_path, mode: str) -> float:
    script = tmp_path / "burn.py"  # a file: the forkserver's workers import __main__'s functions from it
    script.write_text(SCRIPT)
    r = subprocess.run([sys.executable, str(script), mode], cwd=ROOT, capture_output=True, text=True,
                       timeout=120, env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"})
    assert r.returncode == 0, r.stderr
    return float(r.stdout.strip())


def test_forkserver_workers_cpu_reaches_the_command(tmp_path):
    assert _children_cpu(tmp_path, "reap") >= 0.45  # both workers' 0.5 CPU-seconds, now the command's children's
    assert _children_cpu(tmp_path, "keep") < 0.1    # the failure this guards against: lost without the wait
