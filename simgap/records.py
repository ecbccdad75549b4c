"""Where measured records are found: the EMPS positioning-axis records.

simgap does not ship measured data. A record is looked up, in this order, in the folder named
by the environment variable ``SIMGAP_EMPS_DIR`` and in ``../shared/data/emps`` beside the
repository (the layout of a development checkout).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Optional

from .errors import SimgapError

#: environment variable naming a folder that holds DATA_EMPS.mat / DATA_EMPS_PULSES.mat
EMPS_ENV = "SIMGAP_EMPS_DIR"
#: record name -> file: the estimation record and the validation record (with force pulses)
EMPS_RECORDS = {"estimation": "DATA_EMPS.mat", "validation": "DATA_EMPS_PULSES.mat"}


def emps_search_dirs() -> list[Path]:
    """The folders searched for EMPS records, in order."""
    dirs = []
    if os.environ.get(EMPS_ENV):
        dirs.append(Path(os.environ[EMPS_ENV]).expanduser())
    dirs.append(Path(__file__).resolve().parents[2] / "shared" / "data" / "emps")
    return dirs


def find_emps(record: str = "estimation") -> Optional[Path]:
    """Path of an EMPS record (``estimation`` or ``validation``), or None if none is found."""
    if record not in EMPS_RECORDS:
        raise SimgapError(f"unknown EMPS record {record!r}; known: {', '.join(EMPS_RECORDS)}")
    for d in emps_search_dirs():
        if (d / EMPS_RECORDS[record]).is_file():
            return d / EMPS_RECORDS[record]
    return None


def emps_missing_message(record: str = "estimation") -> str:
    """What was searched, and how to point simgap at the records."""
    looked = ", ".join(str(d) for d in emps_search_dirs())
    return (f"EMPS {record} record {EMPS_RECORDS[record]} not found (looked in: {looked}); set {EMPS_ENV} to the "
            f"folder that holds it (the EMPS benchmark's records, from nonlinearbenchmark.org)")


def emps_record(record: str = "estimation") -> Path:
    """Path of an EMPS record; SimgapError saying where it looked if it is missing."""
    path = find_emps(record)
    if path is None:
        raise SimgapError(emps_missing_message(record))
    return path
