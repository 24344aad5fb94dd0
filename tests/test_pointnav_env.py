"""gymnasium.make("plex_ma/PointNav-v0"): gymnasium's checker, episode ends, success,
SPL, rewards, infos and bad input (the vector env comparison is in test_vector_env.py)."""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import plex_ma  # noqa: F401  registers the env
from plex_ma.envs.actions import InvalidAction
from plex_ma.envs.rules import INFO_KEYS

from .env_helpers import SMALL, line_episode

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")


def make(**kw):
    return gymnasium.make("plex_ma/PointNav-v0", **{**SMALL, **kw})


@pytest.mark.parametrize("config", [{}, {"resolution": 128}, {"pose_noise": (0.05, 0.02)}],
                         ids=["64px", "128px", "noisy_pose"])
def test_check_env(config):
    check_env(make(**config).unwrapped)


def test_spaces_and_first_observation():
    env = make()
    obs, info = env.reset(seed=0)
    assert env.observation_space.contains(obs)
    assert env.action_space == gymnasium.spaces.Discrete(4)
    assert obs["rgb"].shape == (64, 64, 3) and obs["depth"].shape == (64, 64, 1)
    assert list(info) == list(INFO_KEYS)
    assert env.unwrapped.scene_ids[info["scene_index"]] == env.unwrapped.scene_id
    assert obs["pointgoal"][0] == pytest.approx(np.hypot(*(env.unwrapped.worlds.sim.goal[0]
                                                         - env.unwrapped.worlds.sim.pos[0])), abs=1e-4)


def test_info_keys_are_fixed_and_numeric_through_episodes():
    env = make(max_steps=15)
    rng = np.random.default_rng(1)
    for seed in range(6):
        _, info = env.reset(seed=seed)
        infos = [info]
        done = False
        while not done:
            _, _, term, trunc, info = env.step(int(rng.integers(0, 4)) if rng.random() < 0.1 else 1)
            infos.append(info)
            done = term or trunc
        assert len(infos) >= 2
        for k, info in enumerate(infos):
            assert list(info) == list(INFO_KEYS), info
            assert all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in info.values()), info
            if k < len(infos) - 1:
                assert info["success"] == 0.0 and info["spl"] == 0.0


def test_render_modes(headless):
    assert make().metadata["render_modes"] == ["human", "rgb_array"]
    img = make(render_mode="rgb_array")
    img.reset(seed=0)
    frame = img.render()
    assert frame.ndim == 3 and frame.dtype == np.uint8
    env = make(render_mode="human")
    with pytest.warns(UserWarning, match="render_mode='human' shows nothing here"):
        env.reset(seed=0)
    env.step(1)
    assert env.render() is None
    env.close()


def test_seeded_runs_repeat():
    runs = []
    for _ in range(2):
        env = make(pose_noise=(0.05, 0.02))
        obs, _ = env.reset(seed=42)
        seq = [obs["pointgoal"].copy()]
        rng = np.random.default_rng(0)
        for _ in range(30):
            obs, r, term, trunc, _ = env.step(int(rng.integers(1, 4)))
            seq.append(np.r_[obs["pointgoal"], r, obs["rgb"].mean()])
        runs.append(np.concatenate(seq))
    np.testing.assert_array_equal(runs[0], runs[1])


def test_truncates_after_max_steps():
    env = make()
    env.reset(seed=1)
    rng = np.random.default_rng(0)
    for t in range(500):
        _, _, term, trunc, info = env.step(int(rng.integers(1, 4)))
        assert not term
        assert trunc == (t == 499)
    assert info["steps"] == 500 and info["success"] == 0.0 and info["spl"] == 0.0
    with pytest.raises(InvalidAction, match="after the episode ended"):  # as in plex_nav_v0
        env.step(1)


@pytest.mark.parametrize("offset,success", [(0.1, True), (0.3, False)])
def test_stop_ends_the_episode_success_within_0_2_m(offset, success):
    env = make()
    env.reset(seed=0)
    ep = line_episode(env.unwrapped, offset, clearance=0.2)
    _, info = env.reset(options={"episode": ep})
    assert info["distance_to_goal"] == pytest.approx(offset, abs=0.02)
    _, r, term, trunc, info = env.step(0)
    assert term and not trunc
    assert info["success"] == float(success)
    assert r == pytest.approx((10.0 if success else 0.0) - 0.01, abs=1e-6)


def test_rewards_and_spl_hand_computed():
    env = make()
    env.reset(seed=0)
    ep = line_episode(env.unwrapped, 1.0, behind=0.5)
    l = ep.geodesic_distance
    env.reset(options={"episode": ep})
    total = 0.0
    # A detour: turn around, 0.5 m back, turn around, 1.5 m forward (path 2.0 m), STOP.
    for a in [2] * 18 + [1] * 2 + [2] * 18 + [1] * 6:
        d0 = env.unwrapped.worlds.sim.distance_to_goal[0]
        _, r, term, _, info = env.step(a)
        d1 = env.unwrapped.worlds.sim.distance_to_goal[0]
        assert r == pytest.approx(d0 - d1 - 0.01, abs=1e-5)
        assert not term
        total += r
    _, r, term, _, info = env.step(0)
    total += r
    assert term and info["success"] == 1.0 and info["collisions"] == 0
    assert info["spl"] == pytest.approx(l / 2.0, abs=1e-5)
    # The episode's reward: the geodesic distance covered, slack on 45 actions, +10.
    assert total == pytest.approx(l - info["distance_to_goal"] - 45 * 0.01 + 10.0, abs=1e-4)


def test_collision_penalty():
    env = make()
    env.reset(seed=3)
    rng = np.random.default_rng(2)
    seen = 0
    for _ in range(400):
        c0 = env.unwrapped.worlds.collisions[0]
        d0 = env.unwrapped.worlds.sim.distance_to_goal[0]
        _, r, term, trunc, info = env.step(int(rng.choice([1, 1, 1, 2, 3])))
        if info["collisions"] > c0:
            seen += 1
            assert r == pytest.approx(d0 - info["distance_to_goal"] - 0.02, abs=1e-5)
        if term or trunc:
            env.reset()
    assert seen > 0


@pytest.mark.parametrize("action,error,match", [
    (4, InvalidAction, "0..3"), (-1, InvalidAction, "0..3"), (1.5, InvalidAction, "non-integer value 1.5"),
    (float("nan"), InvalidAction, "non-integer value nan"), (None, InvalidAction, "integer"),
    ({"action": 1}, ValueError, "integer in 0..3"), (np.array([1, 2]), ValueError, "integer in 0..3"),
    ("1", ValueError, "integer in 0..3"),
])
def test_bad_actions(action, error, match):
    env = make()
    env.reset(seed=0)
    pos = env.unwrapped.worlds.sim.pos.copy()
    with pytest.raises(error, match=match):
        env.step(action)
    np.testing.assert_array_equal(env.unwrapped.worlds.sim.pos, pos)
    assert env.unwrapped.worlds.steps[0] == 0
    env.step(1)
    assert env.unwrapped.worlds.steps[0] == 1


def test_render():
    env = make(render_mode="rgb_array")
    env.reset(seed=0)
    env.step(1)
    img = env.render()
    assert img.ndim == 3 and img.shape[2] == 3 and img.dtype == np.uint8
