import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"


@pytest.hookimpl(tryfirst=True)  # before pytest-xdist's own hook reads the groups
def pytest_collection_modifyitems(config, items):
    for item in items:
        # under pytest-xdist (`-n 2 --dist loadgroup`, the README's command) a file's tests stay on one
        # worker, in file order: a module fixture (a whole `simgap run`) is built once, not once per
        # worker, and a file's tests see each other as in a serial run; the tests that start a local
        # Ray instance share one worker, one instance at a time
        group = "ray" if "ray" in item.keywords else item.nodeid.split("::")[0]
        item.add_marker(pytest.mark.xdist_group(group))
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
