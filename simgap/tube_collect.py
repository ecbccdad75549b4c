"""Collect along the nominal box tubes: an experiment's cover replaced by :mod:`simgap.tube_cover`'s boxes
(``[collect] tube_margin``), for ``simgap run`` (docs/collect.md, "simgap run along the tube, in rounds").

Which tubes. The stochastic synthesis chooses the plan's pace among
:data:`~simgap.synthesis.tube_design.PACES` after the data are in (:mod:`simgap.synthesis.tube_design`),
and a proof reads gamma only inside the data's boxes (:meth:`Certificate.outside`: a tube box in none of
them fails the proof). A cover along the fastest pace's plan alone would leave every other pace's tube
without data: the search could then only prove that one. So the cover is the union over every pace the
search may choose (its plan proved by the nominal model, shorter than the rollouts' horizon: a longer plan
is ranked as unproved), each plan's boxes widened by the margin. The feedback gain K does not move a plan
(the plan has its own gain), only the tube's width around it, which the margin is for. With the pace given
(``plan_input_weight``, or ``K_plan``) only that plan is covered. Overlapping plans share the grid over their
boxes' hull when it is smaller (:func:`simgap.tube_cover.box_grid_points`), so the extra paces cost few
points.
"""

from __future__ import annotations

import numpy as np

from .errors import SimgapError
from .tube_cover import tube_boxes


def covered_paces(syn: dict) -> tuple:
    """The paces (plan input-weight factors) the stochastic synthesis may choose: the given one
    (``plan_input_weight``; ``(None,)`` for a given ``K_plan``), else every pace of the design search."""
    from .synthesis.tube_design import PACES
    if syn.get("K_plan") is not None:
        return (None,)
    if syn.get("plan_input_weight") is not None:
        return (float(syn["plan_input_weight"]),)
    return tuple(PACES)


def along_tube(exp, log=print):
    """``exp`` with its cover along its box tubes: ``[collect] tube_margin`` set, ``[synthesis] method =
    "box_tube"``. A tube is the nominal model's (no gap: the plan x_nom(t), its boxes' half-widths h_t and
    the smallest proved terminal box; the plan does not depend on data, so the region is fixed before any
    run), widened by the margin, for every pace of :func:`covered_paces` whose plan proves and ends within
    the rollouts' horizon (module docstring); the boxes go into ``[collect]``'s cover (``CoverSpec.boxes``),
    so the store's configuration (and hash) records them. Refused, naming why, when no nominal tube
    proves (no gap can help then) or another synthesis method is asked for."""
    import dataclasses

    from .experiment_spec import experiment_spec
    from .synthesis import set_synthesis

    c = exp.collect
    syn = exp.section("synthesis")
    if set_synthesis.method_of(syn) != "box_tube":
        raise SimgapError("[collect] tube_margin covers a box tube's boxes: it needs [synthesis] method = \"box_tube\"")
    if c.region:
        raise SimgapError("[collect] give a region or a tube_margin (a cover along the tube), not both")
    s = exp.system
    margin = np.asarray(c.tube_margin, float)
    if margin.size not in (1, s.n):
        raise SimgapError(f"[collect] tube_margin: one value or {s.n} (one per state {', '.join(s.state_names)}), "
                          f"got {list(c.tube_margin)}")
    ro = exp.section("rollout")
    if "x0" not in ro:
        raise SimgapError("[collect] tube_margin: the tube starts at [rollout] x0; give it")
    x0 = np.asarray(ro["x0"], float)
    if x0.shape != (s.n,):
        raise SimgapError(f"[rollout] x0: need {s.n} values, got {ro['x0']!r}")
    horizon = ro.get("horizon")
    spec = experiment_spec(exp)[0]
    set_synthesis.check_section(s, syn, spec)
    inv = {s.state_names.index(d) if isinstance(d, str) and d in s.state_names else
           (int(d[1:]) - 1 if isinstance(d, str) else int(d)) for d in c.invariant_dims}
    covered = [i for i in range(s.n) if i not in inv]
    los, his, kept, why = [], [], [], []
    for pace in covered_paces(syn):
        opts = dict(syn, terminal="smallest", margin_search=False, per_run=False)
        if pace is not None:
            opts["plan_input_weight"] = pace
        name = "the given K_plan" if pace is None else f"pace x{pace:g}"
        try:
            res = set_synthesis.synthesize(s, spec, None, opts, x0=x0)
        except SimgapError as e:  # this pace has no plan (it leaves X, or no stabilizing LQR): not covered
            why.append(f"{name}: {str(e).removeprefix('box tube: ')}")
            continue
        if res.empty:
            why.append(f"{name}: the nominal tube is not proved ({res.stats.get('diagnosis', '')})")
            continue
        ctrl = res.controller
        if horizon is not None and ctrl.T0 >= int(horizon):
            why.append(f"{name}: its plan's {ctrl.T0} periods outlast the runs' horizon {int(horizon)}")
            continue
        lo, hi = tube_boxes(s.x_lo, s.x_hi, ctrl.x_nom, ctrl.radii, margin, terminal=(ctrl.x_star, ctrl.H),
                            covered=covered)
        los.append(lo)
        his.append(hi)
        kept.append(f"{name} ({ctrl.T0} periods, {len(lo)} boxes, nominal synthesis {res.stats['seconds']:.1f} s)")
    if not kept:
        raise SimgapError("[collect] tube_margin: no nominal tube (no gap) is proved, so there is no tube to collect "
                          "along: " + "; ".join(why))
    lo, hi = np.concatenate(los), np.concatenate(his)
    log(f"[collect] along the nominal tubes of the paces the synthesis may choose: {'; '.join(kept)}"
        + (f"; not covered: {'; '.join(why)}" if why else "")
        + f"; {len(lo)} boxes (half-widths h_t + margin {np.round(margin, 6).tolist()}, the terminal boxes "
        "x* +- (H + margin))")
    boxes = tuple((a, b) for a, b in zip(lo.tolist(), hi.tolist()))
    return dataclasses.replace(exp, collect=dataclasses.replace(c, boxes=boxes))
