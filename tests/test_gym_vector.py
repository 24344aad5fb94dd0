"""``gymnasium.make_vec("plex_ma/PointNav-v0")``: the batched gymnasium vector env against
gymnasium's SyncVectorEnv of single envs (same seeds and actions, same results), its
NEXT_STEP autoreset step by step, its spaces, infos, seeding, errors, render, gymnasium's
vector wrappers, the bench and the CleanRL-style example."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import gymnasium
import numba
import numpy as np
import pytest
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

import plex_ma  # noqa: F401  (registers the env)
from plex_ma.envs.gym_vector import PointNavGymVectorEnv
from plex_ma.envs.actions import InvalidAction
from plex_ma.envs.rules import INFO_KEYS
from plex_ma.envs.sim.episodes import load_episodes

from .env_helpers import SMALL, line_episode

ID = "plex_ma/PointNav-v0"
EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "train_cleanrl_vector.py"


@pytest.fixture(autouse=True)
def one_numba_thread():
    """Few worlds leave the kernels little to share out; under pytest-xdist the two
    workers already fill the two cores (the results do not depend on the thread count,
    which ``test_matches_sync_vector_env`` checks with two)."""
    prev = numba.get_num_threads()
    numba.set_num_threads(1)
    yield
    numba.set_num_threads(prev)


def make(num_envs=3, **kw):
    return gymnasium.make_vec(ID, num_envs=num_envs, vectorization_mode="vector_entry_point", **{**SMALL, **kw})


def make_sync(num_envs=3, **kw):
    return gymnasium.make_vec(ID, num_envs=num_envs, vectorization_mode="sync", **{**SMALL, **kw})


def moves(rng, n, stop_prob=0.05):
    return np.where(rng.random(n) < stop_prob, 0, rng.integers(1, 4, n))


def assert_same_obs(got, want, what):
    assert got.keys() == want.keys(), what
    for k in want:
        assert got[k].dtype == want[k].dtype and got[k].shape == want[k].shape, f"{what}: {k}"
        np.testing.assert_array_equal(got[k], want[k], err_msg=f"{what}: {k}")


def assert_same_infos(got, want, what):
    assert list(got) == list(want), what
    for k in want:
        assert got[k].dtype == want[k].dtype, f"{what}: {k} {got[k].dtype} != {want[k].dtype}"
        np.testing.assert_array_equal(got[k], want[k], err_msg=f"{what}: {k}")


# ----------------------------------------------------------------------------- API

def test_make_vec_gives_the_batched_vector_env():
    env = make(3)
    assert isinstance(env, PointNavGymVectorEnv) and isinstance(env, VectorEnv)
    assert env.num_envs == 3 and env.unwrapped is env
    assert env.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP
    assert env.spec.id == ID and env.spec.kwargs["num_envs"] == 3 and env.spec.kwargs["resolution"] == 64
    # Without a mode, make_vec prefers the registered vector entry point.
    assert isinstance(gymnasium.make_vec(ID, num_envs=2, **SMALL), PointNavGymVectorEnv)
    single = gymnasium.make(ID, **SMALL)
    assert env.single_observation_space == single.observation_space
    assert env.observation_space == batch_space(single.observation_space, 3)
    assert env.single_action_space == gymnasium.spaces.Discrete(4)
    assert env.action_space == gymnasium.spaces.MultiDiscrete([4, 4, 4])
    obs, info = env.reset(seed=0)
    assert env.observation_space.contains(obs)
    assert obs["rgb"].shape == (3, 64, 64, 3) and obs["depth"].shape == (3, 64, 64, 1)
    assert obs["pointgoal"].shape == (3, 2)
    for k in INFO_KEYS:
        assert info[k].shape == (3,) and info[f"_{k}"].tolist() == [True] * 3, k
    obs, rew, term, trunc, info = env.step(env.action_space.sample())
    assert env.observation_space.contains(obs)
    assert rew.dtype == np.float64 and term.dtype == np.bool_ and trunc.dtype == np.bool_
    assert rew.shape == term.shape == trunc.shape == (3,)
    env.close()
    assert env.closed


@pytest.mark.parametrize("num_envs,seed,threads", [(3, 0, 1), (4, 11, 2)])
def test_matches_sync_vector_env(num_envs, seed, threads):
    """Same seeds, same actions: the same observations, rewards, flags and infos as
    SyncVectorEnv of single PointNav-v0 envs, through terminations, truncations and
    the NEXT_STEP resets after them."""
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    cfg = dict(max_steps=25)
    venv, sync = make(num_envs, **cfg), make_sync(num_envs, **cfg)
    assert sync.metadata["autoreset_mode"] == venv.metadata["autoreset_mode"]
    o1, i1 = venv.reset(seed=seed)
    o2, i2 = sync.reset(seed=seed)
    assert_same_obs(o1, o2, "reset")
    assert_same_infos(i1, i2, "reset")
    rng = np.random.default_rng(seed)
    ends = {"term": 0, "trunc": 0}
    for t in range(120):
        a = moves(rng, num_envs)
        o1, r1, te1, tr1, i1 = venv.step(a)
        o2, r2, te2, tr2, i2 = sync.step(a)
        assert_same_obs(o1, o2, f"step {t}")
        assert r1.dtype == r2.dtype
        np.testing.assert_array_equal(r1, r2, err_msg=f"step {t}")
        np.testing.assert_array_equal(te1, te2, err_msg=f"step {t}")
        np.testing.assert_array_equal(tr1, tr2, err_msg=f"step {t}")
        assert_same_infos(i1, i2, f"step {t}")
        ends["term"] += int(te1.sum())
        ends["trunc"] += int(tr1.sum())
    assert ends["term"] >= 5 and ends["trunc"] >= 3, ends
    # A list of seeds, one per world, as SyncVectorEnv takes it.
    seeds = [seed + 7 * i + 1 for i in range(num_envs)]
    assert_same_obs(venv.reset(seed=seeds)[0], sync.reset(seed=seeds)[0], "list seeds")


def test_seeded_reset_repeats():
    env = make(3, max_steps=20)
    rng = np.random.default_rng(1)
    acts = [moves(rng, 3, 0.1) for _ in range(60)]

    def run():
        obs, _ = env.reset(seed=5)
        out = [obs["pointgoal"].copy()]
        for a in acts:
            obs, rew, *_ = env.step(a)
            out += [obs["pointgoal"].copy(), rew]
        return out

    first, second = run(), run()
    for x, y in zip(first, second):
        np.testing.assert_array_equal(x, y)
    other = make(3, max_steps=20)
    assert not np.array_equal(other.reset(seed=6)[0]["pointgoal"], first[0])
    # world i is seeded as a single env's reset(seed=5 + i)
    single = gymnasium.make(ID, **SMALL)
    np.testing.assert_array_equal(single.reset(seed=7)[0]["pointgoal"], first[0][2])


# ----------------------------------------------------------------------------- autoreset

def test_next_step_autoreset_after_termination():
    env = make(3)
    obs0, _ = env.reset(seed=3)
    first_episodes = env.episodes
    obs, rew, term, trunc, info = env.step(np.array([1, 2, 3]))
    last = {k: v.copy() for k, v in obs.items()}
    # World 0 stops: it terminates (no success: the goal is >= 1 m away), the others go on.
    obs, rew, term, trunc, info = env.step(np.array([0, 1, 1]))
    assert term.tolist() == [True, False, False] and not trunc.any()
    assert rew[0] == pytest.approx(-0.01)  # slack, no progress, no success bonus
    assert info["success"][0] == 0.0 and info["spl"][0] == 0.0 and info["steps"][0] == 2
    np.testing.assert_array_equal(obs["rgb"][0], last["rgb"][0])  # STOP does not move: the terminal image
    assert env.episodes[0] is first_episodes[0]
    # The next step ignores world 0's action and starts its next episode.
    obs, rew, term, trunc, info = env.step(np.array([1, 1, 1]))
    assert rew[0] == 0.0 and not term[0] and not trunc[0]
    assert env.episodes[0] is not first_episodes[0]
    assert env.episodes[1:] == first_episodes[1:]
    assert info["steps"].tolist() == [0, 3, 3] and info["collisions"][0] == 0
    ep = env.episodes[0]
    assert info["geodesic_distance"][0] == ep.geodesic_distance
    np.testing.assert_array_equal(env.worlds.sim.pos[0], ep.start_position)  # the FORWARD was not applied
    assert not np.array_equal(obs["pointgoal"][0], obs0["pointgoal"][0])
    # ... and then steps it as usual.
    obs, rew, term, trunc, info = env.step(np.array([2, 1, 1]))
    assert info["steps"].tolist() == [1, 4, 4] and rew[0] == pytest.approx(-0.01)


def test_next_step_autoreset_after_truncation_and_success():
    env = make(2, max_steps=3)
    env.reset(seed=0)
    ep = line_episode(env, 1.0)
    _, info = env.reset(options={"episodes": [ep, ep]})
    assert info["geodesic_distance"].tolist() == [ep.geodesic_distance] * 2
    for t in range(3):
        d_prev = info["distance_to_goal"]
        obs, rew, term, trunc, info = env.step(np.array([1, 2]))  # world 0 walks to the goal, 1 turns
        assert (term | trunc).any() == (t == 2)
    # Both truncate at max_steps = 3 (the STOP would have come next).
    assert trunc.tolist() == [True, True] and not term.any()
    assert info["steps"].tolist() == [3, 3] and info["success"].tolist() == [0.0, 0.0]
    assert d_prev[0] - info["distance_to_goal"][0] > 0.2  # world 0 walked towards the goal
    assert rew[0] == pytest.approx(d_prev[0] - info["distance_to_goal"][0] - 0.01, abs=1e-5)
    assert rew[1] == pytest.approx(-0.01, abs=1e-6)
    obs, rew, term, trunc, info = env.step(np.array([1, 1]))
    assert rew.tolist() == [0.0, 0.0] and not term.any() and not trunc.any()
    assert info["steps"].tolist() == [0, 0]
    # A successful stop: +10 on the terminating step, spl 1 on a straight walk.
    env2 = make(1, max_steps=10)
    env2.reset(seed=0)
    env2.reset(options={"episodes": [line_episode(env2, 0.5)]})
    for a in (1, 1):
        env2.step(np.array([a]))
    obs, rew, term, trunc, info = env2.step(np.array([0]))
    assert term[0] and rew[0] == pytest.approx(10.0 - 0.01)
    assert info["success"][0] == 1.0 and info["spl"][0] == pytest.approx(1.0)
    _, rew, term, _, info = env2.step(np.array([0]))  # the reset step: its STOP is ignored
    assert rew[0] == 0.0 and not term[0] and info["success"][0] == 0.0


def test_reset_mask_resets_only_those_worlds():
    env = make(3)
    env.reset(seed=0)
    for _ in range(2):
        env.step(np.array([1, 1, 1]))
    before = env.episodes
    obs, info = env.reset(options={"reset_mask": np.array([False, True, False])})
    assert info["_steps"].tolist() == [False, True, False]
    assert info["steps"].tolist() == [0, 0, 0]  # zero where masked out, as SyncVectorEnv fills it
    assert env.worlds.steps.tolist() == [2, 0, 2]
    assert env.episodes[0] is before[0] and env.episodes[1] is not before[1]
    with pytest.raises(ValueError, match="reset_mask"):
        env.reset(options={"reset_mask": [True, False, True]})
    with pytest.raises(ValueError, match="at least one"):
        env.reset(options={"reset_mask": np.zeros(3, bool)})
    with pytest.raises(ValueError, match="unknown reset option"):
        env.reset(options={"episode": before[0]})
    with pytest.raises(ValueError, match="one episode per world reset"):
        env.reset(options={"episodes": before[:2]})


def test_fixed_episodes_are_dealt_to_the_worlds_in_turn():
    env = make(3, split="val", num_scenes=None)
    from plex_ma.episodes import default_episode_file

    known = set(env.scene_ids)
    file_eps = [e for e in load_episodes(default_episode_file("procgen", "val")) if e.scene_id in known]
    env.reset(seed=0)
    assert env.episodes == file_eps[:3]
    for _ in range(2):
        env.step(np.array([0, 1, 0]))  # worlds 0 and 2 stop, then reset
    assert env.episodes == [file_eps[3], file_eps[1], file_eps[4]]
    env.reset(seed=1)  # a seeded reset starts the cycle again
    assert env.episodes == file_eps[:3]


# ----------------------------------------------------------------------------- errors

@pytest.mark.parametrize("actions,match", [
    (np.array([1, 1]), r"shape \(2,\)"),
    (np.array([[1, 1, 1]]), r"shape \(1, 3\)"),
    (np.array([1, 4, 1]), r"world\(s\) \[1\] got \[4\]"),
    (np.array([-1, 1, 1]), r"world\(s\) \[0\] got \[-1\]"),
    (np.array([1.0, 1.5, 2.0]), "non-integer"),
    (np.array([1.0, np.nan, 2.0]), "non-integer"),
    (np.array(["a", "b", "c"]), "dtype <U1"),
    (np.array([True, False, True]), "dtype bool"),
    ({"action": [1, 1, 1]}, "dict"),
    ("forward", "str"),
    (None, r"shape \(\)"),
])
def test_bad_actions_raise_and_change_nothing(actions, match):
    env = make(3)
    env.reset(seed=0)
    pos, steps = env.worlds.sim.pos.copy(), env.worlds.steps.copy()
    with pytest.raises(InvalidAction, match=match) as e:
        env.step(actions)
    assert "one per world" in str(e.value)
    np.testing.assert_array_equal(env.worlds.sim.pos, pos)
    np.testing.assert_array_equal(env.worlds.steps, steps)
    env.step(np.array([1, 1, 1]))  # still usable
    env.step([1.0, 2.0, 3.0])  # whole floats and lists are accepted, as the single env accepts them


def test_other_errors():
    with pytest.raises(RuntimeError, match="before reset"):
        make(2).step(np.array([1, 1]))
    with pytest.raises(ValueError, match="num_envs"):
        PointNavGymVectorEnv(num_envs=0, **SMALL)
    with pytest.raises(TypeError, match="unknown config key"):
        make(2, max_episode_steps=10)
    with pytest.raises(ValueError, match="human"):
        make(2, render_mode="human")
    env = make(2)
    with pytest.raises(ValueError, match="one per world"):
        env.reset(seed=[1, 2, 3])
    with pytest.raises(ValueError, match="seed must be"):
        env.reset(seed="zero")
    with pytest.raises(ValueError, match="first reset"):
        env.reset(options={"reset_mask": np.array([True, False])})


# ----------------------------------------------------------------------------- extras

def test_render_rgb_array_matches_sync():
    venv = make(2, render_mode="rgb_array")
    sync = make_sync(2, render_mode="rgb_array")
    assert make(2).render() is None
    venv.reset(seed=4)
    sync.reset(seed=4)
    rng = np.random.default_rng(0)
    for t in range(12):
        a = moves(rng, 2, 0.2)
        venv.step(a)
        sync.step(a)
        got, want = venv.render(), sync.render()
        assert isinstance(got, tuple) and len(got) == 2
        for g, w in zip(got, want):
            assert g.dtype == np.uint8 and g.ndim == 3 and g.shape[2] == 3
            np.testing.assert_array_equal(g, w, err_msg=f"step {t}")


def test_copy_flag():
    env = make(2)
    obs, _ = env.reset(seed=0)
    kept = {k: v.copy() for k, v in obs.items()}
    env.step(np.array([2, 3]))  # turning changes every image
    assert_same_obs(obs, kept, "copy=True keeps returned arrays")
    raw = make(2, copy=False)
    obs, _ = raw.reset(seed=0)
    assert np.shares_memory(obs["rgb"], raw.worlds.sim.rgb)


def test_record_episode_statistics_wrapper():
    env = gymnasium.wrappers.vector.RecordEpisodeStatistics(make(2, max_steps=6))
    env.reset(seed=0)
    returns = np.zeros(2)
    seen = 0
    for t in range(20):
        obs, rew, term, trunc, info = env.step(np.array([1, 3]))
        returns += rew
        done = term | trunc
        if done.any():
            assert info["_episode"].tolist() == done.tolist()
            np.testing.assert_allclose(info["episode"]["r"][done], returns[done], rtol=1e-6)
            assert info["episode"]["l"][done].tolist() == [6] * int(done.sum())
            assert info["steps"][done].tolist() == [6] * int(done.sum())
            returns[done] = 0
            seen += int(done.sum())
        else:
            assert "episode" not in info
    assert seen == 6  # 20 steps = 3 episodes of 6 + 2 reset steps per world
    assert len(env.return_queue) == 6


def test_bench_gymvec_runs(capsys):
    from plex_ma.bench import main

    main(["gymvec", "--num-envs", "2", "--resolution", "32", "--num-scenes", "4", "--steps", "6", "--rounds", "2",
          "--warmup", "2", "--stop-prob", "0.3", "--json"])
    out = json.loads(capsys.readouterr().out)
    assert out["identical"] is True
    for k in ("vector_steps_per_second", "sync_steps_per_second", "speedup", "speedup_min", "speedup_median",
              "speedup_max", "speedup_cpu"):
        assert out[k] > 0, k
    assert out["num_envs"] == 2 and out["resolution"] == 32 and out["steps"] == 12


# ----------------------------------------------------------------------------- example

@pytest.fixture(scope="module")
def example():
    import importlib.util

    spec = importlib.util.spec_from_file_location("train_cleanrl_vector", EXAMPLE)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # its dataclass looks its module up while being defined
    try:
        spec.loader.exec_module(mod)
        yield mod
    finally:
        sys.modules.pop(spec.name, None)


def test_example_advantages_skip_reset_steps_and_bootstrap_truncations(example):
    import torch

    g, lam = 0.9, 0.5
    # One world, 5 steps: t=1 terminates, t=2 is the NEXT_STEP reset step (invalid),
    # t=4 truncates at the end of the rollout (bootstrapped from the next value).
    rewards = torch.tensor([[1.0], [2.0], [0.0], [0.5], [1.5]])
    values = torch.tensor([[0.3], [0.4], [9.0], [0.6], [0.7]])
    terms = torch.tensor([[0.0], [1.0], [0.0], [0.0], [0.0]])
    truncs = torch.tensor([[0.0], [0.0], [0.0], [0.0], [1.0]])
    next_value = torch.tensor([0.8])
    adv = example.compute_advantages(rewards, values, terms, truncs, next_value, g, lam)
    d4 = 1.5 + g * 0.8 - 0.7  # truncated: bootstrap from the terminal observation's value
    d3 = 0.5 + g * 0.7 - 0.6
    d1 = 2.0 - 0.4  # terminated: no bootstrap
    d0 = 1.0 + g * 0.4 - 0.3
    want = [d0 + g * lam * d1, d1, None, d3 + g * lam * d4, d4]
    for t, w in enumerate(want):
        if w is not None:
            assert adv[t, 0].item() == pytest.approx(w, rel=1e-6), t
    # The reset step's value (9.0) must not leak into the terminated step's advantage.
    assert adv[1, 0].item() == pytest.approx(d1)


@pytest.mark.slow
def test_example_trains_a_few_steps(tmp_path):
    cmd = [sys.executable, str(EXAMPLE), "--num-envs", "2", "--num-steps", "16", "--total-timesteps", "64",
           "--resolution", "40", "--num-scenes", "4", "--max-steps", "12", "--update-epochs", "1",
           "--num-minibatches", "2", "--seed", "3"]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert out.returncode == 0, out.stderr[-3000:]
    lines = [l for l in out.stdout.splitlines() if l.startswith("iteration")]
    assert len(lines) == 2, out.stdout  # 64 steps / (2 envs x 16 steps)
    assert "global_step=64" in lines[-1]
    assert "episodes=" in lines[-1] and "episodes=0 " not in lines[-1]  # 12-step episodes did end
    for l in lines:
        loss = float(l.split("loss=")[1].split()[0])
        assert np.isfinite(loss)
