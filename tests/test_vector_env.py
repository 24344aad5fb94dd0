"""The vector envs against the single envs: same seeds, same episodes, same actions must
give identical observations, rewards, turn changes and episode ends."""

from __future__ import annotations

import gymnasium
import numba
import numpy as np
import pytest

from plex_ma.envs import plex_nav_v0
from plex_ma.envs.actions import InvalidAction
from plex_ma.envs.vector import EXECUTOR, INFO_KEYS, PLANNER, PlexVectorEnv, PointNavVectorEnv

from .env_helpers import SMALL, line_episode

AGENTS = ["planner", "executor"]


@pytest.fixture(autouse=True)
def one_numba_thread():
    """A few worlds leave the kernels little to share out, and under pytest-xdist two
    workers already fill the two cores: spinning OpenMP threads would only slow this down.
    (The results do not depend on the thread count.)"""
    prev = numba.get_num_threads()
    numba.set_num_threads(1)
    yield
    numba.set_num_threads(prev)


def _assert_obs_equal(got: dict, want: dict, what: str) -> None:
    assert got.keys() == want.keys(), what
    for k in want:
        np.testing.assert_array_equal(got[k], want[k], err_msg=f"{what}: {k}")


def _finish_aec_episode(aec, info_vec: dict, terminated: bool) -> None:
    """The AEC side of an episode end: flags, final infos, then one dead step each."""
    assert aec.terminations == {a: terminated for a in AGENTS}
    assert aec.truncations == {a: not terminated for a in AGENTS}
    for a in AGENTS:
        assert aec.infos[a] == info_vec
    while aec.agents:
        aec.step(None)


@pytest.mark.parametrize("num_envs,seed,max_steps,eli", [(4, 0, 60, True), (3, 5, 40, False)])
def test_plex_vector_env_matches_aec(num_envs, seed, max_steps, eli):
    cfg = dict(SMALL, max_steps=max_steps, n_ex=5, eli=eli, pose_noise=(0.0, 0.0))
    venv = PlexVectorEnv(num_envs, seed=seed, **cfg)
    turn, pobs, eobs = venv.reset()
    aecs = [plex_nav_v0.raw_env(**cfg) for _ in range(num_envs)]
    for i, aec in enumerate(aecs):
        # A raw_env has one world with its own RNG, so it is given world i's episodes.
        aec.reset(seed=seed + i, options={"episode": venv.worlds.sim.episodes[i]})
        assert AGENTS.index(aec.agent_selection) == turn[i] == PLANNER
        _assert_obs_equal({k: v[i] for k, v in pobs.items()}, aec.observe("planner"), f"world {i} reset planner")
        _assert_obs_equal({k: v[i] for k, v in eobs.items()}, aec.observe("executor"), f"world {i} reset executor")
        assert aec.infos["planner"] == venv.info(i)
    rng = np.random.default_rng(seed)
    n = num_envs
    counts = dict(terminated=0, truncated=0, success=0, turn_changes=0, executor_stops=0)
    # Now and then an episode that starts 0.1 m from its goal replaces the sampled one in
    # both, and the planner stops often there, so that successes are compared too.
    near_goal = line_episode(venv, 0.1, clearance=0.2)
    near = np.zeros(n, bool)
    for t in range(500):
        acts = dict(stop=(rng.random(n) < np.where(near, 0.5, 0.04)).astype(np.int64),
                    subgoal=np.stack([rng.uniform(0, 4, n), rng.uniform(-np.pi, np.pi, n)], 1).astype(np.float32),
                    action=np.where(rng.random(n) < 0.25, 0, rng.integers(1, 4, n)),
                    eli=rng.normal(size=(n, 128)).astype(np.float32))
        out = venv.step(**acts)
        ended_rows = list(np.flatnonzero(out.terminated | out.truncated))
        for i, aec in enumerate(aecs):
            agent = aec.agent_selection
            assert out.acted[i] == AGENTS.index(agent), f"step {t} world {i}"
            if agent == "planner":
                aec.step({"stop": int(acts["stop"][i]), "subgoal": acts["subgoal"][i]})
            else:
                aec.step({"action": int(acts["action"][i]), "eli": acts["eli"][i]})
            assert aec.rewards == {"planner": float(out.rewards[i, PLANNER]),
                                   "executor": float(out.rewards[i, EXECUTOR])}, f"step {t} world {i}"
            ended = bool(out.terminated[i] or out.truncated[i])
            assert (aec.terminations["planner"] or aec.truncations["planner"]) == ended
            if ended:
                info = out.episode_infos[ended_rows.index(i)]
                assert tuple(info) == INFO_KEYS
                _finish_aec_episode(aec, info, bool(out.terminated[i]))
                counts["terminated" if out.terminated[i] else "truncated"] += 1
                counts["success"] += info["success"] > 0
                _assert_obs_equal({k: v[ended_rows.index(i)] for k, v in out.final_executor_obs.items()},
                                  aec.observe("executor"), f"step {t} world {i} final")
                near[i] = rng.random() < 0.3
                if near[i]:
                    venv.worlds.reset_rows([i], [near_goal])
                    out.turn[i] = PLANNER
                    for k, v in venv.worlds.planner_obs([i]).items():
                        out.planner_obs[k][i] = v[0]
                    for k, v in venv.worlds.executor_obs([i]).items():
                        out.executor_obs[k][i] = v[0]
                aec.reset(options={"episode": venv.worlds.sim.episodes[i]})  # the vector env's next episode
            else:
                counts["turn_changes"] += (agent != aec.agent_selection)
                counts["executor_stops"] += bool(out.executor_stopped[i])
                assert bool(out.executor_turn_end[i]) == (agent == "executor" and aec.agent_selection == "planner")
            assert AGENTS.index(aec.agent_selection) == out.turn[i], f"step {t} world {i}"
            if out.turn[i] == PLANNER:
                _assert_obs_equal({k: v[i] for k, v in out.planner_obs.items()}, aec.observe("planner"),
                                  f"step {t} world {i} planner")
            _assert_obs_equal({k: v[i] for k, v in out.executor_obs.items()}, aec.observe("executor"),
                              f"step {t} world {i} executor")
            if not ended:
                assert aec.infos["planner"] == venv.info(i)
    # Many episodes of both kinds and many turn changes were compared.
    assert counts["terminated"] >= 5 and counts["truncated"] >= 5 and counts["success"] >= 2, counts
    assert counts["turn_changes"] >= 100 and counts["executor_stops"] >= 50, counts


def test_plex_vector_env_rejects_bad_actions_without_changes():
    venv = PlexVectorEnv(2, seed=0, **SMALL)
    venv.reset()
    n = 2
    good = dict(stop=np.zeros(n, np.int64), subgoal=np.tile([1.0, 0.0], (n, 1)), action=np.ones(n, np.int64),
                eli=np.zeros((n, 128), np.float32))
    pos = venv.worlds.sim.pos.copy()
    for bad, match in [(dict(good, subgoal=np.tile([np.nan, 0.0], (n, 1))), "NaN"),
                       (dict(good, stop=np.full(n, 3)), "0..1"),
                       (dict(good, subgoal=np.zeros((n, 3))), "shape")]:
        with pytest.raises(InvalidAction, match=match):
            venv.step(**bad)
        np.testing.assert_array_equal(venv.worlds.sim.pos, pos)
        assert np.all(venv.worlds.turn == PLANNER)
    out = venv.step(**good)
    assert np.all(out.turn == EXECUTOR)


@pytest.mark.parametrize("num_envs,seed", [(3, 0), (2, 9)])
def test_pointnav_vector_env_matches_gym(num_envs, seed):
    cfg = dict(SMALL, max_steps=40)
    venv = PointNavVectorEnv(num_envs, seed=seed, **cfg)
    obs = venv.reset()
    envs = [gymnasium.make("plex_ma/PointNav-v0", **cfg) for _ in range(num_envs)]
    for i, e in enumerate(envs):
        o, info = e.reset(seed=seed + i, options={"episode": venv.worlds.sim.episodes[i]})
        _assert_obs_equal({k: v[i] for k, v in obs.items()}, o, f"world {i} reset")
        assert info == venv.worlds.info(i)
    rng = np.random.default_rng(seed)
    terminated = truncated = 0
    for t in range(200):
        actions = np.where(rng.random(num_envs) < 0.05, 0, rng.integers(1, 4, num_envs))
        obs, rew, term, trunc, infos = venv.step(actions)
        ended_rows = list(np.flatnonzero(term | trunc))
        for i, e in enumerate(envs):
            o, r, te, tr, info = e.step(int(actions[i]))
            assert r == float(rew[i]) and te == bool(term[i]) and tr == bool(trunc[i]), f"step {t} world {i}"
            if te or tr:
                assert info == infos[ended_rows.index(i)]
                terminated += te
                truncated += tr
                o, info = e.reset(options={"episode": venv.worlds.sim.episodes[i]})
            _assert_obs_equal({k: v[i] for k, v in obs.items()}, o, f"step {t} world {i}")
    assert terminated >= 5 and truncated >= 3


def test_bench_env_runs(capsys):
    import json

    from plex_ma.bench import main

    main(["env", "--num-envs", "2", "--resolution", "32", "--num-scenes", "4", "--steps", "3", "--aec-turns", "30", "--warmup", "2",
          "--json"])
    out = json.loads(capsys.readouterr().out)
    for k in ("aec_turns_per_second", "vector_steps_per_second", "vector_executor_steps_per_second",
              "sim_steps_per_second", "ratio", "ratio_all_actions", "ratio_cpu"):
        assert out[k] > 0, k
    assert out["num_envs"] == 2 and out["resolution"] == 32


def test_world_views_and_fixed_episodes_through_the_public_api():
    """world(i) copies what one world holds (a later step does not change it); setting
    fixed_episodes makes the worlds take those episodes in order at the next reset; the
    flat env has no sub-goal and no ego map unless built with one."""
    env = PlexVectorEnv(2, seed=0, **SMALL)
    eps = env.generate_episodes(3, seed=7)
    assert [e.episode_id for e in eps] == [e.episode_id for e in env.generate_episodes(3, seed=7)]
    env.fixed_episodes = eps
    env.reset()
    assert env.fixed_episodes == eps
    v = env.world(1)
    assert v.episode is eps[1] and v.turn == PLANNER and v.grid.scene_id == eps[1].scene_id
    np.testing.assert_allclose(v.position, eps[1].start_position)
    assert v.goal_polar[0] == pytest.approx(np.hypot(*(np.asarray(eps[1].goal_position) - v.position)), abs=1e-5)
    assert v.rgb.shape == (SMALL["resolution"], SMALL["resolution"], 3) and v.collisions == 0
    assert env.ego_map(1).shape == (6, 32, 32) and env.world(0, images=False).rgb is None
    before = v.rgb.copy()
    env.step(stop=np.zeros(2, np.int64), subgoal=np.array([[1.0, 0.0], [1.0, 0.0]], np.float32))
    env.step(action=np.array([1, 1]), eli=np.zeros((2, 128), np.float32))  # forward
    np.testing.assert_array_equal(v.rgb, before)  # the view is a copy
    after = env.world(1, images=False)
    assert after.turn == EXECUTOR and after.subgoal_raw_polar is not None
    assert not np.array_equal(after.position, v.position) or after.collisions == 1
    flat = PointNavVectorEnv(1, seed=0, **SMALL)
    flat.reset()
    assert flat.world(0).subgoal is None and flat.world(0).turn is None
    with pytest.raises(RuntimeError, match="egomap=False"):
        flat.ego_map(0)
