"""``python -m plex_ma.record``: record episodes to a Rerun ``.rrd`` file.

    python -m plex_ma.record --checkpoint runs/plex-gru-cpu/latest.pt --episodes 3 --out episodes.rrd
    python -m plex_ma.record --policy random --episodes 2 --out random.rrd --split val
    python -m plex_ma.record --policy random --out one.rrd --topdown-png one.png   # + a top-down PNG
    rerun episodes.rrd                        # open it in the viewer

With ``--checkpoint`` the episodes are run greedily by ``plex_ma.evaluate.run_episodes`` on
one world (the first ``--episodes`` episodes of the split's fixed set; generated ones for
``train``). ``--policy random`` drives the PLEX env with a random planner (random sub-goals,
STOP with a small probability) and a random executor (random moves, STOP with a small
probability). Each episode becomes one recording in the file (see ``plex_ma.viz.record``
for the entity paths). ``--spawn`` also streams the recordings live to a Rerun viewer
(started if none is running; needs a display).
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from plex_ma.envs.rules import ELI_DIM, PLANNER
from plex_ma.envs.sim.core import MOVE_FORWARD, STOP, TURN_LEFT, TURN_RIGHT


class RandomPlanner:
    """Uniform random sub-goals within ``rho_max``; STOP with probability ``stop_prob``."""

    def __init__(self, rho_max: float = 4.0, stop_prob: float = 0.02, rng=None):
        self.rho_max, self.stop_prob = float(rho_max), float(stop_prob)
        self.rng = rng if rng is not None else np.random.default_rng()

    def act(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """(stop (n,), subgoal (n, 2) as (distance m, direction rad))."""
        stop = (self.rng.random(n) < self.stop_prob).astype(np.int64)
        sub = np.stack([self.rng.uniform(0.5, self.rho_max, n), self.rng.uniform(-np.pi, np.pi, n)], 1)
        return stop, sub.astype(np.float32)


class RandomExecutor:
    """Random moves (forward twice as likely as each turn); STOP with probability ``stop_prob``.
    Its ELI is zeros: it has no memory to summarise."""

    def __init__(self, stop_prob: float = 0.05, rng=None):
        self.stop_prob = float(stop_prob)
        self.rng = rng if rng is not None else np.random.default_rng()

    def act(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """(action (n,), eli (n, 128))."""
        moves = self.rng.choice([MOVE_FORWARD, MOVE_FORWARD, TURN_LEFT, TURN_RIGHT], n)
        action = np.where(self.rng.random(n) < self.stop_prob, STOP, moves).astype(np.int64)
        return action, np.zeros((n, ELI_DIM), np.float32)


def run_random_episodes(env, episodes: int, recorder=None, seed: int = 0, planner_stop_prob: float = 0.02,
                        executor_stop_prob: float = 0.05) -> list[dict]:
    """Run ``episodes`` complete episodes of world 0 of a ``PlexVectorEnv`` with the random
    pair, calling ``recorder`` as ``plex_ma.evaluate.run_episodes`` does; returns their infos."""
    rng = np.random.default_rng(seed)
    planner = RandomPlanner(env.config.rho_max, planner_stop_prob, rng)
    executor = RandomExecutor(executor_stop_prob, rng)
    n = env.num_envs
    turn, _, _ = env.reset(seed=seed)
    if recorder is not None:
        recorder.begin(env)
    infos: list[dict] = []
    while len(infos) < episodes:
        if np.any(turn == PLANNER):
            rows = np.flatnonzero(turn == PLANNER)
            stop, sub = planner.act(n)
            res = env.step(stop=stop, subgoal=sub)
            if recorder is not None:
                recorder.step(env, res, rows=rows)
        else:
            action, eli = executor.act(n)
            res = env.step(action=action, eli=eli)
            if recorder is not None:
                recorder.step(env, res)  # a random executor's ELI is all zeros: not logged
        ended = np.flatnonzero(res.terminated | res.truncated)
        infos += [res.episode_infos[k] for k, i in enumerate(ended) if i == 0]
        turn = res.turn
    if recorder is not None:
        recorder.end()
    return infos[:episodes]


def main(argv: list[str] | None = None) -> list[dict]:
    p = argparse.ArgumentParser(prog="python -m plex_ma.record", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    who = p.add_mutually_exclusive_group(required=True)
    who.add_argument("--checkpoint", help="checkpoint file whose networks act (greedily)")
    who.add_argument("--policy", choices=["random"], help="a random planner/executor pair instead")
    p.add_argument("--episodes", type=int, default=1, help="episodes to record")
    p.add_argument("--out", required=True, help="the .rrd file to write")
    p.add_argument("--split", choices=["train", "val", "test"], default="val", help="scene split")
    p.add_argument("--scenes", default=None, help="scene source (default: the checkpoint's, or procgen)")
    p.add_argument("--resolution", type=int, default=64, help="image size (--policy random only)")
    p.add_argument("--max-steps", type=int, default=500, help="episode length limit (--policy random only)")
    p.add_argument("--seed", type=int, default=0, help="seeds the random policy and the train split's episodes")
    p.add_argument("--jpeg-quality", type=int, default=None, help="store RGB images as JPEG of this quality")
    p.add_argument("--no-images", action="store_true", help="leave out the RGB, depth and ego map images")
    p.add_argument("--spawn", action="store_true", help="also stream live to a Rerun viewer (needs a display)")
    p.add_argument("--topdown-png", default=None, help="also write the top-down picture of the last episode here")
    a = p.parse_args(argv)
    if a.episodes < 1:
        p.error("--episodes must be >= 1")
    from plex_ma.viz.record import EpisodeRecorder

    rec = EpisodeRecorder(a.out, max_episodes=a.episodes, images=not a.no_images, jpeg_quality=a.jpeg_quality,
                          spawn=a.spawn, name=None)
    if a.checkpoint:
        import torch

        from plex_ma.evaluate import load_policies, run_episodes
        from plex_ma.trainers.checkpoint import CheckpointError

        # One world means batch-1 inference: more torch threads only spin (and beside other
        # busy processes made an episode several times slower).
        torch.set_num_threads(1)

        try:
            cfg, nets = load_policies(a.checkpoint)
        except CheckpointError as e:
            print(f"error: {e}", file=sys.stderr)
            raise SystemExit(2)
        results = run_episodes(cfg, nets, split=a.split, episodes=a.episodes, scenes=a.scenes, num_envs=1,
                               recorder=rec)
    else:
        from plex_ma.envs.vector import PlexVectorEnv

        kw = dict(resolution=a.resolution, max_steps=a.max_steps, scenes=a.scenes or "procgen", split=a.split)
        env = PlexVectorEnv(1, seed=a.seed, **kw)
        results = run_random_episodes(env, a.episodes, rec, seed=a.seed)
    if a.topdown_png and rec.episodes:
        from PIL import Image

        Image.fromarray(rec.topdown(-1)).save(a.topdown_png)
    for r in rec.episodes:
        print(json.dumps({k: (round(v, 3) if isinstance(v, float) else v) for k, v in r.items()}))
    print(f"wrote {len(rec.episodes)} episode(s) to {a.out}; open with: rerun {a.out}")
    return results


if __name__ == "__main__":
    main(sys.argv[1:])
