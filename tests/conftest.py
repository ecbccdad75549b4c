import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"


def pytest_collection_modifyitems(config, items):
    for item in items:
        if "ray" in item.keywords:
            # one local Ray instance at a time: under pytest-xdist (`-n 2 --dist loadgroup`) the
            # tests that start Ray share one worker instead of racing for its session files
            item.add_marker(pytest.mark.xdist_group("ray"))
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
