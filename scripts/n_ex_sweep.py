"""PLEX success against N_EX, the executor's actions per planner decision.

    python scripts/n_ex_sweep.py --planner map --executor oracle --n-ex 10 14 18 20 30
    python scripts/n_ex_sweep.py --checkpoint pretrained:plex-gru --n-ex 18 30 --scenes r2v --split test

Runs the same fixed episodes (greedy) once per N_EX value through
:func:`plex_ma.trainers.evaluation.run_episodes`, with every other setting taken from the checkpoint (or
the defaults when both agents are stand-ins), and prints success and SPL for each. The
executor turns 10 degrees an action, so at N_EX = 10 it cannot face a sub-goal behind it
before control returns to the planner.
"""

from __future__ import annotations

import argparse

import torch

from plex_ma.config import TrainConfig, replace
from plex_ma.trainers.driver import PLANNER_KINDS
from plex_ma.trainers.evaluation import load_policies, run_episodes, summarize


def main(argv: list[str] | None = None) -> list[dict]:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkpoint", default=None, help="a PLEX checkpoint for the learned agents")
    p.add_argument("--planner", choices=PLANNER_KINDS, default="learned")
    p.add_argument("--executor", choices=["learned", "oracle", "random"], default="learned")
    p.add_argument("--n-ex", type=int, nargs="+", default=[10, 18])
    p.add_argument("--split", choices=["val", "test"], default="val")
    p.add_argument("--scenes", default=None, help="scene source (default: the one trained on)")
    p.add_argument("--episodes", type=int, default=200)
    p.add_argument("--num-envs", type=int, default=16)
    a = p.parse_args(argv)
    learned = "learned" in (a.planner, a.executor)
    if learned and a.checkpoint is None:
        p.error("a learned agent needs --checkpoint")
    if any(n < 1 for n in a.n_ex):
        p.error("--n-ex values must be >= 1")
    torch.set_num_threads(1)
    cfg, nets = load_policies(a.checkpoint) if learned else (TrainConfig(), {})
    rows = []
    print(f"planner {a.planner}, executor {a.executor} ({a.checkpoint or 'no checkpoint'}), "
          f"{a.scenes or cfg.env.scenes}/{a.split}, "
          f"{a.episodes} episodes, greedy")
    print(f"{'N_EX':>5} {'success':>8} {'spl':>6}")
    for n_ex in a.n_ex:
        s = summarize(run_episodes(replace(cfg, n_ex=n_ex), nets, a.split, a.episodes, a.scenes,
                                   num_envs=a.num_envs, planner=a.planner, executor=a.executor))
        rows.append({"n_ex": n_ex, "success": s["success"], "spl": s["spl"]})
        print(f"{n_ex:>5} {s['success']:>8.3f} {s['spl']:>6.3f}", flush=True)
    return rows


if __name__ == "__main__":
    main()
