"""``python -m plex_ma.evaluate``: deterministic evaluation of a checkpoint on fixed episodes.

    python -m plex_ma.evaluate --checkpoint runs/plex-gru-cpu/latest.pt --split test --episodes 1000 --json out.json

The first ``--episodes`` episodes of the split's fixed episode file are each run once with
greedy actions (the planner's mean sub-goal and most likely stop decision, the executor's
most likely action). Prints a table and writes JSON with ``success``, ``spl``, ``reward``,
``distance_to_goal``, ``collisions`` and ``episodes``, overall and again under ``close``
and ``far`` (start-to-goal geodesic distance below / above 5.76 m, the paper's Fig. 5b).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

from plex_ma.cli import Parser, fail, integer, output_path
from plex_ma.config import DEVICE_HELP, TrainConfig
from plex_ma.envs.sim import EpisodeFileError, SceneError, load_episodes
from plex_ma.trainers.checkpoint import CheckpointError
from plex_ma.trainers.device import DeviceError, resolve_device
from plex_ma.trainers.driver import EXECUTOR_KINDS, PLANNER_KINDS
from plex_ma.trainers.evaluation import METRICS, episode_set, format_table, load_policies, run_episodes, summarize
from plex_ma.viz import EpisodeRecorder

__all__ = ["METRICS", "agents_label", "episode_set", "format_table", "load_policies", "main", "run_episodes",
           "summarize"]


def main(argv: list[str] | None = None) -> dict:
    p = Parser(prog="python -m plex_ma.evaluate", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkpoint", default=None,
                   help="checkpoint file (e.g. runs/x/latest.pt, or pretrained:plex-gru); not needed when both "
                        "PLEX agents are stand-ins")
    p.add_argument("--planner", choices=PLANNER_KINDS, default="learned",
                   help="PLEX planner: the checkpoint's, the shortest-path oracle (ground truth), random, or "
                        "shortest paths on the agent's own ego map (map, map-los), or the value-iteration "
                        "module's sub-goal (vin); no ground truth in the last three")
    p.add_argument("--executor", choices=EXECUTOR_KINDS, default="learned",
                   help="PLEX executor: the checkpoint's, the shortest-path oracle (ground truth) or random")
    p.add_argument("--sample", action="store_true", help="sample the learned agents' actions (seeded) instead of greedy")
    p.add_argument("--seed", type=int, default=0, help="seeds --sample and the random stand-ins")
    p.add_argument("--split", choices=["val", "test"], default="test", help="episode set")
    p.add_argument("--episodes", type=integer(1), default=1000, help="how many of the set's episodes to run")
    p.add_argument("--scenes", default=None, help="scene source (default: the one trained on)")
    p.add_argument("--episodes-file", default=None, help="a fixed episode file instead of the split's default")
    p.add_argument("--num-envs", type=integer(1), default=8, help="worlds run in parallel")
    p.add_argument("--json", default=None, type=output_path(), help="write the summary and per-episode results here")
    p.add_argument("--record", default=None, help="also record the episodes to this .rrd file (rerun)")
    p.add_argument("--torch-threads", type=int, default=1,
                   help="torch threads (1: small batches run fastest on a small, shared machine)")
    p.add_argument("--device", default="auto", help=DEVICE_HELP)
    a = p.parse_args(argv)
    if a.torch_threads > 0:
        torch.set_num_threads(a.torch_threads)
    try:
        device = resolve_device(a.device)
    except DeviceError as e:
        p.error(str(e))
    needs_nets = a.checkpoint is not None or "learned" in (a.planner, a.executor)
    if a.checkpoint is None and needs_nets:
        p.error("--checkpoint is needed unless neither --planner nor --executor is learned")
    try:
        cfg, nets = load_policies(a.checkpoint, device) if a.checkpoint else (TrainConfig(), {})
    except CheckpointError as e:
        fail(e)
    if not cfg.method.startswith("plex") and (a.planner, a.executor) != ("learned", "learned"):
        p.error(f"--planner/--executor apply to PLEX; the checkpoint is {cfg.method}")
    try:  # a bad --scenes or --episodes-file: one line, no traceback
        if a.episodes_file:
            load_episodes(a.episodes_file)  # fail before anything is written
        recorder = None
        if a.record:
            recorder = EpisodeRecorder(a.record)
        results = run_episodes(cfg, nets, a.split, a.episodes, a.scenes, a.num_envs, a.episodes_file, recorder,
                               sample=a.sample, planner=a.planner, executor=a.executor, seed=a.seed)
    except (SceneError, EpisodeFileError) as e:
        fail(e)
    summary = summarize(results)
    agents = agents_label(cfg, a.planner, a.executor)
    mode = "sampled" if a.sample else "greedy"
    print(format_table(summary, f"{agents} on {a.scenes or cfg.env.scenes}/{a.split}, {mode} "
                                f"({a.checkpoint or 'no checkpoint'})"))
    if a.json:
        Path(a.json).parent.mkdir(parents=True, exist_ok=True)
        Path(a.json).write_text(json.dumps({**summary, "method": cfg.method, "agents": agents,
                                            "planner": a.planner, "executor": a.executor,
                                            "ground_truth": "oracle" in (a.planner, a.executor), "mode": mode,
                                            "seed": a.seed, "checkpoint": str(a.checkpoint),
                                            "split": a.split, "scenes": a.scenes or cfg.env.scenes,
                                            "per_episode": results}, indent=1))
    return summary


def agents_label(cfg: TrainConfig, planner: str, executor: str) -> str:
    """e.g. 'plex-gru', or 'plex-gru: planner oracle (ground truth), executor learned'."""
    if not cfg.method.startswith("plex") or (planner, executor) == ("learned", "learned"):
        return cfg.method
    gt = lambda k: " (ground truth)" if k == "oracle" else ""  # noqa: E731
    return f"{cfg.method}: planner {planner}{gt(planner)}, executor {executor}{gt(executor)}"


if __name__ == "__main__":
    main(sys.argv[1:])
