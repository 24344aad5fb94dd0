"""``python -m plex_ma.train``: train PLEX or a flat baseline (see ``--help``).

Examples::

    python -m plex_ma.train --preset smoke                     # < 2 minutes, writes a checkpoint
    python -m plex_ma.train --preset cpu --method plex-gru     # the default recipe on 2 CPU cores
    python -m plex_ma.train --preset cpu --method plex-gru --no-eli --run-dir runs/no-eli
    python -m plex_ma.train --preset paper --method ppo-smt    # the paper's settings (needs days)

A run dir that already holds a checkpoint is resumed.
"""

from __future__ import annotations

import json
import sys

from plex_ma.config import parse


def main(argv: list[str] | None = None) -> dict:
    cfg = parse(argv)
    from plex_ma.trainers.plex import make_trainer

    print(f"training {cfg.method}{'' if cfg.eli or not cfg.method.startswith('plex') else ' (no ELI)'} "
          f"for {cfg.total_steps:,} steps with {cfg.num_envs} worlds at {cfg.resolution} px -> {cfg.run_dir}")
    trainer = make_trainer(cfg)
    try:
        result = trainer.train()
    finally:
        trainer.close()
    print(json.dumps({k: round(v, 4) if isinstance(v, float) else v for k, v in result.items()
                      if not k.startswith("learner/")}))
    return result


if __name__ == "__main__":
    main(sys.argv[1:])
