"""How a PLEX planner fails over the shortest-path oracle executor (ground truth).

    python scripts/failure_modes.py --planner map --split val --episodes 200
    python scripts/failure_modes.py --checkpoint runs/x/latest.pt --split val --episodes 200

Runs the planner (greedy; the map planner, or a checkpoint's learned planner) over the
oracle executor on the split's fixed episodes through :func:`plex_ma.trainers.evaluation.run_episodes` and prints, for every failed episode: the
actions it took, its collisions, the agent's largest distance from its mean position over
the episode's last 100 actions ("spread": 0 m means it stood in place), and at the
planner's last decision the (snapped) sub-goal's straight-line distance against its distance along
the true shortest path (a sub-goal behind a wall has the second much larger) and its
direction from the agent's heading (the executor turns 10 degrees an action, so at the
paper's N_EX = 10 it cannot face a sub-goal more than 100 degrees away before control
returns). Ends with
a count of failures whose last 100 actions moved the agent less than 0.05 m.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from plex_ma.config import TrainConfig
from plex_ma.envs.sim.core import wrap_angle
from plex_ma.trainers.evaluation import load_policies, run_episodes

TAIL = 100  # actions at the end of an episode over which the spread is measured


class Observer:
    """Plugs into ``run_episodes`` where a recorder would: keeps each world's positions and
    its latest sub-goal, and the failed episodes' figures when they end."""

    def begin(self, env) -> None:
        self.worlds, self.sim = env.worlds, env.worlds.sim
        self.paths: list[list] = [[] for _ in range(env.num_envs)]
        self.last: list = [None] * env.num_envs  # (straight m, along the path m, direction deg)
        self.fails: dict[int, dict] = {}

    def step(self, env, res, rows=None, eli=None) -> None:
        w, sim = self.worlds, self.sim
        ended = np.flatnonzero(res.terminated | res.truncated)
        for j, info in zip(ended, res.episode_infos):
            if not info["success"] and info["episode_id"] not in self.fails:
                tail = np.array(self.paths[j][-TAIL:]) if self.paths[j] else np.zeros((1, 2))
                self.fails[info["episode_id"]] = {
                    "episode": info["episode_id"], "steps": int(info["steps"]), "collisions": int(info["collisions"]),
                    "distance_to_goal": float(info["distance_to_goal"]),
                    "spread": float(np.linalg.norm(tail - tail.mean(0), axis=1).max()),
                    **dict(zip(("subgoal_straight", "subgoal_path", "subgoal_deg"), self.last[j]))}
            self.paths[j] = []
        if rows is not None:  # planner decisions: the sub-goals just set (snapped, fixed in the world)
            for r in rows:
                dx, dy = w.subgoal[r] - sim.pos[r]
                ang = wrap_angle(np.arctan2(dy, dx) - sim.heading[r])
                self.last[r] = (float(np.hypot(dx, dy)), float(w.subgoal_dist[r]), float(np.degrees(ang)))
        else:  # an executor action in every world
            for j in np.setdiff1d(np.arange(len(self.paths)), ended):
                self.paths[j].append(sim.pos[j].copy())

    def end(self) -> None:
        pass


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
    obs = Observer()
    results = run_episodes(cfg, nets, a.split, a.episodes, num_envs=a.num_envs, recorder=obs, planner=a.planner,
                           executor="oracle")
    failed = {r["episode_id"] for r in results if not r["success"]}
    fails = sorted((f for k, f in obs.fails.items() if k in failed), key=lambda f: f["spread"])
    print(f"{len(fails)} failures in {len(results)} episodes ({a.planner} planner over the oracle executor, "
          f"ground truth)")
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
