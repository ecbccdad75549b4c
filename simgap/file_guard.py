"""Guards for the files a user hands simgap and the paths it writes: every input read and every
output path goes through here.

A file a user can be handed is hostile until checked: it may be a FIFO (reading hangs), a device
(``/dev/zero`` never ends), a symlink loop, a gigabyte of brackets (Python's JSON parser recurses
once per level), or carry terminal escape codes in a name that gets printed. Each guard turns
such a file into a :class:`~simgap.errors.SimgapError` that names the path and the problem,
before any byte is read or any memory is committed.
"""

from __future__ import annotations

import json
import os
import re
import stat
import tempfile
from pathlib import Path

import numpy as np

from .errors import SimgapError
from .fileio import human_bytes

#: JSON inputs (certificates, refined systems, summaries, audits, specs) larger than this are refused
MAX_JSON_BYTES = 256 * 1000 * 1000
#: deepest nesting of arrays and tables accepted in a JSON input (simgap's own files nest < 10 deep)
MAX_JSON_DEPTH = 200

_KINDS = ((stat.S_ISDIR, "a folder"), (stat.S_ISFIFO, "a FIFO (named pipe)"), (stat.S_ISCHR, "a character device"),
          (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"))


def _kind(mode: int) -> str:
    for test, name in _KINDS:
        if test(mode):
            return name
    return "not a regular file"


def _os_problem(path, what: str, e: OSError) -> SimgapError:
    import errno
    if e.errno == errno.ELOOP:
        return SimgapError(f"{what} {str(path)!r} is a symlink loop (the link points back at itself)")
    if e.errno == errno.ENOENT:
        return SimgapError(f"{what} {str(path)!r} does not exist")
    return SimgapError(f"cannot read {what} {str(path)!r}: {e.strerror or e}")


def resolved(path, what: str = "path") -> Path:
    """``Path(path).resolve()``, with a symlink loop (RuntimeError on Python < 3.13, OSError after)
    answered by a SimgapError naming ``what``."""
    try:
        return Path(path).resolve()
    except RuntimeError:
        raise SimgapError(f"{what} {str(path)!r} is a symlink loop (the link points back at itself)") from None
    except OSError as e:
        raise _os_problem(path, what, e) from None


def regular_file(path, what: str = "file", max_bytes: float | None = None) -> Path:
    """Refuse ``path`` unless it is a regular file (through symlinks) of at most ``max_bytes``:
    FIFOs, devices, sockets and folders by their kind, loops and missing files by name."""
    try:
        st = os.stat(path)
    except OSError as e:
        raise _os_problem(path, what, e) from None
    if not stat.S_ISREG(st.st_mode):
        raise SimgapError(f"{what} {str(path)!r} is {_kind(st.st_mode)}, not a regular file (refused)")
    if max_bytes is not None and st.st_size > max_bytes:
        raise SimgapError(f"{what} {str(path)!r} is {human_bytes(st.st_size)}, more than the {human_bytes(max_bytes)} "
                          "such a file can be (refused before reading)")
    return Path(path)


def read_bytes(path, what: str = "file", max_bytes: float = MAX_JSON_BYTES) -> bytes:
    """The bytes of a regular file of at most ``max_bytes``. The file is opened without blocking
    and checked on the open descriptor, so a FIFO swapped in after a check cannot hang the read."""
    regular_file(path, what, max_bytes)
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    except OSError as e:
        raise _os_problem(path, what, e) from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise SimgapError(f"{what} {str(path)!r} is {_kind(st.st_mode)}, not a regular file (refused)")
        with os.fdopen(fd, "rb", closefd=False) as fh:
            data = fh.read(int(max_bytes) + 1)
    except OSError as e:
        raise _os_problem(path, what, e) from None
    finally:
        os.close(fd)
    if len(data) > max_bytes:
        raise SimgapError(f"{what} {str(path)!r} is more than {human_bytes(max_bytes)} (refused)")
    return data


def read_text(path, what: str = "file", max_bytes: float = MAX_JSON_BYTES) -> str:
    """:func:`read_bytes` decoded as UTF-8 (a file that is not text is refused by name)."""
    try:
        return read_bytes(path, what, max_bytes).decode("utf-8")
    except UnicodeDecodeError as e:
        raise SimgapError(f"{what} {str(path)!r} is not UTF-8 text ({e.reason} at byte {e.start})") from None


_STRINGS = re.compile(rb'"(?:[^"\\]|\\.)*"', re.S)


def json_depth(text: str | bytes) -> int:
    """Deepest nesting of ``[`` and ``{`` in JSON ``text`` (brackets inside strings do not count)."""
    raw = text.encode() if isinstance(text, str) else bytes(text)
    b = np.frombuffer(_STRINGS.sub(b'""', raw), dtype=np.uint8)
    step = np.isin(b, (ord("["), ord("{"))).astype(np.int64) - np.isin(b, (ord("]"), ord("}")))
    return int(np.cumsum(step).max(initial=0))


def loads_json(text: str | bytes, what: str, max_depth: int = MAX_JSON_DEPTH):
    """``json.loads`` after a depth check: a file nested deeper than ``max_depth`` is refused by
    name instead of ending in a RecursionError; invalid JSON names ``what``."""
    depth = json_depth(text)
    if depth > max_depth:
        raise SimgapError(f"{what} nests {depth:,} levels of brackets, more than the {max_depth} allowed (refused)")
    try:
        return json.loads(text)
    except (ValueError, RecursionError) as e:
        raise SimgapError(f"{what} is not readable JSON: {e}") from None


def read_json(path, what: str = "file", max_bytes: float = MAX_JSON_BYTES, max_depth: int = MAX_JSON_DEPTH):
    """A JSON input file: :func:`read_text` (a regular file, size-capped) then :func:`loads_json`."""
    return loads_json(read_text(path, what, max_bytes), f"{what} {str(path)!r}", max_depth)


_CONTROL = re.compile(r"[\x00-\x1f\x7f-\x9f\u2028\u2029\u202a-\u202e\u2066-\u2069]")


def printable(text) -> str:
    """``text`` (a name or string from a file) safe to print: control characters, terminal escape
    codes and bidirectional overrides shown escaped (``\\x1b``) instead of acting on the terminal."""
    s = str(text)
    return _CONTROL.sub(lambda m: m.group().encode("unicode_escape").decode("ascii"), s)


# ----------------------------------------------------------------------------------------
# Output paths
# ----------------------------------------------------------------------------------------

def _probe_writable(folder: Path, what: str, path: Path) -> None:
    """Create and delete a temporary file in ``folder``: the only honest writability test
    (permissions, read-only mounts, root)."""
    try:
        fd, tmp = tempfile.mkstemp(dir=folder, prefix=".simgap-write-check.", suffix=".tmp")
        os.close(fd)
        os.unlink(tmp)
    except OSError as e:
        raise SimgapError(f"{what} {str(path)!r}: cannot write in folder {str(folder)!r} "
                          f"({e.strerror or e})") from None


def output_file(path, what: str = "--out") -> Path:
    """Check that a result file can be written at ``path``: not a directory, its folder exists
    and is writable. Nothing is created. Returns ``Path(path)``."""
    p = Path(path)
    if p.is_dir():
        raise SimgapError(f"{what} {str(p)!r} is a folder; give a file name (e.g. {str(p / 'result')!r}"
                          " plus the extension)")
    folder = p.parent if str(p.parent) else Path(".")
    if not folder.exists():
        raise SimgapError(f"{what} {str(p)!r}: folder {str(folder)!r} does not exist; create it first (mkdir -p "
                          f"{str(folder)!r}) or write into an existing folder")
    if not folder.is_dir():
        raise SimgapError(f"{what} {str(p)!r}: {str(folder)!r} is not a folder")
    _probe_writable(folder, what, p)
    return p


def output_dir(path, what: str = "--out") -> Path:
    """Check that a result folder can be used at ``path``: a writable folder, or a path whose
    nearest existing ancestor is a writable folder (it is created later). Nothing is created."""
    p = Path(path)
    if p.exists():
        if not p.is_dir():
            raise SimgapError(f"{what} {str(p)!r} exists and is not a folder")
        _probe_writable(p, what, p)
        return p
    anc = p.absolute().parent
    while not anc.exists():
        anc = anc.parent
    if not anc.is_dir():
        raise SimgapError(f"{what} {str(p)!r}: {str(anc)!r} is a file, not a folder")
    _probe_writable(anc, what, p)
    return p


def output_format(path, what: str, formats) -> str:
    """The extension (lower case) of output ``path`` if it is one of ``formats`` (e.g. ``(".json",)``):
    a file's format comes from its name, so a name promising another format is refused instead of
    written in the command's format (``fit --out f.json`` writing TOML that nothing can read back)."""
    ext = Path(path).suffix.lower()
    if ext not in formats:
        said = f"ends in {ext!r}" if ext else "has no extension"
        raise SimgapError(f"{what} {str(path)!r} {said}, but this command writes "
                          f"{' or '.join(f[1:].upper() for f in formats)} there: give a name ending in "
                          f"{' or '.join(formats)}")
    return ext


def not_twice(outputs) -> None:
    """Refuse two outputs of one command at the same path (the second would replace the first:
    ``refine --save-system o.toml --out o.toml`` lost its report). ``outputs``: (option, path)."""
    seen = {}
    for what, out in outputs:
        key = resolved(out, what)
        if key in seen:
            raise SimgapError(f"{seen[key]} and {what} are both {str(out)!r}: the second would replace the first; "
                              "give each output its own path")
        seen[key] = what


def check_outputs(args) -> None:
    """Check every output a parsed command declares (``set_defaults(outputs=..., output_dirs=...,
    formats=...)``): writable (:func:`output_file`, :func:`output_dir`), named for the format written
    there (:func:`output_format`), no two at one path (:func:`not_twice`) and not over any input
    (:func:`not_over_inputs`)."""
    outs = []
    formats = getattr(args, "formats", {})
    for name in getattr(args, "outputs", ()):
        v = getattr(args, name, None)
        if v is not None:
            what = "--" + name.replace("_", "-")
            outs.append((what, output_file(v, what)))
    for name in getattr(args, "output_dirs", ()):
        v = getattr(args, name, None)
        if v is not None:
            outs.append(("--" + name.replace("_", "-"), output_dir(v, "--" + name.replace("_", "-"))))
    not_over_inputs(outs, _input_paths(args))  # the worst first: an input would be destroyed
    not_twice(outs)
    for name, exts in formats.items():
        if getattr(args, name, None) is not None:
            output_format(getattr(args, name), "--" + name.replace("_", "-"), exts)


def _input_paths(args) -> list:
    """(option, path) of every other argument value that names an existing file or folder: a
    command's inputs, found without each command listing them (a new option is covered too)."""
    skip = set(getattr(args, "outputs", ())) | set(getattr(args, "output_dirs", ())) | {"func", "command"}
    found = []
    for key, value in vars(args).items():
        if key in skip:
            continue
        for v in value if isinstance(value, (list, tuple)) else [value]:
            if isinstance(v, (str, os.PathLike)) and str(v) and os.path.lexists(v):
                found.append(("--" + key.replace("_", "-"), Path(v)))
    return found


def _same_or_inside(out: Path, inp: Path, what: str, src: str) -> bool:
    """True if ``out`` is ``inp`` (also through symlinks or hard links) or lies inside folder ``inp``."""
    o, i = resolved(out, what), resolved(inp, src)
    if o == i or (i.is_dir() and i in o.parents):
        return True
    try:
        return out.exists() and os.path.samefile(out, inp)
    except OSError:
        return False


def not_over_inputs(outputs, inputs) -> None:
    """Refuse an output that is, or lies inside, an input: writing it would destroy what the
    command reads (e.g. ``certify STORE --out STORE/manifest.json``). Both are (option, path) lists."""
    for what, out in outputs:
        for src, inp in inputs:
            if _same_or_inside(Path(out), Path(inp), what, src):
                where = "is" if resolved(out) == resolved(inp) or not Path(inp).is_dir() else "is inside"
                raise SimgapError(f"{what} {str(out)!r} {where} the input {str(inp)!r} ({src}): writing it would "
                                  "destroy the input; choose another output path")
