"""Obstacle maps: the shipped arena, spec lifting, meshes, and every bad map input."""

import re

import numpy as np
import pytest

from simgap.errors import SimgapError
from simgap.maps import ArenaMap, available_maps, load_map
from simgap.systems import pendulum, turtlebot

GOOD = dict(name="t", bounds=[0, 4, 0, 4], robot_radius=0.1, initial_state=[3.5, 2.0, 1.5],
            target=[0.2, 0.9, 0.2, 0.9], obstacles=[[1.7, 2.2, 0.0, 2.6]])


def write(tmp_path, text, name="m.toml"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_arena_ships_and_matches_the_case_study():
    assert "arena" in available_maps()
    m = load_map("arena")
    assert m.bounds.tolist() == [0, 4, 0, 4]
    np.testing.assert_allclose(m.initial_state, [3.5, 2.0, 1.5])
    assert len(m.obstacles) >= 2 and m.robot_radius > 0
    # every obstacle and the target inside or touching [0, 4]^2
    assert np.all(m.obstacles[:, [0, 2]] >= 0) and np.all(m.obstacles[:, [1, 3]] <= 4)
    x0 = m.x0(turtlebot())
    np.testing.assert_allclose(x0, [3.5, 2.0, 1.5])


def test_arena_passages_are_wide_enough():
    """A point robot moving on a 0.05 grid from x0 reaches the target while keeping 0.25 m from every
    grown obstacle (corridors >= 0.5 m for the centre)."""
    m = load_map("arena")
    h = 0.05
    xs = np.arange(0, 4 + h / 2, h)
    X, Y = np.meshgrid(xs, xs, indexing="ij")
    free = np.ones(X.shape, bool)
    for g in m.inflated_obstacles + np.array([-0.25, 0.25, -0.25, 0.25]):
        free &= ~((X >= g[0]) & (X <= g[1]) & (Y >= g[2]) & (Y <= g[3]))
    start = (int(round(3.5 / h)), int(round(2.0 / h)))
    assert free[start]
    seen = np.zeros_like(free)
    seen[start] = True
    frontier = [start]
    while frontier:  # BFS over a small grid (test only)
        nxt = []
        for i, j in frontier:
            for a, b in ((i + 1, j), (i - 1, j), (i, j + 1), (i, j - 1)):
                if 0 <= a < free.shape[0] and 0 <= b < free.shape[1] and free[a, b] and not seen[a, b]:
                    seen[a, b] = True
                    nxt.append((a, b))
        frontier = nxt
    tgt = (X >= m.target[0]) & (X <= m.target[1]) & (Y >= m.target[2]) & (Y <= m.target[3])
    assert (seen & tgt).any()
    # and the straight line from start to target is blocked: the obstacles matter
    t = np.linspace(0, 1, 400)[:, None]
    line = (1 - t) * np.array([3.5, 2.0]) + t * np.array([0.55, 0.55])
    hit = np.zeros(len(line), bool)
    for g in m.inflated_obstacles:
        hit |= (line[:, 0] >= g[0]) & (line[:, 0] <= g[1]) & (line[:, 1] >= g[2]) & (line[:, 1] <= g[3])
    assert hit.any()


def test_spec_lifts_boxes_and_inflates():
    m = load_map("arena")
    s = m.spec(turtlebot())
    assert s.kind == "reach_avoid" and len(s.obstacles) == len(m.obstacles)
    assert s.target.lo[2] == -np.inf and s.target.hi[2] == np.inf
    np.testing.assert_allclose(s.obstacles[0].lo[:2], m.obstacles[0][[0, 2]] - m.robot_radius)
    # a point just outside the physical box but within the radius is an obstacle hit for the spec
    o = m.obstacles[0]
    p = np.array([[o[1] + 0.5 * m.robot_radius, 0.5 * (o[2] + o[3]), 0.3]])
    assert s.in_obstacle(p)[0]
    assert s.reached(np.array([[0.5, 0.5, 3.0]]))[0]  # heading unconstrained
    assert m.simulator_options() == {"obstacles": m.obstacle_boxes}
    assert m.obstacle_boxes[0] == [float(v) for v in o]


def test_meshes_are_trimesh_boxes():
    m = load_map("arena")
    ms = m.meshes(height=0.25)
    assert len(ms["obstacles"]) == len(m.obstacles)
    b = ms["obstacles"][0].bounds
    np.testing.assert_allclose(b[0], [m.obstacles[0][0], m.obstacles[0][2], 0.0])
    np.testing.assert_allclose(b[1], [m.obstacles[0][1], m.obstacles[0][3], 0.25])
    assert ms["target"].is_watertight
    gi = m.meshes(inflated=True)["obstacles"][0].bounds
    np.testing.assert_allclose(gi[0][:2], [m.obstacles[0][0] - 0.1, m.obstacles[0][2] - 0.1])


def test_toml_file_round_trip(tmp_path):
    p = write(tmp_path, """
name = "mine"
bounds = [0, 4, 0, 4]
initial_state = [1.0, 1.0, 0.0]
target = [3, 3.5, 3, 3.5]
obstacles = [[2, 2.5, 0, 2]]
""")
    m = load_map(p)
    assert m.name == "mine" and m.robot_radius == 0.0
    assert ArenaMap.from_dict(m.to_dict()).to_dict() == m.to_dict()


@pytest.mark.parametrize("change, message", [
    (dict(target=[1.8, 2.0, 1.0, 1.5]), "overlaps obstacle 0"),           # target inside an obstacle
    (dict(target=[1.2, 1.65, 1.0, 1.5]), "grown by robot_radius"),        # overlaps only the grown box
    (dict(target=[3.5, 4.5, 3.0, 3.5]), "not inside the arena"),          # target outside X
    (dict(target=[1.0, 1.0, 3.0, 3.5]), "target [1.0, 1.0, 3.0, 3.5] is empty"),  # zero area
    (dict(target=[1.0, 0.5, 3.0, 3.5]), "is empty"),                      # reversed
    (dict(initial_state=[1.9, 1.0, 0.0]), "initial_state"),               # in an obstacle
    (dict(initial_state=[2.25, 1.0, 0.0]), "grown by robot_radius"),      # in the grown obstacle only
    (dict(initial_state=[4.5, 1.0, 0.0]), "outside the arena"),
    (dict(initial_state=[1.0]), "at least (x, y)"),
    (dict(robot_radius=-0.1), "robot_radius"),
    (dict(obstacles=[[1, 2, 3]]), "obstacle 0 must be 4"),
    (dict(obstacles=[[1, 2, 3, float("nan")]]), "finite"),
    (dict(bounds=[0, 4, 4, 0]), "bounds"),
    (dict(colour="red"), "unknown keys"),
])
def test_bad_maps(change, message):
    d = dict(GOOD, **change)
    with pytest.raises(SimgapError, match=re.escape(message)):
        ArenaMap.from_dict(d, source="bad.toml")


def test_missing_keys_and_files(tmp_path):
    d = dict(GOOD)
    del d["target"]
    with pytest.raises(SimgapError, match="missing keys"):
        ArenaMap.from_dict(d)
    with pytest.raises(SimgapError, match="unknown map 'nowhere'"):
        load_map("nowhere")
    with pytest.raises(SimgapError, match="does not exist"):
        load_map(tmp_path / "absent.toml")
    with pytest.raises(SimgapError, match="not valid TOML"):
        load_map(write(tmp_path, "bounds = [0, 4,"))


def test_spec_against_a_system():
    m = ArenaMap.from_dict(dict(GOOD, bounds=[0, 6, 0, 6], target=[4.5, 5.0, 4.5, 5.0]))
    with pytest.raises(SimgapError, match="not inside X of system 'turtlebot'"):
        m.spec(turtlebot())
    with pytest.raises(SimgapError, match="initial_state"):
        ArenaMap.from_dict(dict(GOOD, bounds=[0, 6, 0, 6], initial_state=[5, 5, 0])).x0(turtlebot())
    # a 2-D system: the heading component is dropped by refusing extra components
    with pytest.raises(SimgapError, match="3 components"):
        load_map("arena").x0(pendulum())


def test_clearance_is_the_signed_distance_to_the_grown_obstacles():
    """Outside: Euclidean distance to the nearest grown box (also past a corner); inside: minus
    the depth; the spec's obstacle test agrees with the sign; points broadcast over (..., n)."""
    from simgap.systems import get_system

    m = load_map("arena")                   # grown boxes: robot_radius 0.1 on every side
    sysm = get_system("turtlebot")
    wall = m.inflated_obstacles[0]          # [1.6, 2.3, -0.1, 2.7]
    pts = np.array([[wall[0] - 0.25, 1.0, 0.3],         # left of the wall: 0.25
                    [wall[1] + 0.05, 2.7 + 0.05, 0.0],  # past the top-right corner: 0.05 sqrt 2
                    [wall[0] + 0.1, 1.0, 0.0],          # inside, 0.1 from the left face
                    [(wall[0] + wall[1]) / 2, 1.0, 0.0]])  # inside at the centre line: half the width
    d = m.clearance(pts)
    half = (wall[1] - wall[0]) / 2
    assert np.allclose(d, [0.25, 0.05 * np.sqrt(2), -0.1, -half])
    assert np.array_equal(d < 0, m.spec(sysm).in_obstacle(pts))
    assert m.clearance(np.stack([pts, pts])).shape == (2, 4)
