"""Parity with SCOTS v2 on its vehicle example (numbers measured with SCOTS on this machine)."""

from __future__ import annotations

import numpy as np
import pytest

from simgap.synthesis.abstraction import build_abstraction
from simgap.synthesis.controller import synthesize
from simgap.synthesis.examples import (SCOTS_VEHICLE_TRANSITIONS, SCOTS_VEHICLE_WINNING, VEHICLE_ETA,
                                       vehicle_growth, vehicle_spec, vehicle_system)
from simgap.synthesis.grid import UniformGrid


def test_vehicle_winning_domain_and_transitions_match_scots():
    res = synthesize(vehicle_system(), vehicle_spec(), VEHICLE_ETA, growth=vehicle_growth,
                     strict_domain=False)
    s = res.stats
    assert s["grid_shape"] == [51, 51, 35] and s["inputs"] == 49
    assert s["target_cells"] == 140
    assert s["transitions"] == SCOTS_VEHICLE_TRANSITIONS == 35_772_302
    assert s["winning"] == SCOTS_VEHICLE_WINNING == 48018
    assert s["winning_with_target"] == 48158
    ctrl = res.controller
    x0 = np.array([[0.6, 0.6, 0.0]])
    assert ctrl.winning(x0)[0] and ctrl.steps_to_go(x0)[0] > 0


def test_shared_boxes_equal_scots_formula_per_cell(rng):
    """The translation-invariant boxes equal SCOTS's compute_gb evaluated at the real centers."""
    sysm = vehicle_system()
    g = UniformGrid(sysm.x_lo, sysm.x_hi, VEHICLE_ETA)
    ab = build_abstraction(sysm, g, growth=vehicle_growth, invariant_dims=(0, 1))
    ids = rng.integers(0, g.size, 3000)
    j = rng.integers(0, 49, 3000)
    x = g.points(ids)
    u = sysm.inputs[j]
    eta = g.eta
    z = eta / 1e10
    r = vehicle_growth(np.broadcast_to(eta / 2 + z, x.shape), x, u, 0.3)
    xn = sysm.f(x, u)
    left, right = xn - r - z, xn + r + z
    out = np.any((left <= g.first - eta / 2) | (right >= g.last + eta / 2), axis=1)
    lo = np.floor((left - g.first + eta / 2) / eta).astype(int)
    hi = np.floor((right - g.first + eta / 2) / eta).astype(int)
    mi = g.ids_to_multi(ids)
    k = ab.cell_class(mi)
    alo = mi + ab.off_lo[k, j]
    ahi = mi + ab.off_hi[k, j]
    shape = np.array(g.shape)
    aout = ~ab.ok[k, j] | np.any((alo < 0) | (ahi > shape - 1), axis=1)
    assert np.array_equal(out, aout)
    assert np.array_equal(lo[~out], alo[~out]) and np.array_equal(hi[~out], ahi[~out])
    assert (~out).sum() > 1500


@pytest.mark.slow
def test_vehicle_parity_without_shared_boxes():
    """The generic path (every cell integrated on its own, as SCOTS does) gives the same counts."""
    res = synthesize(vehicle_system(), vehicle_spec(), VEHICLE_ETA, growth=vehicle_growth,
                     strict_domain=False, invariant_dims=())
    assert res.stats["classes"] == 91035
    assert res.stats["transitions"] == 35_772_302 and res.stats["winning"] == 48018
