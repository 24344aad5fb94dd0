"""Import order does not matter: the simulator's kernels run on numba's workqueue threading
layer (not GNU OpenMP) whatever was imported first, give the same results on every layer
and with or without threads, survive fork(), and keep their speed with torch imported
first; a plain ``import plex_ma`` leaves torch's OpenMP runtime alone, and only plex_ma's
own commands (``python -m plex_ma.<module>``) make it wait passively."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import gymnasium
import numpy as np
import pytest

from plex_ma.bench import bench_order
from plex_ma.envs.sim import BatchedSim, generate_episodes
from plex_ma.envs.sim import corners
from plex_ma.envs.sim import kernels as K

from .sim_helpers import bank_of, small_house

def fresh_env(**extra: str) -> dict:
    """This process's environment without the wait policy tests/conftest.py set in it."""
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    return {**env, **extra}


STEPS = """
import hashlib, numpy as np
from plex_ma.envs.vector import PointNavVectorEnv
env = PointNavVectorEnv(3, seed=0, resolution=32, num_scenes=2)
env.reset()
for a in np.random.default_rng(0).integers(1, 4, (30, 3)):
    obs = env.step(a)[0]
digest = hashlib.sha256(b"".join(np.ascontiguousarray(v).tobytes() for v in obs.values())).hexdigest()
"""


def test_import_order_keeps_the_threading_layer_and_wait_policy(monkeypatch):
    """``python -m plex_ma.bench order``'s children, torch imported first against plex_ma
    first, in fresh processes: both run the kernels on the workqueue layer with torch's
    OpenMP wait policy untouched, and give the same observations. These are the causes of
    the slowdowns the benchmark measures (GNU OpenMP spinning beside torch, a wait policy that
    depends on the order); the speed itself is the benchmark's (docs/performance.md)."""
    monkeypatch.delenv("OMP_WAIT_POLICY")  # as in a fresh shell
    out = bench_order(("plex_ma", "torch"), rounds=1, steps=20, num_envs=2, resolution=64, blocks=1)
    assert out["threading_layer"] == {"plex_ma": ["workqueue"], "torch": ["workqueue"]}
    assert out["wait_policy"] == {"plex_ma": ["None"], "torch": ["None"]}
    assert out["identical"]


def test_a_chosen_layer_is_kept_and_gives_the_same_results():
    """NUMBA_THREADING_LAYER set by the user wins (here GNU OpenMP), importing plex_ma after
    torch warns of nothing, and the kernels' results equal this process's (workqueue)."""
    code = "import warnings; warnings.simplefilter('error'); import torch, plex_ma, numba\n" + STEPS + \
        "print(numba.threading_layer(), digest)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                         env=fresh_env(NUMBA_THREADING_LAYER="omp"))
    assert out.returncode == 0, out.stderr
    scope: dict = {}
    exec(STEPS, scope)
    assert K.numba.threading_layer() == "workqueue"
    assert out.stdout.split() == ["omp", scope["digest"]]


@pytest.mark.parametrize("argv0, argv, command", [
    ("-m", ["python", "-m", "plex_ma.train", "--preset", "smoke"], True),
    ("-m", ["python", "-X", "dev", "-mplex_ma.bench", "order"], True),
    ("-m", ["python", "-um", "plex_ma.train"], True),
    ("-m", ["python", "-W", "error", "-Xdev", "-Om", "plex_ma"], True),
    ("-m", ["python", "-m", "cProfile", "-m", "plex_ma.train"], False),  # cProfile's program
    ("-m", ["python", "-m", "mypkg.train"], False),  # another program that imports plex_ma
    ("-c", ["python", "-c", "import plex_ma"], False),
    ("train.py", ["python", "train.py", "-m", "plex_ma.x"], False),
])
def test_only_plex_ma_commands_choose_the_wait_policy(monkeypatch, argv0, argv, command):
    import plex_ma

    monkeypatch.setattr(sys, "argv", [argv0])
    monkeypatch.setattr(sys, "orig_argv", argv)
    assert plex_ma._run_as_command() is command


def test_a_plain_import_leaves_torch_alone_and_commands_wait_passively():
    code = "import os, plex_ma, torch; print(os.environ.get('OMP_WAIT_POLICY'))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, env=fresh_env())
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["None"]
    bench = [sys.executable, "-m", "plex_ma.bench", "sim", "--num-envs", "1", "--resolution", "8", "--steps", "1",
             "--num-scenes", "1", "--json"]
    for env, policy in ((fresh_env(), "PASSIVE"), (fresh_env(OMP_WAIT_POLICY="ACTIVE"), "ACTIVE")):
        out = subprocess.run(bench, capture_output=True, text=True, timeout=300, env=env)
        assert out.returncode == 0, out.stderr
        assert json.loads(out.stdout)["machine"]["omp_wait_policy"] == policy


def test_async_make_vec_after_the_parent_stepped_an_env():
    """gymnasium's async vector env forks its workers; GNU OpenMP killed a child whose
    parent had run a kernel ("fork() called from a process already using GNU OpenMP")."""
    code = """
import gymnasium, numpy as np, plex_ma
e = gymnasium.make("plex_ma/PointNav-v0", resolution=32, num_scenes=2)
e.reset(seed=0)
for _ in range(5):
    e.step(1)
v = gymnasium.make_vec("plex_ma/PointNav-v0", num_envs=2, vectorization_mode="async", resolution=32, num_scenes=2)
v.reset(seed=0)
for _ in range(5):
    obs, r, term, trunc, info = v.step(np.array([1, 2]))
v.close()
print(type(v.unwrapped).__name__, obs["rgb"].shape)
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, env=fresh_env())
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["AsyncVectorEnv", "(2,", "32,", "32,", "3)"]


def test_async_make_vec_in_this_process():
    e = gymnasium.make("plex_ma/PointNav-v0", resolution=32, num_scenes=2)
    e.reset(seed=0)
    e.step(1)
    v = gymnasium.make_vec("plex_ma/PointNav-v0", num_envs=2, vectorization_mode="async", resolution=32, num_scenes=2)
    try:
        obs, _ = v.reset(seed=0)
        s = gymnasium.make_vec("plex_ma/PointNav-v0", num_envs=2, vectorization_mode="sync", resolution=32,
                               num_scenes=2)
        ref, _ = s.reset(seed=0)
        for a in ([1, 2], [3, 1], [1, 1]):
            obs = v.step(np.array(a))[0]
            ref = s.step(np.array(a))[0]
        for k in ref:
            np.testing.assert_array_equal(obs[k], ref[k])
    finally:
        v.close()


def run_sim(monkeypatch, choose) -> list:
    monkeypatch.setattr(K, "pick", choose)
    monkeypatch.setattr(corners, "pick", choose)
    bank = bank_of(small_house(5), small_house(6))
    eps = generate_episodes(bank, 3, seed=0)
    sim = BatchedSim(bank, 3, resolution=32, pose_noise=(0.05, 0.02), seed=11)
    for i, ep in enumerate(eps):
        sim.reset_world(i, ep)
    rng = np.random.default_rng(0)
    rows = np.arange(3)
    frames = []
    for a in rng.integers(0, 4, size=(30, 3)):
        sim.step(a)
        targets = sim.snap_to_navigable(sim.pos + rng.uniform(-3, 3, (3, 2)), rows)
        frames.append((sim.rgb.copy(), sim.depth.copy(), sim.pos.copy(), sim.est_pose.copy(), sim.egomap(),
                       sim.distance_to_goal.copy(), targets, sim.distance_to(targets, rows)))
    return frames


@pytest.mark.skipif(K.numba.get_num_threads() < 2, reason="needs two numba threads")
def test_threaded_and_serial_kernels_agree(monkeypatch):
    threaded = run_sim(monkeypatch, lambda kernel, jobs: kernel)
    serial = run_sim(monkeypatch, lambda kernel, jobs: kernel.serial)
    for fa, fb in zip(threaded, serial):
        for x, y in zip(fa, fb):
            np.testing.assert_array_equal(x, y)


def test_pick():
    assert K.pick(K.render, 1) is K.render.serial
    threads = K.numba.get_num_threads()
    assert K.pick(K.render, 4) is (K.render if threads > 1 else K.render.serial)
    K.numba.set_num_threads(1)
    try:
        assert K.pick(K.render, 4) is K.render.serial
    finally:
        K.numba.set_num_threads(threads)
