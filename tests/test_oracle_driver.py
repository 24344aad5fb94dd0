"""The shortest-path oracles, the rollout driver, and evaluation with stand-in agents."""

from __future__ import annotations

import json

import numpy as np
import pytest

from plex_ma.envs import plex_nav_v0
from plex_ma.envs.sim import generate_episodes
from plex_ma.envs.vector import PlexVectorEnv
from plex_ma.evaluate import main as evaluate_main
from plex_ma.trainers.driver import (OracleExecutorPolicy, OraclePlannerPolicy, PlexDriver, RandomExecutor,
                                     RandomPlanner)

from .env_helpers import SMALL, executor_action, line_episode, planner_action


def _run(env, drv, n_episodes):
    drv.reset(seed=0)
    infos = {}
    while len(infos) < n_episodes:
        drv.decide(lambda d: infos.update({i["episode_id"]: i for i in d.result.episode_infos}))
        s = drv.step()
        infos.update({i["episode_id"]: i for i in s.result.episode_infos})
    return infos


@pytest.mark.parametrize("scenes", ["procgen", "r2v"])
def test_oracles_reach_the_goal(scenes):
    """Both oracles together succeed on >= 95% of fixed test episodes, with SPL near 1."""
    env = PlexVectorEnv(8, seed=0, resolution=16, split="test", scenes=scenes)
    eps = env.worlds.fixed_episodes or generate_episodes(env.worlds.bank, 40, seed=12345)  # r2v: no fixed file
    env.worlds.fixed_episodes = list(eps[:40])
    drv = PlexDriver(env, OraclePlannerPolicy(env), OracleExecutorPolicy(env))
    infos = _run(env, drv, 40)
    success = np.mean([infos[e.episode_id]["success"] for e in env.worlds.fixed_episodes])
    spl = np.mean([infos[e.episode_id]["spl"] for e in env.worlds.fixed_episodes])
    assert success >= 0.95 and spl >= 0.9, (success, spl)


def test_random_stand_ins_do_not_reach_the_goal():
    """The same episodes with random agents: the oracles' success is not the world's doing."""
    env = PlexVectorEnv(8, seed=0, resolution=16, split="test", max_steps=100)
    env.worlds.fixed_episodes = env.worlds.fixed_episodes[:16]
    rng = np.random.default_rng(0)
    drv = PlexDriver(env, RandomPlanner(4.0, stop_prob=0.05, rng=rng), RandomExecutor(rng=rng))
    infos = _run(env, drv, 16)
    assert np.mean([i["success"] for i in infos.values()]) <= 0.1


def test_driver_matches_the_aec_env():
    """The driver over a one-world vector env and the AEC env, fed the same actions from the
    same seed, see the same observations and rewards (the driver adds no rule)."""
    vec = PlexVectorEnv(1, seed=3, **SMALL)
    aec = plex_nav_v0.raw_env(**SMALL)
    rng = np.random.default_rng(1)
    drv = PlexDriver(vec, RandomPlanner(4.0, rng=rng), RandomExecutor(stop_prob=0.2, rng=rng))
    drv.reset(seed=3)
    aec.reset(seed=3, options={"episode": vec.worlds.sim.episodes[0]})  # the same episode
    acted = {"planner": 0, "executor": 0}

    def check_planner(d):
        obs = aec.observe("planner")
        for k, v in d.obs.items():
            np.testing.assert_allclose(obs[k], v[0], atol=1e-6)
        aec.step({"stop": int(d.out["stop"][0]), "subgoal": d.out["subgoal"][0]})
        acted["planner"] += 1

    for _ in range(60):
        drv.decide(check_planner)
        assert aec.agent_selection == "executor"
        obs = aec.observe("executor")
        s = drv.step()
        for k, v in s.obs.items():
            np.testing.assert_allclose(obs[k], v[0], atol=1e-6)
        aec.step({"action": int(s.out["action"][0]), "eli": s.out["eli"][0]})
        acted["executor"] += 1
        assert aec.rewards["executor"] == pytest.approx(float(s.result.rewards[0, 1]), abs=1e-6)
        if s.result.terminated[0] or s.result.truncated[0]:
            break
    assert acted["planner"] >= 2 and acted["executor"] >= 10


def test_executor_stop_penalty():
    """executor_stop_penalty: a STOP short of the sub-goal costs it; a STOP within reach does not."""
    env = plex_nav_v0.env(**SMALL, executor_stop_penalty=-0.5)
    env.reset(seed=0)
    raw = env.unwrapped
    env.reset(options={"episode": line_episode(raw, 2.0)})
    env.step(planner_action(0, 1.0, 0.0))
    env.step(executor_action(0))  # STOP 1 m short of the sub-goal
    assert env.rewards["executor"] == pytest.approx(-0.01 - 0.5, abs=1e-6)
    env.step(planner_action(0, 1.0, 0.0))
    for _ in range(4):
        env.step(executor_action(1))
    env.step(executor_action(0))  # within 0.5 m: the bonus, no penalty
    assert env.rewards["executor"] == pytest.approx(1.0 - 0.01, abs=0.02)
    with pytest.raises(ValueError, match="executor_stop_penalty"):
        plex_nav_v0.env(**SMALL, executor_stop_penalty=1.0)


def test_executor_collision_reward():
    """executor_collision_reward: a blocked move costs the executor that much more, and the
    planner nothing more (walking straight on until the agent runs into a wall)."""
    env = plex_nav_v0.env(**SMALL, executor_collision_reward=-0.2)
    env.reset(seed=0)
    raw = env.unwrapped
    env.reset(options={"episode": line_episode(raw, 1.0)})
    blocked = 0
    for _ in range(120):
        if env.agent_selection == "planner":
            env.step(planner_action(0, 4.0, 0.0))
            continue
        pos, hits = raw.worlds.sim.pos[0].copy(), raw.worlds.collisions[0]
        env.step(executor_action(1))
        if raw.worlds.collisions[0] > hits and np.all(raw.worlds.sim.pos[0] == pos):  # no progress either way
            blocked += 1
            assert env.rewards["executor"] == pytest.approx(-0.01 - 0.01 - 0.2, abs=1e-6)
            assert env.rewards["planner"] == pytest.approx(-0.01 - 0.01, abs=1e-6)
    assert blocked > 0
    with pytest.raises(ValueError, match="executor_collision_reward"):
        plex_nav_v0.env(**SMALL, executor_collision_reward=0.5)


def test_evaluate_with_oracles_says_ground_truth(tmp_path, capsys):
    out = tmp_path / "eval.json"
    evaluate_main(["--planner", "oracle", "--executor", "oracle", "--split", "val", "--episodes", "8", "--json",
                   str(out)])
    text = capsys.readouterr().out
    assert "ground truth" in text
    res = json.loads(out.read_text())
    assert res["ground_truth"] is True and res["success"] >= 0.95 and res["episodes"] == 8
    with pytest.raises(SystemExit):
        evaluate_main(["--planner", "oracle", "--split", "val", "--episodes", "2"])  # learned executor: no checkpoint
