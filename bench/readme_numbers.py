"""Regenerate (or check) the README's numbers from `simgap run` result folders.

    python bench/readme_numbers.py results/pendulum-small results/turtlebot-small            # print
    python bench/readme_numbers.py results/pendulum-small results/turtlebot-small --check    # exit 1 on drift
    python bench/readme_numbers.py results/pendulum-small results/turtlebot-small --write    # update README.md
    python bench/readme_numbers.py results/turtlebot-separation --check   # the separation scan's table

What it covers: the block under "What `simgap run pendulum` prints" (the comparison table of the
pendulum's small profile) and the numeric cells of the Results table's rows for the runs given
(matched by experiment and profile; the row's label text is kept). Everything is read from each
folder's summary.json; nothing is recomputed. tests/test_pipeline.py runs the check for the
pendulum's small profile on the run it makes, so that row and block cannot drift unnoticed.
A folder holding ``separation.json`` (bench/turtlebot_separation.py) is a scan: its Markdown
table goes between the README's ``turtlebot-separation`` markers.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# Results-table label prefix per (experiment, profile)
ROW_LABELS = {("pendulum", "small"): "pendulum, small", ("pendulum", "paper"): "pendulum, paper",
              ("pendulum", "noisy"): "pendulum, noisy", ("turtlebot", "small"): "TurtleBot, small",
              ("turtlebot", "gazebo"): "TurtleBot, gazebo", ("turtlebot", "gazebo_n400"): "TurtleBot, N1hat 400",
              ("pendulum", "tight"): "pendulum, tight", ("turtlebot", "tight"): "TurtleBot, tight",
              ("cartpole", "small"): "cart-pole, Gymnasium", ("cartpole", "tight"): "cart-pole, tight",
              ("cartpole", "refined"): "cart-pole, refined"}
PRINTED_RUN = ("pendulum", "small")  # the run whose printed table the README shows
# the README's block of the TurtleBot separation scan (bench/turtlebot_separation.py)
SEPARATION_MARKERS = ("<!-- turtlebot-separation table (bench/readme_numbers.py) -->",
                      "<!-- end turtlebot-separation table -->")


def separation_table(table: dict) -> str:
    """The scan's Markdown table, made by the scan's own bench script from its separation.json."""
    import importlib.util
    spec = importlib.util.spec_from_file_location("turtlebot_separation", ROOT / "bench" / "turtlebot_separation.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.markdown_table(table)


def apply_separation(readme: str, table: dict) -> tuple:
    """(new README text, differences) with the scan's table between the markers."""
    lines = readme.split("\n")
    try:
        a = lines.index(SEPARATION_MARKERS[0]) + 1
        b = lines.index(SEPARATION_MARKERS[1], a)
    except ValueError:
        return readme, ["README has no turtlebot-separation markers"]
    want = separation_table(table).split("\n")
    if lines[a:b] == want:
        return readme, []
    diff = ("the separation scan's table differs:\n  README: " + "\n          ".join(lines[a:b])
            + "\n  scan:   " + "\n          ".join(want))
    lines[a:b] = want
    return "\n".join(lines), [diff]


def printed_table(summary: dict) -> str:
    """`simgap run`'s comparison table without the (machine-dependent) wall times."""
    from simgap.pipeline import comparison_table
    return comparison_table({k: v for k, v in summary.items() if k not in ("seconds", "wall_seconds")}).rstrip()


def row_cells(summary: dict) -> list:
    """The Results table's numeric cells: gamma det, gamma sto, confidence, audit, winning, failures."""
    det, sto = summary["methods"]["deterministic"], summary["methods"]["stochastic"]

    def g(e):
        return ", ".join(f"{v:.3g}" for v in e["gamma"]["max"])

    def fails(e):
        return f"{e['failures']} / {e['n_rollouts']}" if "failures" in e else "-"

    return [g(det), g(sto), f"{sto['confidence_joint']:.2f}",
            f"{det['audit_pass_rate_joint']:.2f} / {sto['audit_pass_rate_joint']:.2f}",
            f"{det['winning_cells']:,} / {sto['winning_cells']:,}", f"{fails(det)} / {fails(sto)}"]


def _split_row(line: str) -> list:
    return [c.strip() for c in line.strip().strip("|").split("|")]


def apply(readme: str, summaries: list) -> tuple:
    """(new README text, list of differences) with the given runs' numbers put in."""
    lines = readme.split("\n")
    diffs = []
    for s in summaries:
        key = (s["experiment"], s.get("profile"))
        label = ROW_LABELS.get(key)
        if label is None:
            diffs.append(f"{key}: no Results row is known for this run")
            continue
        hits = [i for i, ln in enumerate(lines) if ln.startswith(f"| {label}")]
        if len(hits) != 1:
            diffs.append(f"{label}: {len(hits)} Results rows start with this label (need 1)")
            continue
        i = hits[0]
        cells = _split_row(lines[i])
        want = row_cells(s)
        if cells[1:7] != want:
            diffs.append(f"{label}: README {cells[1:7]} != run {want}")
            lines[i] = "| " + " | ".join([cells[0], *want, *cells[7:]]) + " |"
        if key == PRINTED_RUN:
            table = printed_table(s).split("\n")
            table = table[:table.index("")] if "" in table else table  # notes below the table are not shown
            try:
                a = lines.index("$ simgap run pendulum") + 1
                b = lines.index("", a)
                # the block shows the run's stage lines first; the table starts at its column header
                a = next(i for i in range(a, b) if lines[i].split() == table[0].split())
            except ValueError:
                diffs.append("README has no `$ simgap run pendulum` block")
                continue
            if lines[a:b] != table:
                diffs.append("the printed `simgap run pendulum` table differs:\n  README: "
                             + "\n          ".join(lines[a:b]) + "\n  run:    " + "\n          ".join(table))
                lines[a:b] = table
    return "\n".join(lines), diffs


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("runs", nargs="+", help="`simgap run` result folders")
    p.add_argument("--readme", default=str(ROOT / "README.md"))
    g = p.add_mutually_exclusive_group()
    g.add_argument("--check", action="store_true", help="exit 1 if the README differs from the runs")
    g.add_argument("--write", action="store_true", help="put the runs' numbers into the README")
    args = p.parse_args(argv)
    summaries, scans = [], []
    for r in args.runs:
        if (Path(r) / "separation.json").is_file():
            try:
                scans.append(json.loads((Path(r) / "separation.json").read_text()))
            except (OSError, ValueError) as e:
                print(f"error: {Path(r) / 'separation.json'} is not readable JSON: {e}", file=sys.stderr)
                return 2
            continue
        f = Path(r) / "summary.json"
        if not f.is_file():
            print(f"error: {f} does not exist (run `simgap run` first)", file=sys.stderr)
            return 2
        summaries.append(json.loads(f.read_text()))
    readme = Path(args.readme)
    new, diffs = apply(readme.read_text(), summaries)
    for t in scans:
        new, d = apply_separation(new, t)
        diffs += d
        print(separation_table(t))
    for s in summaries:
        print(f"{s['experiment']} {s.get('profile')}: " + " | ".join(row_cells(s)))
        if (s["experiment"], s.get("profile")) == PRINTED_RUN:
            print(printed_table(s))
    for d in diffs:
        print(("drift: " if args.check else "changed: ") + d)
    if args.write and diffs:
        tmp = readme.with_name(f".{readme.name}.tmp")
        tmp.write_text(new)
        tmp.replace(readme)
    return 1 if args.check and diffs else 0


if __name__ == "__main__":
    sys.exit(main())
