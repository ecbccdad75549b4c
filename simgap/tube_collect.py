"""Collect along the nominal box tube: an experiment's cover replaced by :mod:`simgap.tube_cover`'s boxes
(``[collect] tube_margin``), for ``simgap run`` (docs/collect.md, "simgap run along the tube, in rounds")."""

from __future__ import annotations

import numpy as np

from .errors import SimgapError
from .tube_cover import tube_boxes


def along_tube(exp, log=print):
    """``exp`` with its cover along its box tube: ``[collect] tube_margin`` set, ``[synthesis] method =
    "box_tube"``. The tube is the nominal model's (no gap: the plan x_nom(t), its boxes' half-widths h_t
    and the smallest proved terminal box; the plan does not depend on data, so the region is fixed before
    any run), widened by the margin; the boxes go into ``[collect]``'s cover (``CoverSpec.boxes``), so the
    store's configuration (and hash) records them. Refused, naming why, when the nominal tube does not
    prove (no gap can help then) or another synthesis method is asked for."""
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
    spec = experiment_spec(exp)[0]
    set_synthesis.check_section(s, syn, spec)
    res = set_synthesis.synthesize(s, spec, None, dict(syn, terminal="smallest", margin_search=False,
                                                         per_run=False), x0=x0)
    if res.empty:
        raise SimgapError("[collect] tube_margin: the nominal tube (no gap) is not proved, so there is no tube to "
                          f"collect along: {res.stats.get('diagnosis', '')}")
    ctrl = res.controller
    inv = {s.state_names.index(d) if isinstance(d, str) and d in s.state_names else
           (int(d[1:]) - 1 if isinstance(d, str) else int(d)) for d in c.invariant_dims}
    lo, hi = tube_boxes(s.x_lo, s.x_hi, ctrl.x_nom, ctrl.radii, margin, terminal=(ctrl.x_star, ctrl.H),
                        covered=[i for i in range(s.n) if i not in inv])
    log(f"[collect] along the nominal tube: {ctrl.T0} periods, {len(lo)} boxes (half-widths h_t + margin "
        f"{np.round(margin, 6).tolist()}, the terminal box x* +- (H + margin)); nominal synthesis "
        f"{res.stats['seconds']:.1f} s")
    boxes = tuple((a, b) for a, b in zip(lo.tolist(), hi.tolist()))
    return dataclasses.replace(exp, collect=dataclasses.replace(c, boxes=boxes))
