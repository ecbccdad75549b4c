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


def _outside_code(text: str):
    """(line number, line) of a Markdown text outside fenced code blocks."""
    inside = False
    for i, line in enumerate(text.splitlines(), 1):
        if line.startswith("```"):
            inside = not inside
            continue
        if not inside:
            yield i, line


def _slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces to hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def test_readme_is_short_and_reads_in_order():
    """Issue 54: <= 250 lines, every line outside code under 160 characters, the sections in the
    order a newcomer needs them, the test command exactly the one .ci/run runs."""
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= 250
    long = [f"{i}: {len(line)}" for i, line in _outside_code(text) if len(line) >= 160]
    assert not long, long
    heads = [line[3:] for _, line in _outside_code(text) if line.startswith("## ")]
    assert heads == ["Two commands", "What `simgap run pendulum` prints", "Where to look", "Results",
                     "Deviations from the paper", "Documentation"], heads
    ci = [ln for ln in (ROOT / ".ci" / "run").read_text().splitlines() if ln.startswith("python -m pytest")][0]
    assert f"pip install -e \".[dev]\" && pip install -e examples/plugin && {ci}" in text
    assert "![" in text.split("## Two commands")[0]  # the picture before the commands


def test_readme_links_resolve():
    """Every relative link of the README names a file of the repository and, with #anchor, a heading of
    that file (GitHub's anchors): the docs site checks its own pages, this the README."""
    text = (ROOT / "README.md").read_text()
    links = re.findall(r"\]\(([^)\s]+)\)", text)
    assert len(links) > 20
    bad = []
    for link in links:
        if link.startswith(("http://", "https://")):
            continue
        path, _, anchor = link.partition("#")
        target = ROOT / path if path else ROOT / "README.md"
        if not target.is_file():
            bad.append(link)
        elif anchor:
            slugs = {_slug(line.lstrip("#")) for _, line in _outside_code(target.read_text()) if line.startswith("#")}
            if anchor not in slugs:
                bad.append(link)
    assert not bad, bad


def test_pages_state_the_committed_results():
    """Every number the pages state from a committed source (bench/readme_numbers.py SOURCES: a run's
    summary.json, the TurtleBot scan's separation.json) is that source's; a hand edit of a page or of a
    source fails here. Each source carries the date, load and command of its run."""
    import importlib.util
    import json

    spec = importlib.util.spec_from_file_location("readme_numbers", ROOT / "bench" / "readme_numbers.py")
    rn = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(rn)
    assert rn.main(["--check"]) == 0
    for s in rn.SOURCES:
        prov = json.loads((ROOT / s / "provenance.json").read_text())
        assert prov["date"] and prov["load"] and prov["command"], s
    # the check can fail: a page edited by hand
    summaries, scans = rn.load_sources([ROOT / s for s in rn.SOURCES])
    page = ROOT / "README.md"
    text = page.read_text().replace("| 0.96 | 36,839 / 18,124 |", "| 0.97 | 36,839 / 18,124 |")
    assert text != page.read_text()
    _, diffs = rn.apply_page(page, text, summaries, scans)
    assert len(diffs) == 1 and "pendulum, small" in diffs[0], diffs
