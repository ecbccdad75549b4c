"""What a reader of a fresh clone meets: the paper named, no path outside the repository."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
TITLE = "Towards Certified Sim-to-Real Transfer via Stochastic Simulation-Gap Functions"


def test_readme_names_the_paper_first():
    head = " ".join((ROOT / "README.md").read_text().splitlines()[:15])
    head = re.sub(r"[>*\s]+", " ", head)
    assert TITLE in head
    for author in ("Sangeerth", "Lavaei", "Jagtap"):
        assert author in head


def test_no_doc_depends_on_files_outside_the_repository():
    bad = [f"{p.relative_to(ROOT)}:{i}" for p in DOCS for i, line in enumerate(p.read_text().splitlines(), 1)
           if re.search(r"\.\./shared|shared/(notes|seed|data)", line)]
    assert not bad, bad


def test_every_doc_that_cites_the_paper_names_it():
    missing = [p.name for p in DOCS[1:] if "the paper" in p.read_text().lower() and TITLE not in p.read_text()]
    assert not missing, missing


def test_pendulum_hangs_down_as_the_texts_say():
    """theta = 0 is a stable equilibrium (restoring gravity): the rod hangs down, so no text may call it inverted."""
    import numpy as np

    from simgap.systems import get_system

    s = get_system("pendulum")
    x = np.array([[0.1, 0.0], [-0.1, 0.0]])
    acc = s.f(x, np.zeros((2, 1)))[:, 1]
    assert acc[0] < 0 < acc[1]  # pulled back towards 0
    for p in (ROOT / "assets" / "experiments" / "pendulum.toml", ROOT / "simgap" / "systems.py"):
        assert "inverted pendulum" not in p.read_text().lower(), p


def test_app_doc_lists_the_recorded_entities():
    """docs/app.md's entity list is entity_paths()'s output (test_record.py checks that against a file)."""
    from simgap_viz.record import entity_paths

    text = (ROOT / "docs" / "app.md").read_text()
    block = text.split("<!-- entities:begin -->")[1].split("<!-- entities:end -->")[0]
    listed = re.findall(r"`([^`]+)`", block)
    assert listed == entity_paths(["<s>"], ["<m>"], ("obstacles", "target", "safe"))
