"""Bad input raises a clear error that names the problem: scenes and house parameters
(SceneError), the simulator's arguments and episodes (ValueError)."""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
import pytest

from plex_ma.envs.sim import BatchedSim, Episode, Scene, SceneBank, SceneError, load_scenes, rasterize, scene_bank
from plex_ma.envs.sim.procgen import HouseParams, generate_house

from .sim_helpers import bank_of, room_walls

WALLS = np.array(room_walls(0.0, 0.0, 4.0, 4.0))


@pytest.mark.parametrize("kwargs, words", [
    (dict(walls=np.zeros((0, 4))), "no walls"),
    (dict(walls=[]), "no walls"),
    (dict(walls=np.array([[0.0, 0.0, np.nan, 1.0]])), "walls contains NaN"),
    (dict(walls=np.array([[0.0, 0.0, np.inf, 1.0]])), "walls contains NaN or infinite"),
    (dict(walls=np.zeros((3, 3))), "walls has shape"),
    (dict(walls=[[0.0, 0.0, 1.0]]), "walls has shape"),
    (dict(walls=[["a", 0, 1, 1]]), "walls is not numeric"),
    (dict(walls=WALLS, doors=np.zeros((2, 3))), "doors has shape"),
    (dict(walls=WALLS, doors=[[1.0, np.nan, 2.0, 0.0]]), "doors contains NaN"),
    (dict(walls=WALLS, wall_thickness=0.0), "wall_thickness"),
    (dict(walls=WALLS, wall_thickness=float("nan")), "wall_thickness"),
    (dict(walls=WALLS, boxes=[[1, 1, 2, 2]]), "1 boxes but 0 heights"),
    (dict(walls=WALLS, boxes=[[1, 1, 2, 2]], box_heights=[1.0, 2.0], box_categories=[0]), "1 boxes but 2 heights"),
    (dict(walls=WALLS, boxes=[[2, 1, 1, 2]], box_heights=[1.0], box_categories=[0]), "x_max <= x_min"),
    (dict(walls=WALLS, boxes=[[1, 1, 2, 2]], box_heights=[-1.0], box_categories=[0]), "heights"),
    (dict(walls=WALLS, boxes=[[1, 1, 2, 2]], box_heights=[9.0], box_categories=[0]), "heights"),
    (dict(walls=WALLS, boxes=[[1, 1, 2, 2]], box_heights=[1.0], box_categories=[8]), "categories"),
    (dict(walls=WALLS, boxes=[[1, 1, np.nan, 2]], box_heights=[1.0], box_categories=[0]), "boxes contains NaN"),
])
def test_bad_scenes_raise_scene_error(kwargs, words):
    with pytest.raises(SceneError) as err:
        Scene("bad-scene", **kwargs)
    assert "bad-scene" in str(err.value)  # names the scene
    assert words.lower() in str(err.value).lower()  # and the problem
    assert isinstance(err.value, ValueError)


def test_scene_without_navigable_space_raises():
    tiny = Scene("closet", np.array(room_walls(0.0, 0.0, 0.3, 0.3)))
    with pytest.raises(SceneError, match="closet.*no navigable space"):
        rasterize(tiny)
    with pytest.raises(SceneError, match="cell_size"):
        rasterize(Scene("ok", WALLS), cell_size=0.0)


@pytest.mark.parametrize("params, words", [
    (HouseParams(min_side=3.0), "min_side"),
    (HouseParams(min_side=20.0, max_side=10.0), "max_side"),
    (HouseParams(max_side=100.0), "max_side"),
    (HouseParams(min_side=float("nan")), "min_side"),
    (HouseParams(loop_prob=1.5), "loop_prob"),
    (HouseParams(corridor_prob=-0.1), "corridor_prob"),
    (HouseParams(furniture_per_room=-1.0), "furniture_per_room"),
    (HouseParams(furniture_per_room=float("inf")), "furniture_per_room"),
])
def test_house_params_out_of_range_raise(params, words):
    with pytest.raises(SceneError, match=words):
        generate_house(0, params=params)


@pytest.mark.parametrize("seed", [-1, -(2**40), 1.5, "3", None])
def test_bad_house_seed_raises(seed):
    with pytest.raises(SceneError, match="seed"):
        generate_house(seed)


def test_bad_scene_source_and_split():
    with pytest.raises(ValueError, match="split"):
        load_scenes("procgen", "training")
    with pytest.raises(ValueError, match="split"):
        scene_bank("procgen", "dev")
    with pytest.raises(ValueError, match="num_scenes"):
        load_scenes("procgen", "val", 0)
    with pytest.raises(ValueError, match="unknown scene source"):
        load_scenes("no-such-source", "val")
    with pytest.raises(ValueError, match="at least one scene"):
        SceneBank([])


@lru_cache(maxsize=1)
def bank():
    return bank_of(Scene("box", WALLS))


@pytest.mark.parametrize("kwargs, words", [
    (dict(num_worlds=0), "num_worlds"),
    (dict(num_worlds=-3), "num_worlds"),
    (dict(num_worlds=2.5), "num_worlds"),
    (dict(num_worlds="4"), "num_worlds"),
    (dict(num_worlds=1, resolution=4), "resolution"),
    (dict(num_worlds=1, resolution=2048), "resolution"),
    (dict(num_worlds=1, resolution=64.0), "resolution"),
    (dict(num_worlds=1, pose_noise=(-0.1, 0.0)), "pose_noise"),
    (dict(num_worlds=1, pose_noise=(0.0, float("nan"))), "pose_noise"),
    (dict(num_worlds=1, pose_noise=(0.1,)), "pose_noise"),
    (dict(num_worlds=1, pose_noise=(0.1, 0.1, 0.1)), "pose_noise"),
    (dict(num_worlds=1, pose_noise=None), "pose_noise"),
    (dict(num_worlds=1, pose_noise=("a", "b")), "pose_noise"),
])
def test_bad_simulator_arguments_raise_value_error(kwargs, words):
    with pytest.raises(ValueError, match=words):
        BatchedSim(bank(), **kwargs)


def test_bad_episodes_and_actions_raise_value_error():
    sim = BatchedSim(bank(), 2, resolution=16)
    with pytest.raises(ValueError, match="not loaded"):
        sim.reset_world(0, Episode(0, "elsewhere", (2.0, 2.0), 0.0, (3.0, 3.0), 1.0))
    with pytest.raises(ValueError, match="not navigable"):
        sim.reset_world(0, Episode(0, "box", (0.0, 2.0), 0.0, (3.0, 3.0), 1.0))  # inside a wall
    with pytest.raises(ValueError, match="unreachable"):
        sim.reset_world(0, Episode(0, "box", (2.0, 2.0), 0.0, (9.0, 9.0), 1.0))  # goal outside
    sim.reset_world(0, Episode(0, "box", (2.0, 2.0), math.pi, (3.0, 3.0), 1.0))
    with pytest.raises(ValueError, match="2 actions"):
        sim.step(np.array([1]))
    with pytest.raises(ValueError, match="0..3"):
        sim.step(np.array([1, 4]))
    with pytest.raises(ValueError, match="0..3"):
        sim.step(np.array([-1, 0]))
