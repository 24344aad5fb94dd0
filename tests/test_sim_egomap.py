"""The planner's ego map (docs/spec.md section 2) seen from a known pose in a known room: channel 0
obstacles, channel 1 explored floor, 32x32 cells of 0.5 m, row 0 ahead, column 0 left."""

from __future__ import annotations

import math

import numpy as np
import pytest

from plex_ma.envs.sim import TURN_LEFT, TURN_RIGHT, BatchedSim, Scene

from .test_sim_helpers import room_walls, sim_at

# An 8 m x 8 m room (inner faces at +-3.95 m) with the agent at its centre facing +x, and
# one box (1 m high) ahead and to the left: 2.1-2.4 m ahead, 0.6-1.4 m to the left.
ROOM = Scene("ego", np.array(room_walls(-4.0, -4.0, 4.0, 4.0)), boxes=np.array([[2.1, 0.6, 2.4, 1.4]]),
             box_heights=[1.0], box_categories=[0])
S = BatchedSim.ego_size
CELL = BatchedSim.ego_cell


def ego_cell(forward: float, left: float) -> tuple[int, int]:
    """(row, col) of the ego-map cell holding a point ``forward`` m ahead and ``left`` m to
    the left of the agent: row 0 is the farthest ahead, column 0 the farthest left."""
    return int(math.floor(S / 2 - forward / CELL)), int(math.floor(S / 2 - left / CELL))


def obstacles(m: np.ndarray) -> set[tuple[int, int]]:
    return {(int(r), int(c)) for r, c in zip(*np.nonzero(m[0]))}


@pytest.mark.parametrize("R", [64, 128])
def test_known_room_from_known_pose(R):
    sim = sim_at(ROOM, (0.0, 0.0), 0.0, resolution=R)
    m = sim.egomap()
    assert m.shape == (1, 2, S, S) and m.dtype == np.float32
    assert m.min() >= 0.0 and m.max() <= 1.0
    m = m[0]
    wall_row, _ = ego_cell(3.95, 0.0)  # the front wall's face, 3.95 m ahead
    box = {ego_cell(2.25, 0.8), ego_cell(2.25, 1.2)}  # the box, ahead and to the left
    assert wall_row == 8 and box == {(11, 13), (11, 14)}
    # The front wall spans the whole 90 degree view: 3.95 m to either side.
    wall = {(wall_row, c) for c in range(ego_cell(0, 3.95)[1], ego_cell(0, -3.95)[1] + 1)}
    assert obstacles(m) == wall | box
    # Explored floor lies between the agent and the wall, inside the field of view, and
    # nothing behind the agent (rows >= 16) has been seen.
    free = m[1] > 0
    assert free[wall_row + 1:S // 2].sum() > 40
    assert not free[S // 2:].any() and not m[0, S // 2:].any()
    rows, cols = np.nonzero(free)
    fwd = (S / 2 - rows - 0.5) * CELL
    left = (S / 2 - cols - 0.5) * CELL
    assert np.all(np.abs(left) <= fwd + CELL)  # within the 90 degree cone (one cell of slack)


def test_turning_left_90_degrees_rotates_the_map():
    sim = sim_at(ROOM, (0.0, 0.0), 0.0, resolution=64)
    before = sim.egomap()[0]
    for _ in range(9):
        sim.step(np.array([TURN_LEFT]))
    assert sim.heading[0] == pytest.approx(math.pi / 2)
    after = sim.egomap()[0]
    # What was ahead is now to the right: the map turns clockwise (new[i, j] = old[S-1-j, i]).
    rot = np.rot90(before, k=-1, axes=(1, 2))
    assert (11, 13) in obstacles(before) and (13, 20) in obstacles(rot)
    seen = (rot[0] > 0) | (rot[1] > 0)
    np.testing.assert_array_equal(after[0][seen], rot[0][seen])  # obstacles seen before
    assert np.all(after[1][(rot[1] > 0) & (rot[0] == 0)] > 0)  # floor seen before stays explored
    # The turn revealed the left wall, now ahead.
    assert len(obstacles(after)) > len(obstacles(before))
    # Turning back restores the first view exactly where nothing new was seen.
    for _ in range(9):
        sim.step(np.array([TURN_RIGHT]))
    back = sim.egomap()[0]
    np.testing.assert_array_equal(back[0][before[0] > 0], 1.0)


def test_crop_rotates_with_the_heading_alone():
    # Same allocentric map, heading changed by +90 degrees: exactly the rotated crop.
    sim = sim_at(ROOM, (0.0, 0.0), 0.0, resolution=64)
    for a in (TURN_LEFT, TURN_LEFT, TURN_RIGHT, TURN_RIGHT, TURN_RIGHT):
        sim.step(np.array([a]))
    h = float(sim.est_pose[0, 2])
    sim.est_pose[0, 2] = 0.0
    base = sim.egomap()[0]
    for k in (1, 2, 3):
        sim.est_pose[0, 2] = k * math.pi / 2
        np.testing.assert_array_equal(sim.egomap()[0], np.rot90(base, k=-k, axes=(1, 2)))
    sim.est_pose[0, 2] = h


def test_ego_map_moves_with_the_agent():
    # Two steps forward (0.5 m = one ego cell): the box and the wall come one row closer.
    sim = sim_at(ROOM, (0.0, 0.0), 0.0, resolution=64)
    before = obstacles(sim.egomap()[0])
    sim.step(np.array([1]))
    sim.step(np.array([1]))
    after = obstacles(sim.egomap()[0])
    assert {(r + 1, c) for r, c in before} <= after


def test_egomap_off_raises():
    sim = sim_at(ROOM, (0.0, 0.0), 0.0, resolution=32, egomap=False)
    with pytest.raises(RuntimeError):
        sim.egomap()


@pytest.mark.parametrize("degrees", [10, 20, 30, 40])
@pytest.mark.parametrize("offset", [0.0, 0.125, 0.25, 0.375])
def test_a_door_stays_open_on_the_map(degrees, offset):
    # A wall 2 m ahead with a 0.8 m door, the agent facing it: the room turned by
    # ``degrees`` (so the allocentric map's cells lie askew under the ego map's) and the
    # agent moved ``offset`` to the left. The wall's cells either side are obstacles and a
    # column of cells through the doorway is not (with any sample counting, a quarter of
    # these views closed the door).
    a = math.radians(degrees)
    c, s = math.cos(a), math.sin(a)
    walls = room_walls(-4.0, -4.0, 4.0, 4.0) + [(2.0, -4.0, 2.0, -0.4), (2.0, 0.4, 2.0, 4.0)]
    turned = [(c * x0 - s * y0, s * x0 + c * y0, c * x1 - s * y1, s * x1 + c * y1) for x0, y0, x1, y1 in walls]
    sim = sim_at(Scene("door", np.array(turned) + 5.0), (5.0 - s * offset, 5.0 + c * offset), a, resolution=128)
    m = sim.egomap()[0]
    wall = range(ego_cell(2.2, 0.0)[0], ego_cell(1.7, 0.0)[0] + 1)  # the rows the wall's face can fall in
    for y in (-1.5, -1.0, 1.0, 1.5):
        assert any(m[0, r, ego_cell(0.0, y - offset)[1]] == 1.0 for r in wall)
    doorway = range(ego_cell(0.0, 0.4 - offset)[1], ego_cell(0.0, -0.4 - offset)[1] + 1)
    assert any(all(m[0, r, col] == 0.0 for r in wall) for col in doorway)
