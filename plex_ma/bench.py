"""Benchmarks: ``python -m plex_ma.bench {sim,env,train} [options] [--json]``.

``sim`` steps the raw batched simulator with random movement actions (no STOP, so
episodes run to 500 steps and reset): every step renders RGB-D, updates the ego maps and
looks up the geodesic distance to the goal. Resets (episode sampling with its Dijkstra
field) are included in the timing.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

import numpy as np


def machine() -> dict:
    import numba

    return {"cpus": os.cpu_count(), "numba_threads": numba.get_num_threads(), "platform": platform.platform(),
            "python": platform.python_version()}


def bench_sim(num_envs: int, resolution: int, steps: int, seed: int, scenes: str = "procgen") -> dict:
    from plex_ma.envs.sim import BatchedSim, Geodesics, scene_bank
    from plex_ma.envs.sim.episodes import sample_episode

    bank = scene_bank(scenes, "train")
    sim = BatchedSim(bank, num_envs, resolution=resolution, seed=seed)
    rng = np.random.default_rng(seed)
    geo = Geodesics(bank)
    for i in range(num_envs):
        sim.reset_world(i, *sample_episode(bank, int(rng.integers(len(bank))), rng, geo, i))
    sim.step(rng.integers(1, 4, num_envs))  # compile / warm up
    t_steps = np.zeros(num_envs, np.int64)
    resets = 0
    t0 = time.perf_counter()
    for _ in range(steps):
        sim.step(rng.integers(1, 4, num_envs))
        t_steps += 1
        for i in np.flatnonzero(t_steps >= 500):
            sim.reset_world(int(i), *sample_episode(bank, int(rng.integers(len(bank))), rng, geo, int(i)))
            t_steps[i] = 0
            resets += 1
    dt = time.perf_counter() - t0
    return {"benchmark": "sim", "steps_per_second": steps * num_envs / dt, "num_envs": num_envs,
            "resolution": resolution, "steps": steps * num_envs, "seconds": dt, "resets": resets,
            "memory_per_world_bytes": sim.memory_per_world(), "scene_bank_bytes": bank.nbytes,
            "machine": machine()}


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="python -m plex_ma.bench", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="what", required=True)
    ps = sub.add_parser("sim", help="raw batched simulator throughput")
    ps.add_argument("--num-envs", type=int, default=64, help="worlds stepped per call")
    ps.add_argument("--resolution", type=int, default=128, help="square image size in pixels")
    ps.add_argument("--steps", type=int, default=300, help="batched steps to time")
    ps.add_argument("--seed", type=int, default=0)
    ps.add_argument("--scenes", default="procgen", help="scene source")
    ps.add_argument("--json", action="store_true", help="print one JSON object")
    for name, fn in EXTRA.items():
        fn(sub)
    a = p.parse_args(argv)
    if a.what == "sim":
        out = bench_sim(a.num_envs, a.resolution, a.steps, a.seed, a.scenes)
    else:
        out = a.run(a)
    if a.json:
        print(json.dumps(out))
    else:
        for k, v in out.items():
            print(f"{k:>28}: {v:,.1f}" if isinstance(v, float) else f"{k:>28}: {v}")


# Other benchmarks register an argparse sub-parser builder here (they set ``run``).
EXTRA: dict = {}

try:  # env and train benchmarks live beside the modules they measure
    from plex_ma import bench_extra  # noqa: F401
except ImportError:
    pass

if __name__ == "__main__":
    main()
