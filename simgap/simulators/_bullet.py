"""Small helpers shared by the PyBullet simulators: clients, asset paths, per-run factors."""

from __future__ import annotations

import contextlib
import os
import re
import sys
from pathlib import Path

import numpy as np

from ..errors import SimgapError
from ..paths import ASSETS_DIR
from .base import Simulator

#: repository folder holding the URDF files (``assets/urdf``)
URDF_DIR = ASSETS_DIR / "urdf"


def urdf_path(name: str) -> Path:
    """Absolute path of ``assets/urdf/<name>``; SimgapError if it is missing or leads elsewhere
    (a configuration file never points the simulator at an arbitrary file)."""
    path = (URDF_DIR / str(name)).resolve()
    if not path.is_relative_to(URDF_DIR.resolve()):
        raise SimgapError(f"URDF {str(name)!r}: must be a file under {URDF_DIR} (no absolute path, no ..)")
    if not path.is_file():
        raise SimgapError(f"URDF file not found: {path}")
    return path


@contextlib.contextmanager
def _quiet_c_output():
    """Silence file descriptors 1 and 2 (C-level prints) for the duration of the block.

    PyBullet's C library prints "pybullet build time: ..." on stderr at import and "argv[0]="
    on stdout at connect; neither says anything a user can act on.
    """
    with open(os.devnull, "w") as null, _fds_to(null.fileno()):
        yield


@contextlib.contextmanager
def capture_c_output():
    """Capture what C code writes on file descriptors 1 and 2 during the block (a temporary file
    behind both); yields a list that holds the text afterwards, as its one element."""
    import tempfile
    out: list = []
    with tempfile.TemporaryFile(mode="w+b") as tmp:
        try:
            with _fds_to(tmp.fileno()):
                yield out
        finally:
            tmp.seek(0)
            out.append(tmp.read().decode("utf-8", "replace"))


@contextlib.contextmanager
def _fds_to(target: int):
    """Point file descriptors 1 and 2 at ``target`` during the block (what C code writes goes there);
    a stream without a real descriptor (e.g. captured by pytest) is left alone."""
    saved = []
    try:
        for fd, stream in ((1, sys.stdout), (2, sys.stderr)):
            try:
                stream.flush()
                saved.append((fd, os.dup(fd)))
            except (OSError, ValueError, AttributeError):
                pass
        for fd, _ in saved:
            os.dup2(target, fd)
        yield
    finally:
        for fd, copy in saved:
            os.dup2(copy, fd)
            os.close(copy)


_NO_INERTIA = "No inertial data for link"
_WARNING = re.compile(r"b3Warning\[[^\]]*\]:\s*")


def links_without_inertia(text: str) -> tuple:
    """(link names, the rest) of PyBullet's URDF-import output: each "No inertial data for link,
    using mass=1, ..." warning is followed by a warning that holds the link's name."""
    parts = [p.strip() for p in _WARNING.split(text)]
    names, rest, i = [], [], 0
    while i < len(parts):
        if parts[i].startswith(_NO_INERTIA):
            if i + 1 < len(parts) and parts[i + 1] and " " not in parts[i + 1]:
                names.append(parts[i + 1])
                i += 2
                continue
            names.append("?")
        elif parts[i]:
            rest.append(parts[i])
        i += 1
    return list(dict.fromkeys(names)), rest


def inertia_note(names: list, path) -> str:
    """The one line that replaces PyBullet's per-link "No inertial data" warnings."""
    return (f"{Path(path).name}: {len(names)} link{'s' if len(names) != 1 else ''} without inertial data: "
            f"assumed 1 kg each (PyBullet's default, unit inertia): {', '.join(names)}")


def pybullet_module():
    """The ``pybullet`` module, imported with its C-level build banner kept off the terminal."""
    with _quiet_c_output():
        import pybullet
    return pybullet


def direct_client():
    """A bare private PyBullet client in DIRECT mode, connected without the "argv[0]=" banner."""
    pybullet = pybullet_module()
    with _quiet_c_output():
        from pybullet_utils.bullet_client import BulletClient

        return BulletClient(connection_mode=pybullet.DIRECT)


def bullet_client(dt: float, gravity: float = 9.81, deterministic_pairs: bool = False):
    """A private PyBullet client in DIRECT mode with physics step ``dt`` [s] and gravity -g z.

    One client per simulator object: the module-level pybullet client is not thread-safe and
    clients must never be shared between simulators. ``deterministic_pairs`` sorts Bullet's
    overlapping pairs (contact order independent of history; costs time, only useful with
    contacts).
    """
    client = direct_client()
    client.setGravity(0.0, 0.0, -float(gravity))
    # numSubSteps=0: one stepSimulation call advances exactly dt (no internal substepping)
    client.setPhysicsEngineParameter(fixedTimeStep=float(dt), numSubSteps=0,
                                     deterministicOverlappingPairs=int(deterministic_pairs))
    return client


def relative_factors(rng: np.random.Generator, B: int, std: float) -> np.ndarray:
    """Per-run multiplicative factors 1 + std * z, z ~ N(0,1) clipped to [-3, 3].

    Always draws B normals (even for std = 0) so that the random stream, and hence every other
    draw, does not depend on which keys are configured.
    """
    z = np.clip(rng.standard_normal(B), -3.0, 3.0)
    return 1.0 + std * z


def check_std(value, name: str, max_value: float = np.inf) -> float:
    """A non-negative finite scalar config value (<= max_value), else SimgapError naming it."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise SimgapError(f"{name}: need a number, got {value!r}") from None
    if not np.isfinite(v) or v < 0 or v > max_value:
        raise SimgapError(f"{name}: need a finite value in [0, {max_value:g}], got {value!r}")
    return v


def int_option(value, name: str, lo: int, hi: int) -> int:
    """An integer config value in [lo, hi], else SimgapError naming it."""
    try:
        v = int(value)
    except (TypeError, ValueError):
        raise SimgapError(f"{name}: need an integer in [{lo}, {hi}], got {value!r}") from None
    if isinstance(value, bool) or v != value or not lo <= v <= hi:
        raise SimgapError(f"{name}: need an integer in [{lo}, {hi}], got {value!r}")
    return v


class BulletSimulator(Simulator):
    """A simulator that owns one private PyBullet client (``self._client``), released by close()."""

    _client = None  # set by the subclass's build; a class default so close() works after a failed __init__

    def close(self) -> None:
        if self._client is not None:
            try:
                self._client.disconnect()
            except Exception:  # already gone (e.g. interpreter shutdown)
                pass
            self._client = None

    def __del__(self):
        self.close()
