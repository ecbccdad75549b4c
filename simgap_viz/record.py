"""Headless Rerun recordings (.rrd) of a simgap run, laid out by a default blueprint.

Entities (state-space layers in state units: x = x1, y = x2, z = 0; a third state, e.g. the
TurtleBot heading, is projected away):

* ``world/obstacles``, ``world/target``, ``world/safe`` -- Boxes3D of the specification;
* ``world/winning`` -- Boxes3D of the winning cells (merged over the projected dimensions,
  colored red -> green by the fraction of winning cells);
* ``world/rollouts/paths`` -- every rollout as one LineStrips3D (failures red), static;
* ``world/rollouts/mean``, ``world/rollouts/nominal`` -- the mean trajectory and the nominal model's;
* ``world/rollouts/state`` -- the R current states over the time axes ``step`` (sequence) and
  ``time`` (duration, t * tau), logged column-wise with ``send_columns`` (one call);
* ``gamma/<state>/surface`` -- Mesh3D of gamma_i over the first two variables (others at the
  centre of their range), coordinates normalized to [-1, 1]^2 and z = gamma_i / max(gamma_i);
  ``gamma/<state>/data`` -- the observed gaps g_i(x_r, u) of the data near that slice, same scale
  (green: covered by gamma, red: not); ``gamma/<state>/scale`` -- the z scale (AnyValues);
* ``summary`` -- TextDocument (markdown): certificate table and rollout summary.
"""

from __future__ import annotations

import os
import time
import uuid
from pathlib import Path
from typing import Optional

import numpy as np

from simgap.errors import SimgapError

from . import engine
from .layers import geometry as G


def _boxes2(lo: np.ndarray, hi: np.ndarray, x_lo: np.ndarray, x_hi: np.ndarray, z: float = 0.05):
    """Centers and half sizes (B,3) of planar boxes (first two dims, infinite bounds clipped to X)."""
    lo = np.maximum(np.atleast_2d(lo)[:, :2], x_lo[:2])
    hi = np.minimum(np.atleast_2d(hi)[:, :2], x_hi[:2])
    c = np.zeros((lo.shape[0], 3))
    h = np.full((lo.shape[0], 3), z)
    c[:, :2] = 0.5 * (lo + hi)
    c[:, 2] = z
    h[:, :2] = 0.5 * (hi - lo)
    return c, h


def _xy0(x: np.ndarray) -> np.ndarray:
    """States (..., n) -> (..., 3) positions (x1, x2, 0)."""
    x = np.asarray(x, dtype=np.float32)
    out = np.zeros(x.shape[:-1] + (3,), np.float32)
    k = min(2, x.shape[-1])
    out[..., :k] = x[..., :k]
    return out


def blueprint(state_names) -> "object":
    """Default layout: the state-space view left; gamma views and the summary right; time panel."""
    import rerun.blueprint as rrb

    gamma_views = [rrb.Spatial3DView(origin=f"/gamma/{name}", name=f"gamma_{name}") for name in state_names]
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(rrb.Spatial3DView(origin="/world", name="state space"),
                         rrb.TimeSeriesView(origin="/timeseries", name="mean and nominal trajectories"),
                         row_shares=[3, 1]),
            rrb.Vertical(*gamma_views, rrb.TextDocumentView(origin="/summary", name="summary")),
            column_shares=[3, 2]),
        rrb.TimePanel(expanded=False),
        collapse_panels=False)


def record_run(out: str | Path, system, *, dataset=None, certificate=None, spec=None, synthesis=None,
               rollouts=None, res: int = 41, max_data_points: int = 20000, application_id: str = "simgap",
               recording_id: Optional[str] = None) -> dict:
    """Write a .rrd recording of one run (see module docstring) and return what was logged.

    Parameters
    ----------
    out : path of the .rrd file (written to a temporary name, then renamed: never half-written).
    system : the nominal System (axes, names, tau).
    dataset, certificate, spec, synthesis, rollouts : engine results; each is optional.
    res : vertices per axis of the gamma meshes (res^2 vertices, 2 (res-1)^2 triangles).

    Returns
    -------
    dict with the entity paths, ``n_rollouts``, ``n_steps`` (T+1), ``gamma_vertices``,
    ``gamma_triangles``, ``seconds`` (logging time) and ``bytes`` (file size).
    """
    import rerun as rr

    out = Path(out)
    if out.suffix != ".rrd":
        raise SimgapError(f"recording: the output file must end in .rrd, got {str(out)!r}")
    if not out.parent.exists():
        raise SimgapError(f"recording: folder {str(out.parent)!r} does not exist")
    t0 = time.perf_counter()
    tmp = out.with_name(f".{out.name}.{os.getpid()}.tmp.rrd")
    rec = rr.RecordingStream(application_id, recording_id=recording_id or str(uuid.uuid4()))
    rec.save(str(tmp), default_blueprint=blueprint(system.state_names))
    info = {"entities": [], "n_rollouts": 0, "n_steps": 0, "gamma_vertices": 0, "gamma_triangles": 0}

    def log(path, obj, static=True):
        rec.log(path, obj, static=static)
        info["entities"].append(path)

    x_lo, x_hi = system.x_lo, system.x_hi
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    # state box X as a flat outline
    c, h = _boxes2(x_lo[None], x_hi[None], x_lo, x_hi, z=0.0)
    log("world/X", rr.Boxes3D(centers=c, half_sizes=h, colors=[(120, 120, 120)], labels=["X"]))
    md = [f"# simgap run: {system.name}", ""]

    # ----- specification (obstacle map, target) ------------------------------------------
    if spec is not None:
        obs = list(getattr(spec, "obstacles", ()) or ())
        if obs:
            c, h = _boxes2(np.array([b.lo for b in obs]), np.array([b.hi for b in obs]), x_lo, x_hi, 0.1)
            log("world/obstacles", rr.Boxes3D(centers=c, half_sizes=h, colors=[G.GREY], fill_mode="solid"))
        if getattr(spec, "target", None) is not None:
            c, h = _boxes2(spec.target.lo[None], spec.target.hi[None], x_lo, x_hi, 0.01)
            log("world/target", rr.Boxes3D(centers=c, half_sizes=h, colors=[G.GREEN], fill_mode="solid",
                                           labels=["target"]))
        if getattr(spec, "safe", None) is not None:
            c, h = _boxes2(spec.safe.lo[None], spec.safe.hi[None], x_lo, x_hi, 0.0)
            log("world/safe", rr.Boxes3D(centers=c, half_sizes=h, colors=[G.BLUE], labels=["safe"]))

    # ----- winning domain ----------------------------------------------------------------
    if synthesis is not None:
        centers, widths, values = engine.winning_cells(synthesis)
        if centers.shape[0]:
            cells = G.box_cells(G.Frame(system), centers, widths, values)
            frame = G.Frame(system)
            cxy = cells["positions"][:, :2] * frame.half + frame.center
            hxy = 0.5 * cells["scales"][:, :2] * frame.half
            C = cxy.shape[0]
            cen = np.zeros((C, 3), np.float32)
            cen[:, :2] = cxy
            half = np.zeros((C, 3), np.float32)
            half[:, :2] = hxy * 0.95
            log("world/winning", rr.Boxes3D(centers=cen, half_sizes=half, colors=cells["colors"], fill_mode="solid"))
            info["winning_cells"] = int(C)
        md.append(engine.synthesis_markdown(synthesis))
        md.append("")

    # ----- gamma surfaces and data residuals ------------------------------------------------
    gamma = engine.gamma_function(certificate) if certificate is not None else None
    fixed = list(G.variable_ranges(system).mean(axis=1))
    for i, name in enumerate(system.state_names):
        surf = G.gamma_surface(system, gamma, i, 0, 1, fixed, res=res) if gamma is not None else None
        pts = G.data_points(dataset, system, i, 0, 1, fixed, gamma=gamma, max_points=max_data_points) \
            if dataset is not None else None
        top = max(float(surf["values"].max()) if surf is not None else 0.0,
                  float(pts["gap"].max()) if pts is not None and pts["gap"].size else 0.0)
        z = 1.0 / top if top > 0 and np.isfinite(top) else 1.0
        if surf is not None:
            v = surf["vertices"].copy()
            v[:, 2] *= z
            log(f"gamma/{name}/surface", rr.Mesh3D(vertex_positions=v, triangle_indices=surf["faces"],
                                                  albedo_factor=G.DIM_COLORS[i % len(G.DIM_COLORS)]))
            info["gamma_vertices"] = int(v.shape[0])
            info["gamma_triangles"] = int(surf["faces"].shape[0])
        if pts is not None and pts["points"].shape[0]:
            p = pts["points"].copy()
            p[:, 2] *= z
            log(f"gamma/{name}/data", rr.Points3D(p, colors=pts["colors"], radii=0.01))
        if surf is not None or pts is not None:
            names = G.variable_names(system)
            log(f"gamma/{name}/scale", rr.AnyValues(z_per_state_unit=z, axis_x=names[0], axis_y=names[1],
                                                   fixed=np.asarray(fixed, float)))
    if certificate is not None:
        md.append(engine.certificate_markdown(certificate))
        md.append("")

    # ----- rollouts -------------------------------------------------------------------------
    if rollouts is not None:
        traj, failed, mean, nominal = engine.rollout_arrays(rollouts)
        R, T1, _ = traj.shape
        P = _xy0(traj)  # (R, T+1, 3)
        colors = np.where(np.asarray(failed, bool)[:, None], np.array(G.RED, np.uint8), np.array(G.BLUE, np.uint8))
        log("world/rollouts/paths", rr.LineStrips3D(P, colors=colors, radii=rr.Radius.ui_points(1.0)))
        if mean is not None:
            log("world/rollouts/mean", rr.LineStrips3D([_xy0(mean)], colors=[G.YELLOW], radii=rr.Radius.ui_points(4.0)))
        if nominal is not None:
            log("world/rollouts/nominal", rr.LineStrips3D([_xy0(nominal)], colors=[(0, 0, 0)],
                                                          radii=rr.Radius.ui_points(2.5)))
        steps = np.arange(T1)
        tau = float(getattr(rollouts, "tau", system.tau))
        rec.send_columns(
            "world/rollouts/state",
            indexes=[rr.TimeColumn("step", sequence=steps), rr.TimeColumn("time", duration=steps * tau)],
            columns=[*rr.Points3D.columns(positions=P.transpose(1, 0, 2).reshape(-1, 3),
                                          colors=np.tile(colors, (T1, 1))).partition(np.full(T1, R))])
        info["entities"].append("world/rollouts/state")
        # each state's mean and nominal trajectory over time: the blueprint's time-series view
        for name, path in (("mean", mean), ("nominal", nominal)):
            if path is None:
                continue
            for d, sname in enumerate(system.state_names):
                rec.send_columns(f"timeseries/{sname}/{name}",
                                 indexes=[rr.TimeColumn("step", sequence=steps),
                                          rr.TimeColumn("time", duration=steps * tau)],
                                 columns=rr.Scalars.columns(scalars=np.asarray(path, float)[:, d]))
                info["entities"].append(f"timeseries/{sname}/{name}")
        info["n_rollouts"], info["n_steps"] = int(R), int(T1)
        md.append(engine.rollout_markdown(rollouts))

    log("summary", rr.TextDocument("\n".join(md), media_type=rr.MediaType.MARKDOWN))
    return finish_recording(rec, tmp, out, info, t0)


def finish_recording(rec, tmp: Path, out: Path, info: dict, t0: float) -> dict:
    """Close ``rec``'s file sink, rename ``tmp`` into place as ``out``; add seconds and bytes to ``info``."""
    rec.flush()
    rec.disconnect()  # closes the file sink before the rename
    tmp.replace(out)
    info["seconds"] = time.perf_counter() - t0
    info["bytes"] = out.stat().st_size
    return info


def read_back(path: str | Path) -> dict:
    """Entity path -> {"rows": int, "columns": [names], "static": bool} of a recording (tests, checks)."""
    from rerun.chunk import RrdReader

    out: dict = {}
    for ch in RrdReader(str(path)).store().stream():
        e = out.setdefault(ch.entity_path, {"rows": 0, "columns": set(), "static": ch.is_static, "chunks": []})
        e["rows"] += ch.num_rows
        rb = ch.to_record_batch()
        e["columns"] |= set(rb.schema.names)
        e["chunks"].append(rb)
    return out


def record_refinement(out: str | Path, result, against: Optional[str] = None, bins: int = 60,
                      max_points: int = 20000, seed: int = 0) -> dict:
    """A .rrd of a refinement: each state's residual against one variable, before and after.

    ``result`` is a :class:`simgap.refine.report.RefineResult`. ``against`` defaults to the
    system's first velocity state (e.g. q' for the EMPS axis), where friction shows as a step
    at zero plus a slope. Entities ``refine/<state>/before`` and ``.../after`` (Points2D, at most
    ``max_points`` seeded samples each), ``.../before_mean`` and ``.../after_mean`` (the binned
    means, LineStrips2D) and ``refine/report`` (markdown). Residuals are in state units per
    sampling period, the horizontal axis in the variable's units.
    """
    import rerun as rr
    import rerun.blueprint as rrb
    from simgap.refine.effects import velocity_dims

    out = Path(out)
    if out.suffix != ".rrd":
        raise SimgapError(f"recording: the output file must end in .rrd, got {str(out)!r}")
    if not out.parent.exists():
        raise SimgapError(f"recording: folder {str(out.parent)!r} does not exist")
    s = result.system
    if against is None:
        vd = velocity_dims(s)
        against = s.state_names[vd[0]] if vd else s.state_names[0]
    t0 = time.perf_counter()
    v = result.before.values(against)  # raises SimgapError naming the known variables
    K = v.shape[0]
    keep = np.sort(np.random.default_rng(seed).choice(K, size=min(K, max_points), replace=False))
    names = list(s.state_names)
    tmp = out.with_name(f".{out.name}.{os.getpid()}.tmp.rrd")
    rec = rr.RecordingStream("simgap", recording_id=str(uuid.uuid4()))
    views = [rrb.Spatial2DView(origin=f"/refine/{nm}", name=f"residual {nm} vs {against}") for nm in names]
    rec.save(str(tmp), default_blueprint=rrb.Blueprint(
        rrb.Horizontal(rrb.Vertical(*views), rrb.TextDocumentView(origin="/refine/report", name="report"),
                       column_shares=[3, 1]), collapse_panels=True))
    info = {"entities": [], "against": against, "points": int(keep.size)}
    for i, nm in enumerate(names):
        for which, res, color in (("before", result.before, G.RED), ("after", result.after, G.BLUE)):
            r = res.r[:, i]
            scale = float(np.max(np.abs(result.before.r[:, i]))) or 1.0  # same scale before and after
            pts = np.stack([v[keep], r[keep] / scale * (np.ptp(v) or 1.0) / 2], axis=1).astype(np.float32)
            rec.log(f"refine/{nm}/{which}", rr.Points2D(pts, colors=[color], radii=rr.Radius.ui_points(1.5)),
                    static=True)
            b = res.binned(against, bins)
            ok = np.isfinite(b["mean"][:, i])
            line = np.stack([b["centers"][ok], b["mean"][ok, i] / scale * (np.ptp(v) or 1.0) / 2], axis=1)
            rec.log(f"refine/{nm}/{which}_mean", rr.LineStrips2D([line.astype(np.float32)], colors=[color],
                                                                 radii=rr.Radius.ui_points(3.0)), static=True)
            info["entities"] += [f"refine/{nm}/{which}", f"refine/{nm}/{which}_mean"]
        rec.log(f"refine/{nm}/scale", rr.AnyValues(residual_per_unit_height=scale / ((np.ptp(v) or 1.0) / 2),
                                                   horizontal=against), static=True)
    rep = result.report
    md = [f"# refinement of {s.name}: residual vs {against}", "",
          "red: nominal model f, blue: refined model f' (binned means as lines; vertical axis scaled per state, "
          "see `scale`)", "", "| effect | state | coefficient | stderr | explained |", "|---|---|---|---|---|"]
    for e in rep.get("effects", []):
        md.append(f"| {e['name']} | {names[e['state']]} | {e['coefficient']:.4g} | {e['stderr']:.2g} | "
                  f"{e['explained_fraction']:.3f} |")
    md += ["", "held-out RMS before: " + ", ".join(f"{x:.3g}" for x in rep["rms_before"]),
           "held-out RMS after: " + ", ".join(f"{x:.3g}" for x in rep["rms_after"]),
           f"unexplained: {rep['unexplained']}"]
    rec.log("refine/report", rr.TextDocument("\n".join(md), media_type=rr.MediaType.MARKDOWN), static=True)
    info["entities"].append("refine/report")
    return finish_recording(rec, tmp, out, info, t0)
