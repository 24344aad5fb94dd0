"""How a PLEX planner fails over the shortest-path oracle executor (ground truth).

    python scripts/failure_modes.py --planner map --split val --episodes 200
    python scripts/failure_modes.py --checkpoint runs/x/latest.pt --split val --episodes 200

Runs the planner (greedy; the map planner, or a checkpoint's learned planner) over the
oracle executor on the split's fixed episodes and prints, for every failed episode: the
actions it took, its collisions, the agent's largest distance from its mean position over
the episode's last 100 actions ("spread": 0 m means it stood in place), and at the
planner's last decision the sub-goal's straight-line distance against its distance along
the true shortest path (a sub-goal behind a wall has the second much larger) and its
direction from the agent's heading (the executor turns 10 degrees an action, so it cannot
face a sub-goal more than 100 degrees away within N_EX = 10 actions). Ends with
a count of failures whose last 100 actions moved the agent less than 0.05 m.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from plex_ma.config import TrainConfig
from plex_ma.evaluate import load_policies
from plex_ma.trainers.driver import PlexDriver, make_executor, make_planner
from plex_ma.trainers.plex import env_kwargs
from plex_ma.envs.vector import PlexVectorEnv

TAIL = 100  # actions at the end of an episode over which the spread is measured


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkpoint", default=None, help="a PLEX checkpoint whose planner to run")
    p.add_argument("--planner", choices=["learned", "map"], default="learned")
    p.add_argument("--split", choices=["val", "test"], default="val")
    p.add_argument("--episodes", type=int, default=200)
    p.add_argument("--num-envs", type=int, default=16)
    a = p.parse_args(argv)
    if a.planner == "learned" and a.checkpoint is None:
        p.error("--planner learned needs --checkpoint")
    torch.set_num_threads(1)
    cfg, nets = load_policies(a.checkpoint) if a.checkpoint else (TrainConfig(), {})
    env = PlexVectorEnv(a.num_envs, seed=0, **env_kwargs(cfg, a.split))
    eps = list(env.worlds.fixed_episodes[:a.episodes])
    env.worlds.fixed_episodes = eps
    wanted = {e.episode_id for e in eps}
    worlds, sim = env.worlds, env.worlds.sim
    drv = PlexDriver(env, make_planner(a.planner, env, nets.get("planner"), deterministic=True),
                     make_executor("oracle", env))
    drv.reset()
    paths: list[list] = [[] for _ in range(a.num_envs)]
    last: list = [None] * a.num_envs  # (straight, along the path, direction) of each world's latest sub-goal
    done: dict[int, dict | None] = {}

    def finish(res) -> None:
        ended = np.flatnonzero(res.terminated | res.truncated)
        for j, info in zip(ended, res.episode_infos):
            eid = info["episode_id"]
            if eid in wanted and eid not in done:
                tail = np.array(paths[j][-TAIL:]) if paths[j] else np.zeros((1, 2))
                spread = float(np.linalg.norm(tail - tail.mean(0), axis=1).max())
                done[eid] = None if info["success"] else {
                    "episode": eid, "steps": int(info["steps"]), "collisions": int(info["collisions"]),
                    "distance_to_goal": float(info["distance_to_goal"]), "spread": spread,
                    "subgoal_straight": last[j][0], "subgoal_path": last[j][1], "subgoal_deg": last[j][2]}
            paths[j] = []

    def on_decision(d) -> None:
        for k, r in enumerate(d.rows):
            last[r] = (float(np.hypot(*(worlds.subgoal[r] - sim.pos[r]))), float(worlds.subgoal_dist[r]),
                       float(np.degrees(d.out["subgoal"][k][1])))
        finish(d.result)

    with torch.no_grad():
        while len(done) < len(eps):
            drv.decide(on_decision, until=lambda: len(done) == len(eps))
            if len(done) == len(eps):
                break
            for j in range(a.num_envs):
                paths[j].append(sim.pos[j].copy())
            finish(drv.step().result)
    fails = sorted((f for f in done.values() if f is not None), key=lambda f: f["spread"])
    print(f"{len(fails)} failures in {len(eps)} episodes ({a.planner} planner over the oracle executor, ground truth)")
    print(f"{'episode':>8} {'steps':>5} {'collisions':>10} {'to goal m':>9} {'spread m':>8} "
          f"{'sub-goal m':>10} {'along path m':>12} {'direction deg':>13}")
    for f in fails:
        print(f"{f['episode']:>8} {f['steps']:>5} {f['collisions']:>10} {f['distance_to_goal']:>9.2f} "
              f"{f['spread']:>8.2f} {f['subgoal_straight']:>10.2f} {f['subgoal_path']:>12.2f} {f['subgoal_deg']:>13.0f}")
    still = [f for f in fails if f["spread"] < 0.05]
    behind = sum(abs(f["subgoal_deg"]) > 100 for f in still)
    print(f"standing in place over the last {TAIL} actions: {len(still)} of {len(fails)}; of those, the last "
          f"sub-goal more than 100 degrees from the heading: {behind}")


if __name__ == "__main__":
    main()
