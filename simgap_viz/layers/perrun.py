"""The per-run layer: the certified success probability p_cert as a top-down map over the state
space, and the validated initial states as markers colored by their empirical success rate p_emp.

Both use one color scale for probabilities in [0, 1] (:func:`pcolormap`: dark red 0 -> yellow
0.5 -> dark green 1), so a marker that matches the map around it is a state where the measured
rate is what the map certifies, and a marker greener than its cell shows the bound's slack.
The map is ONE textured plane over the interval MDP's grid (like the winning-domain map, just
above it); with more than two state dimensions each (x1, x2) column shows the largest p_cert over
the other dimensions (the best heading, say), stated in the legend. Values come from the engine's
files (:mod:`simgap_viz.results_perrun`); nothing here computes a probability.

Node names: ``/perrun/map``, ``/perrun/markers`` (+ ``/perrun/rings`` outlines, ``/perrun/labels/<i>``).
"""

from __future__ import annotations

import numpy as np

from . import geometry as G

# ColorBrewer RdYlGn, 5 stops: 0 (dark red) .. 0.5 (pale yellow) .. 1 (dark green)
P_STOPS = np.array([[165, 0, 38], [244, 109, 67], [254, 224, 139], [102, 189, 99], [0, 104, 55]], float)
MAP_Z, MARKER_Z = 0.003, 0.05  # just above the winning map (0.002); markers above the rollouts (<= 0.012)
RING = (20, 20, 20)
MARKER_SIZE, RING_SIZE = 0.05, 0.07  # display units (the square is [-1, 1]^2)


def pcolormap(p) -> np.ndarray:
    """Probabilities (...) in [0, 1] -> (..., 3) uint8 colors on the :data:`P_STOPS` scale."""
    t = np.clip(np.nan_to_num(np.asarray(p, float)), 0.0, 1.0) * (len(P_STOPS) - 1)
    i = np.minimum(t.astype(int), len(P_STOPS) - 2)
    f = (t - i)[..., None]
    return ((1 - f) * P_STOPS[i] + f * P_STOPS[i + 1]).astype(np.uint8)


def pcolorbar(width: int = 256, height: int = 12) -> np.ndarray:
    """(height, width, 3) uint8 image of :func:`pcolormap` from 0 (left) to 1 (right)."""
    return np.repeat(pcolormap(np.linspace(0.0, 1.0, width))[None], height, axis=0)


def pcert_map(controller, max_pixels: int = 1024) -> dict:
    """p_cert of a PerRunController as a top-down image over its grid's first two dimensions.

    Returns dict(image (H, W, 3) uint8, row 0 at the top (+x2), p (n1, n2) the value per (x1, x2)
    column (the largest over further dimensions), lo (2,), hi (2,) the image's extent in state
    units, reduced_dims)."""
    g = controller.grid
    shape = tuple(g.shape) + ((1,) if g.n == 1 else ())
    p = np.asarray(controller.p_cert, float).reshape(shape[0], shape[1], -1).max(axis=2)
    k = max(1, min(64, max_pixels // max(shape[0], shape[1])))  # crisp cell edges under texture filtering
    image = np.repeat(np.repeat(pcolormap(p).transpose(1, 0, 2)[::-1], k, axis=0), k, axis=1)
    lo, hi = g.domain_lo[:2], g.domain_hi[:2]
    if g.n == 1:
        lo, hi = np.array([lo[0], -1.0]), np.array([hi[0], 1.0])
    return {"image": image, "p": p, "lo": lo, "hi": hi, "reduced_dims": max(g.n - 2, 0)}


def markers(frame: G.Frame, states) -> dict:
    """Display points of one controller's validated initial states (a results_perrun.ControllerStates),
    colored by p_emp. Returns dict(points (S, 3) float32, colors (S, 3) uint8)."""
    P = frame.xy(states.x0).astype(np.float32)
    P[:, 2] = MARKER_Z
    return {"points": P, "colors": pcolormap(states.p_emp)}


def _remove(app, name: str) -> None:
    try:
        app.server.scene.remove_by_name(name)
    except Exception:  # node not present
        pass


def _same_states(a, b) -> bool:
    return a.n == b.n and np.array_equal(a.x_lo, b.x_lo) and np.array_equal(a.x_hi, b.x_hi)


def draw(app) -> dict:
    """Draw (or remove) the p_cert map and the markers of ``app.perrun_view["controller"]``.

    Returns what was sent: dict(map=pcert_map(...) or None, markers=markers(...) or None)."""
    pr = getattr(app.run, "per_run", None) if app.run is not None else None
    out = {"map": None, "markers": None}
    if pr is None or not _same_states(app.system, app.run.experiment.system):  # another system is shown
        _remove(app, "/perrun")
        return out
    v = app.perrun_view
    sc = app.server.scene
    frame = G.Frame(app.system)
    m = pcert_map(pr.controller)
    a, b = frame.xy(m["lo"][None])[0], frame.xy(m["hi"][None])[0]
    sc.add_image("/perrun/map", m["image"], render_width=float(b[0] - a[0]), render_height=float(b[1] - a[1]),
                 format="png", position=(float(a[0] + b[0]) / 2, float(a[1] + b[1]) / 2, MAP_Z),
                 wxyz=G.IMAGE_UP, cast_shadow=False, receive_shadow=False, visible=v["map"])
    out["map"] = m
    _remove(app, "/perrun/labels")
    st = pr.controllers.get(v["controller"])
    if st is None:
        _remove(app, "/perrun/markers")
        _remove(app, "/perrun/rings")
        return out
    mk = markers(frame, st)
    # unlit sprites in exact colors (lit meshes would wash the scale out), a dark ring under each;
    # raised so that the camera-facing sprites do not sink into the map at shallow view angles
    rings = mk["points"].copy()
    rings[:, 2] -= 0.002
    sc.add_point_cloud("/perrun/rings", points=rings, colors=RING, point_size=RING_SIZE, point_shape="circle",
                       point_shading="flat", visible=v["markers"])
    sc.add_point_cloud("/perrun/markers", points=mk["points"], colors=mk["colors"], point_size=MARKER_SIZE,
                       point_shape="circle", point_shading="flat", visible=v["markers"])
    for i, p in enumerate(mk["points"]):  # numbers match the rows of the Per run tab's table
        sc.add_label(f"/perrun/labels/{i}", text=str(i), position=(float(p[0]) + 0.04, float(p[1]) + 0.04, MARKER_Z),
                     anchor="bottom-left", font_screen_scale=0.6, visible=v["markers"])
    out["markers"] = mk
    return out
