"""Time in the refinement loop: episodes kept apart, time-dependent residuals flagged."""

import numpy as np
import pytest

from simgap.refine.cases import make_case, verdict
from simgap.refine.data import episodes, history, load_transitions, make_transitions, time_order
from simgap.refine.report import refine
from simgap.errors import SimgapError


def _restart_clocks(data, runs=40):
    """The same record as episodes whose clocks each start at 0 (as a logger of episodes writes)."""
    T = data.K // runs
    return make_transitions(data.x, data.u, data.x_next, data.tau, (np.arange(data.K) % T) * data.tau,
                            source="episodes")


def test_episodes_with_clocks_from_zero_keep_their_histories():
    """Sorting all rows by t across episodes interleaves them: the delay was named an input gain."""
    c = make_case("delay1", 8000)
    d = _restart_clocks(c.data)
    ep = episodes(d)
    assert ep.max() == 39 and np.all(np.bincount(ep) == 200)
    hist, valid = history(d, 1)
    assert valid.sum() == 8000 - 40                  # only each episode's first row lacks history
    k = 201                                          # second row of episode 1: its history is row 200
    np.testing.assert_array_equal(hist[k], np.concatenate([d.x[200], d.u[200]]))
    rep = refine(c.system, d).report
    ok, desc = verdict(c, rep)
    assert ok, desc
    assert rep["history"]["lags"] >= 1 and not any(e["name"] == "input_gain" for e in rep["effects"])


def test_explicit_episode_ids_survive_shuffled_rows_and_files(tmp_path):
    c = make_case("delay1", 8000)
    d = _restart_clocks(c.data)
    ep = episodes(d)
    perm = np.random.default_rng(0).permutation(d.K)
    shuffled = make_transitions(d.x[perm], d.u[perm], d.x_next[perm], d.tau, d.t[perm], episode=ep[perm])
    order = time_order(shuffled)
    np.testing.assert_array_equal(perm[order], np.arange(d.K))      # back in episode-major time order
    # .npz and .csv keep the ids
    shuffled.save_npz(tmp_path / "s.npz")
    back = load_transitions(tmp_path / "s.npz")
    np.testing.assert_array_equal(back.episode, ep[perm])
    cols = np.column_stack([d.x, d.x_next, d.u, np.full(d.K, d.tau), d.t, ep])
    np.savetxt(tmp_path / "s.csv", cols[perm], delimiter=",", comments="",
               header="x1,x2,x1_next,x2_next,u1,tau,t,episode")
    back = load_transitions(tmp_path / "s.csv")
    rep = refine(c.system, back).report
    assert verdict(c, rep)[0], verdict(c, rep)[1]
    with pytest.raises(SimgapError, match="integer ids"):
        make_transitions(d.x, d.u, d.x_next, d.tau, d.t, episode=np.full(d.K, 0.5))
    with pytest.raises(SimgapError, match="need time stamps"):
        make_transitions(d.x, d.u, d.x_next, d.tau, episode=ep)


def test_one_clock_in_shuffled_rows_is_still_one_record():
    c = make_case("delay1", 8000)
    d = c.data
    perm = np.random.default_rng(1).permutation(d.K)
    s = make_transitions(d.x[perm], d.u[perm], d.x_next[perm], d.tau, d.t[perm])
    assert np.all(episodes(s) == 0)
    np.testing.assert_array_equal(perm[time_order(s)], np.argsort(d.t, kind="stable"))
