"""Headless Rerun recordings (.rrd) of a simgap run, laid out by a default blueprint.

A recording holds one or more *methods* (``simgap run`` records ``deterministic`` beside
``stochastic``; ``simgap record`` one, named by its certificate). State-space layers are in state
units (x = x1, y = x2, z = 0; a third state, e.g. the TurtleBot heading, is projected away).
Entities (``<m>`` a method, ``<s>`` a state name; :func:`entity_paths` lists them for a run):

* ``world/X``, ``world/obstacles``, ``world/target``, ``world/safe`` -- Boxes3D of X and the specification;
* ``world/<m>/winning`` -- Boxes3D of the winning cells (merged over the projected dimensions,
  colored red -> green by the fraction of winning cells);
* ``world/<m>/<role>`` -- the sets a set method proved, from its statement
  (:mod:`simgap.synthesis.statement`), projected onto (x1, x2): an ellipsoid's shadow
  (``invariant_set``), a box tube's boxes per period (``tube``), its noise tube (``noise_tube``),
  terminal and target boxes; LineStrips3D in the method's color (the nominal model's under
  ``world/nominal``); ``timeseries/<s>/<m>/tube_lo``, ``..._hi`` (and ``noise_tube_*``) the tube's band
  along each state per period;
* ``world/<m>/rollouts/paths`` -- every rollout as one LineStrips3D (failures red), static;
* ``world/<m>/rollouts/mean_map`` -- the mean map m+ = E fhat(m, u(m)), the sequence the
  guarantee is about (magenta); ``.../mean`` the average of the rollouts (yellow) and
  ``.../nominal`` the nominal model's trajectory (black);
* ``world/<m>/rollouts/state`` -- the R current states over the time axes ``step`` (sequence) and
  ``time`` (duration, t * tau), logged column-wise with ``send_columns`` (one call);
* ``timeseries/<s>/<m>/mean_map``, ``.../mean``, ``.../nominal`` -- each state over time (Scalars);
* ``gamma/<m>/<s>/surface`` -- Mesh3D of gamma_s over the first two variables (others at the
  centre of their range), coordinates normalized to [-1, 1]^2 and z = gamma_s / top_s, with top_s
  the largest gamma_s or data gap over ALL methods (so the methods' surfaces compare by height);
  ``gamma/<m>/<s>/data`` -- the observed gaps g_s(x_r, u) of the data near that slice, same scale
  (green: covered by gamma, red: not); ``gamma/<m>/<s>/scale`` -- the z scale and units (AnyValues);
* ``summary`` -- TextDocument (markdown): per method the synthesis, certificate and rollout summaries.
"""

from __future__ import annotations

import time
import uuid
from pathlib import Path
from typing import Mapping, Optional

import numpy as np

from simgap.errors import SimgapError
from simgap.systems import labelled, units

from . import engine
from .layers import geometry as G

# surface color per method (other names cycle through the dimension colors)
METHOD_COLORS = {"stochastic": (230, 120, 40), "deterministic": (70, 130, 230)}
MAGENTA = (220, 40, 200)
STAGES = ("dataset", "certificate", "synthesis", "rollouts", "invariant_set")


def method_color(name: str, i: int = 0):
    return METHOD_COLORS.get(name, G.DIM_COLORS[i % len(G.DIM_COLORS)])


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


def blueprint(state_names, methods=("stochastic",), state_units=None, x_lo=None, x_hi=None) -> "object":
    """Default layout, made to fit a 1280 x 800 window: one state-space view per method over the time
    series per state (left); one gamma view per state with every method's surface, and the summary
    (right). View titles are short (the method; the state and its unit); the time series carry no
    legend over the curves (the summary gives the key: a method's color, the mean map full, the
    rollout average lighter, the nominal model darker; hovering names a curve); the state-space
    views look at X (``x_lo``, ``x_hi`` of the first two states) from the front and above, the gamma
    views at their square [-1, 1]^2 x [0, 1]."""
    import rerun.blueprint as rrb

    methods = list(methods)
    su = list(state_units or [""] * len(state_names))
    eye = None
    if x_lo is not None and x_hi is not None:
        lo, hi = np.asarray(x_lo, float)[:2], np.asarray(x_hi, float)[:2]
        c, span = 0.5 * (lo + hi), float(np.max(hi - lo))
        eye = rrb.EyeControls3D(position=(float(c[0]), float(c[1] - 0.45 * span), 1.3 * span),
                                look_target=(float(c[0]), float(c[1]), 0.0), eye_up=(0.0, 0.0, 1.0))
    worlds = [rrb.Spatial3DView(origin="/world", name=m, eye_controls=eye,
                                contents=["+ /world/**", *[f"- /world/{o}/**" for o in methods if o != m]])
              for m in methods]
    series = [rrb.TimeSeriesView(origin=f"/timeseries/{s}", name=labelled(s, u),
                                 plot_legend=rrb.PlotLegend(visible=False))
              for s, u in zip(state_names, su)]
    geye = rrb.EyeControls3D(position=(-0.8, -3.0, 2.4), look_target=(0.0, 0.0, 0.3), eye_up=(0.0, 0.0, 1.0))
    gammas = [rrb.Spatial3DView(origin="/gamma", name=f"gamma_{s}", eye_controls=geye,
                                contents=[f"+ /gamma/{m}/{s}/**" for m in methods])
              for s in state_names]
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(rrb.Horizontal(*worlds), rrb.Horizontal(*series), row_shares=[3, 2]),
            rrb.Vertical(*gammas, rrb.TextDocumentView(origin="/summary", name="summary")),
            column_shares=[3, 2]),
        rrb.TimePanel(expanded=False),
        collapse_panels=True)


def entity_paths(state_names, methods=("stochastic", "deterministic"), spec_parts=("safe",), rollouts=True) -> list:
    """The entities :func:`record_run` writes for a run with every stage. docs/app.md's list is
    ``entity_paths(["<s>"], ["<m>"], ("obstacles", "target", "safe"))``, checked by
    ``tests/test_docs.py``; ``tests/test_record.py`` checks it against a recording read back."""
    out = ["world/X", *[f"world/{p}" for p in spec_parts]]
    for m in methods:
        out.append(f"world/{m}/winning")
        if rollouts:
            out += [f"world/{m}/rollouts/{k}" for k in ("paths", "mean", "nominal", "mean_map", "state")]
            out += [f"timeseries/{s}/{m}/{k}" for s in state_names for k in ("mean", "nominal", "mean_map")]
        out += [f"gamma/{m}/{s}/{k}" for s in state_names for k in ("surface", "data", "scale")]
    return out + ["summary"]


def _stages(obj) -> dict:
    """A method's stage results from a dict or an object with those attributes (e.g. MethodResults)."""
    get = obj.get if isinstance(obj, Mapping) else (lambda k, d=None: getattr(obj, k, d))
    return {k: get(k, None) for k in STAGES}


def record_run(out: str | Path, system, *, dataset=None, certificate=None, spec=None, synthesis=None,
               rollouts=None, methods: Optional[Mapping] = None, method: Optional[str] = None, res: int = 41,
               max_data_points: int = 20000, application_id: str = "simgap",
               recording_id: Optional[str] = None) -> dict:
    """Write a .rrd recording of one run (see module docstring) and return what was logged.

    Parameters
    ----------
    out : path of the .rrd file (written to a temporary name, then renamed: never half-written).
    system : the nominal System (axes, names, units, tau).
    methods : {name: stages}, each a dict or object with ``dataset``, ``certificate``, ``synthesis``,
        ``rollouts`` (each optional), e.g. ``{"deterministic": ..., "stochastic": ...}``.
    dataset, certificate, synthesis, rollouts : one method's results instead of ``methods``,
        recorded under the name ``method`` (default: the certificate's method, else ``run``).
    spec : the specification (obstacles, target, safe set), shared by the methods.
    res : vertices per axis of the gamma meshes (res^2 vertices, 2 (res-1)^2 triangles).

    Returns
    -------
    dict with the entity paths, ``methods``, ``n_rollouts`` and ``n_steps`` (T+1) of the last method
    with rollouts, ``gamma_vertices``, ``gamma_triangles``, ``winning_cells`` (per method, as ``geometry.WINNING_CELLS`` defines them),
    ``seconds`` (logging time) and ``bytes`` (file size).
    """
    import rerun as rr

    if methods is None:
        name = method or getattr(certificate, "method", None) or "run"
        methods = {str(name): dict(dataset=dataset, certificate=certificate, synthesis=synthesis, rollouts=rollouts)}
    methods = {str(k): _stages(v) for k, v in methods.items()}
    out = Path(out)
    if out.suffix != ".rrd":
        raise SimgapError(f"recording: the output file must end in .rrd, got {str(out)!r}")
    if not out.parent.exists():
        raise SimgapError(f"recording: folder {str(out.parent)!r} does not exist")
    su, _ = units(system)
    t0 = time.perf_counter()
    rec, mem = open_recording(blueprint(system.state_names, list(methods), su, system.x_lo, system.x_hi),
                              application_id, recording_id)
    info = {"entities": [], "methods": list(methods), "n_rollouts": 0, "n_steps": 0, "gamma_vertices": 0,
            "gamma_triangles": 0, "winning_cells": {}}

    def log(path, obj, static=True):
        rec.log(path, obj, static=static)
        info["entities"].append(path)

    try:
        x_lo, x_hi = system.x_lo, system.x_hi
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        c, h = _boxes2(x_lo[None], x_hi[None], x_lo, x_hi, z=0.0)  # state box X as a flat outline
        log("world/X", rr.Boxes3D(centers=c, half_sizes=h, colors=[(120, 120, 120)]))  # no label over the views
        md = [f"# simgap run: {system.name}", "",
              "State space: X in grey, the safe set outlined in blue, the target green, obstacles grey boxes; "
              + " x ".join(labelled(s_, u) for s_, u in zip(system.state_names[:2], su))
              + ". Time series: one color per method; the mean map full, the rollout average lighter, the "
              "nominal model darker (hover a curve for its name).", ""]
        _log_spec(log, rr, spec, x_lo, x_hi)
        # one height scale per state over every method: the surfaces compare by height
        gamma = {m: engine.gamma_function(st["certificate"]) if st["certificate"] is not None else None
                 for m, st in methods.items()}
        fixed = list(G.variable_ranges(system).mean(axis=1))
        layers = {m: [_gamma_layers(system, gamma[m], st["dataset"], i, fixed, res, max_data_points)
                      for i in range(system.n)] for m, st in methods.items()}
        tops = [max([L[i]["top"] for L in layers.values()] + [0.0]) for i in range(system.n)]
        for k, (m, st) in enumerate(methods.items()):
            md += [f"## {m}", ""]
            if st["synthesis"] is not None:
                info["winning_cells"][m] = _log_winning(log, rr, system, m, st["synthesis"])
                md += [engine.synthesis_markdown(st["synthesis"]), ""]
            if st["invariant_set"] is not None:
                stmt = st["invariant_set"].statement()
                if system.n >= 2:
                    _log_sets(log, rr, stmt, m, method_color(m, k))
                T = int(np.asarray(st["rollouts"].trajectories).shape[1]) - 1 if st["rollouts"] is not None \
                    else 2 * int(getattr(st["invariant_set"], "T0", 0)) + 1
                _log_bands(rec, info, rr, system, stmt, m, method_color(m, k), T)
                md += [statement_markdown(stmt), ""]
            for i, name in enumerate(system.state_names):
                _log_gamma(log, rr, info, f"gamma/{m}/{name}", layers[m][i], tops[i], method_color(m, k),
                           G.variable_names(system), fixed, su[i])
            if st["certificate"] is not None:
                md += [engine.certificate_markdown(st["certificate"]), ""]
            if st["rollouts"] is not None:
                _log_rollouts(rec, log, rr, info, system, m, st["rollouts"])
                md += [engine.rollout_markdown(st["rollouts"]), ""]
        log("summary", rr.TextDocument("\n".join(md), media_type=rr.MediaType.MARKDOWN))
    except BaseException:
        rec.disconnect()  # nothing was written yet: the recording is in memory
        raise
    return finish_recording(rec, mem, out, info, t0)


def statement_markdown(stmt) -> str:
    """A method's statement (:mod:`simgap.synthesis.statement`) as markdown: headline, rows, p_cert, notes."""
    rows = "\n".join(f"| {r.label} | {r.value} | {r.about.replace('_', ' ')} |" for r in stmt.rows)
    per = "" if stmt.per_run is None else (f"\n\n**p_cert {stmt.per_run.p_cert:.4f}**: P({stmt.per_run.event}) "
                                           f">= p_cert; rests on {stmt.per_run.rests_on}")
    return (f"**{stmt.headline}**\n\n| what | value | about |\n|---|---|---|\n{rows}{per}"
            + "".join(f"\n\n*{n}*" for n in stmt.notes))


def _log_sets(log, rr, stmt, m: str, color) -> None:
    """``world/<m>/<role>``: each set of the statement projected onto (x1, x2) (a tube's boxes per period)."""
    widths = {"tube": 1.0, "noise_tube": 0.5, "terminal": 2.5, "ellipsoid": 2.5, "target": 2.0}
    for ds in stmt.sets:
        if ds.kind == "cells":
            continue
        role = "invariant_set" if ds.role == "ellipsoid" else ds.role
        log(f"world/{m}/{role}", rr.LineStrips3D([_xy0(o) for o in ds.outlines((0, 1))],
                                                 colors=[G.GREEN if ds.role == "target" else color],
                                                 radii=rr.Radius.ui_points(widths.get(ds.role, 1.0)),
                                                 labels=[ds.label] if ds.role in ("terminal", "target") else None))


def _log_bands(rec, info, rr, system, stmt, m: str, color, T: int) -> None:
    """``timeseries/<s>/<m>/<role>_lo`` and ``_hi``: the statement's boxes along each state per period
    (a tube's band around the plan, then its terminal box), beside the runs' time series."""
    tau = float(system.tau)
    for ds in stmt.sets:
        if ds.kind != "boxes" or ds.role not in ("tube", "noise_tube"):
            continue
        for d, sname in enumerate(system.state_names):
            t, lo, hi = ds.band(d, T)
            times = [rr.TimeColumn("step", sequence=t), rr.TimeColumn("time", duration=t * tau)]
            for edge, v in (("lo", lo), ("hi", hi)):
                ent = f"timeseries/{sname}/{m}/{ds.role}_{edge}"
                rec.log(ent, rr.SeriesLines(colors=[tuple(int(c) for c in color)], widths=[0.5],
                                            names=[f"{m}: {ds.label} ({edge})"]), static=True)
                rec.send_columns(ent, indexes=times, columns=rr.Scalars.columns(scalars=np.asarray(v, float)))
                info["entities"].append(ent)


def _log_spec(log, rr, spec, x_lo, x_hi) -> None:
    if spec is None:
        return
    obs = list(getattr(spec, "obstacles", ()) or ())
    if obs:
        c, h = _boxes2(np.array([b.lo for b in obs]), np.array([b.hi for b in obs]), x_lo, x_hi, 0.1)
        log("world/obstacles", rr.Boxes3D(centers=c, half_sizes=h, colors=[G.GREY], fill_mode="solid"))
    if getattr(spec, "target", None) is not None:
        c, h = _boxes2(spec.target.lo[None], spec.target.hi[None], x_lo, x_hi, 0.01)
        log("world/target", rr.Boxes3D(centers=c, half_sizes=h, colors=[G.GREEN], fill_mode="solid"))
    if getattr(spec, "safe", None) is not None:
        c, h = _boxes2(spec.safe.lo[None], spec.safe.hi[None], x_lo, x_hi, 0.0)
        log("world/safe", rr.Boxes3D(centers=c, half_sizes=h, colors=[G.BLUE]))  # labels would float over the map


def _log_winning(log, rr, system, m: str, synthesis) -> int:
    centers, widths, values = engine.winning_cells(synthesis)
    if not centers.shape[0]:
        return 0
    frame = G.Frame(system)
    cells = G.box_cells(frame, centers, widths, values)
    cxy = cells["positions"][:, :2] * frame.half + frame.center
    hxy = 0.5 * cells["scales"][:, :2] * frame.half
    C = cxy.shape[0]
    cen = np.zeros((C, 3), np.float32)
    cen[:, :2] = cxy
    half = np.zeros((C, 3), np.float32)
    half[:, :2] = hxy * 0.95
    log(f"world/{m}/winning", rr.Boxes3D(centers=cen, half_sizes=half, colors=cells["colors"], fill_mode="solid"))
    return G.winning_cells_count(synthesis.controller)  # cells, as the CLI counts them (one box per column)


def _gamma_layers(system, gamma, dataset, i, fixed, res, max_points) -> dict:
    surf = G.gamma_surface(system, gamma, i, 0, 1, fixed, res=res) if gamma is not None else None
    pts = G.data_points(dataset, system, i, 0, 1, fixed, gamma=gamma, max_points=max_points) \
        if dataset is not None else None
    top = max(float(surf["values"].max()) if surf is not None else 0.0,
              float(pts["gap"].max()) if pts is not None and pts["gap"].size else 0.0)
    return {"surf": surf, "pts": pts, "top": top if np.isfinite(top) else 0.0}


def _log_gamma(log, rr, info, path, layer, top, color, names, fixed, unit) -> None:
    surf, pts = layer["surf"], layer["pts"]
    z = 1.0 / top if top > 0 else 1.0
    if surf is not None:
        v = surf["vertices"].copy()
        v[:, 2] *= z
        log(f"{path}/surface", rr.Mesh3D(vertex_positions=v, triangle_indices=surf["faces"], albedo_factor=color))
        info["gamma_vertices"] = int(v.shape[0])
        info["gamma_triangles"] = int(surf["faces"].shape[0])
    if pts is not None and pts["points"].shape[0]:
        p = pts["points"].copy()
        p[:, 2] *= z
        log(f"{path}/data", rr.Points3D(p, colors=pts["colors"], radii=0.01))
    if surf is not None or pts is not None:
        log(f"{path}/scale", rr.AnyValues(z_per_state_unit=z, top=top, unit=f"{unit}/step" if unit else "",
                                          axis_x=names[0], axis_y=names[1], fixed=np.asarray(fixed, float)))


def _log_rollouts(rec, log, rr, info, system, m: str, rollouts) -> None:
    traj, failed, mean, nominal = engine.rollout_arrays(rollouts)
    mean_map = getattr(rollouts, "mean_map_trajectory", None)
    R, T1, _ = traj.shape
    P = _xy0(traj)  # (R, T+1, 3)
    colors = np.where(np.asarray(failed, bool)[:, None], np.array(G.RED, np.uint8), np.array(G.BLUE, np.uint8))
    base = f"world/{m}/rollouts"
    log(f"{base}/paths", rr.LineStrips3D(P, colors=colors, radii=rr.Radius.ui_points(1.0)))
    lines = (("mean", mean, G.YELLOW, 3.0), ("nominal", nominal, (0, 0, 0), 2.0), ("mean_map", mean_map, MAGENTA, 2.5))
    for key, path, color, width in lines:
        if path is not None:
            log(f"{base}/{key}", rr.LineStrips3D([_xy0(path)], colors=[color], radii=rr.Radius.ui_points(width)))
    steps = np.arange(T1)
    tau = float(getattr(rollouts, "tau", system.tau))
    times = [rr.TimeColumn("step", sequence=steps), rr.TimeColumn("time", duration=steps * tau)]
    rec.send_columns(f"{base}/state", indexes=times,
                     columns=[*rr.Points3D.columns(positions=P.transpose(1, 0, 2).reshape(-1, 3),
                                                   colors=np.tile(colors, (T1, 1))).partition(np.full(T1, R))])
    info["entities"].append(f"{base}/state")
    # each state's trajectories over time (the time-series views show every method): the mean map
    # in the method's color, the rollout average lighter, the nominal model's darker
    mc = np.array(method_color(m, list(info["methods"]).index(m)), float)
    shade = {"mean_map": mc, "mean": 0.5 * mc + 127.5, "nominal": 0.5 * mc}
    for key, path, _, _ in lines:
        if path is None or len(path) != T1:
            continue
        for d, sname in enumerate(system.state_names):
            ent = f"timeseries/{sname}/{m}/{key}"
            rec.log(ent, rr.SeriesLines(colors=[tuple(int(c) for c in shade[key])],
                                        names=[f"{m}: {key.replace('_', ' ')}"]), static=True)
            rec.send_columns(ent, indexes=times, columns=rr.Scalars.columns(scalars=np.asarray(path, float)[:, d]))
            info["entities"].append(ent)
    info["n_rollouts"], info["n_steps"] = int(R), int(T1)


def open_recording(blueprint, application_id: str = "simgap", recording_id: Optional[str] = None):
    """(stream, memory sink) of a new recording held in memory with ``blueprint`` as its default.

    Recordings are written by :func:`finish_recording`, never by Rerun's own file sink: that
    sink writes from a thread of its own, and on a full disk it truncates the file silently or
    deadlocks ``flush``/``disconnect`` (seen with rerun 0.41). Held in memory, the recording's
    exact size is known and it is written like every other result (:func:`simgap.fileio.atomic_file`).
    """
    import rerun as rr

    rec = rr.RecordingStream(application_id, recording_id=recording_id or str(uuid.uuid4()))
    mem = rec.memory_recording()
    rec.send_blueprint(blueprint, make_active=True, make_default=True)
    return rec, mem


def finish_recording(rec, mem, out: Path, info: dict, t0: float) -> dict:
    """Write the recording in ``mem`` to ``out`` atomically, read it back whole before it takes
    the final name (a truncated file is never announced), and add seconds and bytes to ``info``.
    A failed write (full disk, file-size limit) is a SimgapError naming ``out`` and the bytes
    needed; no temporary file is left."""
    from simgap import fileio

    rec.flush()
    data = mem.drain_as_bytes()
    rec.disconnect()

    def whole(tmp: Path) -> None:
        try:
            read_back(tmp)
        except Exception as e:  # noqa: BLE001 - rerun's reader raises several types for a bad file
            raise SimgapError(f"cannot write {str(out)!r}: the recording does not read back whole ({e})") from None

    with fileio.atomic_file(out, "wb", need=len(data), verify=whole) as fh:
        fh.write(data)
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
    views = [rrb.Spatial2DView(origin=f"/refine/{nm}", name=f"residual {nm} vs {against}") for nm in names]
    rec, mem = open_recording(rrb.Blueprint(
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
    return finish_recording(rec, mem, out, info, t0)
