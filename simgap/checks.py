"""Boundary checks shared by the commands: command-line value types, network addresses, and the
memory, disk and time limits every stage's cost model is held to.

Every command checks how big the work is *before* doing any work, so bad input ends with a
:class:`~simgap.errors.SimgapError` that names the problem (and, for sizes, the estimated
numbers) instead of a traceback, a hang or a half-written file. The cost models live beside the
stage they price (:func:`simgap.collect.check_collection`, :mod:`simgap.perrun.cost`); the
guards on input files and output paths in :mod:`simgap.file_guard`.
"""

from __future__ import annotations

import argparse
import ipaddress
import math
import os
import shutil
import socket
from pathlib import Path
from typing import Optional, Sequence

from .errors import SimgapError
from .fileio import human_bytes  # noqa: F401  (in fileio, whose write errors use it: fileio imports no checks)
from .memory import available_memory, check_memory  # noqa: F401  (light: stages import them directly)

#: work estimated to take longer than this is refused (the numbers are printed)
MAX_SECONDS = 365 * 24 * 3600.0
#: floating-point operations of a certify rank check + LP above which it is refused (~hours here)
MAX_CERTIFY_FLOPS = 2e12


# ----------------------------------------------------------------------------------------
# Command-line value types (argparse ``type=``): errors become "argument --x: message"
# ----------------------------------------------------------------------------------------

def _integer(text: str) -> int:
    """An integer from ``"12"`` or an integral float such as ``"1e6"``."""
    try:
        return int(text)
    except ValueError:
        pass
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if not math.isfinite(v) or v != int(v):
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}")
    return int(v)


def count(lo: int = 1):
    """argparse type: an integer >= ``lo`` (``1e6`` notation accepted)."""
    def parse(text: str) -> int:
        v = _integer(text)
        if v < lo:
            raise argparse.ArgumentTypeError(f"must be an integer >= {lo}, got {text!r}")
        return v
    parse.__name__ = f"integer >= {lo}"
    return parse


def probability(text: str) -> float:
    """argparse type: a number strictly between 0 and 1 (0, 1, NaN and inf refused)."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number in (0, 1), got {text!r}") from None
    if not 0.0 < v < 1.0:  # NaN fails both comparisons
        raise argparse.ArgumentTypeError(f"must be in (0, 1) (strictly), got {text!r}")
    return v


def port(text: str) -> int:
    """argparse type: a TCP port 0..65535 (0 = any free port)."""
    v = _integer(text)
    if not 0 <= v <= 65535:
        raise argparse.ArgumentTypeError(f"port must be 0..65535, got {text!r}")
    return v


def host(text: str) -> str:
    """argparse type: an IP address to bind (or ``localhost``). Names are not resolved: no DNS."""
    if text == "localhost":
        return text
    try:
        return str(ipaddress.ip_address(text))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"not an IP address: {text!r} (e.g. 127.0.0.1 for this machine only, 0.0.0.0 for every "
            "interface, or localhost)") from None


def check_bindable(host_: str, port_: int = 0) -> None:
    """Bind and release ``(host, port)`` once (port 0: any), so a server that cannot start says
    why at once (e.g. an address that is not this machine's)."""
    family = socket.AF_INET6 if ":" in host_ else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host_, port_))
        except OSError as e:
            where = f"{host_}:{port_}" if port_ else host_
            raise SimgapError(f"cannot listen on {where}: {e.strerror or e}") from None


def reachable(address: str, timeout: float = 5.0, what: str = "server") -> None:
    """Open and close a TCP connection to ``host:port`` (``ray://`` prefix allowed) within
    ``timeout`` seconds, else SimgapError; ``auto`` is not checked."""
    a = address.strip()
    if a in ("", "auto", "local"):
        return
    for prefix in ("ray://", "http://", "https://"):
        if a.startswith(prefix):
            a = a[len(prefix):]
    h, sep, p = a.rpartition(":")
    if not sep or not h:
        raise SimgapError(f"{what} address {address!r}: expected HOST:PORT, e.g. 127.0.0.1:6379")
    try:
        pnum = int(p)
    except ValueError:
        raise SimgapError(f"{what} address {address!r}: port {p!r} is not a number") from None
    if not 0 < pnum <= 65535:
        raise SimgapError(f"{what} address {address!r}: port must be 1..65535")
    try:
        with socket.create_connection((h.strip("[]"), pnum), timeout=timeout):
            pass
    except OSError as e:
        raise SimgapError(f"cannot reach the {what} at {address} within {timeout:g} s ({e.strerror or e}); "
                          "is it running?") from None


# ----------------------------------------------------------------------------------------
# Conflicting options
# ----------------------------------------------------------------------------------------

def one_of(options: dict, what: str, hint: str = "") -> None:
    """The one rule for options that set the same thing: refuse two or more of ``options`` given
    together (a value other than None), naming each as the user wrote it, instead of using one of
    them silently. ``options``: the user's spelling (``"--grid"``, ``"[synthesis] K"``) -> value;
    ``what``: the thing they all set. The stage commands and ``simgap run`` call it on the same
    keys, so a conflict is refused the same way wherever it is written."""
    given = [k for k, v in options.items() if v is not None]
    if len(given) > 1:
        raise SimgapError(f"{' and '.join(given)} both set {what}: give only one of them"
                          + (f" ({hint})" if hint else ""))


# ----------------------------------------------------------------------------------------
# Sizes
# ----------------------------------------------------------------------------------------

def human_seconds(s: float) -> str:
    for unit, d in (("years", 365 * 86400.0), ("days", 86400.0), ("h", 3600.0), ("min", 60.0)):
        if s >= d:
            return f"{s / d:.3g} {unit}"
    return f"{s:.3g} s"


def check_disk(need: float, folder, what: str, hint: str = "") -> None:
    """Refuse writing an estimated ``need`` bytes below ``folder`` (nearest existing ancestor)."""
    p = Path(folder).absolute()
    while not p.exists():
        p = p.parent
    free = shutil.disk_usage(p).free
    if need > free:
        raise SimgapError(f"{what} needs about {human_bytes(need)} of disk in {str(p)!r}, {human_bytes(free)} is free"
                          + (f"; {hint}" if hint else ""))


def check_seconds(seconds: Optional[float], what: str, hint: str = "") -> None:
    if seconds is not None and seconds > MAX_SECONDS:
        raise SimgapError(f"{what} would take about {human_seconds(seconds)}" + (f"; {hint}" if hint else ""))


def basis_terms(n_vars: int, degree: int) -> int:
    """Number of monomials of total degree <= ``degree`` in ``n_vars`` variables: C(v + d, d)."""
    return math.comb(n_vars + degree, degree) if degree >= 0 else 0


def check_basis(n_pairs: int, n_vars: int, degrees: Sequence[int], extra_terms: int = 0,
                what: str = "certify") -> None:
    """Refuse a certify basis whose design matrices or LP cannot be handled.

    Per state dimension the design matrix is K x P float64 (P = C(v + d, d) monomials plus the
    user's terms); the rank check and the linear program cost about K P^2 flops each. A basis
    with more terms than data pairs cannot have unique coefficients.
    """
    sizes = [basis_terms(n_vars, int(d)) + extra_terms for d in degrees]
    P = max(sizes)
    deg = max(int(d) for d in degrees)
    head = f"{what}: degree {deg} gives {P:,} basis terms per dimension"
    if P > n_pairs:
        raise SimgapError(f"{head} but the data have only {n_pairs:,} (x_r, u) pairs, so the coefficients "
                          "cannot be unique; use a smaller degree (the paper uses 1 or 2)")
    check_memory(8.0 * n_pairs * sum(sizes) * 2, f"{head}; with {n_pairs:,} pairs the design matrices",
                 "use a smaller degree")
    flops = 2.0 * n_pairs * float(P) ** 2 * len(sizes)
    if flops > MAX_CERTIFY_FLOPS:
        raise SimgapError(f"{head}; with {n_pairs:,} pairs the rank check and linear program need about "
                          f"{flops:.2g} floating-point operations (hours on this machine); use a smaller "
                          "degree (the paper uses 1 or 2) or name the terms you need")


def check_degree_values(degrees: Sequence[int], values: dict, state_names: Sequence[str], what: str,
                        remedy: dict) -> None:
    """Refuse a polynomial basis degree that the data's grid cannot separate.

    On data where a variable z_j takes only v_j distinct values, prod_a (z_j - a) over those values
    is zero at every row, so z_j^(v_j) is a combination of 1, z_j, ..., z_j^(v_j - 1): a basis with
    every monomial of total degree <= d has linearly dependent columns when d >= v_j (the scenario
    program would refuse it, but only after the collection). ``degrees``: per state dimension
    (negative: no monomials); ``values``: variable name -> v_j for the variables in the basis;
    ``remedy``: variable name -> the setting that gives it more values. Known from the cover and
    the input set alone, so it runs before any collection."""
    for i, d in enumerate(degrees):
        if d is None or int(d) < 1:
            continue
        for var, v in values.items():
            if int(d) >= int(v):
                raise SimgapError(
                    f"{what} = {int(d)} for {state_names[i]}: the data will have only {int(v)} value(s) of {var}, "
                    f"so {var}^{int(v)} is a combination of its lower powers on the data and the basis's terms "
                    f"are linearly dependent (found only after the collection otherwise): use a degree <= "
                    f"{int(v) - 1} for {state_names[i]}, or {remedy.get(var, f'more values of {var}')} "
                    f"(at least {int(d) + 1} values)")


#: a single command's simulator work estimated above this is refused (override: SIMGAP_NO_SIZE_CHECK=1)
MAX_COMMAND_SECONDS = 6 * 3600.0


def check_sim_work(runs: float, memory: float, what: str, hint: str, rate_per_worker: Optional[float] = None,
                   workers: int = 1) -> None:
    """Refuse ``runs`` simulator periods that need more than the available memory, or (at the
    calibrated ``rate_per_worker``) more than :data:`MAX_COMMAND_SECONDS`, naming the numbers."""
    check_memory(memory, what, hint)
    if rate_per_worker and not os.environ.get("SIMGAP_NO_SIZE_CHECK"):
        secs = runs / (rate_per_worker * max(1, workers))
        if secs > MAX_COMMAND_SECONDS:
            raise SimgapError(f"{what} ({runs:.3g} simulator periods) would take about {human_seconds(secs)}; {hint} "
                              "(or set SIMGAP_NO_SIZE_CHECK=1 to run it anyway)")
