import json
import os
from collections import defaultdict
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
#: seconds per xdist group (a test file, or "ray") measured in a default run; the groups a run measures
#: are updated by `python -m pytest -n 2 --dist loadgroup --store-durations` (docs/tests.md)
DURATIONS = Path(__file__).with_name("durations.json")


def _group(nodeid: str, keywords) -> str:
    # under pytest-xdist (`-n 2 --dist loadgroup`, the README's command) a file's tests stay on one
    # worker, in file order: a module fixture (a whole `simgap run`) is built once, not once per
    # worker, and a file's tests see each other as in a serial run; the tests that start a local
    # Ray instance share one worker, one instance at a time
    return "ray" if "ray" in keywords else nodeid.split("::")[0]


def pytest_addoption(parser):
    parser.addoption("--store-durations", action="store_true",
                     help=f"write each test file's seconds in this run to {DURATIONS.name} (the groups' order)")


def pytest_configure(config):
    # the groups go out longest first (the durations table), not xdist's most-tests first: files of
    # a few long tests (a whole `simgap run`, a browser) came last and one worker ran them alone
    if hasattr(config.option, "loadscopereorder"):
        config.option.loadscopereorder = False


_SECONDS = defaultdict(float)  # group -> seconds in this run (the controller sees every worker's reports)


def pytest_runtest_logreport(report):
    _SECONDS[_group(report.nodeid.split("@")[0], report.keywords)] += report.duration


def pytest_sessionfinish(session, exitstatus):
    if session.config.getoption("--store-durations") and _SECONDS and not hasattr(session.config, "workerinput"):
        d = dict(json.loads(DURATIONS.read_text()) if DURATIONS.is_file() else {})
        d.update({k: round(v, 1) for k, v in _SECONDS.items()})  # the groups this run measured
        DURATIONS.write_text(json.dumps(dict(sorted(d.items(), key=lambda kv: -kv[1])), indent=1) + "\n")


@pytest.hookimpl(tryfirst=True)  # before pytest-xdist's own hook reads the groups
def pytest_collection_modifyitems(config, items):
    known = json.loads(DURATIONS.read_text()) if DURATIONS.is_file() else {}
    for item in items:
        item.add_marker(pytest.mark.xdist_group(_group(item.nodeid, item.keywords)))
    # longest groups first; a file not in the table yet goes first (it may be long)
    index = {it.nodeid: k for k, it in enumerate(items)}
    items.sort(key=lambda it: (-known.get(_group(it.nodeid, it.keywords), float("inf")), index[it.nodeid]))
    # runs of hours (over CI's time): only on request, whatever SIMGAP_SLOW says
    if os.environ.get("SIMGAP_HOURS") != "1":
        hours = pytest.mark.skip(reason="a run of hours: set SIMGAP_HOURS=1 (and SIMGAP_SLOW=1) to run")
        for item in items:
            if "hours" in item.keywords:
                item.add_marker(hours)
    if os.environ.get("SIMGAP_SLOW") == "1":
        return
    skip = pytest.mark.skip(reason="paper-scale run: set SIMGAP_SLOW=1 to run")
    for item in items:
        if "slow" in item.keywords:
            item.add_marker(skip)


@pytest.fixture
def rng():
    import numpy as np
    return np.random.default_rng(12345)
