"""Drawing the app's layers into the viser scene (one scene node per layer, batched geometry).

Node names: ``/map``, ``/gamma/surface``, ``/gamma/data``, ``/winning``, ``/rollouts/all`` (every
rollout as ONE line-segments node), ``/rollouts/mean``, ``/rollouts/nominal``, ``/bodies``.
The state-space layers live in the display square [-1, 1]^2 (see :mod:`.geometry`); the
simulator bodies are drawn in metres next to it, offset by ``BODIES_OFFSET``.
"""

from __future__ import annotations

import numpy as np

from .. import engine
from . import geometry as G

BODIES_OFFSET = (2.6, 0.0, 0.0)


def _remove(app, name: str) -> None:
    try:
        app.server.scene.remove_by_name(name)
    except Exception:  # node not present
        pass


def draw_system(app) -> None:
    """Static layers of the current system: ground grid, map/spec, simulator bodies."""
    sc = app.server.scene
    frame = G.Frame(app.system)
    sc.add_grid("/grid", width=2.0, height=2.0, cell_size=0.25, plane="xy", position=(0.0, 0.0, -0.001))
    names = variable_names_md(app)
    sc.add_label("/grid/label_x", text=names[0], position=(1.1, -1.05, 0.0))
    sc.add_label("/grid/label_y", text=names[1], position=(-1.1, 1.05, 0.0))
    _remove(app, "/map")
    for name, mesh in engine.map_meshes(app, frame):
        _add_mesh(sc, f"/map/{name}", mesh, visible=app.layers_visible["map"])
    _remove(app, "/bodies")
    for name, mesh, pos in engine.body_meshes(app):
        _add_mesh(sc, f"/bodies/{name}", mesh, position=tuple(np.add(pos, BODIES_OFFSET)),
                  visible=app.layers_visible["bodies"])


def _add_mesh(sc, name, mesh, position=(0.0, 0.0, 0.0), visible=True):
    """A trimesh as a viser simple mesh in its (first) face color, opacity from its alpha."""
    fc = np.asarray(mesh.visual.face_colors)
    rgba = fc[0] if fc.size else np.array([150, 150, 150, 255])
    opacity = None if rgba[3] >= 255 else float(rgba[3]) / 255.0
    sc.add_mesh_simple(name, np.asarray(mesh.vertices), np.asarray(mesh.faces), color=tuple(int(c) for c in rgba[:3]),
                       opacity=opacity, position=position, visible=visible)


def variable_names_md(app) -> list:
    s = app.system
    names = list(s.state_names)
    return names if len(names) >= 2 else names + [""]


def draw_gamma(app) -> dict:
    """Gamma surface of the selected dimension over the selected variables, and the data gaps.

    Returns what was drawn: dict(vertices, faces, points) (empty arrays when nothing).
    """
    sc = app.server.scene
    v = app.view
    cert = app.results.get("certify")
    data = app.results.get("collect")
    out = {"vertices": np.zeros((0, 3)), "faces": np.zeros((0, 3), np.uint32), "points": np.zeros((0, 3))}
    gamma = engine.gamma_function(cert) if cert is not None else None
    if gamma is None and data is None:
        _remove(app, "/gamma")
        return out
    s = app.system
    fixed = v["fixed"] if v["fixed"] is not None else list(G.variable_ranges(s).mean(axis=1))
    surf = None
    if gamma is not None:
        surf = G.gamma_surface(s, gamma, v["dim"], v["a"], v["b"], fixed, res=41, zscale=1.0)
    pts = None
    if data is not None:
        pts = G.data_points(data, s, v["dim"], v["a"], v["b"], fixed, gamma=gamma, zscale=1.0)
    if v.get("zscale") is None:  # fix the height scale once per dimension so changes are visible
        top = max([float(np.max(surf["values"])) if surf is not None else 0.0,
                   float(np.max(pts["gap"])) if pts is not None and pts["gap"].size else 0.0])
        if top > 0 and np.isfinite(top):
            v["zscale"] = 1.0 / top
    z = v.get("zscale") or 1.0
    if surf is not None:
        verts = surf["vertices"].copy()
        verts[:, 2] *= z
        vals = surf["values"]
        # viser's own mesh material (non-metallic); GLB meshes without a material render washed out
        sc.add_mesh_simple("/gamma/surface", verts, surf["faces"], color=G.DIM_COLORS[v["dim"] % len(G.DIM_COLORS)],
                           side="double", opacity=0.7, visible=app.layers_visible["gamma"])
        out["vertices"], out["faces"] = verts, surf["faces"]
        out["range"] = (float(vals.min()), float(vals.max()))
    else:
        _remove(app, "/gamma/surface")
    if pts is not None and pts["points"].shape[0]:
        p = pts["points"].copy()
        p[:, 2] *= z
        sc.add_point_cloud("/gamma/data", points=p, colors=pts["colors"], point_size=0.02, point_shape="circle",
                           visible=app.layers_visible["data"])
        out["points"] = p
        app.last_data_covered = pts["covered"]
    else:
        _remove(app, "/gamma/data")
    return out


def draw_winning(app) -> int:
    """Winning domain as one batched-box node, colored by the fraction of winning cells per (x1, x2)."""
    res = app.results.get("synthesize")
    if res is None:
        _remove(app, "/winning")
        return 0
    centers, widths, values = engine.winning_cells(res)
    if centers.shape[0] == 0:
        _remove(app, "/winning")
        return 0
    frame = G.Frame(app.system)
    cells = G.box_cells(frame, centers, widths, values)
    import trimesh
    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    C = cells["positions"].shape[0]
    app.server.scene.add_batched_meshes_simple(
        "/winning", vertices=box.vertices, faces=box.faces,
        batched_wxyzs=np.tile([1.0, 0.0, 0.0, 0.0], (C, 1)), batched_positions=cells["positions"],
        batched_scales=cells["scales"] * np.array([0.95, 0.95, 1.0]), batched_colors=cells["colors"],
        opacity=0.5, visible=app.layers_visible["winning"])
    return C


def draw_rollouts(app) -> int:
    """All rollouts as one line-segments node (failures red), the mean trajectory (yellow, thick)
    and the nominal model's trajectory (black)."""
    res = app.results.get("rollout")
    if res is None:
        _remove(app, "/rollouts")
        return 0
    frame = G.Frame(app.system)
    traj, failed, mean, nominal = engine.rollout_arrays(res)
    seg = G.rollout_segments(frame, traj, failed)
    sc = app.server.scene
    vis = app.layers_visible["rollouts"]
    sc.add_line_segments("/rollouts/all", points=seg["points"], colors=seg["colors"], thickness=1.0,
                         thickness_units="screen", visible=vis)
    if mean is not None:
        sc.add_line_segments("/rollouts/mean", points=G.polyline_segments(frame, mean), colors=G.YELLOW,
                             thickness=5.0, thickness_units="screen", visible=vis)
    if nominal is not None:
        sc.add_line_segments("/rollouts/nominal", points=G.polyline_segments(frame, nominal), colors=(0, 0, 0),
                             thickness=3.0, thickness_units="screen", visible=vis)
    return seg["points"].shape[0]


RESIDUAL_PLANE_Y = -1.5


def draw_residuals(app, state: int = None, var: str = None, max_points: int = 20000) -> int:
    """Refinement residuals r_i = x+ - f_i (red) and x+ - f'_i (green) against one variable, as two
    point clouds in the vertical plane y = RESIDUAL_PLANE_Y (x: the variable over its range mapped to
    [-1, 1]; z: r scaled so that max |r| before = 0.8), with the binned means as lines."""
    res = app.results.get("refine")
    if res is None:
        _remove(app, "/refine")
        return 0
    s = res.system
    v = app.view
    state = v.get("res_state", s.n - 1) if state is None else state
    var = v.get("res_var") or s.state_names[-1] if var is None else var
    x, r0 = res.before.against(var)
    _, r1 = res.after.against(var)
    K = x.size
    idx = np.arange(K) if K <= max_points else np.sort(np.random.default_rng(0).choice(K, max_points, replace=False))
    lo, hi = float(x.min()), float(x.max())
    px = 2 * (x[idx] - lo) / max(hi - lo, 1e-12) - 1
    scale = 0.8 / max(float(np.abs(r0[:, state]).max()), 1e-15)
    sc = app.server.scene
    for name, r, col in (("before", r0, G.RED), ("after", r1, G.GREEN)):
        P = np.stack([px, np.full(idx.size, RESIDUAL_PLANE_Y), 0.5 + scale * r[idx, state]], axis=1)
        sc.add_point_cloud(f"/refine/{name}", points=P.astype(np.float32), colors=col, point_size=0.012,
                           point_shape="circle")
    for name, rr, col in (("before_mean", res.before, (120, 0, 0)), ("after_mean", res.after, (0, 100, 0))):
        b = rr.binned(var, bins=30)
        ok = np.isfinite(b["mean"][:, state])
        c = b["centers"][ok]
        P = np.stack([2 * (c - lo) / max(hi - lo, 1e-12) - 1, np.full(c.size, RESIDUAL_PLANE_Y - 0.01),
                      0.5 + scale * b["mean"][ok, state]], axis=1)
        if P.shape[0] >= 2:
            sc.add_line_segments(f"/refine/{name}", points=np.stack([P[:-1], P[1:]], axis=1).astype(np.float32),
                                 colors=col, thickness=3.0, thickness_units="screen")
    sc.add_label("/refine/label", text=f"residual of {s.state_names[state]} vs {var} (red: f, green: f')",
                 position=(-1.0, RESIDUAL_PLANE_Y, 1.45))
    return int(idx.size)


def draw_results(app) -> None:
    draw_gamma(app)
    draw_winning(app)
    draw_rollouts(app)
    draw_residuals(app)


LAYER_NODES = {"gamma": ("/gamma/surface",), "data": ("/gamma/data",), "map": ("/map",),
               "winning": ("/winning",), "rollouts": ("/rollouts",), "bodies": ("/bodies",)}
