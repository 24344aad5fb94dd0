"""Observations pinned for fixed seeds: the simulator, the AEC env, the compat view and the
vector env give, step for step, the RGB-D, ego maps, goal and sub-goal vectors, rewards and
infos they gave when tests/data/pinned_observations.json was written, so a faster kernel or
a leaner env layer cannot change what an agent sees.

Each step is reduced to checksums: integer ones (RGB, ego-map cells, weighted by a fixed
random pattern so that a moved pixel shows) must match exactly; float ones (depth, vectors,
rewards, distances) to a relative 1e-6, the tolerance for kernels that reorder float sums.

Regenerate the file (``python -m tests.test_pinned_observations``) only when a change to the
observations is intended."""

from __future__ import annotations

import json
import pathlib

import numpy as np
import pytest

from plex_ma.envs import plex_nav_v0
from plex_ma.envs.sim import BatchedSim, scene_bank
from plex_ma.envs.sim.episodes import Geodesics, sample_episode
from plex_ma.envs.vector import PlexVectorEnv

PINNED = pathlib.Path(__file__).parent / "data" / "pinned_observations.json"
CONFIG = dict(resolution=64, num_scenes=4, pose_noise=(0.05, 0.02))
FLOAT_RTOL = 1e-6

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")


def _weights(shape) -> np.ndarray:
    return np.random.default_rng(12345).integers(1, 1000, int(np.prod(shape))).reshape(shape)


def checksums(prefix: str, x) -> dict:
    """The sum of ``x`` weighted by a fixed random pattern (so that a moved value shows):
    ``{prefix + ":i": int}`` for integer-valued arrays (exact), ``{prefix + ":f": float}``
    for others."""
    a = np.asarray(x)
    w = _weights(a.shape)
    if a.dtype.kind in "iub" or (a.dtype.kind == "f" and a.size and np.all(a * 16 == np.round(a * 16))):
        # integer arrays and ego maps (multiples of 1/16): exact integers
        q = np.round(np.asarray(a, np.float64) * 16).astype(np.int64)
        return {f"{prefix}:i": int((q * w).sum())}
    return {f"{prefix}:f": float((np.asarray(a, np.float64) * w).sum())}


def obs_checksums(prefix: str, obs) -> dict:
    out = {}
    if isinstance(obs, dict):
        for k in sorted(obs):
            out.update(obs_checksums(f"{prefix}.{k}", obs[k]))
        return out
    return checksums(prefix, obs)


def run_sim(steps: int = 120) -> list[dict]:
    """The raw simulator: 3 worlds at 128 px, random moves, ego maps and sub-goal distances."""
    bank = scene_bank("procgen", "train", 4)
    geo = Geodesics(bank)
    rng = np.random.default_rng(3)
    sim = BatchedSim(bank, 3, resolution=128, pose_noise=(0.05, 0.02), seed=4)
    for i in range(3):
        sim.reset_world(i, *sample_episode(bank, int(rng.integers(len(bank))), rng, geo))
    targets = sim.snap_to_navigable(sim.pos + rng.uniform(-3, 3, (3, 2)), np.arange(3))
    rows = []
    for t in range(steps):
        sim.step(rng.integers(0, 4, 3), rng.random(3) < 0.9)
        if t % 40 == 39:
            i = t // 40 % 3
            sim.reset_world(i, *sample_episode(bank, int(rng.integers(len(bank))), rng, geo))
        rows.append({**checksums("rgb", sim.rgb), **checksums("depth", sim.depth),
                     **checksums("ego", sim.egomap()), **checksums("d_goal", sim.distance_to_goal),
                     **checksums("d_sub", sim.distance_to(targets, np.arange(3))),
                     **checksums("pose", sim.est_pose)})
    return rows


def _aec_action(rng, agent: str, compat: bool):
    if compat:
        if agent == "planner":
            return 0 if rng.random() < 0.03 else int(rng.integers(1, 33))
        return int(rng.integers(0, 4))
    if agent == "planner":
        return {"stop": int(rng.random() < 0.03),
                "subgoal": np.array([rng.uniform(0, 4), rng.uniform(-np.pi, np.pi)], np.float32)}
    return {"action": int(rng.integers(0, 4)), "eli": rng.normal(size=128).astype(np.float32)}


def run_aec(turns: int = 300, compat: bool = False) -> list[dict]:
    """``plex_nav_v0.env()`` (or ``compat_env()``) driven turn by turn, every ``last()`` pinned."""
    env = plex_nav_v0.compat_env(**CONFIG) if compat else plex_nav_v0.env(**CONFIG)
    rng = np.random.default_rng(5)
    rows = []
    seed = 0
    while len(rows) < turns:
        env.reset(seed=seed)
        seed += 1
        for agent in env.agent_iter(turns - len(rows)):
            obs, rew, term, trunc, info = env.last()
            rows.append({"agent": agent, **obs_checksums("obs", obs), "reward": float(rew), "term": bool(term),
                         "trunc": bool(trunc), **{f"info.{k}": v for k, v in sorted(info.items())
                                                  if not isinstance(v, np.ndarray)}})
            env.step(None if term or trunc else _aec_action(rng, agent, compat))
    return rows


def run_vector(steps: int = 150) -> list[dict]:
    """``PlexVectorEnv`` at 4 worlds with autoreset."""
    n = 4
    venv = PlexVectorEnv(n, seed=6, **CONFIG)
    venv.reset()
    rng = np.random.default_rng(7)
    rows = []
    for _ in range(steps):
        out = venv.step(stop=(rng.random(n) < 0.05).astype(np.int64),
                        subgoal=np.stack([rng.uniform(0, 4, n), rng.uniform(-np.pi, np.pi, n)], 1),
                        action=rng.integers(0, 4, n), eli=rng.normal(size=(n, 128)).astype(np.float32))
        row = {**checksums("turn", out.turn), **obs_checksums("planner", out.planner_obs),
               **obs_checksums("executor", out.executor_obs), **checksums("rewards", out.rewards),
               **checksums("acted", out.acted), **checksums("ended", out.terminated | out.truncated),
               "infos": [sorted(i.items()) for i in out.episode_infos]}
        if out.final_executor_obs is not None:
            row.update(obs_checksums("final", out.final_executor_obs))
            row.update(checksums("final_pose", out.final_pose))
        rows.append(row)
    return rows


RUNS = {"sim": run_sim, "aec": run_aec, "compat": lambda: run_aec(compat=True), "vector": run_vector}


def _compare(got: list[dict], want: list[dict], name: str) -> None:
    assert len(got) == len(want)
    for t, (g, w) in enumerate(zip(got, want)):
        g = json.loads(json.dumps(g))  # tuples as lists, as stored
        assert sorted(g) == sorted(w), f"{name} step {t}: keys differ"
        for k, wv in w.items():
            gv = g[k]
            if isinstance(wv, float) and k.endswith(":f") or k in ("reward",) or k.startswith("info."):
                assert gv == pytest.approx(wv, rel=FLOAT_RTOL, abs=1e-9), f"{name} step {t} {k}: {gv} != {wv}"
            elif k == "infos":
                assert len(gv) == len(wv), f"{name} step {t}: ended episodes differ"
                for gi, wi in zip(gv, wv):
                    assert dict(gi) == pytest.approx(dict(wi), rel=FLOAT_RTOL), f"{name} step {t} infos"
            else:
                assert gv == wv, f"{name} step {t} {k}: {gv} != {wv}"


@pytest.mark.parametrize("name", list(RUNS))
def test_observations_are_pinned(name):
    want = json.loads(PINNED.read_text())[name]
    got = RUNS[name]()
    assert len({json.dumps(r, sort_keys=True) for r in got}) > len(got) // 2  # the agents did move
    _compare(got, want, name)


def test_checksums_see_a_moved_value():
    a = np.zeros((4, 4), np.uint8)
    b = a.copy()
    a[0, 1] = b[1, 0] = 7
    assert a.sum() == b.sum() and checksums("x", a)["x:i"] != checksums("x", b)["x:i"]
    assert checksums("x", a + 0.01)["x:f"] != checksums("x", b + 0.01)["x:f"]


if __name__ == "__main__":
    PINNED.parent.mkdir(exist_ok=True)
    PINNED.write_text(json.dumps({name: run() for name, run in RUNS.items()}, separators=(",", ":")) + "\n")
    print(f"wrote {PINNED}")
