"""2-D plots in the panel (viser's uPlot charts), where a plot says more than the 3-D scene.

* gamma along one variable (the View tab's slice, the other variables at their sliders) with the
  observed data gaps of the rows near that line: how much room the certificate leaves;
* the audit's margins gamma - gap at fresh points, as a histogram per dimension (from the
  per-point margins ``audit_<method>.json`` stores), for a run's certificate;
* the refinement residuals before and after (binned means against the chosen variable).

Each function computes nothing itself: it reads engine results and the layer geometry.
"""

from __future__ import annotations

import numpy as np

from simgap.systems import labelled, units

from ..layers import geometry as G

ORANGE, BLUE, RED, GREEN = "#f07800", "#2850c8", "#d23232", "#28a050"
PADDING = (12, 24, 0, 0)  # the charts' padding (top, right, bottom, left) [px], see add()


def _axes(x: str, y: str) -> tuple:
    return ({"label": x, "size": 40}, {"label": y, "size": 72})


def y_label(unit: str, k: int = 0) -> str:
    """gamma's axis label: "gamma, gap [1e-3 rad/s]" (values in units of 10^k of the state's unit, a
    next state's, per step). Short: uPlot clips a rotated label longer than the chart is high, which
    the earlier "gamma, gap [rad/s/step] [x 1e-3]" was in the panel (tests/test_browser_app.py)."""
    scale = f"1e{k}" if k else ""
    inner = " ".join(t for t in (scale, unit) if t)
    return "gamma, gap" + (f" [{inner}]" if inner else "")


def _empty(plot) -> None:
    plot.visible = False


def gamma_slice(app, plot, res: int = 161) -> int:
    """gamma_dim along the View tab's first variable, data gaps as points; returns the points shown."""
    cert, data = app.results.get("certify"), app.results.get("collect")
    if cert is None:
        _empty(plot)
        return 0
    s, v = app.system, app.view
    fixed = v["fixed"] if v["fixed"] is not None else list(G.variable_ranges(s).mean(axis=1))
    a, dim = v["a"], v["dim"]
    names = G.variable_names(s)
    lo, hi = G.variable_ranges(s)[a]
    P = np.tile(np.asarray(fixed, float), (res, 1))
    P[:, a] = np.linspace(lo, hi, res)
    xs = P[:, a]
    gam = np.asarray(cert.gamma(P[:, :s.n], P[:, s.n:]), dtype=float)[:, dim]
    gap = np.full(res, np.nan)
    # rows on the line: every variable but a near its fixed value (a slice over (a, a))
    rows = G.data_slice(data, s, a, a, fixed, max_points=4000) if data is not None else np.zeros(0, int)
    if rows.size:
        xd = np.hstack([data.x, data.u])[rows, a]
        order = np.argsort(np.concatenate([xs, xd]), kind="stable")
        xs = np.concatenate([xs, xd])[order]
        gam = np.concatenate([gam, np.full(xd.shape, np.nan)])[order]
        gap = np.concatenate([gap, data.gap()[rows, dim]])[order]
    plot.series = ({"label": names[a]}, {"label": f"gamma_{s.state_names[dim]}", "stroke": BLUE, "width": 2,
                                         "spanGaps": True},
                   {"label": "data gap", "stroke": ORANGE, "width": 0, "points": {"show": True, "size": 4,
                                                                                   "fill": ORANGE}})
    # uPlot's tick labels keep a few decimals: show small or large values in units of 10^k
    top = float(np.nanmax(np.concatenate([gam, gap])))
    k = int(np.floor(np.log10(top))) if top > 0 else 0
    k = k if (k < -2 or k > 3) else 0
    plot.data = (xs, gam / 10.0 ** k, gap / 10.0 ** k)
    su, iu = units(s)
    vu = (list(su) + list(iu))[a]
    plot.axes = _axes(labelled(names[a], vu), y_label(su[dim], k))
    # from 0: gamma and gaps are >= 0, and a flat gamma (a constant certificate) has no range of
    # its own for uPlot to scale to
    plot.scales = {"x": {"time": False}, "y": {"range": (0.0, 1.1 * top / 10.0 ** k if top > 0 else 1.0)}}
    plot.title = f"gamma_{s.state_names[dim]} along {names[a]}"
    plot.visible = True
    return int(rows.size)


def audit_margins(app, plot, bins: int = 30) -> bool:
    """Histogram of the audit's margins gamma - gap at fresh points per dimension, each divided by
    its dimension's largest margin so the dimensions share one axis (a bar left of 0 is a point
    where the estimated gap exceeds gamma). Older reports without per-point margins show their
    margin quantiles instead."""
    rep = app.audit
    run = app.run
    shown = app.results.get("certify")
    # the nominal model of an invariant-set run shows the stochastic certificate and its audit
    src = None if run is None else run.methods.get(app.run_method, run.methods.get("stochastic"))
    if rep is None or src is None or shown is not src.certificate:
        _empty(plot)
        return False
    dims = list(rep.get("per_dim", {}))
    if not dims:
        _empty(plot)
        return False
    colors = ("#2850c8", "#e07020", "#30a050", "#a040c0")
    if all("margins" in rep["per_dim"][d] for d in dims):
        m = [np.asarray(rep["per_dim"][d]["margins"], float) for d in dims]
        scale = [max(float(np.abs(v).max()), 1e-300) for v in m]
        edges = np.linspace(min(0.0, min(float((v / sc).min()) for v, sc in zip(m, scale))), 1.0, bins + 1)
        centers = 0.5 * (edges[:-1] + edges[1:])
        ys = [np.histogram(v / sc, edges)[0].astype(float) for v, sc in zip(m, scale)]
        series = [{"label": "margin / max margin"}] + [
            {"label": f"{d} (max {sc:.3g}, {int((v < 0).sum())} < 0)", "stroke": colors[k % 4], "width": 2,
             "points": {"show": True, "size": 4}} for k, (d, v, sc) in enumerate(zip(dims, m, scale))]
        plot.data = (centers,) + tuple(ys)
        plot.axes = _axes("(gamma - gap) / largest margin", "audit points")
        kind = "margin histogram"
    else:
        qs = sorted(float(q) for q in rep["per_dim"][dims[0]]["margin_quantiles"])
        series, ys = [{"label": "quantile"}], []
        for k, d in enumerate(dims):
            mq = rep["per_dim"][d]["margin_quantiles"]
            y = np.array([mq[_key(mq, q)] for q in qs], float)
            ys.append(y)
            series.append({"label": f"{d} [{y.min():.3g} .. {y.max():.3g}]", "stroke": colors[k % 4], "width": 2,
                           "points": {"show": True, "size": 5}})
        plot.data = (np.array(qs),) + tuple(ys)
        plot.axes = _axes("quantile of the audit points", "gamma - gap")
        kind = "margin quantiles"
    plot.series = tuple(series)
    pj = rep.get("joint", {}).get("fraction_holds")
    # short, centred: a long title runs under the chart's fullscreen icon; the rest is in the legend
    plot.title = f"audit: {kind}" + (f", joint holds {pj:.3f}" if pj is not None else "")
    series[0]["label"] = f"{series[0]['label']} ({rep.get('points', '?')} points x {rep.get('runs', '?')} runs)"
    plot.visible = True
    return True


def _key(d: dict, q: float) -> str:
    for k in d:
        if float(k) == q:
            return k
    raise KeyError(q)


def residuals(app, plot) -> bool:
    """Binned mean residual of the chosen state against the chosen variable, before (f) and after (f')."""
    res = app.results.get("refine")
    if res is None:
        _empty(plot)
        return False
    s = res.system
    v = app.view
    state = v.get("res_state", s.n - 1)
    var = v.get("res_var") or s.state_names[-1]
    b0, b1 = res.before.binned(var, bins=30), res.after.binned(var, bins=30)
    plot.data = (np.asarray(b0["centers"], float), np.asarray(b0["mean"][:, state], float),
                 np.asarray(b1["mean"][:, state], float))
    plot.series = ({"label": var}, {"label": "before (f)", "stroke": RED, "width": 2},
                   {"label": "after (f')", "stroke": GREEN, "width": 2})
    plot.axes = _axes(var, f"residual {s.state_names[state]}")
    plot.title = f"mean residual of {s.state_names[state]} against {var}"
    plot.visible = True
    return True


def add(gui, title: str):
    """An empty, hidden chart (its data and series are set by the functions above)."""
    z = np.zeros(2)
    # x is a state variable or a margin, not a time: uPlot's default x scale would print dates
    # padding (top, right, bottom, left) [px]: room above the plot for the top tick's label (uPlot's
    # default let the title and that label clip at the canvas' top) and right of it for the last x
    # tick's (0: uPlot sizes the axes' sides itself)
    return gui.add_uplot(data=(z, z), series=({"label": "x"}, {"label": "y"}), title=title, aspect=1.4,
                         scales={"x": {"time": False}}, visible=False, padding=PADDING)
