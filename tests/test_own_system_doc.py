"""docs/own-system.md stays runnable: its commands parse with today's CLI and name files that exist,
the files it quotes are the files in examples/arm/, and its `python -c` snippets print what it shows."""

import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "own-system.md"


def _blocks():
    """(info string, text) of every fenced block, in order."""
    return re.findall(r"^```(\w*)\n(.*?)^```$", DOC.read_text(), flags=re.S | re.M)


def _commands():
    out = []
    for _, text in _blocks():
        for line in text.splitlines():
            if line.startswith(("simgap ", "python bench/")):
                out.append(line)
    return out


def test_every_simgap_command_parses_and_names_existing_files():
    """A renamed option or a moved file makes a command of the doc fail before anyone runs it."""
    from simgap.cli import build_parser

    cmds = _commands()
    assert len(cmds) >= 15
    parser = build_parser()
    for cmd in cmds:
        argv = shlex.split(cmd)
        if argv[0] == "simgap":
            parser.parse_args(argv[1:])  # SystemExit (argparse's error) fails the test
        for a in argv:
            for part in a.split("="):
                if part.startswith(("examples/", "assets/", "bench/")):
                    assert (ROOT / part).exists(), f"{cmd}: {part} does not exist"


def test_quoted_files_are_the_examples():
    """The system file and the simulator sections the doc shows are the files' own text."""
    files = {p.name: p.read_text() for p in (ROOT / "examples" / "arm").glob("*.toml")}
    quoted = [t for info, t in _blocks() if info == "toml"]
    system = next(t for t in quoted if t.startswith('format = "simgap-system"\nname = "arm"'))
    assert system in files["arm.toml"]
    for kind, name in (("mujoco", "arm_mujoco.toml"), ("pybullet_urdf", "arm_urdf.toml")):
        block = next(t for t in quoted if t.startswith(f'[simulator]\nkind = "{kind}"'))
        assert block in files[name], name


def test_python_snippets_print_what_the_doc_shows():
    """Each `python -c` block is run from the repository root; its output must be the next block."""
    pytest.importorskip("mujoco")
    blocks = _blocks()
    ran = 0
    for (info, text), (_, shown) in zip(blocks, blocks[1:]):
        if not text.startswith("python -c"):
            continue
        code = shlex.split(text)[2]
        res = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300,
                             env={**__import__("os").environ, "PYTHONPATH": str(ROOT)})
        assert res.returncode == 0, res.stderr
        assert res.stdout.strip() == shown.strip(), (text, res.stdout)
        ran += 1
    assert ran >= 4
