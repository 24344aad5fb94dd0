"""The planner's ego map (docs/spec.md section 2) seen from a known pose in a known room: channel 0
obstacles, channel 1 explored floor, 32x32 cells of 0.5 m, row 0 ahead, column 0 left;
channels 2-5 the obstacles of each cell's quarters (64x64 cells of 0.25 m once unpacked)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from plex_ma.envs.sim import TURN_LEFT, TURN_RIGHT, BatchedSim, Scene

from .sim_helpers import room_walls, sim_at

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
    assert m.shape == (1, 6, S, S) and m.dtype == np.float32
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


def fine_obstacles(m: np.ndarray) -> np.ndarray:
    """The quarter cells' obstacles of ego maps (k, 6, S, S) unpacked to (k, 2S, 2S)."""
    return torch.nn.functional.pixel_shuffle(torch.as_tensor(m[:, 2:6]), 2)[:, 0].numpy()


def test_fine_channels_in_the_known_room():
    """The quarter cells (0.25 m) hold the front wall's face (3.75-4 m ahead: fine row 16
    across the view) and the box (2-2.5 m ahead, 0.5-1.5 m left: rows 22-23, columns
    26-29), and no other cell; in this room, aligned with the grids, any quarter's obstacle
    blocks its 0.5 m cell."""
    m = sim_at(ROOM, (0.0, 0.0), 0.0, resolution=64).egomap()
    f = fine_obstacles(m)[0]
    rows, cols = np.nonzero(f)
    assert set(rows.tolist()) == {16, 22, 23}
    assert {(r, c) for r, c in zip(rows, cols) if r > 16} == {(r, c) for r in (22, 23) for c in range(26, 30)}
    np.testing.assert_array_equal(f.reshape(S, 2, S, 2).max(axis=(1, 3)), m[0, 0])


def test_a_narrow_door_closes_a_cell_and_stays_open_in_the_quarters():
    """A 0.6 m door 2 m ahead, centred on the agent, half fills each of the two 0.5 m cells
    it spans, so both read as wall (the door is closed on the 32 x 32 map); its two 0.25 m
    quarter cells stay free. The value-iteration module's sub-goal for a goal 3 m ahead
    goes through the door on the fine map and not on the coarse one."""
    from plex_ma.networks.value_iteration import ValueIteration

    walls = room_walls(-4.0, -4.0, 4.0, 4.0) + [(2.0, -4.0, 2.0, -0.3), (2.0, 0.3, 2.0, 4.0)]
    m = sim_at(Scene("door", np.array(walls)), (0.0, 0.0), 0.0, resolution=64).egomap()
    row = 12  # the wall's face, 2 m ahead, lies in the cell 1.5-2 m ahead
    seen = slice(12, 20)  # its cells within the 90 degree view (2 m either side)
    assert m[0, 0, row, seen].all()  # the door included: closed
    f = fine_obstacles(m)[0]
    door = [S - 1, S]  # the quarter cells 0-0.25 m either side of the centre line
    assert not f[2 * row, door].any()
    assert f[2 * row, 2 * seen.start:2 * seen.stop].sum() == 2 * (seen.stop - seen.start) - 2
    ego, goal = torch.as_tensor(m), torch.tensor([[3.0, 0.0]])
    _, fine = ValueIteration(fine=True)(ego, goal)
    _, coarse = ValueIteration()(ego, goal)
    assert abs(fine[0, 1]) < 0.15 and fine[0, 0] > 1.5  # straight ahead, through the door
    assert abs(coarse[0, 1]) > 0.3  # round the closed door


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
    base = sim.egomap()
    for k in (1, 2, 3):
        sim.est_pose[0, 2] = k * math.pi / 2
        m = sim.egomap()
        np.testing.assert_array_equal(m[0, :2], np.rot90(base[0, :2], k=-k, axes=(1, 2)))
        # the quarter cells turn with the map they unpack to
        np.testing.assert_array_equal(fine_obstacles(m)[0], np.rot90(fine_obstacles(base)[0], k=-k))
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


def test_crop_needs_a_power_of_two_cell():
    """The crop multiplies by the inverse of the map's cell size, which is its division only
    for a power of two; another size is refused rather than cropped slightly differently."""
    from plex_ma.envs.sim import kernels as K

    amap = np.zeros((1, 16, 16), np.uint8)
    pose = np.zeros((1, 3))
    out = np.zeros((1, 6, 4, 4), np.float32)
    for cs, ok in ((0.25, True), (0.5, True), (0.3, False)):
        args = (amap, np.full((1, 2), -2.0), cs, pose, 0.5, out, np.zeros(1, np.int64), np.zeros(1, np.int64))
        if ok:
            K.egomap_crop.serial(*args)
        else:
            with pytest.raises(ValueError, match="power of two"):
                K.egomap_crop.serial(*args)
