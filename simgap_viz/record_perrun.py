"""Headless Rerun recording of the per-run results (``simgap run`` with ``[perrun]``): perrun.rrd.

Entities (state units, first two state dimensions; further dimensions are projected by the max):

* ``perrun/p_cert`` -- Points2D at the interval-MDP cell centers, colored by the certified success
  probability p_cert on the app's scale (dark red 0 -> yellow 0.5 -> dark green 1,
  :func:`simgap_viz.layers.perrun.pcolormap`), labelled with its value;
* ``perrun/<controller>/p_emp`` -- Points2D at the validated initial states, colored by p_emp,
  labelled "p_emp [CI] / p_cert";
* ``perrun/summary`` -- TextDocument (markdown) with the per-controller table.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from simgap.errors import SimgapError

from .layers.perrun import pcolormap
from .record import finish_recording, open_recording


def record_per_run(out: str | Path, controller, per_run: dict) -> dict:
    """Write ``out`` (.rrd, atomically) from a PerRunController and the summary's ``per_run`` dict."""
    import rerun as rr
    import rerun.blueprint as rrb

    out = Path(out)
    if out.suffix != ".rrd":
        raise SimgapError(f"recording: the output file must end in .rrd, got {str(out)!r}")
    t0 = time.perf_counter()
    rec, mem = open_recording(rrb.Blueprint(rrb.Horizontal(
        rrb.Spatial2DView(origin="/perrun", name="p_cert map and p_emp markers"),
        rrb.TextDocumentView(origin="/perrun/summary", name="per-run summary"), column_shares=[3, 1])))
    g = controller.grid
    pts = g.points(np.arange(g.size))[:, :2]
    # project further dimensions away by the best cell (the map shows the most that is certified)
    key, inv = np.unique(np.round(pts / g.eta[:2]).astype(np.int64), axis=0, return_inverse=True)
    best = np.zeros(len(key))
    np.maximum.at(best, inv.ravel(), controller.p_cert)
    xy = key * g.eta[:2]
    rec.log("perrun/p_cert", rr.Points2D(xy.astype(np.float32), colors=pcolormap(best),
                                         radii=float(min(g.eta[:2])) / 2, labels=[f"{v:.3f}" for v in best]),
            static=True)
    info = {"entities": ["perrun/p_cert"], "cells": int(len(key))}
    md = ["# per-run guarantees", "", f"horizon {per_run['horizon']} periods, {per_run['n_rollouts']} rollouts "
          "per initial state", "", "| controller | state | p_cert | p_emp | 95% CI |", "|---|---|---|---|---|"]
    for name, c in per_run["controllers"].items():
        xs = np.array([s["x0"] for s in c["states"]], float)[:, :2]
        pe = np.array([s["p_emp"] for s in c["states"]])
        labels = [f"{s['p_emp']:.3f} [{s['ci95'][0]:.3f}, {s['ci95'][1]:.3f}] / "
                  + ("-" if s["p_cert"] is None else f"{s['p_cert']:.3f}") for s in c["states"]]
        rec.log(f"perrun/{name}/p_emp", rr.Points2D(xs.astype(np.float32), colors=pcolormap(pe),
                                                    radii=rr.Radius.ui_points(6.0), labels=labels), static=True)
        info["entities"].append(f"perrun/{name}/p_emp")
        for i, s in enumerate(c["states"]):
            pc = "-" if s["p_cert"] is None else f"{s['p_cert']:.4f}"
            md.append(f"| {name} | {np.round(s['x0'], 4).tolist()} | {pc} | {s['p_emp']:.4f} | "
                      f"[{s['ci95'][0]:.4f}, {s['ci95'][1]:.4f}] |")
    rec.log("perrun/summary", rr.TextDocument("\n".join(md), media_type=rr.MediaType.MARKDOWN), static=True)
    info["entities"].append("perrun/summary")
    return finish_recording(rec, mem, out, info, t0)
