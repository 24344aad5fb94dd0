"""Rendered depth against known geometry: planar depth, intrinsics, field of view, image
shapes and dtypes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from plex_ma.envs.sim import BatchedSim, Episode, Scene
from plex_ma.envs.sim.scene import CEILING_HEIGHT

from .sim_helpers import bank_of, room_walls, sim_at

CAM = BatchedSim.camera_height
RESOLUTIONS = [64, 96, 97, 128, 256]

# A wide room: the agent stands at (1, 0.025) facing +x; the front wall's face is at
# x = 3.0 (2 m ahead) and the side walls' faces at y = +-3.5, so the front wall fills
# the whole 90 degree field of view (the edge rays reach it at |y| < 2.1).
WIDE = Scene("wide", np.array(room_walls(-0.05, -3.55, 3.05, 3.55)))
AGENT = (1.0, 0.025)


def focal(R: int) -> float:
    return (R / 2) / math.tan(BatchedSim.hfov / 2)


def rows_offset(R: int) -> np.ndarray:
    """Vertical offset of each image row's centre from the optical centre, in pixels (up > 0)."""
    return R / 2 - np.arange(R) - 0.5


@pytest.mark.parametrize("R", RESOLUTIONS)
def test_wall_ahead_reads_its_planar_distance_in_every_column(R):
    sim = sim_at(WIDE, AGENT, 0.0, resolution=R)
    depth = sim.depth[0, :, :, 0]
    # Rows whose rays meet the wall between floor and ceiling at 2 m (with a margin).
    band = np.abs(rows_offset(R)) * 2.0 / focal(R) < 0.95 * CAM
    assert band.sum() >= R // 2
    centre = depth[band][:, R // 2 - 1:R // 2 + 1]
    np.testing.assert_allclose(centre, 0.2, atol=1e-6)
    # Planar depth (Habitat's convention): the edge columns of a fronto-parallel wall read
    # the same 2 m, not the ray length 2 / cos(45 deg) = 2.83 m.
    np.testing.assert_allclose(depth[band][:, [0, R - 1]], 0.2, atol=1e-6)
    np.testing.assert_allclose(depth[band], 0.2, atol=1e-6)


@pytest.mark.parametrize("R", RESOLUTIONS)
def test_floor_and_ceiling_depth_match_the_pinhole_model(R):
    sim = sim_at(WIDE, AGENT, 0.0, resolution=R)
    depth = sim.depth[0, :, :, 0] * 10.0
    off = rows_offset(R)
    f = focal(R)
    # Floor rows: planar depth cam_height * f / (row offset), the same in every column.
    floor = (off < 0) & (CAM * f < 1.95 * np.abs(off))
    assert floor.sum() >= 2
    want = CAM * f / -off[floor]
    np.testing.assert_allclose(depth[floor], np.repeat(want[:, None], R, 1), rtol=1e-5)
    # Ceiling rows (2.5 m high, 1.25 m above the camera): the mirror image of the floor.
    ceil = (off > 0) & ((CEILING_HEIGHT - CAM) * f < 1.95 * off)
    want = (CEILING_HEIGHT - CAM) * f / off[ceil]
    np.testing.assert_allclose(depth[ceil], np.repeat(want[:, None], R, 1), rtol=1e-5)


@pytest.mark.parametrize("R", [64, 97, 128])
def test_horizontal_field_of_view_is_90_degrees(R):
    # A 4 m wide corridor (faces at y = +-2) whose end wall is 9.9 m ahead: column j sees a
    # side wall at planar depth 2 / tan(phi_j) with tan(phi_j) = (R/2 - j - 0.5) / f and
    # f = (R/2) / tan(45 deg).
    sc = Scene("corridor", np.array(room_walls(-0.55, -2.05, 10.05, 2.05)))
    sim = sim_at(sc, (0.1, 0.0), 0.0, resolution=R)
    horizon = sim.depth[0, R // 2, :, 0] * 10.0
    tan_phi = np.abs(R / 2 - np.arange(R) - 0.5) / focal(R)
    want = 2.0 / np.maximum(tan_phi, 1e-9)
    side = want < 9.9
    assert side[0] and side[-1] and not side[R // 2]
    np.testing.assert_allclose(horizon, np.minimum(want, 9.9), rtol=1e-4)
    # The outermost columns look (almost) exactly 45 degrees to either side.
    assert math.degrees(math.atan(tan_phi[0])) == pytest.approx(45.0, abs=45.0 / R)


@pytest.mark.parametrize("R", [64, 97])
def test_field_of_view_is_symmetric(R):
    # An asymmetric scene and its mirror image about the agent's line of sight
    # (y -> 0.05 - y, the agent at y = 0.025) give left-right mirrored depth images.
    walls = np.array(room_walls(-0.05, -3.55, 3.05, 3.55) + [(1.5, 1.0, 2.5, 1.0)], np.float64)
    boxes = np.array([[2.0, 0.6, 2.4, 1.4], [1.5, -2.0, 1.8, -1.2], [0.6, -0.9, 0.9, -0.5]])
    heights, cats = [1.0, 0.5, 2.0], [0, 1, 4]
    mw = walls.copy()
    mw[:, [1, 3]] = 0.05 - walls[:, [1, 3]]
    mb = boxes.copy()
    mb[:, 1], mb[:, 3] = 0.05 - boxes[:, 3], 0.05 - boxes[:, 1]
    a = sim_at(Scene("a", walls, boxes=boxes, box_heights=heights, box_categories=cats), (0.5, 0.025), 0.0,
               resolution=R).depth[0, :, :, 0]
    b = sim_at(Scene("b", mw, boxes=mb, box_heights=heights, box_categories=cats), (0.5, 0.025), 0.0,
               resolution=R).depth[0, :, :, 0]
    assert np.abs(a - a[:, ::-1]).max() > 0.05  # the scene itself is not symmetric
    np.testing.assert_allclose(a, b[:, ::-1], atol=1e-6)


@pytest.mark.parametrize("R", RESOLUTIONS)
def test_observation_shapes_dtypes_and_ranges(R):
    bank = bank_of(WIDE)
    sim = BatchedSim(bank, 2, resolution=R)
    for i, pos in enumerate([(1.0, 0.025), (0.3, -2.9)]):
        sim.reset_world(i, Episode(i, "wide", pos, 0.7 * i, (2.0, 0.0), 1.0))
    sim.step(np.array([1, 2]))
    assert sim.rgb.shape == (2, R, R, 3) and sim.rgb.dtype == np.uint8
    assert sim.depth.shape == (2, R, R, 1) and sim.depth.dtype == np.float32
    assert np.all(np.isfinite(sim.depth)) and sim.depth.min() >= 0.0 and sim.depth.max() <= 1.0
    assert sim.rgb.std() > 5  # not a blank image


def test_depth_is_clipped_at_10_m():
    # A 20 m hall: the far wall (19.5 m ahead) reads 1.0 (10 m, the clip), never more.
    sc = Scene("hall", np.array(room_walls(-0.05, -6.05, 20.05, 6.05)))
    sim = sim_at(sc, (0.5, 0.0), 0.0, resolution=64)
    d = sim.depth[0, :, :, 0]
    assert d.max() == pytest.approx(1.0)
    np.testing.assert_allclose(d[30:34, 28:36], 1.0)


def test_depth_follows_the_agent():
    # One step forward brings the wall 0.25 m closer; turning 180 degrees shows the back
    # wall (face at x = 0) 1.25 m away.
    sim = sim_at(WIDE, AGENT, 0.0, resolution=64)
    sim.step(np.array([1]))
    assert sim.depth[0, 31, 31, 0] == pytest.approx(0.175, abs=1e-6)
    for _ in range(18):
        sim.step(np.array([2]))
    assert sim.depth[0, 31, 31, 0] == pytest.approx(0.125, abs=1e-5)
