"""``python -m plex_ma.train``: train PLEX or a flat baseline (see ``--help``).

Examples::

    python -m plex_ma.train --preset smoke                     # < 2 minutes, writes a checkpoint
    python -m plex_ma.train --preset cpu --method plex-gru     # the default recipe on 2 CPU cores
    python -m plex_ma.train --preset cpu --method plex-gru --no-eli --run-dir runs/no-eli
    python -m plex_ma.train --preset paper --method ppo-smt    # the paper's settings (needs days)

A run dir that already holds a checkpoint is resumed. Data-parallel (DD-PPO) over K workers,
each with its own ``--num-envs`` worlds (see docs/distributed.md)::

    torchrun --nproc_per_node=2 --standalone -m plex_ma.train --preset cpu

SIGTERM or SIGINT: the current rollout and its update finish, a checkpoint is written, and the
process exits with 128 + the signal number (143, 130); a second signal stops at once.
"""

from __future__ import annotations

import json
import sys

from plex_ma.cli import fail, unwritable
from plex_ma.config import parse
from plex_ma.envs.sim import EpisodeFileError, SceneError
from plex_ma.trainers import distributed, make_trainer
from plex_ma.trainers.checkpoint import CheckpointError
from plex_ma.trainers.device import DeviceError, resolve_device
from plex_ma.viz import record_training_episode


def main(argv: list[str] | None = None) -> dict:
    try:
        cfg = parse(argv)
    except ValueError as e:  # a bad value: one line naming the flag, no traceback
        fail(e)
    if why := unwritable(cfg.run_dir, directory=True):
        fail(f"--run-dir {why}")
    try:
        device = resolve_device(cfg.device)
    except DeviceError as e:
        fail(e)
    # torchrun with WORLD_SIZE > 1: join the group (nccl, each rank on its LOCAL_RANK GPU,
    # when the networks run on CUDA; gloo on the CPU)
    ctx = distributed.init_from_env(cfg.dist_timeout, backend=None if device.type == "cuda" else "gloo")
    workers = f" per worker x {ctx.world_size} workers ({ctx.backend})" if ctx.active else ""
    if ctx.is_main:
        print(f"training {cfg.method}{'' if cfg.env.eli or not cfg.method.startswith('plex') else ' (no ELI)'} "
              f"for {cfg.total_steps:,} steps with {cfg.num_envs} worlds{workers} at {cfg.env.resolution} px on {f'cuda:{ctx.local_rank}' if ctx.active and device.type == 'cuda' else device} "
              f"-> {cfg.run_dir}")
    with distributed.graceful_stop():
        try:
            trainer = make_trainer(cfg, record=record_training_episode)  # rerun recordings into the run dir
        except (CheckpointError, SceneError, EpisodeFileError) as e:
            # a bad --checkpoint, run dir, --scenes or --episodes-file: one line, no traceback,
            # and nothing written (the run dir is made at the first update's log)
            fail(e)
        try:
            result = trainer.train()
        finally:
            trainer.close()
    if ctx.is_main:
        print(json.dumps({k: round(v, 4) if isinstance(v, float) else v for k, v in result.items()
                          if not k.startswith("learner/")}))
    distributed.shutdown()
    sig = distributed.stop_signal()
    if sig is not None:
        if ctx.is_main:
            print(f"stopped by signal {sig}: checkpoint saved at step {trainer.step:,}; run the same command to resume",
                  flush=True)
        sys.exit(128 + sig)
    return result


if __name__ == "__main__":
    main(sys.argv[1:])
