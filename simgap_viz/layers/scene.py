"""Drawing the app's layers into the viser scene: few nodes, batched geometry, one frame.

Every state-space layer lives in one display frame: the first two state dimensions mapped to
the square [-1, 1]^2 (z = 0, see :mod:`.geometry`). The winning domain is one opaque image on it,
the rollouts one translucent image on top (a density; the bold mean map, mean and nominal
trajectories thin line segments, the last two dashed). The gamma surface, over the two
variables the View tab picks, stands on its own square behind the map (``SURFACE_OFFSET``) with
heights z = gamma / top in [0, 1], its own ticks and a vertical gamma axis, and only where gamma
varies enough to see (``GAMMA_VISIBLE``; otherwise the legend gives its value). The layers are
listed in :data:`LAYERS` (:class:`Layer`): the View tab's checkboxes and the redraws follow from it.
A TurtleBot's arena and robot are drawn in the same frame (metres mapped like x, y), so the map
appears once at one scale; the pendulum's rod, which has no place in the (theta, omega) plane,
stands beside the square. Node names: ``/grid``, ``/axes``, ``/map``, ``/winning``,
``/gamma/surface``, ``/gamma/axes``, ``/gamma/data``, ``/zaxis``, ``/invariant`` (an invariant-set run's
ellipsoids, projected onto the map's two states), ``/rollouts/{all,mean,nominal,now}``, ``/bodies``, ``/refine``.

Frame cost in software WebGL (SwiftShader, bench/bench_viz.py --browser) decides the drawing:
no shadow maps (the default light's three shadow cascades re-render the scene three times per
frame), the surface unlit with vertex colors (a lit PBR surface costs its screen area times an
environment-map shader), the rollout subset rasterized into one image (as geometry, viser's
``add_line_segments`` costs about 30 ms per 1000 segments there, since it extrudes each into six
triangles, and even 1-pixel GL lines about 3 ms), and layers whose inputs did not change are not
sent again.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np

from simgap.systems import labelled, units

from .. import engine
from . import geometry as G
from .bodies import MODEL_BODIES

PENDULUM_PIVOT = (1.9, 0.0, 1.2)  # where the pendulum's pivot stands, beside the state square
PENDULUM_ROD = 1.0  # its rod's length [m] (assets/urdf/pendulum.urdf): the free end hangs at z = 0.2
MODEL_LEFT = 1.5  # a robot file's model stands beside the square: its bounding box starts at this x
MODEL_SIZE = 2.5  # ... and is scaled to this largest extent (display units)
MODEL_FIXED_SPAN = 4.0  # a fixed geom more than this times the moving geoms' span is not drawn (a ground plane)
SURFACE_RES = 41
GAMMA_VISIBLE = 0.15  # a gamma that varies by less than this share of its largest value on the slice is
# not drawn as a surface (a flat sheet over the map says nothing a number cannot): the legend gives its value
SURFACE_OPACITY = 0.6
SURFACE_OFFSET = (0.0, 2.7, 0.0)  # the gamma surface stands on its own square behind the map, never over it:
# its variables need not be the map's (x1, x2), and the map stays readable (display units)
N_DRAW = 1000  # rollouts drawn by default: every one of a run's 1000, as a density (geometry.rollout_image)


@dataclass(frozen=True)
class Layer:
    """One scene layer: its View-tab checkbox, the scene nodes it owns and how it is drawn.

    ``draw(app)`` reads the app's results and settings and sends (or removes) its nodes; it is called
    by :func:`draw_system` (``system=True``: the system's map and bodies) or :func:`draw_results`
    (everything computed). A new layer (e.g. a controller's invariant set) is one entry here
    (:func:`register_layer`) and one draw function; the View tab, the visibility flags and the
    redraws follow from the entry.
    """
    key: str
    label: Optional[str]  # the View tab's checkbox (None: no checkbox, always drawn)
    nodes: tuple
    draw: Callable
    system: bool = False
    default: bool = True


LAYERS: list = []  # in drawing order


def register_layer(layer: Layer) -> None:
    """Add ``layer`` (or replace the one with its key), drawn after the layers already registered."""
    LAYERS[:] = [lay for lay in LAYERS if lay.key != layer.key] + [layer]


def default_visibility() -> dict:
    """Layer key -> shown at start (the app's ``layers_visible``)."""
    return {lay.key: lay.default for lay in LAYERS}


def _remove(app, name: str) -> None:
    _drawn(app).pop(name, None)
    try:
        app.server.scene.remove_by_name(name)
    except Exception:  # node not present
        pass


def _drawn(app) -> dict:
    """What each layer last sent to the scene (node name -> key of its inputs)."""
    d = getattr(app, "_drawn_keys", None)
    if d is None:
        d = app._drawn_keys = {}
    return d


def plane_dims(app) -> tuple:
    """The two states the map plane shows: ``app.view["dims"]`` (the projection selector of a set
    method's run), else the first two."""
    d = tuple(int(i) for i in (getattr(app, "view", None) or {}).get("dims") or (0, 1))
    n = app.system.n
    return d if len(d) == 2 and d[0] != d[1] and all(0 <= i < n for i in d) else (0, 1)


def plane_frame(app) -> G.Frame:
    return G.Frame(app.system, plane_dims(app))


def _unchanged(app, name: str, result, *params) -> bool:
    """True if ``name`` was last drawn from this very ``result`` object and equal ``params``
    (nothing to send); else records them as drawn (holding the result, so its id is not reused)."""
    d = _drawn(app)
    prev = d.get(name)
    if prev is not None and prev[0] is result and prev[1] == params:
        return True
    d[name] = (result, params)
    return False


# ----- static layers ----------------------------------------------------------------------------
def draw_system(app) -> None:
    """Layers of the current system: ground grid, axis ticks, map/spec, simulator bodies; fits the camera."""
    sc = app.server.scene
    sc.configure_default_lights(enabled=True, cast_shadow=False)
    sc.add_grid("/grid", width=2.0, height=2.0, cell_size=0.25, plane="xy", position=(0.0, 0.0, -0.004),
                cell_color=(215, 215, 215), section_color=(170, 170, 170))
    draw_axes(app)
    for lay in LAYERS:
        if lay.system:
            lay.draw(app)
    fit_camera(app)


def draw_axes(app) -> None:
    """Tick labels in state units along the map square's edges (x1 along x, x2 along y)."""
    _remove(app, "/axes")
    s = app.system
    names = [labelled(n, u) for n, u in zip(s.state_names, units(s)[0])] + ([""] if s.n < 2 else [])
    frame = plane_frame(app)
    _square_axes(app.server.scene, "/axes", frame.lo, frame.hi, [names[d] for d in frame.dims] + names[1:1])


def _square_axes(sc, prefix: str, lo, hi, names, offset=(0.0, 0.0, 0.0)) -> None:
    """Ticks of two variables over [lo, hi] (2,) along the front and left edges of the square
    [-1, 1]^2 + ``offset``; each axis' name past its far end (never on a tick); the second axis'
    tick at the corner shared with the first is left out."""
    ox, oy, oz = (float(v) for v in offset)
    for d, axis in ((0, "x"), (1, "y")):
        a, b = float(lo[d]), float(hi[d])
        for k, t in enumerate(G.nice_ticks(a, b, 5)):
            u = 2 * (t - 0.5 * (a + b)) / (b - a) if b > a else 0.0
            if axis == "y" and u < -0.9:  # would crowd the first axis' first tick at the corner
                continue
            pos = (ox + u, oy - 1.06, oz) if axis == "x" else (ox - 1.06, oy + u, oz)
            sc.add_label(f"{prefix}/{axis}{k}", text=f"{t:.3g}", position=pos,
                         anchor="top-center" if axis == "x" else "center-right", font_screen_scale=0.7)
        if names[d]:
            pos, anchor = (((ox + 1.16, oy - 1.06, oz), "top-left") if axis == "x"
                           else ((ox - 1.06, oy + 1.14, oz), "bottom-right"))
            sc.add_label(f"{prefix}/{axis}_name", text=names[d], position=pos, anchor=anchor)


def draw_map(app) -> None:
    """The specification as outlines on the plane (one node): safe set blue, target green,
    obstacles as the spec grows them (robot radius) red."""
    _remove(app, "/map")
    try:
        spec = app.current_spec()
    except Exception:  # no specification for this system: nothing to outline
        return
    segs, cols = G.spec_outlines(plane_frame(app), spec)
    if len(segs):
        segs[..., 2] = 0.01
        app.server.scene.add_line_segments("/map", points=segs, colors=cols, thickness=3.0,
                                           thickness_units="screen", visible=app.layers_visible["map"])


def _add_mesh(sc, name, mesh, position=(0.0, 0.0, 0.0), visible=True, wxyz=(1.0, 0.0, 0.0, 0.0)):
    """A trimesh as a viser simple mesh in its (first) face color, opacity from its alpha."""
    fc = np.asarray(mesh.visual.face_colors)
    rgba = fc[0] if fc.size else np.array([150, 150, 150, 255])
    opacity = None if rgba[3] >= 255 else float(rgba[3]) / 255.0
    return sc.add_mesh_simple(name, np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces),
                              color=tuple(int(c) for c in rgba[:3]), opacity=opacity, position=position,
                              wxyz=wxyz, visible=visible)


def variable_names_md(app) -> list:
    s = app.system
    names = list(s.state_names)
    return names if len(names) >= 2 else names + [""]


# ----- simulator bodies --------------------------------------------------------------------------
def draw_bodies(app) -> None:
    """The simulator's bodies from their URDFs (trimesh), posed by :func:`pose_bodies`.

    Pendulum: the rod under a frame at ``PENDULUM_PIVOT`` that rotates about +y by theta.
    TurtleBot: the arena's obstacles and the robot in the state frame (x, y mapped like the
    square, the same scale for z); the robot under a frame moved to (x, y, theta).
    """
    sc = app.server.scene
    _remove(app, "/bodies")
    app.body_frame = None
    app.body_model = None
    base = engine.base_system(app.system)
    vis = app.layers_visible["bodies"]
    if app.settings.simulator in MODEL_BODIES:
        draw_model_bodies(app)
        return
    bodies = engine.body_meshes(app)
    if not bodies:
        return
    if base.name == "pendulum":
        app.body_frame = sc.add_frame("/bodies/pendulum", show_axes=False, position=PENDULUM_PIVOT, visible=vis)
        for name, mesh, _pos in bodies:
            _add_mesh(sc, f"/bodies/pendulum/{name}", mesh)
        # under the rod's free end at rest (pivot - 1 m): above the pivot, the label ran into the rod
        # where the view from above draws the rod's upper end
        sc.add_label("/bodies/label", text="PyBullet pendulum (1 m rod)", anchor="top-center",
                     position=(PENDULUM_PIVOT[0], 0.0, PENDULUM_PIVOT[2] - PENDULUM_ROD - 0.1), visible=vis)
    elif base.name == "turtlebot":
        frame = G.Frame(base)
        k = 1.0 / float(frame.half.max())  # metres -> display units, the same for x, y and z
        app.body_frame = sc.add_frame("/bodies/robot", show_axes=False, visible=vis, scale=k)
        for name, mesh, _pos in bodies:
            m = mesh.copy()
            if name.startswith("robot_"):  # robot meshes about its own origin, moved by the frame
                _add_mesh(sc, f"/bodies/robot/{name}", m)
            else:  # arena coordinates = state coordinates
                m.apply_translation([-frame.center[0], -frame.center[1], 0.0])
                m.apply_scale(k)
                _add_mesh(sc, f"/bodies/{name}", m, visible=vis)
    pose_bodies(app, None)


def draw_model_bodies(app) -> None:
    """The robot file's geometry (simulator kind ``mujoco``: the MJCF's geoms; ``pybullet_urdf``: the
    URDF's visual shapes), one node per shape under ``/bodies/model``: a frame that stands the
    model beside the square (its bounding box at the resting pose from x = ``MODEL_LEFT``, centred
    in y, on the ground; metres, scaled to ``MODEL_SIZE``, a ground plane left out). :func:`pose_bodies`
    moves each shape to its pose for a state. Without MuJoCo (or with a file that does not load)
    a label says why nothing is drawn."""
    sc = app.server.scene
    vis = app.layers_visible["bodies"]
    bodies, note = _model(app)
    if bodies is None:
        if note:
            sc.add_label("/bodies/label", text=note, anchor="bottom-left", position=(MODEL_LEFT, 0.0, 0.1),
                         visible=vis, font_screen_scale=0.7)
        return
    _, lo, hi, k, shown = _model_placement(app, bodies)
    offset = np.array([MODEL_LEFT - k * lo[0], -0.5 * k * (lo[1] + hi[1]), -k * lo[2]])
    frame = sc.add_frame("/bodies/model", show_axes=False, position=tuple(offset), scale=k, visible=vis)
    handles = [_add_mesh(sc, f"/bodies/model/{i}_{name}", mesh, visible=bool(shown[i]) if i < shown.size else True)
               for i, (name, mesh) in enumerate(zip(bodies.names, bodies.meshes))]
    # in front of the model (seen from above, a label over it would hide it)
    sc.add_label("/bodies/label", text=f"{MODEL_BODIES[app.settings.simulator][0]}: {bodies.path.name}",
                 anchor="top-center", visible=vis,
                 position=(MODEL_LEFT + 0.5 * k * (hi[0] - lo[0]), -0.5 * k * (hi[1] - lo[1]) - 0.05, 0.0))
    app.body_frame = frame
    app.body_model = (bodies, handles)
    pose_bodies(app, None)


def _model(app) -> tuple:
    """The app's robot-file bodies (built once per file and system), and the note when there are none."""
    exp = getattr(app, "experiment", None)
    cfg = exp.simulator if exp is not None else None
    key = (engine.base_system(app.system).name, app.settings.simulator,
           None if cfg is None else (cfg.kind, str(cfg.options.get("model", cfg.options.get("urdf"))),
                                     cfg.options.get("model_sha256", cfg.options.get("urdf_sha256"))))
    cached = getattr(app, "_model_bodies_cache", None)
    if cached is None or cached[0] != key:
        cached = app._model_bodies_cache = (key, engine.model_bodies(app))
    return cached[1]


def _model_placement(app, bodies) -> tuple:
    """(rest state, lo (3,), hi (3,) [m] of the shown geoms at it, display scale k, shown (G,) bool).

    A geom is shown unless it stays fixed and is more than ``MODEL_FIXED_SPAN`` times larger than
    the geoms the state moves (a ground plane of 2 m under a 0.2 m arm would shrink the arm to a few
    pixels); the shown geoms are scaled to ``MODEL_SIZE`` display units (up or down)."""
    base = engine.base_system(app.system)
    x = _rest_state(app, base)
    placed = [m for _, m in bodies.meshes_at(x)]
    if not placed:
        return x, np.zeros(3), np.zeros(3), 1.0, np.zeros(0, bool)
    b = np.array([m.bounds for m in placed])                       # (G, 2, 3)
    moved = np.array([m.bounds for _, m in bodies.meshes_at(x + 0.3)])
    moves = np.abs(moved - b).max(axis=(1, 2)) > 1e-9
    ext = np.ptp(b, axis=1).max(axis=1)
    span = float(np.ptp(np.concatenate(b[moves]), axis=0).max()) if moves.any() else float(ext.max())
    shown = moves | (ext <= MODEL_FIXED_SPAN * span)
    lo, hi = b[shown, 0].min(axis=0), b[shown, 1].max(axis=0)
    e = float(np.max(hi - lo))
    return x, lo, hi, MODEL_SIZE / e if e > 0 else 1.0, shown


def _rest_state(app, base) -> np.ndarray:
    """The rollouts' initial state: the settings', the map's, else the middle of X."""
    x = app.settings.x0 if app.settings.x0 is not None else \
        app.arena.x0(base) if getattr(app, "arena", None) is not None else 0.5 * (base.x_lo + base.x_hi)
    return np.asarray(x, dtype=float)


def pose_bodies(app, x) -> None:
    """Move the bodies to state ``x`` (n,) (None: the experiment's or a resting pose)."""
    fr = getattr(app, "body_frame", None)
    if fr is None:
        return
    base = engine.base_system(app.system)
    x = _rest_state(app, base) if x is None else np.asarray(x, dtype=float)
    mj = getattr(app, "body_model", None)
    if mj is not None:
        bodies, handles = mj
        pos, wxyz = bodies.poses(x)
        for h, p, q in zip(handles, pos, wxyz):
            h.position, h.wxyz = tuple(float(v) for v in p), tuple(float(v) for v in q)
        return
    if base.name == "pendulum":
        th = float(x[0])
        fr.wxyz = (np.cos(th / 2), 0.0, np.sin(th / 2), 0.0)  # the hinge turns about +y
    elif base.name == "turtlebot":
        p = G.Frame(base).xy(x[None])[0]
        th = float(x[2]) if x.size > 2 else 0.0
        fr.position = (float(p[0]), float(p[1]), 0.0)
        fr.wxyz = (np.cos(th / 2), 0.0, 0.0, np.sin(th / 2))


# ----- gamma surface and data gaps -------------------------------------------------------------
def draw_gamma(app) -> dict:
    """Gamma surface of the selected dimension over the selected variables, and the data gaps.

    Heights and colors z = gamma / top, ``top`` one scale per data set and slice for the session
    (it only grows; the legend and a vertical axis give it). The surface is sent only when gamma
    varies by at least ``GAMMA_VISIBLE`` of its largest value on the slice (or the View tab asks
    for flat ones too, ``view["flat_gamma"]``); the data gaps only with the surface (or before any
    certificate). Returns dict(vertices, faces, points, range, top, margin, shown) ("range"/"top"
    only with a certificate; "shown": the surface was sent).
    """
    sc = app.server.scene
    v = app.view
    cert = app.results.get("certify")
    data = app.results.get("collect")
    out = {"vertices": np.zeros((0, 3)), "faces": np.zeros((0, 3), np.uint32), "points": np.zeros((0, 3))}
    gamma = engine.gamma_function(cert) if cert is not None else None
    if gamma is None and data is None:
        _remove(app, "/gamma")
        _remove(app, "/zaxis")
        app.legend = None
        return out
    s = app.system
    fixed = v["fixed"] if v["fixed"] is not None else list(G.variable_ranges(s).mean(axis=1))
    surf = G.gamma_surface(s, gamma, v["dim"], v["a"], v["b"], fixed, res=SURFACE_RES) if gamma is not None else None
    pts = G.data_points(data, s, v["dim"], v["a"], v["b"], fixed, gamma=gamma, max_points=20000) \
        if data is not None else None
    # one height and color scale per (data, slice) for the whole session: it only grows, so a tighter
    # certificate's surface stands lower and darker than a looser one's instead of being stretched
    # to the same picture (the legend prints the scale and the slice's own range)
    top_now = max([float(np.max(surf["values"])) if surf is not None else 0.0,
                   float(np.max(pts["gap"])) if pts is not None and pts["gap"].size else 0.0])
    tops = v.setdefault("tops", {})
    key = (id(data), s.name, v["dim"], v["a"], v["b"])
    top = max(tops.get(key, 0.0), top_now if np.isfinite(top_now) else 0.0)
    top = top if top > 0 else 1.0
    tops[key] = top
    v["zscale"] = z = 1.0 / top
    su = units(s)[0][v["dim"]]
    legend = {"dim": s.state_names[v["dim"]], "top": top, "unit": f"{su}/step" if su else ""}
    shown = False
    if surf is not None:
        verts = surf["vertices"].copy()
        verts[:, 2] *= z
        vals = surf["values"]
        lo, hi = float(vals.min()), float(vals.max())
        constant = hi - lo <= 1e-9 * max(abs(hi), 1e-300)
        varies = hi > 0 and (hi - lo) / hi >= GAMMA_VISIBLE
        # only a gamma that varies enough to see is a surface (translucent, unlit vertex colors on the
        # session scale, the legend's colors exactly); a nearly flat one would be a sheet over the map
        # that says no more than its value, which the legend prints
        shown = app.layers_visible["gamma"] and (varies or bool(v.get("flat_gamma")))
        if shown:
            sc.add_glb("/gamma/surface", G.glb(verts, G.colormap(vals / top), surf["faces"], unlit=True,
                                               opacity=SURFACE_OPACITY),
                       cast_shadow=False, receive_shadow=False, position=SURFACE_OFFSET)
            rng = G.variable_ranges(s)
            vnames, vunits = G.variable_names(s), list(units(s)[0]) + list(units(s)[1])
            _remove(app, "/gamma/axes")
            _square_axes(sc, "/gamma/axes", rng[[v["a"], v["b"]], 0], rng[[v["a"], v["b"]], 1],
                         [labelled(vnames[j], vunits[j]) for j in (v["a"], v["b"])], SURFACE_OFFSET)
        else:
            _remove(app, "/gamma/surface")
            _remove(app, "/gamma/axes")
        out["vertices"], out["faces"] = verts, surf["faces"]
        out["range"] = legend["range"] = (lo, hi)
        out["constant"] = legend["constant"] = constant
        legend["varies"] = varies
        out["top"] = top
    else:
        _remove(app, "/gamma/surface")
    out["shown"] = legend["shown"] = shown
    # the data gaps are heights on the surface's scale: drawn with the surface (or before any certificate),
    # always over the surface's square behind the map, with its axes: raised points drawn over the map
    # itself would spill past the map's square in the view from above and hide the winning domain
    bare = gamma is None and pts is not None and pts["points"].shape[0] and app.layers_visible["data"]
    if bare:
        rng = G.variable_ranges(s)
        vnames, vunits = G.variable_names(s), list(units(s)[0]) + list(units(s)[1])
        _remove(app, "/gamma/axes")
        _square_axes(sc, "/gamma/axes", rng[[v["a"], v["b"]], 0], rng[[v["a"], v["b"]], 1],
                     [labelled(vnames[j], vunits[j]) for j in (v["a"], v["b"])], SURFACE_OFFSET)
    elif gamma is None:
        _remove(app, "/gamma/axes")
    if pts is not None and pts["points"].shape[0] and app.layers_visible["data"] and (shown or gamma is None):
        p = pts["points"].copy()
        p[:, 2] *= z
        if gamma is not None:
            margin = pts["margin"]
            mscale = float(np.quantile(margin[margin >= 0], 0.95)) if np.any(margin >= 0) else 1.0
            colors = G.margin_colors(margin, mscale)
            out["margin"] = margin
            legend["margin_scale"] = mscale
            legend["uncovered"] = int(np.count_nonzero(margin < 0))
        else:
            colors = pts["colors"]
        sc.add_point_cloud("/gamma/data", points=p, colors=colors, point_size=0.007, point_shape="circle",
                           position=SURFACE_OFFSET)
        out["points"] = p
        legend["points"] = int(p.shape[0])
        app.last_data_covered = pts["covered"]
    else:
        _remove(app, "/gamma/data")
    legend["elevated"] = elevated = bool(shown or bare)  # something stands on the surface's square
    if elevated:
        _draw_zaxis(app, top, legend["dim"] + (f" [{legend['unit']}]" if legend["unit"] else ""))
    else:
        _remove(app, "/zaxis")
    was = (app.legend or {}).get("elevated")
    app.legend = legend
    if was is not None and was != elevated:  # the scene's height changed: refit the camera
        fit_camera(app)
    return out


def _draw_zaxis(app, top: float, name: str) -> None:
    """A vertical axis at the surface square's far corner with gamma ticks (state units of ``name``)."""
    sc = app.server.scene
    _remove(app, "/zaxis")
    x, y = 1.0 + SURFACE_OFFSET[0], 1.0 + SURFACE_OFFSET[1]
    ticks = G.nice_ticks(0.0, top, 4)
    segs = [[[x, y, 0.0], [x, y, 1.0]]] + [[[x, y, t / top], [x + 0.04, y, t / top]] for t in ticks]
    sc.add_line_segments("/zaxis/line", points=np.asarray(segs, np.float32), colors=(60, 60, 60), thickness=2.0,
                         thickness_units="screen")
    for k, t in enumerate(ticks):
        sc.add_label(f"/zaxis/t{k}", text=f"{t:.3g}", position=(x + 0.06, y, t / top), anchor="center-left",
                     font_screen_scale=0.7)
    sc.add_label("/zaxis/name", text=f"gamma_{name}", position=(x, y, 1.08), anchor="bottom-center")


# ----- winning domain --------------------------------------------------------------------------
def draw_winning(app) -> int:
    """The winning domain as ONE opaque image just below the surface (see geometry.winning_map).

    Returns the number of winning (x1, x2) columns drawn (target columns not counted)."""
    res = app.results.get("synthesize")
    if res is None or res.controller.size_with_target == 0 or not app.layers_visible["winning"]:
        _remove(app, "/winning")
        app.winning_counts = None
        return 0
    if _unchanged(app, "/winning", res):
        return app.winning_counts["winning"]
    blocked, allowed = engine.cell_labels(res)
    wm = G.winning_map(res.controller, blocked, allowed)
    frame = G.Frame(app.system)
    a, b = frame.xy(wm["lo"][None])[0], frame.xy(wm["hi"][None])[0]
    app.server.scene.add_image("/winning", wm["image"], render_width=float(b[0] - a[0]),
                               render_height=float(b[1] - a[1]), format="png",
                               position=(float(a[0] + b[0]) / 2, float(a[1] + b[1]) / 2, 0.002), wxyz=G.IMAGE_UP,
                               cast_shadow=False, receive_shadow=False)
    app.winning_counts = {**wm["counts"], "max_steps": wm["max_steps"], "reduced_dims": wm["reduced_dims"],
                          "kind": res.controller.kind}
    return wm["counts"]["winning"]


# ----- proved sets -----------------------------------------------------------------------------
SET_COLORS = {"deterministic": (31, 119, 180), "stochastic": (255, 127, 14), "nominal": (44, 160, 44)}  # the figures'
#: the loaded method's sets by role: color and line width [px]
ROLE_STYLE = {"tube": ((230, 110, 0), 1.5), "noise_tube": ((150, 150, 150), 1.0), "terminal": ((120, 40, 0), 3.0),
              "target": ((20, 150, 60), 2.5), "ellipsoid": (None, 3.0)}
#: at most this many boxes of a tube drawn (every k-th period, the last always)
MAX_BOXES = 60


def _statements(app) -> list:
    """(method, Statement) of every method of the loaded run with a proved set (the nominal model last)."""
    run = getattr(app, "run", None)
    if run is None:
        return []
    out = [(m, r.statement) for m, r in run.methods.items()]
    if getattr(run, "nominal", None) is not None:
        out.append(("nominal", run.nominal.statement))
    return [(m, st) for m, st in out if st is not None and st.proved and any(s.kind != "cells" for s in st.sets)]


def draw_invariant_sets(app) -> list:
    """The sets each method of a loaded set-method run proved, in its own words (its
    :class:`~simgap.synthesis.statement.Statement`), projected onto the map plane's two states: the
    loaded method's every set (a tube's boxes along the plan, its noise tube, the terminal and target
    boxes; an ellipsoid's shadow: every (x1, x2) of a point of E, not its slice), the other methods'
    first set in their color. Returns [(method, role, label, color, half-widths (2,) of the last
    outline drawn)]."""
    stmts = _statements(app) if app.layers_visible.get("invariant", True) and app.system.n >= 2 else []
    dims = plane_dims(app)
    key = (tuple(m for m, _ in stmts), getattr(app, "run_method", None), dims)
    run = getattr(app, "run", None)
    if getattr(app, "invariant_drawn", None) is not None and _unchanged(app, "/invariant", run, key):
        return app.invariant_drawn
    _remove(app, "/invariant")
    _unchanged(app, "/invariant", run, key)  # recorded again (_remove forgets it)
    drawn = []
    frame = plane_frame(app)
    sc = app.server.scene
    for m, st in stmts:
        mine = m == getattr(app, "run_method", None)
        for k, ds in enumerate(st.sets if mine else st.sets[:1]):
            if ds.kind == "cells":
                continue
            color, width = ROLE_STYLE.get(ds.role, (None, 2.0))
            color = color if mine and color is not None else SET_COLORS.get(m, G.GREEN)
            every = max(1, -(-len(ds.centers) // MAX_BOXES)) if ds.kind == "boxes" else 1
            outl = ds.outlines(dims, every)
            P = np.concatenate([G.polyline_segments(frame, _lift(o, dims, app.system.n)) for o in outl])
            P[..., 2] = 0.009 + 0.0005 * k
            sc.add_line_segments(f"/invariant/{m}/{ds.role}", points=P, colors=color, thickness=width,
                                 thickness_units="screen")
            drawn.append((m, ds.role, ds.label, color, 0.5 * np.ptp(outl[-1], axis=0)))
    app.invariant_drawn = drawn
    return drawn


def _lift(outline: np.ndarray, dims, n: int) -> np.ndarray:
    """A (k, 2) outline on states ``dims`` as (k, n) states (the others 0) for the frame's map."""
    x = np.zeros((len(outline), n))
    x[:, list(dims)] = outline
    return x


# ----- rollouts ---------------------------------------------------------------------------------
def draw_rollouts(app) -> int:
    """A subset of the rollouts (every failure first, up to ``app.view["n_draw"]``) as ONE
    image on the plane (every step), failures red; the mean (or mean-map) and nominal
    trajectories bold. Returns the number of trajectory segments in the image."""
    res = app.results.get("rollout")
    if res is None or not app.layers_visible["rollouts"]:
        _remove(app, "/rollouts")
        app.rollout_drawn = None
        return 0
    if _unchanged(app, "/rollouts", res, int(app.view.get("n_draw", N_DRAW)), plane_dims(app)):
        show_time(app, app.view.get("t", None))
        return app.rollout_drawn["segments"]
    frame = plane_frame(app)
    traj, failed, mean, nominal = engine.rollout_arrays(res)
    idx = G.rollout_subset(failed, int(app.view.get("n_draw", N_DRAW)))
    sc = app.server.scene
    if idx.size:  # one image on the plane (see geometry.rollout_image), every step of every drawn rollout
        sc.add_image("/rollouts/all", G.rollout_image(frame, traj[idx], failed[idx]), render_width=2.0,
                     render_height=2.0, format="png", position=(0.0, 0.0, 0.004), wxyz=G.IMAGE_UP, cast_shadow=False,
                     receive_shadow=False)
        nseg = int(idx.size) * (traj.shape[1] - 1)
    else:
        _remove(app, "/rollouts/all")
        nseg = 0
    # thin, and the mean and nominal dashed, so that the rollouts' density shows beside and between them
    for name, path, color, width, dash in (
            ("mean_map", engine.mean_map_trajectory(res), (200, 40, 200), 1.5, None),
            ("mean", mean, G.YELLOW, 2.5, (0.025, 0.045, 0.0)), ("nominal", nominal, (20, 20, 20), 1.5,
                                                                  (0.025, 0.045, 0.035))):
        if path is None:
            _remove(app, f"/rollouts/{name}")
            continue
        P = G.polyline_segments(frame, path) if dash is None else G.dashed_segments(frame, path, *dash)
        P[..., 2] = 0.008
        sc.add_line_segments(f"/rollouts/{name}", points=P, colors=color, thickness=width,
                             thickness_units="screen")
    app.rollout_drawn = {"drawn": int(idx.size), "total": int(failed.size), "failed": int(failed.sum()),
                         "failed_drawn": int(failed[idx].sum()), "segments": nseg}
    show_time(app, app.view.get("t", None))
    return nseg


def show_time(app, t) -> None:
    """Mark the drawn rollouts' states at step ``t`` (None: hide) and pose the bodies along the
    chosen rollout (``app.view["rollout_index"]``)."""
    res = app.results.get("rollout")
    if res is None or t is None:
        _remove(app, "/rollouts/now")
        pose_bodies(app, None)
        return
    traj, failed, _, _ = engine.rollout_arrays(res)
    t = int(np.clip(t, 0, traj.shape[1] - 1))
    idx = G.rollout_subset(failed, int(app.view.get("n_draw", N_DRAW)))
    frame = plane_frame(app)
    P = frame.xy(traj[idx, t]).astype(np.float32)
    P[:, 2] = 0.012
    col = np.where(failed[idx, None], np.array(G.RED, np.uint8), np.array((30, 60, 160), np.uint8))
    app.server.scene.add_point_cloud("/rollouts/now", points=P, colors=col, point_size=0.025,
                                     point_shape="circle", visible=app.layers_visible["rollouts"])
    r = int(np.clip(app.view.get("rollout_index", 0), 0, traj.shape[0] - 1))
    pose_bodies(app, traj[r, t])


# ----- camera ------------------------------------------------------------------------------------
def scene_bounds(app) -> tuple:
    """(lo (3,), hi (3,)) of everything drawn: the square, the surface's [0, 1] heights, the
    pendulum beside it, the refinement plane."""
    surface = bool((getattr(app, "legend", None) or {}).get("elevated"))
    lo, hi = np.array([-1.1, -1.1, 0.0]), np.array([1.1, 1.1, 0.1])
    if surface:  # the surface's square behind the map, heights up to 1 and the axis name above
        hi[1], hi[2] = SURFACE_OFFSET[1] + 1.1, 1.15
    base = engine.base_system(app.system)
    if base.name == "pendulum" and app.layers_visible.get("bodies", True):
        hi[0] = max(hi[0], PENDULUM_PIVOT[0] + 0.2)
        hi[2] = max(hi[2], PENDULUM_PIVOT[2] + 0.1)
    mj = getattr(app, "body_model", None)
    if mj is not None and app.layers_visible.get("bodies", True):
        _, blo, bhi, k, _ = _model_placement(app, mj[0])
        hi[0] = max(hi[0], MODEL_LEFT + k * (bhi[0] - blo[0]))
        hi[2] = max(hi[2], k * (bhi[2] - blo[2]) + 0.2)
    if app.results.get("refine") is not None:  # the residual plane: points at z in [-0.3, 1.3], label at 1.45
        lo[1] = min(lo[1], RESIDUAL_PLANE_Y)
        lo[2] = min(lo[2], RESIDUAL_Z[0])
        hi[2] = max(hi[2], RESIDUAL_Z[1])
    return lo, hi


def fit_camera(app, clients=None) -> None:
    """Point every client's camera (and the initial camera) at the whole scene from the front-left,
    above: look at the centre of the bounds, at a distance that fits their diagonal; a client whose
    window size is known (``app.windows``) gets the scene centred in the part the panel leaves."""
    import contextlib
    look, pos = window_camera(app, None)
    app.server.initial_camera.position = tuple(pos)
    app.server.initial_camera.look_at = tuple(look)
    app.server.initial_camera.up = (0.0, 0.0, 1.0)
    # under the app's fit lock: no window size recorded meanwhile is fitted over with the default
    with getattr(app, "fit_lock", None) or contextlib.nullcontext():
        windows = getattr(app, "windows", {})
        for client in (list(app.server.get_clients().values()) if clients is None else clients):
            cl_look, cl_pos = window_camera(app, windows.get(getattr(client, "client_id", None)))
            try:
                with client.atomic():
                    client.camera.up_direction = (0.0, 0.0, 1.0)
                    client.camera.position = tuple(cl_pos)
                    client.camera.look_at = tuple(cl_look)
            except Exception:  # a client that just went away
                pass


def window_camera(app, win=None) -> tuple:
    """(look_at, position) of the camera :func:`fit_camera` sends to a window ``win`` ({"size": (w,
    h), "panel": px}, as ``app.windows`` records it), or the default one (``win`` None)."""
    lo, hi = scene_bounds(app)
    c = 0.5 * (lo + hi)
    r = 0.5 * float(np.linalg.norm(hi - lo))
    surface = bool((getattr(app, "legend", None) or {}).get("elevated"))
    d = np.array([-0.3, -1.0, 1.0]) if surface else np.array([-0.08, -0.4, 1.0])  # the flat map: from high above
    d /= np.linalg.norm(d)
    right = np.cross(-d, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    # the flat map: close, but whole (a model beside the square widens the scene: 60 % of its width
    # must fit in half the free part's width at the look-at distance)
    dist = r * 1.75 if surface else max(r * 1.12, 2.4, 0.6 * float(hi[0] - lo[0]) / (np.tan(_FOV / 2) * _FREE_ASPECT))
    if win is not None:  # this window's size and panel: the scene centred in the part the panel leaves
        return _fit_to_window(c, d, right, dist, win["size"], win["panel"], closer=not surface)
    look = c + 0.3 * r * right  # the control panel covers the canvas' right third
    return look, look + d * dist


#: the free canvas' aspect (width left of the panel / height) the distances of fit_camera were chosen
#: for: 1280 x 800 with the panel covering 30 % of the width
_FREE_ASPECT = 1.6 * 0.7
_FOV = np.deg2rad(75.0)  # viser's default vertical field of view


def _fit_to_window(c, d, right, dist: float, size, panel: float, closer: bool = True) -> tuple:
    """(look_at, position) that centre the scene in the canvas left of the panel: the camera turns
    right by the panel's share of the half width at the look-at distance; the distance grows when the
    free part is narrower than the one the distances were chosen for and, with ``closer`` (the flat
    map seen from above, not the taller scene with the surface's square, which already fills the
    height), shrinks by at most 15 % when it is wider, so a wide window shows a larger map."""
    w, h = float(size[0]), float(max(size[1], 1))
    share = min(max(panel / max(w, 1.0), 0.0), 0.6)
    free = (w / h) * (1.0 - share)
    dist = dist * float(np.clip(_FREE_ASPECT / free, 0.85 if closer else 1.0, 2.0))
    half_width = dist * np.tan(_FOV / 2.0) * (w / h)
    look = c + share * half_width * right
    return look, look + d * dist


# ----- refinement residuals ----------------------------------------------------------------------
RESIDUAL_PLANE_Y = -1.6
RESIDUAL_Z = (-0.35, 1.55)  # heights the residual plane's points and label can take (scene_bounds)


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
    if _unchanged(app, "/refine", res, state, var, max_points):
        return app._drawn_residuals
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
    app._drawn_residuals = int(idx.size)
    fit_camera(app)  # the plane lies in front of the square: bring it into the frame
    return int(idx.size)


def draw_results(app) -> None:
    """Every result layer, in registration order (the gamma layer also draws the data gaps)."""
    for lay in LAYERS:
        if not lay.system and lay.key != "data":
            lay.draw(app)


for _layer in (Layer("winning", "Winning domain", ("/winning",), draw_winning),
               Layer("map", "Map / spec", ("/map",), draw_map, system=True),
               Layer("invariant", "Proved sets", ("/invariant",), draw_invariant_sets),
               Layer("rollouts", "Rollouts", ("/rollouts",), draw_rollouts),
               Layer("gamma", "Gamma surface", ("/gamma/surface", "/gamma/axes", "/zaxis"), draw_gamma),
               Layer("data", "Data gaps", ("/gamma/data",), draw_gamma),
               Layer("bodies", "Simulator bodies", ("/bodies",), draw_bodies, system=True),
               Layer("refine", None, ("/refine",), draw_residuals)):
    register_layer(_layer)
LAYER_NODES = {lay.key: lay.nodes for lay in LAYERS}
