"""Paper-style figures of a finished run (``simgap plot RUN``), drawn with matplotlib.

Every figure is read from the run's files (:func:`simgap_viz.results.load_run`); nothing is
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
* ``p_cert`` -- for a run with ``[perrun]``: the certified per-run success probability per
  interval-MDP cell with the validated initial states colored by p_emp.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from simgap.errors import SimgapError
from simgap.systems import labelled, units

METHOD_STYLE = {"deterministic": "tab:blue", "stochastic": "tab:orange"}
FORMATS = ("png", "pdf")


def _plt():
    import matplotlib
    matplotlib.use("Agg")  # files only: no display needed
    import matplotlib.pyplot as plt
    return plt


def save(fig, out_dir: Path, name: str) -> list:
    """Write ``name``.png and .pdf into ``out_dir`` atomically; return the paths."""
    paths = []
    for ext in FORMATS:
        final = out_dir / f"{name}.{ext}"
        tmp = out_dir / f".{name}.{os.getpid()}.tmp.{ext}"
        try:
            fig.savefig(tmp, dpi=150, bbox_inches="tight")
            tmp.replace(final)
        finally:
            tmp.unlink(missing_ok=True)
        paths.append(final)
    _plt().close(fig)
    return paths


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
        _box(ax, b, system, facecolor="0.45", edgecolor="0.2", lw=0.5, label="obstacle grown by the robot radius" if i == 0 else None,
             zorder=3)  # the spec's boxes: the map's obstacles grown by robot_radius (what the centre avoids)
    if getattr(spec, "target", None) is not None:
        _box(ax, spec.target, system, facecolor=(0.2, 0.7, 0.3, 0.35), edgecolor="green", lw=1.2, label="target",
             zorder=2)
    if getattr(spec, "safe", None) is not None:
        _box(ax, spec.safe, system, fill=False, edgecolor="k", lw=1.2, ls="--", label="safe set", zorder=4)


def _draw_runs(ax, X, ok, idx, mm, mean, R) -> None:
    """Rollouts as thin translucent lines (1000 read as a density, 100 as single lines), failures
    red on top, then the mean map bold and the rollout average dashed."""
    alpha = float(np.clip(20.0 / max(R, 1), 0.03, 0.6))
    ax.plot(X[idx, :, 0].T, X[idx, :, 1].T, color="tab:blue", lw=0.5, alpha=alpha, zorder=1)
    if (~ok).any():
        ax.plot(X[~ok, :, 0].T, X[~ok, :, 1].T, color="red", lw=0.6, alpha=0.6, zorder=5)
    if mm is not None:
        ax.plot(mm[:, 0], mm[:, 1], color="magenta", lw=1.3, label="mean map (guarantee)", zorder=6)
    ax.plot(mean[:, 0], mean[:, 1], color="k", lw=0.8, ls="--", label="rollout average", zorder=6)


def trajectories(run, spec, out_dir: Path, max_drawn: int = 1000) -> list:
    """Rollouts over (x1, x2), one panel per method (see module docstring)."""
    plt = _plt()
    system = run.experiment.system
    labels, _ = _axis_labels(system)
    methods = [m for m in ("deterministic", "stochastic") if m in run.methods and run.methods[m].rollouts is not None]
    if not methods:
        return []
    fig, axes = plt.subplots(1, len(methods), figsize=(5.2 * len(methods), 4.6), squeeze=False,
                             sharex=True, sharey=True)
    for ax, m in zip(axes[0], methods):
        ro = run.methods[m].rollouts
        X = np.asarray(ro.trajectories)[:, :, :2]
        ok = np.asarray(ro.success, bool)
        R = X.shape[0]
        idx = np.flatnonzero(ok)[: max(0, max_drawn - int((~ok).sum()))]
        _spec_patches(ax, spec, system)
        mm = None if ro.mean_map_trajectory is None else np.asarray(ro.mean_map_trajectory)
        mean = np.asarray(ro.mean_trajectory)
        _draw_runs(ax, X, ok, idx, mm, mean, R)
        span = np.ptp(X.reshape(-1, 2)[:, :2], axis=0) if X.size else np.zeros(2)
        ends = X[:, -1, :2]
        spread = np.ptp(ends, axis=0)
        box = system.x_hi[:2] - system.x_lo[:2]
        if np.all(spread < 0.05 * box) and np.all(span > 0):  # the runs' spread is invisible at this scale: zoom
            ins = ax.inset_axes([0.52, 0.04, 0.45, 0.36])
            _draw_runs(ins, X, ok, idx, mm, mean, R)
            c, h = ends.mean(axis=0), np.maximum(2.5 * spread, 1e-3 * box)
            ins.set_xlim(c[0] - h[0], c[0] + h[0])
            ins.set_ylim(c[1] - h[1], c[1] + h[1])
            ins.tick_params(labelsize=6)
            ins.set_title("zoom: final states", fontsize=7)
            ax.indicate_inset_zoom(ins, edgecolor="0.3")
        ax.plot(*np.asarray(ro.x0)[:2], "o", color="k", ms=5, label="x0", zorder=7)
        ax.plot([], [], color="tab:blue", lw=1, label=f"{R} rollouts")
        ax.plot([], [], color="red", lw=1, label=f"failures: {int((~ok).sum())} / {R}")
        ax.set_xlim(system.x_lo[0], system.x_hi[0])
        ax.set_ylim(system.x_lo[1], system.x_hi[1])
        ax.set_xlabel(labels[0])
        ax.set_title(f"{m} gap")
        if system.state_names[:2] == ("x", "y") or (units(system)[0][:2] == ("m", "m")):
            ax.set_aspect("equal")
    axes[0][0].set_ylabel(labels[1])
    axes[0][-1].legend(loc="best", fontsize=7, framealpha=0.9)
    fig.suptitle(f"{system.name}: closed-loop rollouts in the stochastic simulator")
    return save(fig, out_dir, "trajectories")


def states_time(run, out_dir: Path, max_drawn: int = 1000) -> list:
    """Each state over time, rows = states, columns = methods (see module docstring)."""
    plt = _plt()
    system = run.experiment.system
    labels, _ = _axis_labels(system)
    methods = [m for m in ("deterministic", "stochastic") if m in run.methods and run.methods[m].rollouts is not None]
    if not methods:
        return []
    n = system.n
    fig, axes = plt.subplots(n, len(methods), figsize=(5.2 * len(methods), 2.3 * n), squeeze=False, sharex=True,
                             sharey="row")
    for j, m in enumerate(methods):
        ro = run.methods[m].rollouts
        X = np.asarray(ro.trajectories)[:max_drawn]
        t = np.arange(X.shape[1]) * float(ro.tau)
        alpha = float(np.clip(20.0 / max(X.shape[0], 1), 0.03, 0.6))
        for i in range(n):
            ax = axes[i][j]
            ax.plot(t, X[:, :, i].T, color=METHOD_STYLE.get(m, "tab:blue"), lw=0.5, alpha=alpha)
            if ro.mean_map_trajectory is not None:
                ax.plot(t, np.asarray(ro.mean_map_trajectory)[:, i], color="magenta", lw=1.0, label="mean map")
            ax.plot(t, np.asarray(ro.mean_trajectory)[:, i], color="k", lw=0.7, ls="--", label="rollout average")
            if j == 0:
                ax.set_ylabel(labels[i])
            if i == 0:
                ax.set_title(f"{m} gap ({X.shape[0]} rollouts)")
            if i == n - 1:
                ax.set_xlabel("time [s]")
    axes[0][-1].legend(loc="best", fontsize=7)
    fig.suptitle(f"{system.name}: states over time, deterministic vs stochastic gap")
    return save(fig, out_dir, "states_time")


def gamma_slices(run, out_dir: Path, res: int = 201) -> list:
    """gamma_i along each state variable per method, with the nearby data gaps (see module docstring)."""
    plt = _plt()
    system = run.experiment.system
    labels, su = _axis_labels(system)
    n = system.n
    centre = 0.5 * (system.x_lo + system.x_hi)
    U = system.inputs
    u_mid = U[np.argmin(np.abs(U - U.mean(axis=0)).sum(axis=1))]
    fig, axes = plt.subplots(n, n, figsize=(3.6 * n, 2.6 * n), squeeze=False)
    for m, res_m in run.methods.items():
        cert, ds = res_m.certificate, res_m.dataset
        color = METHOD_STYLE.get(m, "tab:green")
        gaps = ds.gap() if ds is not None else None
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
                ax.plot(xs[:, j], g[:, i], color=color, lw=1.5, label=f"gamma, {m}")
                if near is not None and near.any():
                    ax.plot(ds.x[near, j], gaps[near, i], ".", color=color, ms=2, alpha=0.6,
                            label=f"data gap |mean - f|, {m}")
                ax.set_xlabel(labels[j])
                unit = f" [{su[i]} per step]" if su[i] else ""
                ax.set_ylabel(f"gamma_{system.state_names[i]}{unit}")
                ax.set_ylim(bottom=0)
    axes[0][-1].legend(fontsize=6, loc="best")
    fixed = ", ".join(f"{labelled(s, u)} = {c:.3g}" for s, u, c in zip(system.state_names, su, centre))
    inp = ", ".join(f"{labelled(nm, iu)} = {v:.3g}" for nm, iu, v in zip(system.input_names, units(system)[1], u_mid))
    fig.suptitle(f"{system.name}: gamma along each state (others at the centre of X: {fixed}; {inp})", fontsize=9)
    fig.tight_layout()
    return save(fig, out_dir, "gamma_slices")


def p_cert(run, out_dir: Path) -> list:
    """The per-run p_cert map with the validated initial states (see module docstring)."""
    if run.per_run is None:
        return []
    from .layers.perrun import pcert_map
    plt = _plt()
    system = run.experiment.system
    labels, _ = _axis_labels(system)
    pm = pcert_map(run.per_run.controller)
    fig, ax = plt.subplots(figsize=(6.2, 4.8))
    from matplotlib.colors import LinearSegmentedColormap
    from .layers.perrun import P_STOPS
    cmap = LinearSegmentedColormap.from_list("pcert", np.asarray(P_STOPS, float) / 255.0)
    im = ax.imshow(pm["p"].T, origin="lower", extent=(pm["lo"][0], pm["hi"][0], pm["lo"][1], pm["hi"][1]),
                   cmap=cmap, vmin=0, vmax=1, aspect="auto", interpolation="nearest")
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
    ax.legend(fontsize=7, loc="best")
    return save(fig, out_dir, "p_cert")


def plot_run(path, out_dir=None, max_drawn: int = 1000) -> list:
    """Every figure of the run folder ``path`` into ``out_dir`` (default ``path/figures``); the paths written."""
    from simgap.pipeline import experiment_spec

    from .results import load_run

    run = load_run(path)
    out = Path(out_dir) if out_dir is not None else Path(path) / "figures"
    if out.exists() and not out.is_dir():
        raise SimgapError(f"{str(out)!r} exists and is not a folder")
    if not out.parent.is_dir():
        raise SimgapError(f"folder {str(out.parent)!r} does not exist")
    spec, _, _ = experiment_spec(run.experiment)
    out.mkdir(exist_ok=True)
    written = []
    written += trajectories(run, spec, out, max_drawn)
    written += states_time(run, out, max_drawn)
    written += gamma_slices(run, out)
    written += p_cert(run, out)
    return written
