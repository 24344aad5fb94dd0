"""compat_env: PettingZoo's tests, the Box/Discrete layout, the action mask and mapping,
bad input, pickling; and the SuperSuit claims of both docstrings on the native env."""

from __future__ import annotations

import math
import pickle
import re
import warnings

import numpy as np
import pytest
import supersuit as ss
from gymnasium import spaces
from pettingzoo.test import api_test, performance_benchmark, render_test, seed_test

from plex_ma.envs import compat, plex_nav_v0
from plex_ma.envs.actions import InvalidAction

from .env_helpers import SMALL, line_episode, planner_action, state_snapshot, assert_same_state

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")

K = 33  # STOP + 4 distances x 8 directions
EGO = 6 * 32 * 32  # the planner's ego map, flattened
L = 2 + EGO + 2  # one-hot id, the planner's ego map and goal vector (longer than the executor's RGB-D 32x32)
PAD = dict(SMALL, pad=True)  # one padded layout for both agents


# ---------------------------------------------------------------- PettingZoo's tests
@pytest.mark.parametrize("config", [dict(SMALL), dict(SMALL, resolution=128), dict(SMALL, n_ex=2, max_steps=8)],
                         ids=["64px", "128px", "truncating"])
def test_api(config):
    api_test(plex_nav_v0.compat_env(**config), num_cycles=400)


def test_seed():
    seed_test(lambda: plex_nav_v0.compat_env(**SMALL), num_cycles=200)


def test_render(headless):
    assert plex_nav_v0.compat_env(**SMALL).metadata["render_modes"] == ["human", "rgb_array"]
    render_test(lambda render_mode=None: plex_nav_v0.compat_env(render_mode=render_mode, **SMALL))


def test_performance_benchmark(capsys):
    performance_benchmark(plex_nav_v0.compat_env(**SMALL))  # runs ~5 s and only prints
    assert "turns per second" in capsys.readouterr().out


# ---------------------------------------------------------------- layout
def test_spaces_are_flat_shared_and_stable():
    env = plex_nav_v0.compat_env(**PAD)
    ob, act = env.observation_space("planner"), env.action_space("planner")
    assert ob == env.observation_space("executor") and act == env.action_space("executor")
    assert ob is env.observation_space("planner")
    assert isinstance(act, spaces.Discrete) and act.n == K
    assert isinstance(ob, spaces.Dict) and set(ob.spaces) == {"observation", "action_mask"}
    box = ob["observation"]
    assert isinstance(box, spaces.Box) and box.shape == (L,) and box.dtype == np.float32
    assert ob["action_mask"].shape == (K,) and ob["action_mask"].dtype == np.int8
    assert env.unwrapped.config.eli is False


def test_every_accessor_gives_the_same_spaces():
    """``observation_space(agent)``, ``action_space(agent)``, the ``observation_spaces`` /
    ``action_spaces`` dicts, and all of them on ``unwrapped`` and on the turn-based
    parallel view: skrl and RLlib read ``unwrapped.observation_spaces``."""
    from pettingzoo.utils.conversions import turn_based_aec_to_parallel

    env = plex_nav_v0.compat_env(**PAD)
    par = turn_based_aec_to_parallel(plex_nav_v0.compat_env(**PAD))
    ob, act = env.observation_space("planner"), env.action_space("planner")
    for view in (env, env.unwrapped, par, par.unwrapped):
        for agent in ("planner", "executor"):
            assert view.observation_space(agent) == ob and view.action_space(agent) == act
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # the parallel view calls the dicts deprecated
                assert view.observation_spaces[agent] == ob and view.action_spaces[agent] == act
    assert env.unwrapped is env and par.unwrapped is not par  # the compat env is the innermost env
    assert env.native.observation_space("planner") != ob  # the native env keeps its own spaces
    env.reset(seed=0)
    assert ob.contains(env.observe("planner"))


def test_turn_based_parallel_view_steps():
    from pettingzoo.utils.conversions import turn_based_aec_to_parallel

    par = turn_based_aec_to_parallel(plex_nav_v0.compat_env(**{**SMALL, "max_steps": 20}))
    obs, infos = par.reset(seed=0)
    rng = np.random.default_rng(0)
    episodes = 0
    for _ in range(120):
        for a in par.agents:
            assert par.observation_space(a).contains(obs[a])
        # every agent gets an action its mask allows; only the acting agent's is used
        obs, rewards, term, trunc, infos = par.step(
            {a: int(rng.choice(np.flatnonzero(obs[a]["action_mask"]))) for a in par.agents})
        if not par.agents:
            episodes += 1
            obs, infos = par.reset()
    assert episodes >= 2


def test_observation_layout():
    env = plex_nav_v0.compat_env(**PAD)
    env.reset(seed=3)
    raw = env.native
    native_p = raw.observe("planner")
    o = env.observe("planner")
    x, mask = o["observation"], o["action_mask"]
    assert x.dtype == np.float32 and x.shape == (L,)
    np.testing.assert_array_equal(x[:2], [1, 0])
    np.testing.assert_array_equal(x[2:2 + EGO], native_p["ego_map"].ravel())
    np.testing.assert_array_equal(x[2 + EGO:], native_p["goal"])
    np.testing.assert_array_equal(mask, np.ones(K, np.int8))

    env.step(5)  # a sub-goal: now the executor
    assert env.agent_selection == "executor"
    native_e = raw.observe("executor")
    o = env.observe("executor")
    x, mask = o["observation"], o["action_mask"]
    np.testing.assert_array_equal(x[:2], [0, 1])
    img = x[2:2 + 4096].reshape(4, 32, 32)
    rgb = native_e["rgb"].astype(np.float64).reshape(32, 2, 32, 2, 3).mean(axis=(1, 3)) / 255
    np.testing.assert_allclose(img[:3], rgb.transpose(2, 0, 1), atol=1e-6)
    depth = native_e["depth"].reshape(32, 2, 32, 2).mean(axis=(1, 3))
    np.testing.assert_allclose(img[3], depth, atol=1e-6)
    np.testing.assert_array_equal(x[2 + 4096:2 + 4096 + 2], native_e["subgoal"])
    assert np.all(x[2 + 4096 + 2:] == 0)  # padding
    np.testing.assert_array_equal(mask, np.r_[np.ones(4), np.zeros(K - 4)].astype(np.int8))
    assert env.observation_space("executor").contains(o)


def test_nearest_pixel_downsampling_and_options():
    env = plex_nav_v0.compat_env(resolution=48, num_scenes=4, image_size=20, subgoal_distances=(0.5, 1.5),
                                 subgoal_directions=4, pad=True)
    assert env.action_space("planner").n == 1 + 2 * 4
    # The planner's 2 + EGO + 2 values are the longer part; the executor's are padded.
    assert env.observation_space("planner")["observation"].shape == (max(2 + EGO + 2, 2 + 4 * 20 * 20 + 2),)
    env.reset(seed=0)
    env.step(3)
    native = env.native.observe("executor")
    x = env.observe("executor")["observation"]
    idx = ((np.arange(20) + 0.5) * 48 / 20).astype(int)
    np.testing.assert_allclose(x[2:2 + 400].reshape(20, 20), native["rgb"][idx][:, idx, 0] / 255, atol=1e-6)
    assert np.all(x[2 + 1600 + 2:] == 0)
    api_test(env, num_cycles=50)
    with pytest.raises(ValueError, match="eli"):
        plex_nav_v0.compat_env(eli=True, **SMALL)
    with pytest.raises(ValueError, match="subgoal_distances"):
        plex_nav_v0.compat_env(subgoal_distances=(1.0, 5.0), **SMALL)
    with pytest.raises(ValueError, match="image_size"):
        plex_nav_v0.compat_env(image_size=128, **SMALL)


def test_subgoal_grid():
    grid = compat.subgoal_grid((1.0, 2.0, 3.0, 4.0), 8)
    assert grid.shape == (32, 2)
    assert np.all(np.abs(grid[:, 1]) <= math.pi)
    np.testing.assert_allclose(grid[1 * 8 + 2], [2.0, math.pi / 2], atol=1e-6)
    np.testing.assert_allclose(grid[3 * 8 + 4], [4.0, -math.pi], atol=1e-6)


# ---------------------------------------------------------------- action mapping
def test_planner_and_executor_actions_map_to_native_ones():
    env = plex_nav_v0.compat_env(**SMALL)
    env.reset(seed=0)
    raw = env.native
    w = raw.worlds
    ep = line_episode(raw, 2.0)
    env.reset(options={"episode": ep})
    pose = w.sim.est_pose[0].copy()
    env.step(1 + 1 * 8 + 0)  # 2 m straight ahead
    np.testing.assert_allclose(w.subgoal_raw[0], pose[:2] + 2.0 * np.array([math.cos(pose[2]), math.sin(pose[2])]),
                               atol=1e-5)
    assert env.agent_selection == "executor"
    p0 = w.sim.pos[0].copy()
    env.step(1)  # MOVE_FORWARD
    assert np.hypot(*(w.sim.pos[0] - p0)) == pytest.approx(0.25)
    h0 = w.sim.heading[0]
    env.step(2)  # TURN_LEFT
    assert w.sim.heading[0] - h0 == pytest.approx(math.radians(10))
    env.step(3)  # TURN_RIGHT
    assert w.sim.heading[0] == pytest.approx(h0)
    env.step(0)  # STOP: back to the planner, which sees a zero ELI (the channel is off)
    assert env.agent_selection == "planner"
    assert np.all(raw.observe("planner")["eli"] == 0)
    assert np.all(w.eli == 0)
    env.step(0)  # the planner's STOP ends the episode
    assert env.terminations == {"planner": True, "executor": True}
    o, r, term, trunc, info = env.last()
    assert term and info["success"] in (0.0, 1.0)
    env.step(None)
    env.step(None)
    assert env.agents == []


def test_planner_gets_all_its_rewards():
    env = plex_nav_v0.compat_env(**SMALL)
    env.reset(seed=2)
    env.step(1 + 2 * 8 + 1)
    pending = env.rewards["planner"]
    while env.agent_selection == "executor":
        env.step(1)
        pending += env.rewards["planner"]
    assert pending != 0
    assert env.last()[1] == pytest.approx(pending, abs=1e-6)


# ---------------------------------------------------------------- bad input
@pytest.mark.parametrize("turn", ["planner", "executor"])
@pytest.mark.parametrize("action,match", [
    (K, "out of range"), (-1, "out of range"), (1.0, "integer"), (float("nan"), "integer"),
    (np.array([1, 2]), "integer"), (np.array(1.0), "integer"), ({"stop": 1}, "integer"), ("1", "integer"),
    (None, "alive"), (True, "bool"),
])
def test_bad_actions(turn, action, match):
    env = plex_nav_v0.compat_env(**SMALL)
    env.reset(seed=0)
    if turn == "executor":
        env.step(3)
    before = state_snapshot(env)
    with pytest.raises(InvalidAction, match=match):
        env.step(action)
    assert_same_state(before, state_snapshot(env))
    env.step(np.int64(1))
    assert env.unwrapped.worlds.planner_decisions[0] == 1
    assert env.unwrapped.worlds.steps[0] == (1 if turn == "executor" else 0)


@pytest.mark.parametrize("action", [4, 17, 32])
def test_masked_executor_actions_are_rejected(action):
    # pad_action_space_v0 alone would turn these into 0 (STOP) without a word.
    env = plex_nav_v0.compat_env(**PAD)
    env.reset(seed=0)
    env.step(3)
    before = state_snapshot(env)
    with pytest.raises(InvalidAction, match="masked out"):
        env.step(action)
    assert_same_state(before, state_snapshot(env))


def test_steps_after_the_end():
    env = plex_nav_v0.compat_env(**SMALL)
    env.reset(seed=0)
    env.step(0)
    with pytest.raises(InvalidAction, match="only valid action is None"):
        env.step(3)
    env.step(None)
    env.step(None)
    with pytest.raises(InvalidAction, match="after the episode ended"):
        env.step(None)
    with pytest.raises(InvalidAction, match="after the episode ended"):
        env.step(1)
    env.reset()
    env.step(1)


def test_pickle_round_trip():
    env = plex_nav_v0.compat_env(image_size=16, **SMALL)
    env.reset(seed=1)
    copy = pickle.loads(pickle.dumps(env))
    copy.reset(seed=1)
    env.reset(seed=1)
    for a in [5, 1, 1, 2, 0, 9, 3]:
        np.testing.assert_array_equal(copy.observe(copy.agent_selection)["observation"],
                                      env.observe(env.agent_selection)["observation"])
        env.step(a)
        copy.step(a)
        assert copy.rewards == env.rewards
    assert copy.observation_space("planner")["observation"].shape == (2 + EGO + 2,)


# ---------------------------------------------------------------- SuperSuit on the native env
WORKING = {
    "clip_reward_v0": lambda e: ss.clip_reward_v0(e, -1, 1),
    "sticky_actions_v0": lambda e: ss.sticky_actions_v0(e, 0.25),
    "frame_skip_v0": lambda e: ss.frame_skip_v0(e, 3),
}
FAIL_ON_BUILD = {
    "color_reduction_v0": lambda e: ss.color_reduction_v0(e),
    "resize_v1": lambda e: ss.resize_v1(e, 32, 32),
    "frame_stack_v1": lambda e: ss.frame_stack_v1(e, 4),
    "normalize_obs_v0": lambda e: ss.normalize_obs_v0(e),
    "dtype_v0": lambda e: ss.dtype_v0(e, np.float32),
    "flatten_v0": lambda e: ss.flatten_v0(e),
    "reshape_v0": lambda e: ss.reshape_v0(e, (4,)),
    "pad_observations_v0": lambda e: ss.pad_observations_v0(e),
    "pad_action_space_v0": lambda e: ss.pad_action_space_v0(e),
    "agent_indicator_v0": lambda e: ss.agent_indicator_v0(e),
    "black_death_v3": lambda e: ss.black_death_v3(e),
}
FAIL_ON_STEP = {
    "clip_actions_v0": lambda e: ss.clip_actions_v0(e),
    "max_observation_v0": lambda e: ss.max_observation_v0(e, 2),
    "delay_observations_v0": lambda e: ss.delay_observations_v0(e, 2),
}


def _supersuit_names(doc: str, heading: str) -> set[str]:
    section = doc.split(heading, 1)[1].split("\n#", 1)[0]
    return set(re.findall(r"\b[a-z_]+_v\d\b", section)) - {"plex_nav_v0"}


def test_docstrings_name_only_checked_wrappers():
    known = set(WORKING) | set(FAIL_ON_BUILD) | set(FAIL_ON_STEP)
    native = _supersuit_names(plex_nav_v0.__doc__, "## SuperSuit wrappers")
    ours = _supersuit_names(compat.__doc__, "## SuperSuit on the native")
    assert native and ours
    assert native <= known and ours <= known, (native - known, ours - known)
    # Both docstrings say the same three work; the compat one lists every other one tested.
    for name in WORKING:
        assert name in native and name in ours
    assert set(FAIL_ON_BUILD) | set(FAIL_ON_STEP) <= ours


@pytest.mark.parametrize("name", list(WORKING))
def test_supersuit_wrappers_that_work_on_native_env(name):
    api_test(WORKING[name](plex_nav_v0.env(**SMALL)), num_cycles=100)


@pytest.mark.parametrize("name", list(FAIL_ON_BUILD))
def test_supersuit_wrappers_that_fail_on_build(name):
    with pytest.raises((AssertionError, AttributeError, TypeError, ValueError)):
        FAIL_ON_BUILD[name](plex_nav_v0.env(**SMALL))


@pytest.mark.parametrize("name", list(FAIL_ON_STEP))
def test_supersuit_wrappers_that_fail_in_use(name):
    env = FAIL_ON_STEP[name](plex_nav_v0.env(**SMALL))
    with pytest.raises((AssertionError, AttributeError, TypeError, ValueError)):
        api_test(env, num_cycles=20)


@pytest.mark.parametrize("name", list(WORKING))
def test_supersuit_wrappers_that_work_on_compat_env(name):
    api_test(WORKING[name](plex_nav_v0.compat_env(**SMALL)), num_cycles=100)


@pytest.mark.parametrize("name", ["frame_stack_v1", "normalize_obs_v0", "dtype_v0", "agent_indicator_v0"])
def test_supersuit_observation_wrappers_refuse_compat_env(name):
    assert name in compat.__doc__.split("On ``compat_env()``", 1)[1]
    with pytest.raises((AssertionError, AttributeError)):
        FAIL_ON_BUILD[name](plex_nav_v0.compat_env(**SMALL))


def test_delay_observations_shows_the_other_agents_mask_on_compat_env():
    env = ss.delay_observations_v0(plex_nav_v0.compat_env(**PAD), 2)
    for agent in env.possible_agents:  # api_test samples unseeded; seed it so the stale mask is always hit
        env.action_space(agent).seed(0)
    with pytest.raises(InvalidAction, match="masked out"):
        api_test(env, num_cycles=200)


def test_clip_reward_clips_the_planner_success():
    env = ss.clip_reward_v0(plex_nav_v0.env(**SMALL), -1, 1)
    raw = env.unwrapped
    env.reset(seed=0)
    env.reset(options={"episode": line_episode(raw, 0.1, clearance=0.2)})
    env.step(planner_action(1))
    assert env.unwrapped.infos["planner"]["success"] == 1.0
    assert raw.rewards["planner"] == 10.0 and env.rewards["planner"] == 1.0


def test_frame_skip_repeats_executor_actions_and_replays_the_planner():
    env = ss.frame_skip_v0(plex_nav_v0.env(**SMALL), 3)
    w = env.unwrapped.worlds
    env.reset(seed=0)
    env.step(planner_action(0, 2.0, 0.3))
    assert w.planner_decisions[0] == 1 and w.steps[0] == 0
    env.step({"action": 2, "eli": np.zeros(128, np.float32)})
    assert w.steps[0] == 3  # the executor's action, three times
    # Its STOP hands control back; the wrapper then replays the planner's last sub-goal
    # (and the executor's STOP) until its skip count runs out: the documented caveat.
    env.step({"action": 0, "eli": np.zeros(128, np.float32)})
    assert w.planner_decisions[0] > 1


@pytest.mark.parametrize("resolution, size", [(128, 32), (64, 32), (96, 32), (160, 32), (32, 32), (256, 32), (70, 10),
                                              (36, 12)])
def test_flat_image_is_numpys_block_mean_bit_for_bit(resolution, size):
    """The flat executor image is numpy's float32 block mean exactly (RGB then divided by 255),
    whether the compiled kernel (blocks under 8 pixels) or numpy computed it; sizes that do
    not divide the resolution take the nearest pixel."""
    rng = np.random.default_rng(resolution)
    rgb = rng.integers(0, 256, (resolution, resolution, 3), dtype=np.uint8)
    for depth in (rng.random((resolution, resolution, 1), dtype=np.float32),
                  (rng.random((resolution, resolution, 1)) ** 3).astype(np.float32)):
        got = np.full((4, size, size), np.nan, np.float32)
        compat._flat_image(rgb, depth, got)
        if resolution % size:
            idx = ((np.arange(size) + 0.5) * resolution / size).astype(np.int64)
            mean = [img[idx][:, idx].astype(np.float32) for img in (rgb, depth)]
        else:
            k = resolution // size
            mean = [img.reshape(size, k, size, k, img.shape[2]).mean(axis=(1, 3), dtype=np.float32)
                    for img in (rgb, depth)]
        want = np.concatenate([mean[0] / np.float32(255.0), mean[1]], axis=2).transpose(2, 0, 1)
        np.testing.assert_array_equal(got.view(np.uint32), want.view(np.uint32))
