"""Write (or check) the numbers the README and the docs pages state about runs, from the runs' own files.

    python bench/readme_numbers.py                                   # check every page against bench/results
    python bench/readme_numbers.py --write                           # rewrite the pages from bench/results
    python bench/readme_numbers.py results/pendulum-small --check    # check against a run of your own
    python bench/readme_numbers.py results/pendulum-small --write    # put a fresh run's numbers in

Sources are `simgap run` result folders (their summary.json) and scan folders (a ``separation.json``
made by bench/turtlebot_separation.py). Without arguments the committed sources under bench/results/
are used (SOURCES): each carries a ``provenance.json`` with the date, the load average and the
command of the run it came from, and the pages say that date and load next to the numbers.

What a source writes, per page (PAGES), found by its anchor in the page's text:

* ``printed``: the comparison table under ``$ simgap run pendulum`` (README.md,
  docs/getting-started.md), without the machine-dependent wall times;
* ``rows``: the numeric cells of a results-table row, matched by its label (the first cell, a link's
  text) and the run's (experiment, profile): README.md's compact row (stochastic gamma, confidence,
  winning cells, failures) and docs/results.md's full row (both gammas, confidence, audits, winning
  cells, failures); the row's other cells are kept;
* ``separation``: the TurtleBot scan's tables between the SEPARATION_MARKERS
  (docs/turtlebot-separation.md).

Nothing is recomputed: every number is formatted from the source file. tests/test_docs.py checks
every page against the committed sources (a hand edit of a page or of a source fails it) and
tests/test_pipeline.py the pendulum's small profile against the run it makes.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# the committed sources the pages are written from (folders under bench/results)
SOURCES = ["bench/results/runs/pendulum-small", "bench/results/runs/turtlebot-small",
           "bench/results/runs/arm_mujoco-small", "bench/results/runs/husky-base", "bench/results/runs/cartpole-tube",
           "bench/results/runs/double_pendulum-base",
           "bench/results/turtlebot-separation"]
# full results-table label prefix per (experiment, profile): docs/results.md
ROW_LABELS = {("pendulum", "small"): "pendulum, small", ("pendulum", "paper"): "pendulum, paper",
              ("pendulum", "noisy"): "pendulum, noisy", ("turtlebot", "small"): "TurtleBot, small",
              ("turtlebot", "gazebo"): "TurtleBot, gazebo", ("turtlebot", "gazebo_n400"): "TurtleBot, N1hat 400",
              ("pendulum", "tight"): "pendulum, tight", ("turtlebot", "tight"): "TurtleBot, tight",
              ("cartpole", "small"): "cart-pole, Gymnasium", ("cartpole", "tight"): "cart-pole, tight",
              ("cartpole", "refined"): "cart-pole, refined", ("cartpole", "tube"): "cart-pole, box tube",
              ("double_pendulum", None): "double pendulum, box tube",
              ("arm_mujoco", "small"): "arm, MuJoCo",
              ("husky", None): "husky"}
# the README's compact table: one row per case study
README_LABELS = {("pendulum", "small"): "pendulum, small", ("pendulum", "paper"): "pendulum, paper",
                 ("turtlebot", "small"): "TurtleBot", ("arm_mujoco", "small"): "arm", ("cartpole", "tube"): "cart-pole",
                 ("double_pendulum", None): "double pendulum",
                 ("husky", None): "husky"}
PRINTED_RUN = ("pendulum", "small")  # the run whose printed table the pages show
SEPARATION_MARKERS = ("<!-- turtlebot-separation table (bench/readme_numbers.py) -->",
                      "<!-- end turtlebot-separation table -->")
# what each page holds (looked up by file name, so a copy of a page elsewhere is treated the same)
PAGES = {"README.md": {"printed": True, "rows": "compact"},
         "getting-started.md": {"printed": True},
         "results.md": {"rows": "full"},
         "turtlebot-separation.md": {"separation": True}}
PAGE_PATHS = ["README.md", "docs/getting-started.md", "docs/results.md", "docs/turtlebot-separation.md"]


def separation_table(table: dict) -> str:
    """The scan's Markdown table, made by the scan's own bench script from its separation.json."""
    import importlib.util
    spec = importlib.util.spec_from_file_location("turtlebot_separation", ROOT / "bench" / "turtlebot_separation.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.markdown_table(table)


def apply_separation(text: str, table: dict) -> tuple:
    """(new page text, differences) with the scan's table between the markers."""
    lines = text.split("\n")
    try:
        a = lines.index(SEPARATION_MARKERS[0]) + 1
        b = lines.index(SEPARATION_MARKERS[1], a)
    except ValueError:
        return text, ["the page has no turtlebot-separation markers"]
    want = separation_table(table).split("\n")
    if lines[a:b] == want:
        return text, []
    diff = ("the separation scan's table differs:\n  page: " + "\n        ".join(lines[a:b])
            + "\n  scan: " + "\n        ".join(want))
    lines[a:b] = want
    return "\n".join(lines), [diff]


def printed_table(summary: dict) -> str:
    """`simgap run`'s comparison table without the (machine-dependent) wall times."""
    from simgap.pipeline import comparison_table
    return comparison_table({k: v for k, v in summary.items() if k not in ("seconds", "wall_seconds")}).rstrip()


def _gamma(e: dict) -> str:
    return ", ".join(f"{v:.3g}" for v in e["gamma"]["max"])


def _tube(summary: dict) -> bool:
    """A box-tube run: its rows state the proof's margin (and p_cert) instead of winning cells."""
    return (summary.get("sections", {}).get("synthesis") or {}).get("method") == "box_tube"


def _tube_gamma(summary: dict, e: dict, major: bool = False) -> str:
    """gamma's max per state with the states named (a tube row's gamma cell); ``major``: only the states whose
    gamma is at least a tenth of the largest, to 2 digits (the README's short cell)."""
    g, names = e["gamma"]["max"], summary["system"]["state_names"]
    keep = [i for i, v in enumerate(g) if not major or v >= 0.1 * max(g)]
    return ", ".join(f"{g[i]:.2g}" if major else f"{g[i]:.3g}" for i in keep) + \
        " (" + ", ".join(names[i] for i in keep) + ")"


def _tube_result(e: dict) -> str:
    """'tube, margin s[, p_cert p]', or 'no tube (tolerable s x gamma)', of one method's box tube."""
    syn = e.get("synthesis") or {}
    s = syn.get("gap_scale")
    if not e["winning_cells"]:
        return "no tube" + ("" if s is None else f" (tolerable {s:.3g} x gamma)")
    p = (e.get("per_run_empirical") or {}).get("p_cert")
    return "tube, margin " + ("any" if s is None else f"{s:.3g}") + ("" if p is None else f", p_cert {p:.3g}")


def _proof_confidence(e: dict) -> str:
    """The confidence the tube's proof states: every round's certificate at once, all rows."""
    c = e.get("confidence_all_rounds", e.get("confidence_joint_simultaneous"))
    return "-" if c is None else f"{c:.3g} (all rows)"  # 3 digits: 0.995 is not 1.00


def row_cells(summary: dict) -> list:
    """docs/results.md's numeric cells: gamma det, gamma sto, confidence, audit, winning (a tube run: the
    tube and its margin per method), failures."""
    det, sto = summary["methods"]["deterministic"], summary["methods"]["stochastic"]

    def fails(e):
        return f"{e['failures']} / {e['n_rollouts']}" if "failures" in e else "-"

    audit = f"{det['audit_pass_rate_joint']:.2f} / {sto['audit_pass_rate_joint']:.2f}"
    if _tube(summary):
        return [_tube_gamma(summary, det), _tube_gamma(summary, sto), _proof_confidence(sto), audit,
                f"{_tube_result(det)} / {_tube_result(sto)}", f"{fails(det)} / {fails(sto)}"]
    return [_gamma(det), _gamma(sto), f"{sto['confidence_joint']:.2f}", audit,
            f"{det['winning_cells']:,} / {sto['winning_cells']:,}", f"{fails(det)} / {fails(sto)}"]


def compact_cells(summary: dict) -> list:
    """The README's numeric cells: gamma sto, confidence, winning det / sto (a tube run: the stochastic tube,
    its margin and p_cert), failures det / sto (of 1000)."""
    det, sto = summary["methods"]["deterministic"], summary["methods"]["stochastic"]
    n = {e.get("n_rollouts") for e in (det, sto) if e.get("n_rollouts") is not None} or {1000}
    fails = f"{det.get('failures', '-')} / {sto.get('failures', '-')}" + ("" if n == {1000} else f" (of {n.pop()})")
    if _tube(summary):
        return [_tube_gamma(summary, sto, major=True), _proof_confidence(sto), _tube_result(sto), fails]
    return [_gamma(sto), f"{sto['confidence_joint']:.2f}", f"{det['winning_cells']:,} / {sto['winning_cells']:,}",
            fails]


def run_key(summary: dict) -> tuple:
    """(name, profile) of a run: the experiment's name, or for a folder's generic ``experiment.toml``
    (examples/husky, examples/racecar) the folder's name."""
    name = summary["experiment"]
    if name == "experiment" and summary.get("config_file"):
        name = Path(summary["config_file"]).parent.name
    return name, summary.get("profile")


def _split_row(line: str) -> list:
    return [c.strip() for c in line.strip().strip("|").split("|")]


def _label(cell: str) -> str:
    """A row's label with a Markdown link reduced to its text."""
    return re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", cell)


def apply(text: str, summaries: list, rows: str = "full", printed: bool = True) -> tuple:
    """(new page text, list of differences) with the given runs' numbers put in: their results-table
    rows (``rows``: "full", "compact" or "" for none) and, with ``printed``, the printed table."""
    lines = text.split("\n")
    diffs = []
    for s in summaries:
        key = run_key(s)
        if rows:
            labels, cells_of, first = ((ROW_LABELS, row_cells, 1) if rows == "full" else (README_LABELS, compact_cells, 2))
            label = labels.get(key)
            if label is None:  # the README's compact table has a row for some runs only
                if rows == "full":
                    diffs.append(f"{key}: no results row is known for this run")
            else:
                hits = [i for i, ln in enumerate(lines) if ln.startswith("| ")
                        and (_label(_split_row(ln)[0]) + " ").startswith(label + " ")]
                if len(hits) != 1:
                    diffs.append(f"{label}: {len(hits)} results rows start with this label (need 1)")
                else:
                    i = hits[0]
                    cells = _split_row(lines[i])
                    want = cells_of(s)
                    if cells[first:first + len(want)] != want:
                        diffs.append(f"{label}: page {cells[first:first + len(want)]} != run {want}")
                        cells[first:first + len(want)] = want
                        lines[i] = "| " + " | ".join(cells) + " |"
        if printed and key == PRINTED_RUN:
            table = printed_table(s).split("\n")
            table = table[:table.index("")] if "" in table else table  # notes below the table are not shown
            try:
                a = lines.index("$ simgap run pendulum") + 1
                b = lines.index("", a)
                # the block shows the run's stage lines first; the table starts at its column header
                a = next(i for i in range(a, b) if lines[i].split() == table[0].split())
            except (ValueError, StopIteration):
                diffs.append("the page has no `$ simgap run pendulum` block")
                continue
            if lines[a:b] != table:
                diffs.append("the printed `simgap run pendulum` table differs:\n  page: "
                             + "\n        ".join(lines[a:b]) + "\n  run:  " + "\n        ".join(table))
                lines[a:b] = table
    return "\n".join(lines), diffs


def apply_page(path: Path, text: str, summaries: list, scans: list) -> tuple:
    """(new text, differences) of one page, by what PAGES says it holds (by file name)."""
    spec = PAGES.get(path.name)
    if spec is None:
        return text, [f"{path}: not a page with run numbers (known: {', '.join(PAGES)})"]
    diffs = []
    if summaries and (spec.get("rows") or spec.get("printed")):
        mine = [s for s in summaries if spec.get("rows") or run_key(s) == PRINTED_RUN]
        text, diffs = apply(text, mine, spec.get("rows", ""), spec.get("printed", False))
    if spec.get("separation"):
        for t in scans:
            text, d = apply_separation(text, t)
            diffs += d
    return text, [f"{path.name}: {d}" for d in diffs]


def provenance(folder: Path) -> str:
    """'date, load average, command' of a committed source, from its provenance.json."""
    f = folder / "provenance.json"
    if not f.is_file():
        return "no provenance.json"
    p = json.loads(f.read_text())
    return f"{p['date']}, load average {p['load']}: {p['command']}"


def load_sources(folders: list) -> tuple:
    """(summaries, scans) of the given folders; raises ValueError naming an unreadable one."""
    summaries, scans = [], []
    for r in map(Path, folders):
        f = r / "separation.json" if (r / "separation.json").is_file() else r / "summary.json"
        if not f.is_file():
            raise ValueError(f"{r / 'summary.json'} does not exist (run `simgap run` first)")
        try:
            data = json.loads(f.read_text())
        except (OSError, ValueError) as e:
            raise ValueError(f"{f} is not readable JSON: {e}") from None
        (scans if f.name == "separation.json" else summaries).append(data)
    return summaries, scans


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("runs", nargs="*", help="`simgap run` result folders or scan folders (default: SOURCES)")
    p.add_argument("--page", action="append", help="a page to check or write (repeatable; default: all pages)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--check", action="store_true", help="exit 1 if a page differs from the sources")
    g.add_argument("--write", action="store_true", help="put the sources' numbers into the pages")
    args = p.parse_args(argv)
    folders = args.runs or [str(ROOT / s) for s in SOURCES]
    try:
        summaries, scans = load_sources(folders)
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if not args.runs:
        for s in SOURCES:
            print(f"source {s}: {provenance(ROOT / s)}")
    pages = [Path(x) for x in (args.page or [str(ROOT / q) for q in PAGE_PATHS])]
    all_diffs = []
    for page in pages:
        new, diffs = apply_page(page, page.read_text(), summaries, scans)
        all_diffs += diffs
        if args.write and diffs and new != page.read_text():
            tmp = page.with_name(f".{page.name}.tmp")
            tmp.write_text(new)
            tmp.replace(page)
    if not (args.check or args.write):
        for t in scans:
            print(separation_table(t))
        for s in summaries:
            print(" ".join(map(str, run_key(s))) + ": " + " | ".join(row_cells(s)))
            if run_key(s) == PRINTED_RUN:
                print(printed_table(s))
    for d in all_diffs:
        print(("drift: " if args.check else "changed: ") + d)
    return 1 if args.check and all_diffs else 0


if __name__ == "__main__":
    sys.exit(main())
