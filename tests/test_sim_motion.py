"""Motion and obstacles: the agent (a disc of radius 0.1 m) never enters an obstacle of the
scene's exact geometry; a collision is flagged exactly when a forward move falls short."""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from plex_ma.envs.sim import (MOVE_FORWARD, STOP, TURN_LEFT, TURN_RIGHT, BatchedSim, Episode, Geodesics, Scene,
                              SceneBank, rasterize)
from plex_ma.envs.sim.scene import AGENT_RADIUS

from .sim_helpers import (obstacle_clearance, random_navigable_point, room_walls, segment_distance, wall_pieces,
                               sim_at, small_house)


def furnished_room() -> Scene:
    """Two rooms joined by a door, an interior wall stub, furniture against walls and
    free-standing, and a narrow gap between two boxes."""
    walls = room_walls(0.0, 0.0, 8.0, 5.0) + [(4.0, 0.0, 4.0, 5.0), (1.0, 3.0, 2.5, 3.0)]
    doors = [(4.0, 2.0, 4.0, 2.9)]
    boxes = [(0.05, 0.05, 1.0, 0.8), (2.0, 1.0, 2.6, 1.6), (2.95, 1.0, 3.3, 1.6), (5.0, 3.5, 6.5, 4.95),
             (6.0, 1.0, 6.4, 1.4)]
    return Scene("furnished", np.array(walls), doors=np.array(doors), boxes=np.array(boxes),
                 box_heights=[0.75, 0.5, 0.9, 2.0, 1.2], box_categories=[0, 1, 3, 4, 5])


def closed_room() -> Scene:
    """One room without doors: a wall stub, a pillar and boxes."""
    walls = room_walls(0.0, 0.0, 5.0, 4.0) + [(2.0, 4.0, 2.0, 2.5), (3.5, 1.5, 3.5, 1.5)]
    boxes = [(0.5, 0.5, 1.5, 1.0), (3.0, 2.8, 3.4, 3.2)]
    return Scene("closed", np.array(walls), wall_thickness=0.2, boxes=np.array(boxes), box_heights=[0.5, 1.0],
                 box_categories=[1, 7])


WORLDS = {"house": small_house, "furnished": furnished_room, "closed": closed_room}


@lru_cache(maxsize=3)
def world(name: str):
    scene = WORLDS[name]()
    grid = rasterize(scene)
    return scene, grid, SceneBank([grid])


def test_scenes_have_obstacles_and_doors():
    for name in WORLDS:
        scene, grid, _ = world(name)
        rects, _ = wall_pieces(scene)
        assert len(scene.boxes) and (name == "closed" or len(rects) > len(scene.walls))
        assert int(grid.component.max()) == 0  # one connected navigable component


actions = st.lists(st.sampled_from([MOVE_FORWARD] * 4 + [TURN_LEFT, TURN_RIGHT, STOP]), min_size=1, max_size=250)


@settings(max_examples=40, deadline=None)
@given(name=st.sampled_from(sorted(WORLDS)), seed=st.integers(0, 2**32 - 1), acts=actions)
def test_random_walks_never_enter_obstacles(name, seed, acts):
    scene, grid, bank = world(name)
    rng = np.random.default_rng(seed)
    start = random_navigable_point(grid, rng)
    sim = BatchedSim(bank, 1, resolution=8, egomap=False)
    sim.reset_world(0, Episode(0, scene.scene_id, tuple(start), float(rng.uniform(-math.pi, math.pi)),
                               tuple(start), 1.0))
    solid_walls = scene.walls if not len(scene.doors) else None
    for a in acts:
        old, h = sim.pos[0].copy(), float(sim.heading[0])
        collided = bool(sim.step(np.array([a]))[0])
        p = sim.pos[0]
        assert grid.is_navigable(p), f"centre {p} left the navigable cells"
        clearance = obstacle_clearance(p, scene)
        assert clearance >= AGENT_RADIUS - 1e-9, f"disc at {p} overlaps an obstacle ({clearance:.4f} m)"
        if solid_walls is not None:
            assert segment_distance(p, solid_walls).min() >= scene.wall_thickness / 2 + AGENT_RADIUS - 1e-9
        if a == MOVE_FORWARD:
            target = old + 0.25 * np.array([math.cos(h), math.sin(h)])
            short = float(np.hypot(*(p - target))) > 1e-9
            assert collided == short, f"collision flag {collided} but the move fell short: {short}"
            # a blocked move may slide, but never goes backwards or beyond the step
            progress = float(np.dot(p - old, [math.cos(h), math.sin(h)]))
            assert -1e-9 <= progress <= 0.25 + 1e-9
            assert float(np.hypot(*(p - old))) <= 0.25 + 1e-9
        else:
            assert not collided
            np.testing.assert_array_equal(p, old)
            turn = {TURN_LEFT: 10.0, TURN_RIGHT: -10.0, STOP: 0.0}[a]
            dh = (float(sim.heading[0]) - h + math.pi) % (2 * math.pi) - math.pi
            assert math.degrees(dh) == pytest.approx(turn, abs=1e-9)


def test_forward_in_free_space_moves_exactly_a_quarter_metre():
    sim = sim_at(Scene("box", np.array(room_walls(0.0, 0.0, 6.0, 6.0))), (1.0, 1.0), math.radians(30), resolution=8)
    for k in range(1, 9):
        assert not sim.step(np.array([MOVE_FORWARD]))[0]
        np.testing.assert_allclose(sim.pos[0], [1.0 + 0.25 * k * math.cos(math.radians(30)),
                                                1.0 + 0.25 * k * math.sin(math.radians(30))], atol=1e-12)
    assert sim.path_length[0] == pytest.approx(2.0)


def test_head_on_collision_stops_at_the_wall_and_oblique_one_slides():
    room = Scene("box", np.array(room_walls(0.0, 0.0, 4.0, 4.0)))  # inner faces at 0.05 and 3.95
    sim = sim_at(room, (2.0, 2.0), 0.0, resolution=8)
    hits = [bool(sim.step(np.array([MOVE_FORWARD]))[0]) for _ in range(12)]
    assert hits[:6] == [False] * 6 and all(hits[7:])  # 2.0 + 6 * 0.25 = 3.5, then the wall
    x_stop = sim.pos[0, 0]
    # flush against the wall: 0.1 m from it, give or take one 0.0125 m sub-step
    assert 3.95 - AGENT_RADIUS - 0.0125 <= x_stop <= 3.95 - AGENT_RADIUS + 1e-9
    assert sim.pos[0, 1] == pytest.approx(2.0)
    # At 45 degrees into the same wall the agent keeps the move's y component (it slides
    # along the wall), advances in x only while it stays clear, and collides.
    sim = sim_at(room, (3.0, 1.0), math.radians(45), resolution=8)
    step = 0.25 * math.sqrt(0.5)
    for _ in range(6):
        before = sim.pos[0].copy()
        if sim.step(np.array([MOVE_FORWARD]))[0]:
            break
    else:
        pytest.fail("never reached the wall")
    moved = sim.pos[0] - before
    assert moved[1] == pytest.approx(step) and moved[0] < step - 1e-6
    assert sim.pos[0, 0] <= 3.95 - AGENT_RADIUS + 1e-9
    before = sim.pos[0].copy()
    assert sim.step(np.array([MOVE_FORWARD]))[0]  # now flush against the wall: pure slide
    moved = sim.pos[0] - before
    assert moved[1] == pytest.approx(step) and abs(moved[0]) < 0.0125


@pytest.mark.parametrize("gap, passable", [(0.25, True), (0.15, False)])
def test_gaps_wider_than_the_agent_are_passable(gap, passable):
    # A room split at x = 2 by a wall that leaves a gap of `gap` metres below the room's
    # top wall (inner face at y = 1.95): the agent (0.2 m across) passes 0.25 m, not 0.15 m.
    end = round(1.95 - gap - 0.05, 2)  # the wall's end point; its square cap adds 0.05
    sc = Scene("gap", np.array(room_walls(0.0, 0.0, 4.0, 2.0) + [(2.0, 0.0, 2.0, end)]))
    grid = rasterize(sc)
    geo = Geodesics(SceneBank([grid]))
    y = 1.95 - gap / 2
    d = geo.distance(0, np.array([1.0, 1.0]), np.array([3.0, 1.0]))
    if not passable:
        assert d == math.inf
        return
    detour = 2 * math.hypot(1.0, y - 1.0)  # through the gap's centre line
    assert detour - 1e-9 <= d < 1.1 * detour
    sim = sim_at(sc, (1.0, y), 0.0, resolution=8)
    for _ in range(8):
        assert not sim.step(np.array([MOVE_FORWARD]))[0]
    assert sim.pos[0, 0] == pytest.approx(3.0)


def test_stop_and_inactive_worlds_do_not_move():
    room = Scene("box", np.array(room_walls(0.0, 0.0, 4.0, 4.0)))
    bank = SceneBank([rasterize(room)])
    sim = BatchedSim(bank, 2, resolution=8)
    for i in range(2):
        sim.reset_world(i, Episode(i, "box", (1.0, 1.0), 0.0, (3.0, 3.0), 1.0))
    sim.step(np.array([STOP, MOVE_FORWARD]))
    np.testing.assert_array_equal(sim.pos[0], [1.0, 1.0])
    np.testing.assert_allclose(sim.pos[1], [1.25, 1.0])
    sim.step(np.array([MOVE_FORWARD, MOVE_FORWARD]), active=np.array([False, True]))
    np.testing.assert_array_equal(sim.pos[0], [1.0, 1.0])
    np.testing.assert_allclose(sim.pos[1], [1.5, 1.0])


def test_moves_never_squeeze_between_diagonal_cells():
    # Two navigable squares of the grid that touch only at a corner form two components
    # (the geodesic search links 4-neighbours only). No forward move may take the agent
    # from one to the other: its sub-goal, snapped into its component, would be cut off.
    import dataclasses

    from scipy import ndimage

    room = rasterize(Scene("box", np.array(room_walls(0.0, 0.0, 4.0, 4.0))))
    nav = np.zeros_like(room.nav)
    nav[20:40, 20:40] = True  # square A
    nav[40:60, 40:60] = True  # square B, touching A at the corner of cells (39, 39) and (40, 40)
    comp, n = ndimage.label(nav)
    assert n == 2
    grid = dataclasses.replace(room, nav=nav, component=comp.astype(np.int32) - 1)
    bank = SceneBank([grid])
    cs = grid.cell_size
    corner = np.array(grid.origin) + 40 * cs
    crossed = 0
    for deg in np.arange(30.0, 60.0, 0.7):
        for back in (0.05, 0.13, 0.3):
            h = math.radians(deg)
            start = corner - back * np.array([math.cos(h), math.sin(h)])
            if not grid.is_navigable(start):
                continue
            sim = sim_at(bank, start, h, resolution=8, egomap=False)
            for _ in range(4):
                sim.step(np.array([MOVE_FORWARD]))
                r, c = np.floor((sim.pos[0] - grid.origin) / cs).astype(int)[::-1]
                crossed += grid.component[r, c] != grid.component[39, 39]
    assert crossed == 0
