"""How the executor's turns end, by the sub-goal's distance and whether it needs a detour.

    python scripts/executor_turns.py --checkpoint RUN/latest.pt [--planner map-los] [--executor oracle] [--steps 800]

Runs greedy PLEX (the checkpoint's networks, or the stand-ins named) in 16 val worlds for
``--steps`` executor steps through the rollout driver and records every executor turn that
ends inside an episode: the sub-goal's straight-line distance at the start of the turn
(``d0``), its geodesic distance then, and the straight-line distance left at the end.
A sub-goal "needs a detour" when its geodesic distance exceeds 1.2 x d0 + 0.05 m (a wall
or furniture in the way). Prints the share of detour sub-goals and, per d0 band and per
kind, how often the turn ended within 0.2 m / 0.5 m of the sub-goal, how often by STOP,
the mean fraction of d0 left, and the actions used.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from plex_ma.config import TrainConfig, replace
from plex_ma.envs.vector import PlexVectorEnv
from plex_ma.trainers.driver import PLANNER_KINDS, PlexDriver, make_executor, make_planner
from plex_ma.trainers.evaluation import load_policies
from plex_ma.trainers.base import env_kwargs

DETOUR_RATIO, DETOUR_SLACK = 1.2, 0.05


def turns(cfg: TrainConfig, nets: dict, planner: str, executor: str, steps: int, worlds: int = 16) -> np.ndarray:
    """(turns, 6): d0, geodesic at the start, distance left, reached, stopped, actions."""
    env = PlexVectorEnv(worlds, seed=0, **env_kwargs(cfg, "val"))
    rng = np.random.default_rng(0)
    drv = PlexDriver(env, make_planner(planner, env, nets.get("planner"), True, rng),
                     make_executor(executor, env, nets.get("executor"), True, rng))
    drv.reset(seed=0)
    w, rows = env.worlds, np.arange(worlds)
    d0, g0, used = np.zeros(worlds), np.zeros(worlds), np.zeros(worlds, np.int64)
    out = []
    for _ in range(steps):
        drv.decide()
        new = drv.starts.copy()
        straight = np.linalg.norm(w.subgoal - w.sim.pos, axis=1)
        geodesic = w.sim.distance_to(w.subgoal, rows)
        d0[new], g0[new], used[new] = straight[new], geodesic[new], 0
        res = drv.step().result
        used += 1
        for k in np.flatnonzero(res.executor_turn_end & ~(res.terminated | res.truncated)):
            left = float(np.linalg.norm(w.subgoal[k] - w.sim.pos[k]))
            out.append((d0[k], g0[k], left, res.executor_reached[k], res.executor_stopped[k], used[k]))
    return np.array(out, np.float64)


def report(a: np.ndarray) -> str:
    detour = a[:, 1] > DETOUR_RATIO * a[:, 0] + DETOUR_SLACK
    lines = [f"turns {len(a)}; sub-goals needing a detour {detour.mean():.2f}; "
             f"d0 quantiles 10/50/90%: {np.round(np.quantile(a[:, 0], [0.1, 0.5, 0.9]), 2).tolist()} m"]

    def row(name, m):
        left = a[m, 2] / np.maximum(a[m, 0], 0.1)
        return (f"  {name:<22} n={m.sum():5d}  within 0.2 m {np.mean(a[m, 2] < 0.2):.2f}  within 0.5 m "
                f"{np.mean(a[m, 2] < 0.5):.2f}  STOP {np.mean(a[m, 4]):.2f}  d0 left {left.mean():.2f}  "
                f"actions {a[m, 5].mean():.1f}")
    for lo, hi in [(0, 0.5), (0.5, 1), (1, 2), (2, 3), (3, 99)]:
        m = (a[:, 0] >= lo) & (a[:, 0] < hi)
        if m.any():
            lines.append(row(f"d0 in [{lo}, {hi}) m", m))
    for name, m in (("straight", ~detour), ("detour", detour)):
        if m.any():
            lines.append(row(name, m))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkpoint", default=None, help="checkpoint file (or pretrained:NAME)")
    p.add_argument("--planner", choices=PLANNER_KINDS, default="learned")
    p.add_argument("--executor", choices=["learned", "oracle", "random"], default="learned")
    p.add_argument("--steps", type=int, default=800, help="executor steps of the 16 worlds")
    a = p.parse_args(argv)
    torch.set_num_threads(1)
    cfg, nets = load_policies(a.checkpoint) if a.checkpoint else (replace(TrainConfig(method="plex-gru"), n_ex=18), {})
    print(f"planner {a.planner}, executor {a.executor}, N_EX {cfg.env.n_ex}")
    print(report(turns(cfg, nets, a.planner, a.executor, a.steps)))


if __name__ == "__main__":
    main()
