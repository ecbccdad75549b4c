"""`simgap plot RUN`: the paper's figures from a finished run (matplotlib), with units and every rollout."""

import subprocess
import sys

import numpy as np
import pytest

from test_viz_results import run_dir  # noqa: F401  (the tiny real run folder, module-scoped fixture)


@pytest.fixture
def captured(monkeypatch):
    """Figures handed to figures.save, kept open for inspection (then saved as usual)."""
    from simgap_viz import figures
    figs = {}
    real = figures.save

    def keep(fig, out_dir, name):
        figs[name] = {"axes": [(a.get_xlabel(), a.get_ylabel(), a.get_title(), len(a.get_lines()),
                                [t.get_text() for t in (a.get_legend().get_texts() if a.get_legend() else [])])
                               for a in fig.axes]}
        return real(fig, out_dir, name)

    monkeypatch.setattr(figures, "save", keep)
    return figs


def test_plot_run_figures(run_dir, tmp_path, captured):  # noqa: F811
    from PIL import Image

    from simgap_viz.figures import plot_run
    from simgap_viz.results import load_run
    run = load_run(run_dir)
    written = plot_run(run_dir, tmp_path / "fig")
    names = {p.name for p in written}
    assert names == {f"{n}.{e}" for n in ("trajectories", "states_time", "gamma_slices") for e in ("png", "pdf")}
    for p in written:
        if p.suffix == ".png":
            im = np.asarray(Image.open(p).convert("RGB"), float)
            assert im.shape[0] > 300 and im.std() > 10, p  # a drawn picture, not a blank canvas
        else:
            assert p.read_bytes()[:5] == b"%PDF-"
    assert not list((tmp_path / "fig").glob(".*tmp*"))

    # units on the axes; every rollout drawn (one line each) plus mean map and rollout average
    traj = captured["trajectories"]["axes"]
    main = [a for a in traj if a[2].endswith("gap")]
    assert [a[2] for a in main] == ["deterministic gap", "stochastic gap"]
    for (xl, yl, title, lines, legend), m in zip(main, ("deterministic", "stochastic")):
        ro = run.methods[m].rollouts
        R = ro.trajectories.shape[0]
        assert xl == "theta [rad]"
        assert lines == R + 2 + 1 + 2  # rollouts, mean map + average, x0, two legend stubs
    assert main[0][1] == "omega [rad/s]"
    fails = int((~np.asarray(run.methods["stochastic"].rollouts.success)).sum())
    assert f"failures: {fails} / {R}" in main[1][4]
    st = captured["states_time"]["axes"]
    assert {a[1] for a in st if a[1]} == {"theta [rad]", "omega [rad/s]"} and "time [s]" in {a[0] for a in st}
    gs = captured["gamma_slices"]["axes"]
    assert {a[1] for a in gs} == {"gamma_theta [rad per step]", "gamma_omega [rad/s per step]"}


def test_plot_cli_and_bad_input(run_dir, tmp_path):  # noqa: F811
    r = subprocess.run([sys.executable, "-m", "simgap", "plot", str(run_dir), "--out", str(tmp_path / "f")],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "trajectories.pdf" in r.stdout and (tmp_path / "f" / "gamma_slices.png").is_file()
    for args, msg in (([str(tmp_path)], "no summary.json"), ([str(run_dir), "--out", str(tmp_path / "no" / "f")],
                                                               "does not exist"),
                      ([str(run_dir), "--max-drawn", "0"], "--max-drawn")):
        r = subprocess.run([sys.executable, "-m", "simgap", "plot", *args], capture_output=True, text=True,
                           timeout=300)
        assert r.returncode == 2 and msg in r.stderr and "Traceback" not in r.stderr, (args, r.stderr)
    assert not (tmp_path / "no").exists()
