"""Paper-style figures of a finished run (``simgap plot RUN``), drawn with matplotlib.

Every figure is read from the run's files (:func:`simgap_viz.results.load_run`, or stage-by-stage
outputs, :func:`simgap_viz.results.load_stages`); nothing is
recomputed but gamma on a line (the certificate's own function) and the specification's boxes.
Each is written as PNG and PDF, atomically (temporary name, then renamed):

* ``trajectories`` -- the closed-loop rollouts of each method over the first two states (the
  pendulum's (theta, omega) plane, the TurtleBot's arena with its obstacles and target), thin
  translucent lines, failures red, the mean map m+ = E fhat(m, u(m)) (what the guarantee is
  about) bold, the rollout average dashed, the safe set outlined (paper Figs. 1 and 3);
* ``states_time`` -- every state over time, per method: the rollouts thin, the mean map bold
  (for the pendulum the omega row is the paper's Fig. 5, deterministic vs stochastic);
* ``gamma_slices`` -- gamma_i of each method along each state variable, the others at the
  centre of X and the input at the middle of U, with the data gaps near that line;
* ``invariant_sets`` -- for an invariant-set run (``[synthesis] method = "invariant_set"``): the
  PROJECTION of each proved ellipsoid E onto pairs of states (the shadow of E, the set of (x_a, x_b)
  of its points: the ellipse of the block of P^-1, not the slice through x*), each method's rollouts
  over the same pair thin and translucent, the mean map bold, x0 and the safe set; a method whose
  proof failed is named with its margin;
* ``p_cert`` -- for a run with ``[perrun]``: the certified per-run success probability per
  interval-MDP cell with the validated initial states colored by p_emp.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from simgap.errors import SimgapError
from simgap.systems import labelled, units

METHOD_STYLE = {"deterministic": "tab:blue", "stochastic": "tab:orange",  # one color per method, every figure
                "nominal": "tab:green"}  # an invariant-set run's nominal model (no gap)
MEAN_MAP, AVERAGE = dict(color="k", lw=1.0), dict(color="0.35", lw=0.8, ls=(0, (3, 2)))
FORMATS = ("png", "pdf")
#: every figure simgap plot writes (stems; one file per format)
FIGURES = ("trajectories", "states_time", "gamma_slices", "invariant_sets", "p_cert")
#: the figures folder's own list of what simgap plot wrote there, with sha256 (what it may replace)
FIGURE_LIST = ".simgap-figures.json"
# figure sizes [in] and fonts [pt]: "paper" fits a two-column paper's text width (7 in; a panel per
# method is one column wide), "slide" a 16:9 slide
STYLES = {"paper": {"width": 7.0, "row": 2.4, "font": 8, "small": 6.5, "dpi": 300},
          "slide": {"width": 11.0, "row": 3.6, "font": 14, "small": 11, "dpi": 150}}


def _plt():
    import matplotlib
    matplotlib.use("Agg")  # files only: no display needed
    import matplotlib.pyplot as plt
    return plt


def _rc(style: str) -> dict:
    st = STYLES[style]
    return {"font.size": st["font"], "axes.titlesize": st["font"], "axes.labelsize": st["font"],
            "xtick.labelsize": st["small"], "ytick.labelsize": st["small"], "legend.fontsize": st["small"],
            "figure.titlesize": st["font"], "pdf.fonttype": 42, "lines.linewidth": 1.0}


def _styled(fn):
    """Draw ``fn``'s figure with its ``style``'s fonts (matplotlib resolves text sizes when an artist is made)."""
    import functools

    @functools.wraps(fn)
    def wrapper(*args, style: str = "paper", **kw):
        with _plt().rc_context(_rc(style)):
            return fn(*args, style=style, **kw)
    return wrapper


def _figure(style: str, rows: int, cols: int, height_rows: float | None = None, **kw):
    """A figure of the style's width with ``rows`` x ``cols`` axes (constrained layout, legend below)."""
    st = STYLES[style]
    fig, axes = _plt().subplots(rows, cols, figsize=(st["width"], st["row"] * (height_rows or rows) + 0.5),
                                squeeze=False, layout="constrained", **kw)
    fig._simgap_style = style
    return fig, axes


def save(fig, out_dir: Path, name: str) -> list:
    """Write ``name``.png and .pdf into ``out_dir`` atomically; return the paths. Rasterized artists
    (the dense rollouts) are embedded as images in the PDF at the style's dpi, the rest stays vector."""
    paths = []
    style = getattr(fig, "_simgap_style", "paper")
    with _plt().rc_context(_rc(style)):
        # lay the figure out and measure its tight box once for every format (each savefig with
        # bbox_inches="tight" would lay it out twice: a draw to measure, then the drawing)
        fig.set_dpi(STYLES[style]["dpi"])
        fig.draw_without_rendering()
        bbox = fig.get_tightbbox().padded(0.02)
        fig.set_layout_engine("none")
        _rasterize_runs(fig, STYLES[style]["dpi"])  # the runs as one image per axes, at its final size
        for ext in FORMATS:
            final = out_dir / f"{name}.{ext}"
            tmp = out_dir / f".{name}.{os.getpid()}.tmp.{ext}"
            try:
                _pending(out_dir, final.name, tmp.name)  # listed before it exists: a kill leaves nothing unowned
                fig.savefig(tmp, dpi=STYLES[style]["dpi"], bbox_inches=bbox)
                _pending(out_dir, final.name, tmp.name, tmp)
                tmp.replace(final)
                _list_figures(out_dir, [final])
            finally:
                tmp.unlink(missing_ok=True)
            paths.append(final)
    _plt().close(fig)
    return paths


def text_overlaps(fig) -> list:
    """Pairs of visible, non-empty texts of ``fig`` (tick labels, axis labels, titles, legend and figure
    texts) whose drawn extents intersect, as (text, text) strings; [] for a figure that reads cleanly."""
    fig.canvas.draw()
    r = fig.canvas.get_renderer()
    texts = list(fig.texts)
    for ax in fig.axes:
        texts += [ax.xaxis.label, ax.yaxis.label, ax.title, ax._left_title, ax._right_title, *ax.texts,
                  ax.xaxis.get_offset_text(), ax.yaxis.get_offset_text()]
        for axis in (ax.xaxis, ax.yaxis):  # the labels of the ticks drawn (inside the view interval)
            lo, hi = sorted(axis.get_view_interval())
            eps = 1e-9 * max(abs(hi - lo), 1e-300)
            texts += [t.label1 for t in axis.get_major_ticks() if lo - eps <= t.get_loc() <= hi + eps]
        if ax.get_legend() is not None:
            texts += ax.get_legend().get_texts()
    for lg in fig.legends:
        texts += lg.get_texts()
    boxes = [(t.get_text(), t.get_window_extent(r)) for t in texts
             if t.get_visible() and t.get_text().strip() and t.get_figure() is not None]
    out = []
    for i in range(len(boxes)):
        for j in range(i + 1, len(boxes)):
            a, b = boxes[i][1], boxes[j][1]
            if a.x0 < b.x1 - 0.5 and b.x0 < a.x1 - 0.5 and a.y0 < b.y1 - 0.5 and b.y0 < a.y1 - 0.5:
                out.append((boxes[i][0], boxes[j][0]))
    return out


def _few_ticks(ax, n: int = 5) -> None:
    """At most ``n`` round ticks per axis, so tick labels never run together."""
    from matplotlib.ticker import MaxNLocator
    ax.xaxis.set_major_locator(MaxNLocator(n))
    ax.yaxis.set_major_locator(MaxNLocator(n))


def _axis_labels(system):
    su, iu = units(system)
    return [labelled(s, u) for s, u in zip(system.state_names, su)], su


def _box(ax, box, system, **kw):
    from matplotlib.patches import Rectangle
    lo = np.maximum(np.asarray(box.lo, float)[:2], system.x_lo[:2])
    hi = np.minimum(np.asarray(box.hi, float)[:2], system.x_hi[:2])
    ax.add_patch(Rectangle(lo, *(hi - lo), **kw))


def _spec_patches(ax, spec, system) -> None:
    if spec is None:
        return
    for i, b in enumerate(getattr(spec, "obstacles", ()) or ()):
        _box(ax, b, system, facecolor="0.45", edgecolor="0.2", lw=0.5,
             label="obstacle grown by the robot radius" if i == 0 else None,
             zorder=3)  # the spec's boxes: the map's obstacles grown by robot_radius (what the centre avoids)
    if getattr(spec, "target", None) is not None and getattr(spec, "kind", "reach_avoid") == "reach_avoid":
        _box(ax, spec.target, system, facecolor=(0.2, 0.7, 0.3, 0.35), edgecolor="green", lw=1.0, label="target",
             zorder=2)
    if getattr(spec, "safe", None) is not None:
        _box(ax, spec.safe, system, fill=False, edgecolor="k", lw=1.0, ls="--", label="safe set", zorder=4)


def _lines(ax, paths: np.ndarray, color, lw: float, alpha: float, zorder: float = 1.0) -> None:
    """Many polylines (R, T, 2) drawn as ONE image per axes (:func:`_rasterize_runs`, at save time,
    once the axes' size and limits are known): each line translucent on its own, so 1000 runs read
    as a density, as one raster artist instead of R Line2D objects (matplotlib drew 190,000 of
    them for a 4-state run in 69 s; a PDF keeps the image, the rest stays vector). The lines count
    in the axes' data limits."""
    paths = np.asarray(paths, float)
    if paths.shape[0] == 0:
        return
    if not hasattr(ax, "_simgap_runs"):
        ax._simgap_runs = []
    ax._simgap_runs.append((paths, color, float(lw), float(alpha), float(zorder)))
    finite = paths.reshape(-1, 2)
    finite = finite[np.all(np.isfinite(finite), axis=1)]
    if finite.size:
        ax.update_datalim(finite)
        ax.autoscale_view()


#: samples per group of runs in one axes' image (1000 runs x 400 periods: about 7 per segment, a
#: segment a few pixels long; more only where the lines are longer than the samples are apart)
RUN_SAMPLES = 3_000_000


def _rasterize_runs(fig, dpi: float) -> None:
    """Replace each axes' registered runs (:func:`_lines`) by one RGBA image at the axes' size in
    pixels at ``dpi`` (:func:`~simgap_viz.layers.geometry.density_rgba`), the groups composited in
    zorder, failures last; the axes' limits kept."""
    from matplotlib.colors import to_rgb

    from .layers.geometry import density_rgba
    axes = [a for ax in fig.axes for a in (ax, *ax.child_axes)]
    for ax in dict.fromkeys(axes):
        runs = getattr(ax, "_simgap_runs", None)
        if not runs:
            continue
        (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
        bb = ax.get_window_extent()
        W, H = max(2, int(round(bb.width * dpi / fig.dpi))), max(2, int(round(bb.height * dpi / fig.dpi)))
        out = np.zeros((H, W, 4), float)
        for paths, color, lw, alpha, _z in sorted(runs, key=lambda r: r[4]):
            P = np.empty(paths.shape, np.float32)
            P[..., 0] = (paths[..., 0] - x0) / (x1 - x0) * W
            P[..., 1] = (paths[..., 1] - y0) / (y1 - y0) * H
            img = density_rgba(P, W, H, [int(255 * c) for c in to_rgb(color)], alpha,
                               width=max(1, int(round(lw * dpi / 72.0))), max_samples=RUN_SAMPLES)
            a = img[..., 3:4] / 255.0
            out[..., :3] = img[..., :3] / 255.0 * a + out[..., :3] * (1 - a)  # alpha over
            out[..., 3:4] = a + out[..., 3:4] * (1 - a)
        rgb = np.where(out[..., 3:4] > 0, out[..., :3] / np.maximum(out[..., 3:4], 1e-12), 0.0)
        rgba = np.round(255 * np.concatenate([rgb, out[..., 3:4]], axis=-1)).astype(np.uint8)  # 1/8 of float's memory
        ax.imshow(rgba, extent=(x0, x1, y0, y1), origin="upper", aspect="auto", interpolation="none",
                  zorder=min(r[4] for r in runs))
        ax.set_xlim(x0, x1)
        ax.set_ylim(y0, y1)
        ax._simgap_runs = []


def _draw_runs(ax, X, ok, idx, mm, mean, R, color, zorder: float = 1.0) -> None:
    """Rollouts as thin translucent lines in the method's color (1000 read as a density, 100 as single
    lines; one rasterized artist, so a PDF stays small), failures red on top, then the mean map and
    the rollout average."""
    alpha = float(np.clip(20.0 / max(R, 1), 0.03, 0.6))
    _lines(ax, X[idx], color, 0.5, alpha, zorder)
    if (~ok).any():
        _lines(ax, X[~ok], "red", 0.6, 0.6, 5)
    if mm is not None:
        ax.plot(mm[:, 0], mm[:, 1], zorder=6, **MEAN_MAP)
    ax.plot(mean[:, 0], mean[:, 1], zorder=6, **AVERAGE)


INSET = (0.3, 0.27)  # inset size in axes fractions; its title takes TITLE above it
TITLE = 0.08
LABELS = (0.12, 0.09)  # room the inset's tick labels take left of and below it (axes fractions)


def inset_place(ax, points: np.ndarray, avoid=()) -> list:
    """Where an inset of size :data:`INSET` covers the fewest of ``points`` (P, 2) (data coordinates)
    and none of the ``avoid`` boxes ((lo (2,), hi (2,)) in data coordinates, e.g. the zoomed region):
    [x0, y0, w, h] in axes fractions, on a 9 x 9 grid of positions (ties: nearer the lower right)."""
    w, h = INSET
    m = 0.03
    cand = sorted(((x, y) for y in np.linspace(m + LABELS[1], 1 - h - TITLE - m, 9)
                   for x in np.linspace(m + LABELS[0], 1 - w - m, 9)),
                  key=lambda c: (1 - c[0]) ** 2 + c[1] ** 2)
    P = ax.transAxes.inverted().transform(ax.transData.transform(np.asarray(points, float).reshape(-1, 2)))
    boxes = [ax.transAxes.inverted().transform(ax.transData.transform(np.array([lo, hi]))) for lo, hi in avoid]
    best, score = None, None
    for x, y in cand:
        # the inset with its tick labels (left, below) and title (above)
        x0, x1, y0, y1 = x - LABELS[0], x + w + 0.01, y - LABELS[1], y + h + TITLE
        inside = np.count_nonzero((P[:, 0] >= x0) & (P[:, 0] <= x1) & (P[:, 1] >= y0) & (P[:, 1] <= y1))
        hit = any(b[0, 0] < x1 and x0 < b[1, 0] and b[0, 1] < y1 and y0 < b[1, 1] for b in boxes)
        dx = np.maximum(np.maximum(x0 - P[:, 0], P[:, 0] - x1), 0)
        dy = np.maximum(np.maximum(y0 - P[:, 1], P[:, 1] - y1), 0)
        clear = float(np.min(np.hypot(dx, dy))) if P.size else 1.0
        sc = (hit, inside, -min(clear, 0.1))
        if score is None or sc < score:
            best, score = [x, y, w, h], sc
    return best


def _legend(fig, handles, style: str, ncol: int | None = None) -> None:
    """The figure's one legend, below its axes."""
    fig.legend(handles=handles, loc="outside lower center", frameon=False,
               ncol=ncol or min(len(handles), 4 if style == "paper" else 3))


def _handles(methods, runs, spec, extra=()) -> list:
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch
    hs = [Line2D([], [], color=METHOD_STYLE.get(m, "tab:green"), lw=1.5, label=f"{_name(m)}: {n} rollouts")
          for m, n in zip(methods, runs)]
    # the nominal model's set is proved for f alone: its mean map is no guarantee about the simulator
    mm = ("mean map (the guarantee)" if "nominal" not in methods else
          "mean map (no guarantee: nominal model)" if len(methods) == 1 else "mean map (the guarantee; nominal: none)")
    hs += [Line2D([], [], label=mm, **MEAN_MAP),
           Line2D([], [], label="rollout average", **AVERAGE)]
    hs += list(extra)
    if spec is not None:
        if getattr(spec, "safe", None) is not None:
            hs.append(Patch(fill=False, edgecolor="k", ls="--", label="safe set"))
        if getattr(spec, "target", None) is not None and getattr(spec, "kind", "reach_avoid") == "reach_avoid":
            hs.append(Patch(facecolor=(0.2, 0.7, 0.3, 0.35), edgecolor="green", label="target"))
        if getattr(spec, "obstacles", None):
            hs.append(Patch(facecolor="0.45", edgecolor="0.2", label="obstacle"))
    return hs


def _methods(run) -> list:
    """The methods with rollouts: deterministic, stochastic and (an invariant-set run) the nominal model."""
    out = [m for m in ("deterministic", "stochastic") if m in run.methods and run.methods[m].rollouts is not None]
    nom = getattr(run, "nominal", None)
    return out + (["nominal"] if nom is not None and nom.rollouts is not None else [])


def _result(run, m):
    """The MethodResults of ``m`` (an invariant-set run's nominal model: ``run.nominal``)."""
    return run.nominal if m == "nominal" else run.methods[m]


def _name(m: str) -> str:
    """A method as the figures name it: "stochastic gap", ..., "nominal model (no gap)"."""
    return "nominal model (no gap)" if m == "nominal" else f"{m} gap"


@_styled
def trajectories(run, spec, out_dir: Path, max_drawn: int = 1000, style: str = "paper") -> list:
    """Rollouts over (x1, x2), one panel per method (see module docstring)."""
    from matplotlib.lines import Line2D
    system = run.system
    labels, _ = _axis_labels(system)
    methods = _methods(run)
    if not methods or system.n < 2:  # one state: its time course (states_time) is the picture
        return []
    fig, axes = _figure(style, 1, len(methods), height_rows=1.35, sharex=True, sharey=True)
    runs, fails = [], 0
    for ax, m in zip(axes[0], methods):
        ro = _result(run, m).rollouts
        color = METHOD_STYLE.get(m, "tab:green")
        X = np.asarray(ro.trajectories)[:, :, :2]
        ok = np.asarray(ro.success, bool)
        R = X.shape[0]
        runs.append(R)
        fails += int((~ok).sum())
        idx = np.flatnonzero(ok)[: max(0, max_drawn - int((~ok).sum()))]
        _spec_patches(ax, spec, system)
        # every path drawn here is over (x1, x2): the mean map and the average hold all n states
        mm = None if ro.mean_map_trajectory is None else np.asarray(ro.mean_map_trajectory)[:, :2]
        mean = np.asarray(ro.mean_trajectory)[:, :2]
        _draw_runs(ax, X, ok, idx, mm, mean, R, color)
        ax.plot(*np.asarray(ro.x0)[:2], "o", color="k", ms=4, zorder=7)
        ax.set_xlim(system.x_lo[0], system.x_hi[0])
        ax.set_ylim(system.x_lo[1], system.x_hi[1])
        _few_ticks(ax)
        ax.set_xlabel(labels[0])
        # three panels' titles fit on two lines each
        ax.set_title(f"{_name(m)}:{chr(10) if len(methods) > 2 else ' '}{int((~ok).sum())} of {R} runs fail"
                     + _per_run_words(getattr(_result(run, m), "statement", None)).replace(", ", "; " if len(
                         methods) > 2 else "\n", 1))
        if system.state_names[:2] == ("x", "y") or (units(system)[0][:2] == ("m", "m")):
            ax.set_aspect("equal")
        span = np.ptp(X.reshape(-1, 2), axis=0) if X.size else np.zeros(2)
        ends = X[:, -1, :2]
        spread = np.ptp(ends, axis=0) if R else np.zeros(2)
        box = system.x_hi[:2] - system.x_lo[:2]
        if R and np.all(spread < 0.05 * box) and np.all(span > 0):  # the runs' spread is invisible at this scale: zoom
            c, hw = ends.mean(axis=0), np.maximum(2.5 * spread, 1e-3 * box)
            pts = np.concatenate([X[idx[:: max(1, idx.size // 200)]].reshape(-1, 2), mean[:, :2],
                                  np.asarray(ro.x0)[None, :2]] + ([mm[:, :2]] if mm is not None else []))
            ins = ax.inset_axes(inset_place(ax, pts, avoid=[(c - hw, c + hw)]))
            _draw_runs(ins, X, ok, idx, mm, mean, R, color)
            ins.set_xlim(c[0] - hw[0], c[0] + hw[0])
            ins.set_ylim(c[1] - hw[1], c[1] + hw[1])
            from matplotlib.ticker import MaxNLocator
            ins.xaxis.set_major_locator(MaxNLocator(2, prune="upper"))  # the last label would pass the inset's edge
            ins.yaxis.set_major_locator(MaxNLocator(3))
            ins.tick_params(labelsize=STYLES[style]["small"] - 1, pad=1)
            ins.set_title("zoom: final states", fontsize=STYLES[style]["small"], pad=2)
            ax.indicate_inset_zoom(ins, edgecolor="0.3")
    axes[0][0].set_ylabel(labels[1])
    extra = [Line2D([], [], color="k", marker="o", ls="", ms=4, label="x0")]
    if fails:
        extra.append(Line2D([], [], color="red", lw=1, label="failed run"))
    _legend(fig, _handles(methods, runs, spec, extra), style)
    return save(fig, out_dir, "trajectories")


@_styled
def states_time(run, out_dir: Path, max_drawn: int = 1000, style: str = "paper") -> list:
    """Each state over time, rows = states, columns = methods (see module docstring)."""
    system = run.system
    labels, _ = _axis_labels(system)
    methods = _methods(run)
    if not methods:
        return []
    n = system.n
    fig, axes = _figure(style, n, len(methods), height_rows=0.55 * n + 0.3, sharex=True, sharey="row")
    runs, bands = [], {}
    for j, m in enumerate(methods):
        ro = _result(run, m).rollouts
        st = getattr(_result(run, m), "statement", None)
        X = np.asarray(ro.trajectories)[:max_drawn]
        runs.append(X.shape[0])
        t = np.arange(X.shape[1]) * float(ro.tau)
        alpha = float(np.clip(20.0 / max(X.shape[0], 1), 0.03, 0.6))
        for i in range(n):
            ax = axes[i][j]
            _lines(ax, np.stack([np.broadcast_to(t, X.shape[:2]), X[:, :, i]], axis=-1),
                   METHOD_STYLE.get(m, "tab:green"), 0.5, alpha)
            for role, kw in (("tube", dict(alpha=0.25, lw=0)), ("noise_tube", dict(fill=False, lw=0.6, ls=":"))):
                ds = st.set_of(role) if st is not None else None
                if ds is not None and ds.kind == "boxes":
                    k, blo, bhi = ds.band(i, X.shape[1] - 1)
                    if kw.get("fill", True):
                        ax.fill_between(k * float(ro.tau), blo, bhi, color=METHOD_STYLE.get(m, "tab:green"),
                                        zorder=0.5, **{q: v for q, v in kw.items() if q != "fill"})
                    else:
                        for edge in (blo, bhi):
                            ax.plot(k * float(ro.tau), edge, color="0.3", zorder=0.6, lw=kw["lw"], ls=kw["ls"])
                    bands.setdefault(role, ds.label)
            if ro.mean_map_trajectory is not None:
                ax.plot(t, np.asarray(ro.mean_map_trajectory)[:, i], **{**MEAN_MAP, "lw": 0.7})
            ax.plot(t, np.asarray(ro.mean_trajectory)[:, i], **AVERAGE)
            _few_ticks(ax, 4)
            if j == 0:
                ax.set_ylabel(labels[i])
            if i == 0:
                ax.set_title(_name(m) + _per_run_words(st))
            if i == n - 1:
                ax.set_xlabel("time [s]")
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch
    extra = ([Patch(color="0.6", alpha=0.4, label=bands["tube"] + ", per period")] if "tube" in bands else []) \
        + ([Line2D([], [], color="0.3", lw=0.6, ls=":", label=bands["noise_tube"])] if "noise_tube" in bands else [])
    _legend(fig, _handles(methods, runs, None, extra), style)
    note = mean_map_switch_note(run, methods)
    if note:  # the legend's title: laid out with it, so it can overlap nothing
        import textwrap
        lg = fig.legends[0]
        lg.set_title("\n".join(textwrap.wrap(note, 150 if style == "paper" else 120)),
                     prop={"size": STYLES[style]["small"]})
        lg.get_title().set_color("0.25")
    return save(fig, out_dir, "states_time")


def mean_map_switch_note(run, methods) -> str:
    """Why the mean map's curve has steps the runs' average has not, naming its largest one ("" if
    there is none to name).

    The mean map m+ = E fhat(m, u(m)) applies the controller at ONE state, the mean, and a symbolic
    controller is constant on each grid cell and may pick a very different valid input in the next
    cell: where m crosses into such a cell, m+ steps by tau times the change of input's effect (no
    angle wrap is involved). The runs spread over many cells, so their average changes smoothly. The
    step named is, per method with a controller, the one in the horizon's second half where the mean
    map's step differs most from the average's (state units divided by X's width) and the input at m changed.
    """
    parts = []
    for m in methods:
        res = _result(run, m)
        ro, syn = res.rollouts, res.synthesis
        mm = getattr(ro, "mean_map_trajectory", None)
        ctrl = getattr(syn, "controller", None)
        if mm is None or ctrl is None or not hasattr(ctrl, "input_index"):
            continue
        mm, mt = np.asarray(mm, float), np.asarray(ro.mean_trajectory, float)
        T = min(mm.shape[0], mt.shape[0]) - 1
        if T < 4:
            continue
        width = np.maximum(run.system.x_hi - run.system.x_lo, 1e-300)
        dev = np.abs(np.diff(mm[:T + 1], axis=0) - np.diff(mt[:T + 1], axis=0)) / width  # (T, n)
        try:
            u_idx = np.asarray(ctrl.input_index(mm[:T]))
        except Exception:  # a state outside the controller's grid: nothing to name
            continue
        switched = np.zeros(T, bool)
        switched[1:] = (u_idx[1:] != u_idx[:-1]) & (u_idx[1:] >= 0) & (u_idx[:-1] >= 0)
        late = np.arange(T) >= T // 2
        score = np.where((switched & late)[:, None], dev, -1.0)
        k, i = np.unravel_index(int(np.argmax(score)), score.shape)
        if score[k, i] <= 0:
            continue
        u0, u1 = ctrl.inputs[u_idx[k - 1]], ctrl.inputs[u_idx[k]]
        fmt = lambda u: ", ".join(f"{v:.3g}" for v in np.ravel(u))  # noqa: E731
        parts.append(f"{_name(m)}, t = {k * float(ro.tau):.3g} s: {run.system.state_names[i]} steps by "
                     f"{mm[k + 1, i] - mm[k, i]:+.3g} as the input at the mean switches from {fmt(u0)} to {fmt(u1)}")
    if not parts:
        return ""
    return ("Steps of the mean map (bold): it applies the controller at one state, the mean, and the controller is "
            "constant on each grid cell, so its input changes at once where the mean enters another cell ("
            + "; ".join(parts) + "); no angle wrap. The runs spread over many cells, so their average moves smoothly.")


@_styled
def gamma_slices(run, out_dir: Path, res: int = 201, style: str = "paper") -> list:
    """gamma_i along each state variable per method, with the nearby data gaps (see module docstring)."""
    from matplotlib.lines import Line2D
    system = run.system
    labels, su = _axis_labels(system)
    n = system.n
    if not any(r.certificate is not None for r in run.methods.values()):
        return []
    centre = 0.5 * (system.x_lo + system.x_hi)
    U = system.inputs
    u_mid = U[np.argmin(np.abs(U - U.mean(axis=0)).sum(axis=1))]
    fig, axes = _figure(style, n, n, height_rows=0.9 * n if n <= 2 else 0.62 * n)
    handles = []
    for m in sorted(run.methods, key=lambda k: (k not in METHOD_STYLE, list(METHOD_STYLE).index(k)
                                                   if k in METHOD_STYLE else 0, k)):
        res_m = run.methods[m]
        cert, ds = res_m.certificate, res_m.dataset
        if cert is None:  # stage outputs without a certificate: no gamma to draw
            continue
        color = METHOD_STYLE.get(m, "tab:green")
        gaps = ds.gap() if ds is not None else None
        any_near = False
        for j in range(n):  # along x_j
            xs = np.tile(centre, (res, 1))
            xs[:, j] = np.linspace(system.x_lo[j], system.x_hi[j], res)
            g = np.asarray(cert.gamma(xs, np.tile(u_mid, (res, 1))), float)
            near = None
            if gaps is not None:  # rows within one cover radius of the line, same input
                d = np.abs(ds.x - centre) / np.maximum(system.x_hi - system.x_lo, 1e-12)
                d[:, j] = 0
                near = (d.max(axis=1) <= max(float(ds.epsilon) / float(np.min(system.x_hi - system.x_lo)), 0.02)) \
                    & np.all(np.isclose(ds.u, u_mid), axis=1)
            for i in range(n):
                ax = axes[i][j]
                ax.plot(xs[:, j], g[:, i], color=color, lw=1.2)
                if near is not None and near.any():
                    any_near = True
                    dots = np.column_stack([ds.x[near, j], gaps[near, i]])
                    _lines(ax, np.stack([dots, dots], axis=1), color, 1.5, 0.6)  # dots, in the axes' one image
                _few_ticks(ax, 4)
                if i == n - 1:
                    ax.set_xlabel(labels[j])
                if j == 0:
                    unit = f" [{su[i]}/step]" if su[i] else ""
                    ax.set_ylabel(f"gamma_{system.state_names[i]}{unit}")
        handles.append(Line2D([], [], color=color, lw=1.2, label=f"gamma, {m} gap"))
        if any_near:
            handles.append(Line2D([], [], color=color, marker=".", ls="", label=f"data gap |mean - f|, {m}"))
    for ax in axes.ravel():  # after every method is drawn: set_ylim stops autoscaling
        ax.set_ylim(bottom=0)
        ax.ticklabel_format(axis="y", style="sci", scilimits=(-2, 3), useMathText=True)
    fixed = ", ".join(f"{labelled(s_, u)} = {c:.3g}" for s_, u, c in zip(system.state_names, su, centre))
    inp = ", ".join(f"{labelled(nm, iu)} = {v:.3g}" for nm, iu, v in zip(system.input_names, units(system)[1], u_mid))
    fig.suptitle(f"gamma along each state, the others at the centre of X ({fixed}; {inp})",
                 fontsize=STYLES[style]["small"])
    _legend(fig, handles, style, ncol=2)
    return save(fig, out_dir, "gamma_slices")


def state_pairs(n: int, most: int = 6) -> list:
    """The pairs of states an n-D set is drawn over: every pair while there are at most ``most``
    (a 4-state system's six), else consecutive ones (0, 1), (2, 3), ..."""
    import itertools
    pairs = list(itertools.combinations(range(n), 2))
    if len(pairs) > most:
        pairs = [(i, i + 1) for i in range(0, n - 1, 2)]
    return pairs


def _set_methods(run) -> list:
    """(name, MethodResults) of every method with a proved set, widest first (drawn first, beneath:
    a thinner set drawn later stays visible inside a wider one), the nominal model's runs beneath."""
    out = [(m, r) for m, r in ((m, run.methods[m]) for m in ("stochastic", "deterministic") if m in run.methods)]
    if getattr(run, "nominal", None) is not None:
        out.append(("nominal", run.nominal))
    return [(m, r) for m, r in out if _statement(r) is not None and _statement(r).proved
            and any(ds.kind != "cells" for ds in _statement(r).sets)]


def _statement(res):
    """A method's statement: the loaded one, else its set controller's own (results built by hand)."""
    st = getattr(res, "statement", None)
    if st is None and getattr(res, "invariant_set", None) is not None:
        st = res.invariant_set.statement()
    return st


def _no_set_notes(run) -> list:
    """One line per method of a set-method run whose proof failed: its name and margin s."""
    from .results import unproved_sets
    return [f"{m} gap: nothing proved" + ("" if s_ is None else f" (margin s = {s_:.2g}: proved only if gamma "
                                                                f"were <= s x its size)")
            for m, s_ in unproved_sets(run)]


#: how each role of a method's sets is drawn (the method's color; the line width and style)
SET_LINES = {"tube": dict(lw=0.4, alpha=0.6), "noise_tube": dict(lw=0.6, ls=":"),
             "terminal": dict(lw=1.4), "ellipsoid": dict(lw=1.4)}
TARGET = dict(color="green", lw=1.2, ls="-.")
#: the sets' drawing order by role (a later method's within a role above an earlier one's)
ROLE_Z = {"tube": 8.0, "noise_tube": 8.2, "terminal": 8.4, "ellipsoid": 8.4}
#: the method's runs beneath the other methods' (the nominal model's most), so none covers the others
RUN_Z = {"stochastic": 1.0, "deterministic": 0.95, "nominal": 0.9}


def _per_run_words(st) -> str:
    """", p_cert 0.92 (400 periods)" for a statement with a per-run probability, else ""."""
    return "" if st is None or st.per_run is None else f", p_cert {st.per_run.p_cert:.3g} ({st.per_run.horizon} periods)"


@_styled
def invariant_sets(run, spec, out_dir: Path, max_drawn: int = 1000, style: str = "paper") -> list:
    """The proved sets of a set-method run, each method's in its own words (its statement: a tube's
    boxes along the plan, its noise tube and terminal box, the target box; an ellipsoid's shadow),
    projected onto pairs of states, with the rollouts (see module docstring)."""
    from matplotlib.lines import Line2D
    sets = _set_methods(run)
    if not sets:
        return []
    system = run.system
    labels, _ = _axis_labels(system)
    pairs = state_pairs(system.n)
    if not pairs:  # one state: no pair to project onto
        return []
    cols = min(3, len(pairs))
    rows = -(-len(pairs) // cols)
    fig, axes = _figure(style, rows, cols, height_rows=rows * (1.0 if cols > 1 else 1.4))
    for ax in axes.ravel()[len(pairs):]:
        ax.set_visible(False)
    runs, safe_seen, drawn_roles, target, shown, same_as = {}, False, {}, False, {}, {}
    target_of = next((m for m, r in sets if _statement(r).set_of("target") is not None), None)
    for ax, (a, b) in zip(axes.ravel(), pairs):
        lo, hi = [], []
        for m, res in sets:
            color = METHOD_STYLE.get(m, "tab:green")
            ro = res.rollouts
            if ro is not None:
                X = np.asarray(ro.trajectories)[:max_drawn][:, :, [a, b]]
                ok = np.asarray(ro.success, bool)[:max_drawn]
                runs[m] = X.shape[0]
                mm = None if ro.mean_map_trajectory is None else np.asarray(ro.mean_map_trajectory)[:, [a, b]]
                _draw_runs(ax, X, ok, np.flatnonzero(ok), mm, np.asarray(ro.mean_trajectory)[:, [a, b]],
                           X.shape[0], color, zorder=RUN_Z.get(m, 1.0))
                ax.plot(*np.asarray(ro.x0)[[a, b]], "o", color="k", ms=3, zorder=7)
                lo.append(X.reshape(-1, 2).min(axis=0))
                hi.append(X.reshape(-1, 2).max(axis=0))
            for ds in _statement(res).sets:
                if ds.kind == "cells":
                    continue
                if ds.role == "target":  # one method's (the methods share the experiment's target)
                    if m == target_of:
                        for R_ in ds.outlines((a, b)):
                            ax.plot(R_[:, 0], R_[:, 1], zorder=3, **TARGET)
                        target = True
                    continue
                style_ = SET_LINES.get(ds.role, dict(lw=1.0))
                every = max(1, -(-len(ds.centers) // 40)) if ds.kind == "boxes" else 1
                outl = ds.outlines((a, b), every)
                pts = np.concatenate(outl)
                same = next((k for k, v in shown.items() if k[0] == (a, b) and k[1] == ds.role
                             and v.shape == pts.shape and np.allclose(v, pts, rtol=1e-6, atol=1e-9)), None)
                if same is not None:  # the same set as a method's drawn before: named with it, drawn once
                    same_as.setdefault((same[2], ds.role), set()).add(m)
                    continue
                shown[(a, b), ds.role, m] = pts
                z = ROLE_Z.get(ds.role, 8.0) + 0.01 * len(shown)
                from matplotlib.collections import LineCollection
                if ds.kind == "boxes" and ds.role in ("tube", "noise_tube") and \
                        np.all(ds.half_widths[:-1][:, [a, b]].max(axis=0) < 1e-4 * np.ptp(pts, axis=0).clip(1e-12)):
                    # boxes of no visible width: the plan they sit on, as a line
                    ax.plot(ds.centers[:-1, a], ds.centers[:-1, b], color=color, lw=1.0, ls=(0, (1, 1)), zorder=z,
                            gid=f"{ds.role}:{m}:{a},{b}")
                    drawn_roles.setdefault((m, ds.role), ds.label + " (no width: the plan)")
                else:
                    ax.add_collection(LineCollection(outl, colors=[color], linewidths=style_["lw"],
                                                     linestyles=style_.get("ls", "-"), alpha=style_.get("alpha", 1.0),
                                                     zorder=z, gid=f"{ds.role}:{m}:{a},{b}"))
                    drawn_roles.setdefault((m, ds.role), ds.label)
                lo.append(pts.min(axis=0))
                hi.append(pts.max(axis=0))
        lo, hi = np.min(lo, axis=0), np.max(hi, axis=0)
        pad = 0.12 * np.maximum(hi - lo, 1e-9)
        if spec is not None and getattr(spec, "safe", None) is not None:
            from matplotlib.patches import Rectangle
            slo = np.maximum(np.asarray(spec.safe.lo, float)[[a, b]], system.x_lo[[a, b]])
            shi = np.minimum(np.asarray(spec.safe.hi, float)[[a, b]], system.x_hi[[a, b]])
            ax.add_patch(Rectangle(slo, *(shi - slo), fill=False, edgecolor="k", lw=1.0, ls="--", zorder=4))
            # an edge of S inside the view (else S lies beyond the frame, around everything drawn)
            safe_seen |= bool(np.any((slo > lo - pad) & (slo < hi + pad)) or np.any((shi > lo - pad) & (shi < hi + pad)))
        ax.set_xlim(lo[0] - pad[0], hi[0] + pad[0])
        ax.set_ylim(lo[1] - pad[1], hi[1] + pad[1])
        _few_ticks(ax, 4)
        ax.ticklabel_format(style="sci", scilimits=(-2, 3), useMathText=True)
        ax.set_xlabel(labels[a])
        ax.set_ylabel(labels[b])
    hs = []
    for (m, role), label in drawn_roles.items():
        st_ = SET_LINES.get(role, dict(lw=1.0))
        also = sorted(same_as.get((m, role), ()))
        plan = label.endswith("(no width: the plan)")
        hs.append(Line2D([], [], color=METHOD_STYLE.get(m, "tab:green"), lw=1.0 if plan else max(st_["lw"], 1.0),
                         ls=(0, (1, 1)) if plan else st_.get("ls", "-"),
                         label=f"{label}, {' = '.join(_name(x) for x in [m] + also)}"))
    hs += [Line2D([], [], color=METHOD_STYLE.get(m, "tab:green"), lw=4, alpha=0.4, label=f"{_name(m)}: {n} runs")
           for m, n in runs.items()]
    if target:
        hs.append(Line2D([], [], label="target box", **TARGET))
    hs += [Line2D([], [], label="mean map", **MEAN_MAP), Line2D([], [], label="rollout average", **AVERAGE),
           Line2D([], [], color="k", marker="o", ls="", ms=3, label="x0")]
    stmts = {m: _statement(r) for m, r in sets}
    names = list(dict.fromkeys(st.name for st in stmts.values()))
    title = (f"{' / '.join(names)}: projections onto pairs of states"
             + (" (the shadow of E, not its slice through x*)" if any(st.set_name == "E" for st in stmts.values())
                else ""))
    title += "".join(f"; {_name(m)}{_per_run_words(st)}" for m, st in stmts.items() if st.per_run)
    if spec is not None and getattr(spec, "safe", None) is not None:
        from matplotlib.patches import Patch
        if safe_seen:
            hs.append(Patch(fill=False, edgecolor="k", ls="--", label="safe set"))
        else:
            title += "; the safe set lies beyond every frame"
    notes = _no_set_notes(run)
    import textwrap
    fig.suptitle("\n".join(textwrap.wrap(title, 140) + notes), fontsize=STYLES[style]["small"])
    _legend(fig, hs, style, ncol=3)
    return save(fig, out_dir, "invariant_sets")


@_styled
def p_cert(run, out_dir: Path, style: str = "paper") -> list:
    """The per-run p_cert map with the validated initial states (see module docstring)."""
    if run.per_run is None:
        return []
    from .layers.perrun import pcert_map
    system = run.system
    labels, _ = _axis_labels(system)
    pm = pcert_map(run.per_run.controller)
    fig, axs = _figure(style, 1, 1, height_rows=1.5)
    ax = axs[0][0]
    from matplotlib.colors import LinearSegmentedColormap
    from .layers.perrun import P_STOPS
    cmap = LinearSegmentedColormap.from_list("pcert", np.asarray(P_STOPS, float) / 255.0)
    im = ax.imshow(pm["p"].T, origin="lower", extent=(pm["lo"][0], pm["hi"][0], pm["lo"][1], pm["hi"][1]),
                   cmap=cmap, vmin=0, vmax=1, aspect="auto", interpolation="nearest", rasterized=True)
    cb = fig.colorbar(im, ax=ax)
    cb.set_label("p_cert (certified lower bound on P[one run satisfies the spec])")
    marks = {"perrun": "o", "baseline": "s", "stochastic": "^", "deterministic": "v"}
    for name, c in run.per_run.controllers.items():
        ax.scatter(c.x0[:, 0], c.x0[:, 1], c=c.p_emp, cmap=cmap, vmin=0, vmax=1, marker=marks.get(name, "D"),
                   edgecolors="k", s=36, label=f"p_emp, {name}")
    ax.set_xlabel(labels[0])
    ax.set_ylabel(labels[1])
    extra = f" (max over {pm['reduced_dims']} further dimension(s))" if pm["reduced_dims"] else ""
    # a drawn p_cert says what it rests on, as the table, summary and GUI legend do
    ax.set_title(f"{system.name}: per-run p_cert per cell{extra}, horizon {run.per_run.horizon}\n"
                 "conditional on the estimated Lipschitz constants and the Markov assumption", fontsize=9)
    _few_ticks(ax)
    _legend(fig, ax.get_legend_handles_labels()[0], style)
    return save(fig, out_dir, "p_cert")


def plot_run(path, out_dir=None, max_drawn: int = 1000, style: str = "paper", log=None) -> list:
    """Every figure of the run folder ``path`` (or of a loaded :class:`~simgap_viz.results.RunResults`,
    e.g. stage outputs from :func:`~simgap_viz.results.load_stages`: the figures their stages allow)
    into ``out_dir`` (default ``path/figures``); the paths written.

    ``style``: "paper" (7 in wide, 8 pt: a two-column paper's text width) or "slide" (11 in, 14 pt)."""
    if style not in STYLES:
        raise SimgapError(f"style must be one of {', '.join(STYLES)}, got {style!r}")
    from .results import RunResults, describe_stages, load_run, run_spec

    run = path if isinstance(path, RunResults) else load_run(path)  # a run folder, or loaded stage outputs
    if run.stages is not None and not any(m.rollouts is not None or m.certificate is not None
                                          for m in run.methods.values()):
        raise SimgapError("nothing to draw: the figures need rollouts (--rollouts) or a certificate (--cert); "
                          + "; ".join(describe_stages(run)))
    out = Path(out_dir) if out_dir is not None else run.path / "figures"
    if out.exists() and not out.is_dir():
        raise SimgapError(f"{str(out)!r} exists and is not a folder")
    if not out.parent.is_dir():
        raise SimgapError(f"folder {str(out.parent)!r} does not exist")
    from simgap.file_guard import output_dir
    try:  # a read-only results folder: said before anything is drawn, with the way out
        output_dir(out, "--out" if out_dir is not None else "figures folder")
    except SimgapError as e:
        if out_dir is not None:
            raise
        raise SimgapError(f"{e}: the results folder is not writable; draw the figures elsewhere with --out FOLDER "
                          "(e.g. simgap plot RUN --out /tmp/figures)") from None
    spec = run_spec(run)[0]
    _check_replaceable(out)  # before anything is drawn or written
    out.mkdir(exist_ok=True)
    written = []
    import time
    steps = (("trajectories", lambda: trajectories(run, spec, out, max_drawn, style=style)),
             ("states_time", lambda: states_time(run, out, max_drawn, style=style)),
             ("gamma_slices", lambda: gamma_slices(run, out, style=style)),
             ("invariant_sets", lambda: invariant_sets(run, spec, out, max_drawn, style=style)),
             ("p_cert", lambda: p_cert(run, out, style=style)))
    t0 = time.perf_counter()
    for k, (name, draw) in enumerate(steps, 1):
        if log:  # a progress line per figure: a 4-state run with 3 x 1000 rollouts takes seconds each
            log(f"[plot] {k}/{len(steps)} {name} ... ({time.perf_counter() - t0:.1f} s so far)")
        written += draw()
    if log:
        log(f"[plot] done in {time.perf_counter() - t0:.1f} s: {len(written)} files")
    _list_figures(out, written)
    return written


def _figure_table(out: Path) -> dict:
    """``out``/FIGURE_LIST as a dict with ``files`` {name: sha256} and ``pending`` {name: {tmp, sha256}}
    (a figure being written: its temporary name, and its sha256 once drawn); empty tables when the list
    is absent or unreadable."""
    from simgap.file_guard import read_json
    try:
        d = read_json(out / FIGURE_LIST, "figure list") if (out / FIGURE_LIST).is_file() else {}
    except SimgapError:
        d = {}
    d = d if isinstance(d, dict) else {}
    files = d.get("files") if isinstance(d.get("files"), dict) else {}
    pending = d.get("pending") if isinstance(d.get("pending"), dict) else {}
    return {"format": "simgap-figures", "files": dict(files),
            "pending": {k: v for k, v in pending.items() if isinstance(v, dict)}}


def _pending(out: Path, name: str, tmp: str, drawn: Path = None) -> None:
    """Write ahead in FIGURE_LIST that ``name`` is being written through ``tmp`` (with the drawn file's
    sha256 once ``drawn``): after a kill at any point, the next ``simgap plot`` knows the temporary file and
    the figure as its own (resumable) instead of refusing them as a user's."""
    from simgap import fileio
    from simgap.results_folder import file_digest
    t = _figure_table(out)
    t["pending"][name] = {"tmp": tmp, **({"sha256": file_digest(drawn)} if drawn is not None else {})}
    fileio.write_json(out / FIGURE_LIST, t)


def _resume(out: Path) -> None:
    """Finish what a killed ``simgap plot`` left: remove the temporary files its list names (only
    those: hidden, listed as pending) and list a figure renamed just before the kill."""
    from simgap import fileio
    from simgap.results_folder import file_digest
    if not (out / FIGURE_LIST).is_file():
        return
    t = _figure_table(out)
    if not t["pending"]:
        return
    names = {f"{s}.{e}" for s in FIGURES for e in FORMATS}
    for name, p in t.pop("pending").items():
        tmp = p.get("tmp")
        if (isinstance(tmp, str) and tmp.startswith(".") and "/" not in tmp and ".tmp." in tmp
                and (out / tmp).is_file() and not (out / tmp).is_symlink()):
            (out / tmp).unlink()
        f = out / name
        if (name in names and isinstance(p.get("sha256"), str) and f.is_file() and not f.is_symlink()
                and file_digest(f) == p["sha256"]):
            t["files"][name] = p["sha256"]
    t["pending"] = {}
    fileio.write_json(out / FIGURE_LIST, t)


def _check_replaceable(out: Path) -> None:
    """Refuse to write figures into ``out`` over files simgap plot did not write there: a figure
    name present but not listed in ``out``/FIGURE_LIST with its current sha256 (a user's own file, or
    one changed since) is named, and nothing is written."""
    from simgap.file_guard import printable
    from simgap.results_folder import file_digest
    if not out.is_dir():
        return
    t = _figure_table(out)
    pending = {n: p.get("sha256") for n, p in t["pending"].items()}  # drawn and renamed just before a kill
    foreign = [n for n in (f"{s}.{e}" for s in FIGURES for e in FORMATS)
               if (out / n).exists() and ((out / n).is_symlink() or not (out / n).is_file()
                                          or file_digest(out / n) not in (t["files"].get(n), pending.get(n)))]
    if foreign:
        raise SimgapError(f"{str(out)!r} holds file(s) simgap plot would overwrite that it did not write there (or "
                          f"that changed since): {', '.join(printable(n) for n in foreign)}. Nothing was written; "
                          "move them away or give another --out")
    _resume(out)  # only now (nothing refused): a killed plot's leftovers go, its last figure is listed


def _list_figures(out: Path, written: list) -> None:
    """Add the figures just written to ``out``/FIGURE_LIST with their sha256."""
    from simgap import fileio
    from simgap.results_folder import file_digest
    t = _figure_table(out)
    for p in written:
        t["files"][Path(p).name] = file_digest(Path(p))
        t["pending"].pop(Path(p).name, None)
    fileio.write_json(out / FIGURE_LIST, t)


def _listed_figures(out: Path) -> dict:
    """{file name: sha256} of ``out``/FIGURE_LIST; empty when it is absent or unreadable (then every
    figure-named file counts as not ours)."""
    return _figure_table(out)["files"]
