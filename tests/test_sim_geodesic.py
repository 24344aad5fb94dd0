"""Geodesic distance: the simulator's Dijkstra fields and A* against a reference Dijkstra
(scipy) over the same 8-connected navigable grid without corner cutting."""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from plex_ma.envs.sim import Geodesics, Scene, SceneBank, rasterize

from .test_sim_helpers import (random_navigable_point, reference_field, reference_lookup, room_walls,
                               small_house, two_rooms_no_door)


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
