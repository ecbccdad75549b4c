"""The controller file: one .npz format for every controller kind (grid and invariant set).

A controller file holds its arrays and a ``meta`` JSON string with ``format``, ``version``,
``kind``, ``hold``, the system's description, the specification and a content digest over meta
and arrays (:func:`simgap.fileio.content_digest`): a file changed after it was written is refused,
and rollouts name their controller by that digest. The kinds' own classes
(:class:`~simgap.synthesis.controller.Controller`, :class:`~simgap.synthesis.ellipsoid_controller.EllipsoidController`)
say which arrays they keep; this module writes and checks what they share.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .. import fileio
from ..errors import SimgapError

FORMAT = "simgap-controller"
VERSION = 2


def _json_default(o):
    if hasattr(o, "tolist"):
        return o.tolist()
    return str(o)


def write_controller(path, meta: dict, kind: str, hold: int, system, spec, arrays: dict) -> Path:
    """Write ``arrays`` and ``meta`` (plus format, version, kind, hold, the system's description and
    the spec) as a controller .npz (temp file, then rename); ``meta`` gets the digest the file records."""
    path = Path(path)
    out = dict(meta)
    out.update({"format": FORMAT, "version": VERSION, "kind": kind, "hold": int(hold)})
    if system is not None:
        out["system"] = system.describe()
    if spec is not None:
        out["spec"] = spec.to_dict()
    out.pop("digest", None)
    out = json.loads(json.dumps(out, default=_json_default))  # the JSON the file holds
    out["digest"] = fileio.content_digest(out, arrays)
    meta["digest"] = out["digest"]  # what the file records: rollouts name the controller by it
    (path.parent if str(path.parent) else Path(".")).mkdir(parents=True, exist_ok=True)
    return fileio.savez(path, compressed=True, **arrays, meta=np.array(json.dumps(out)))


def check_digest(path, meta: dict, arrays: dict) -> None:
    """Refuse a controller file whose meta and arrays no longer match the digest it records."""
    want = meta.get("digest")
    have = fileio.content_digest({k: v for k, v in meta.items() if k != "digest"}, arrays)
    if want != have:
        raise SimgapError(f"controller file {str(path)!r} was modified after it was written (refused): its "
                          f"content digest is {have[:16]}... but the file records {str(want)[:16]}...")
