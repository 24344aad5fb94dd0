"""Geodesic distance: the simulator's Dijkstra fields, A* and corner graphs against a
reference Dijkstra (scipy) over the same 8-connected navigable grid without corner cutting."""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from plex_ma.envs.sim import Geodesics, Scene, SceneBank, rasterize

from .sim_helpers import (random_navigable_point, reference_distance, reference_field, reference_lookup,
                               reference_straight, room_walls, small_house, two_rooms_no_door)


@lru_cache(maxsize=1)
def house():
    grid = rasterize(small_house())
    bank = SceneBank([grid])
    return grid, bank, Geodesics(bank)


def field64(geo: Geodesics, grid, goal) -> np.ndarray:
    out = np.empty(grid.kind.size, np.float64)
    geo.field(0, goal, out=out)
    return out


def test_reference_sees_walls():
    # The reference itself: an L-shaped detour in a room split by a wall with a gap.
    walls = room_walls(0.0, 0.0, 4.0, 4.0) + [(2.0, 0.0, 2.0, 3.0)]
    grid = rasterize(Scene("gap", np.array(walls)))
    f = reference_field(grid, np.array([1.0, 0.5]))
    d = reference_lookup(grid, f, np.array([3.0, 0.5]))
    # around the wall's end (the agent's centre passes at y >= 3.15), not through it
    assert d > 2 * math.hypot(1.0, 3.15 - 0.5)
    assert d < 1.1 * 2 * math.hypot(1.0, 3.25 - 0.5)


def test_field_equals_reference_dijkstra():
    grid, bank, geo = house()
    rng = np.random.default_rng(0)
    for _ in range(3):
        goal = random_navigable_point(grid, rng)
        ours = field64(geo, grid, goal)
        ref = reference_field(grid, goal)
        reach = np.isfinite(ref)
        assert reach.sum() > 1000
        np.testing.assert_allclose(ours[reach], ref[reach], rtol=0, atol=1e-9)
        assert np.all(ours[~reach] >= 1e29)  # unreachable and non-navigable cells
        # The float32 field of the public API rounds the same values.
        np.testing.assert_allclose(geo.field(0, goal)[reach], ref[reach], rtol=1e-6)
        for _ in range(30):
            p = random_navigable_point(grid, rng)
            want = reference_lookup(grid, ref, p)
            assert geo.lookup(0, ours, p) == pytest_approx(want)
            assert geo.distance(0, p, goal) == pytest_approx(want)  # A*


def test_field_at_bucket_edges_equals_reference():
    """The field's bucket queue closes a cell once its distance falls in the current
    bucket [k cs, (k+1) cs). A goal on a cell centre puts the straight-line distances at
    exact multiples of cs, right on the bucket edges, where rounding decides the bucket."""
    grid, bank, geo = house()
    rng = np.random.default_rng(5)
    for _ in range(3):
        rc = np.argwhere(grid.nav)[rng.integers(int(grid.nav.sum()))]
        goal = grid.cell_center(rc)
        ours = field64(geo, grid, goal)
        ref = reference_field(grid, goal)
        reach = np.isfinite(ref)
        np.testing.assert_allclose(ours[reach], ref[reach], rtol=0, atol=1e-9)
        assert np.all(ours[~reach] >= 1e29)


def pytest_approx(x):
    return pytest.approx(x, rel=0, abs=1e-9)


def test_astar_equals_reference_between_far_points():
    grid, bank, geo = house()
    rng = np.random.default_rng(1)
    goal = random_navigable_point(grid, rng)
    ref = reference_field(grid, goal)
    far = [p for p in (random_navigable_point(grid, rng) for _ in range(200))
           if reference_lookup(grid, ref, p) > 6.0][:10]
    assert len(far) >= 5
    for p in far:
        want = reference_lookup(grid, ref, p)
        assert geo.distance(0, p, goal) == pytest_approx(want)
        assert geo.distance(0, goal, p) == pytest_approx(want)  # symmetric


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_geodesic_is_never_below_euclidean(seed):
    grid, bank, geo = house()
    rng = np.random.default_rng(seed)
    a, b = random_navigable_point(grid, rng), random_navigable_point(grid, rng)
    euclid = float(np.hypot(*(a - b)))
    d = geo.distance(0, a, b)
    assert math.isfinite(d)  # the small house is connected
    assert d >= euclid - 1e-9
    # the field lookup agrees with A*
    assert geo.lookup(0, field64(geo, grid, b), a) == pytest_approx(d)


def test_distance_to_goal_is_the_straight_line_in_the_open_and_the_grid_path_behind_a_wall():
    """The geodesic is the shortest path through free space: near the goal in the open it is
    the straight line (the grid's octile path and its links to cell centres read 0.205 m
    for 0.187 m, which decided whether a stop succeeded), and behind a wall the grid path
    round it."""
    from plex_ma.envs.sim import BatchedSim, Episode

    walls = room_walls(0.0, 0.0, 4.0, 4.0) + [(2.0, 0.0, 2.0, 3.0)]
    grid = rasterize(Scene("gap", np.array(walls)))
    sim = BatchedSim(SceneBank([grid]), 1, resolution=8, egomap=False)
    goal = np.array([1.0, 0.5])
    sim.reset_world(0, Episode(0, "gap", (3.0, 0.5), 0.0, tuple(goal), 5.0))
    ref = reference_field(grid, goal)
    grid_d = reference_lookup(grid, ref, np.array([3.0, 0.5]))
    assert sim.distance_to_goal[0] == pytest.approx(grid_d, abs=1e-5)  # round the wall's end (float32 field)
    gaps = 0
    rng = np.random.default_rng(0)
    for _ in range(200):
        ang = rng.uniform(-np.pi, np.pi)
        p = goal + rng.uniform(0.15, 0.25) * np.array([np.cos(ang), np.sin(ang)])
        if not grid.is_navigable(p):
            continue
        sim.reset_world(0, Episode(0, "gap", tuple(p), 0.0, tuple(goal), 1.0))
        e = float(np.hypot(*(p - goal)))
        assert sim.distance_to_goal[0] == pytest.approx(e, abs=1e-12)
        assert sim.distance_to(goal[None], np.array([0]))[0] == pytest.approx(e, abs=1e-12)
        gaps += reference_lookup(grid, ref, p) > e + 0.01
    assert gaps > 20  # where the grid alone reads a centimetre or more too far


def test_unreachable_points_are_inf():
    grid = rasterize(two_rooms_no_door())
    bank = SceneBank([grid])
    geo = Geodesics(bank)
    left, right = np.array([1.5, 1.5]), np.array([4.5, 1.5])
    assert geo.distance(0, left, right) == math.inf
    f = geo.field(0, right)
    assert geo.lookup(0, f, left) == math.inf
    assert geo.lookup(0, f, right + 0.3) == pytest.approx(0.3 * math.sqrt(2), abs=1e-6)
    # Inside a wall and outside the grid are unreachable too.
    assert geo.distance(0, left, np.array([3.0, 1.5])) == math.inf
    assert geo.distance(0, left, np.array([50.0, 50.0])) == math.inf
    assert geo.lookup(0, f, np.array([-20.0, 1.0])) == math.inf
    # Within one room distances stay finite and euclidean in free space.
    assert geo.distance(0, left, left + np.array([0.5, 0.5])) == pytest_approx(math.hypot(0.5, 0.5))


def test_corners_of_a_lone_obstacle_are_its_four_diagonal_neighbours():
    """A corner sits diagonally beside an obstacle's convex corner; a wall's straight side
    and the concave corners of a room make none."""
    from plex_ma.envs.sim.corners import corner_mask
    from plex_ma.envs.sim.kernels import move_mask

    nav = np.ones((7, 9), bool)
    nav[3, 4] = False  # one blocked cell in open floor
    got = corner_mask(move_mask(nav))
    want = np.zeros_like(nav)
    want[[2, 2, 4, 4], [3, 5, 3, 5]] = True
    assert np.array_equal(got, want)
    nav[:, 6] = False  # a wall across the room: straight sides, concave room corners
    nav[3, 4] = True
    assert not corner_mask(move_mask(nav)).any()


def random_obstacle_scene(seed: int) -> Scene:
    """A 4 m x 3 m room with random walls at any angle (their rasterised edges are
    staircases of corners) and random boxes."""
    rng = np.random.default_rng(seed)
    walls = room_walls(0.0, 0.0, 4.0, 3.0)
    for _ in range(rng.integers(1, 6)):
        walls.append(tuple(rng.uniform([0, 0, 0, 0], [4, 3, 4, 3])))
    boxes = [(x, y, x + rng.uniform(0.1, 1.0), y + rng.uniform(0.1, 1.0))
             for x, y in rng.uniform([0, 0], [3.5, 2.5], (rng.integers(0, 4), 2))]
    return Scene(f"obstacles-{seed}", np.array(walls), boxes=np.array(boxes).reshape(-1, 4),
                 box_heights=np.full(len(boxes), 0.8), box_categories=np.zeros(len(boxes), np.int64))


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_distance_to_equals_reference_dijkstra_among_random_obstacles(seed):
    """The sub-goal distance between any two points (the corner graph's, or the straight
    line where the agent could walk it) equals the reference Dijkstra's with the same
    shortcut, among random walls at any angle and boxes; ``inf`` exactly where the
    reference cannot reach."""
    from plex_ma.envs.sim import BatchedSim

    grid = rasterize(random_obstacle_scene(seed))
    rng = np.random.default_rng(seed)
    sim = BatchedSim(SceneBank([grid]), 16, resolution=8, egomap=False)
    for _ in range(3):
        target = random_navigable_point(grid, rng)
        ref = reference_field(grid, target)
        for i in range(16):
            sim.pos[i] = random_navigable_point(grid, rng)
        got = sim.distance_to(np.repeat(target[None], 16, 0), np.arange(16))
        want = np.array([reference_distance(grid, ref, p, target) for p in sim.pos])
        assert np.array_equal(np.isinf(got), np.isinf(want))
        fin = np.isfinite(want)
        np.testing.assert_allclose(got[fin], want[fin], rtol=0, atol=1e-9)


def test_distance_to_in_a_scene_with_too_many_corners_for_a_table(monkeypatch):
    """A scene with more corners than ``MAX_TABLE_CORNERS`` (walls at an angle are
    staircases of corners) gets no table and is answered by A* over the grid: the same
    distances as the reference."""
    from plex_ma.envs.sim import BatchedSim, corners

    grid = rasterize(random_obstacle_scene(7))
    bank = SceneBank([grid])
    n = int(corners.corner_mask(bank.moves).sum())
    assert n > 20
    monkeypatch.setattr(corners, "MAX_TABLE_CORNERS", n - 1)
    sim = BatchedSim(bank, 8, resolution=8, egomap=False)
    rng = np.random.default_rng(7)
    target = random_navigable_point(grid, rng)
    ref = reference_field(grid, target)
    for i in range(8):
        sim.pos[i] = random_navigable_point(grid, rng)
    got = sim.distance_to(np.repeat(target[None], 8, 0), np.arange(8))
    assert bank.corners.n_corners[0] == -1 and len(bank.corners.D) == 0
    want = np.array([reference_distance(grid, ref, p, target) for p in sim.pos])
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)


def test_distance_to_in_houses_equals_astar():
    """Sub-goals as the planner sets them (within 4 m, snapped; many behind walls) in
    procedural houses and real floor plans: the distance equals an independent A* (or the
    straight line, where the agent could walk it) from every position of a random walk, in
    rows of any subset of the worlds."""
    from plex_ma.envs.sim import BatchedSim, scene_bank
    from plex_ma.envs.sim.episodes import sample_episode

    checked = detour = 0
    for source in ("procgen", "r2v"):
        bank = scene_bank(source, "train", 4)
        geo = Geodesics(bank)
        rng = np.random.default_rng(0)
        sim = BatchedSim(bank, 4, resolution=8, egomap=False)
        for i in range(4):
            sim.reset_world(i, *sample_episode(bank, i, rng, geo))
        for step in range(60):
            if step % 6 == 0:
                ang = sim.heading + rng.uniform(-np.pi, np.pi, 4)
                raw = sim.pos + rng.uniform(0, 4, (4, 1)) * np.stack([np.cos(ang), np.sin(ang)], 1)
                targets = sim.snap_to_navigable(raw, np.arange(4))
            else:
                sim.step(rng.integers(1, 4, 4))
            rows = rng.permutation(4)[: rng.integers(1, 5)]
            got = sim.distance_to(targets, rows)
            assert np.all(np.isinf(np.delete(got, rows)))  # other rows untouched
            for i in rows:
                want = geo.distance(int(sim.scene_idx[i]), sim.pos[i], targets[i])
                grid = bank.grids[int(sim.scene_idx[i])]
                if reference_straight(grid, sim.pos[i], targets[i]):
                    want = min(want, float(np.hypot(*(targets[i] - sim.pos[i]))))
                assert got[i] == pytest.approx(want, rel=0, abs=1e-9)
                checked += 1
                detour += want > 1.3 * np.hypot(*(sim.pos[i] - targets[i])) + 0.1
        assert bank.corners.done[:4].all() and bank.corners.n_corners[:4].min() > 0
    assert checked > 200 and detour >= 20  # walls in the way, where the corners matter


def test_distance_to_an_unreachable_target_is_inf():
    from plex_ma.envs.sim import BatchedSim

    grid = rasterize(two_rooms_no_door())
    sim = BatchedSim(SceneBank([grid]), 1, resolution=8, egomap=False)
    sim.pos[0] = (1.5, 1.5)
    assert sim.distance_to(np.array([[4.5, 1.5]]), np.array([0]))[0] == math.inf
    target = np.array([[2.0, 2.0]])
    assert sim.distance_to(target, np.array([0]))[0] == pytest.approx(math.hypot(0.5, 0.5))
    sim.pos[0] = (1.0, 1.0)
    assert sim.distance_to(target, np.array([0]))[0] == pytest.approx(math.hypot(1.0, 1.0))


@settings(max_examples=40, deadline=None)
@given(st.floats(-1.0, 7.0), st.floats(-1.0, 4.0))
def test_snapped_subgoal_is_the_nearest_reachable_cell_centre(x, y):
    """Snapping (how the env places a sub-goal that is not navigable): the result is the
    nearest navigable cell centre of the agent's room (brute force over all cells); the other
    room, behind a wall without a door, is never chosen."""
    from plex_ma.envs.sim import BatchedSim

    grid = rasterize(two_rooms_no_door())
    sim = BatchedSim(SceneBank([grid]), 1, resolution=8, egomap=False)
    sim.pos[0] = (1.5, 1.5)  # left room
    got = sim.snap_to_navigable(np.array([[x, y]]), np.array([0]))[0]
    r, c = grid.world_to_cell(sim.pos[0])
    same = grid.nav & (grid.component == grid.component[r, c])
    pr, pc = grid.world_to_cell(np.array([x, y]))
    if 0 <= pr < grid.shape[0] and 0 <= pc < grid.shape[1] and same[pr, pc]:
        assert np.array_equal(got, [x, y])  # already reachable: kept as it is
        return
    rows, cols = np.nonzero(same)
    centres = grid.cell_center(np.stack([rows, cols], 1))
    best = np.min(np.hypot(centres[:, 0] - x, centres[:, 1] - y))
    assert math.hypot(got[0] - x, got[1] - y) == pytest.approx(best, abs=1e-9)
    assert got[0] < 3.0  # still in the left room


def test_move_mask_allows_exactly_the_grid_steps_of_the_search_graph():
    """The search graph as bits: a step is allowed into a navigable cell on the grid, and a
    diagonal one only when both cells beside it are navigable (no corner cutting)."""
    from plex_ma.envs.sim.kernels import MOVE_DC, MOVE_DR, move_mask

    rng = np.random.default_rng(3)
    nav = rng.random((7, 9)) < 0.7
    m = move_mask(nav)
    H, W = nav.shape
    for r in range(H):
        for c in range(W):
            for j, (dr, dc) in enumerate(zip(MOVE_DR, MOVE_DC)):
                rr, cc = r + dr, c + dc
                want = (nav[r, c] and 0 <= rr < H and 0 <= cc < W and nav[rr, cc]
                        and (dr == 0 or dc == 0 or (nav[r, cc] and nav[rr, c])))
                assert bool(m[r, c] >> j & 1) == want, (r, c, dr, dc)


def test_bench_geodesic_runs(capsys):
    """``python -m plex_ma.bench geodesic``: the corner graphs and A* agree on its queries."""
    import json

    from plex_ma.bench import main

    main(["geodesic", "--queries", "60", "--astar-queries", "30", "--num-scenes", "3", "--json"])
    out = json.loads(capsys.readouterr().out)
    assert out["queries"] == 60 and out["astar_queries"] == 30 and out["scenes"] == 3
    assert out["max_abs_difference_m"] < 1e-9
    assert out["corner_graph_us_per_query"] > 0 and out["astar_us_per_query"] > 0
