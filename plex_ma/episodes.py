"""Fixed evaluation episode files, and their command line.

``python -m plex_ma.episodes make --scenes procgen --split test --num-episodes 1000 --seed 2 --out PATH``
samples episodes by Habitat's rules (:func:`plex_ma.envs.sim.generate_episodes`, spread
round-robin over the split's scenes, deterministic in the seed) and writes them as a
gzipped JSON episode file. ``python -m plex_ma.episodes show PATH`` prints a summary:
episode count, scenes, quantiles of the geodesic distance, and the close/far split at
5.76 m (the paper's Fig. 5b).

The package ships the default files (``envs/sim/data/episodes/``), made by exactly these
commands (:data:`~plex_ma.envs.sim.episodes.DEFAULT_FILES` holds the counts and seeds)::

    python -m plex_ma.episodes make --scenes procgen --split val --num-episodes 500 --seed 1 \\
        --out envs/sim/data/episodes/procgen_val.json.gz
    python -m plex_ma.episodes make --scenes procgen --split test --num-episodes 1000 --seed 2 \\
        --out envs/sim/data/episodes/procgen_test.json.gz

They use the default scenes of each split (16 val and 16 test houses). Regenerating a
file with the same command reproduces it byte for byte, as long as the scene source and
the simulator's grid are unchanged. :func:`~plex_ma.envs.sim.episodes.default_episode_file` returns their paths.
"""

from __future__ import annotations

__all__ = ["CLOSE_FAR_SPLIT", "DEFAULT_FILES", "default_episode_file", "main", "make", "summary"]

import argparse
import sys
from collections import Counter
from pathlib import Path

import numpy as np

from plex_ma.cli import Parser, output_path
from plex_ma.envs.sim import EpisodeFileError, SceneError, generate_episodes, load_episodes, save_episodes, scene_bank
from plex_ma.envs.sim.episodes import CLOSE_FAR_SPLIT, DEFAULT_FILES, default_episode_file


def make(scenes: str, split: str, num_episodes: int, seed: int, out: str | Path,
         num_scenes: int | None = None) -> list:
    """Sample ``num_episodes`` episodes over the scenes of ``split`` and write them to ``out``."""
    if num_episodes < 1:
        raise ValueError(f"--num-episodes must be >= 1, got {num_episodes}")
    if seed < 0:
        raise ValueError(f"--seed must be >= 0, got {seed}")
    bank = scene_bank(scenes, split, num_scenes)
    episodes = generate_episodes(bank, num_episodes, seed)
    save_episodes(episodes, out)
    return episodes


def summary(episodes: list) -> dict:
    """Count, scenes, geodesic distance quantiles and the close/far split of episodes."""
    d = np.array([e.geodesic_distance for e in episodes], np.float64)
    per_scene = Counter(e.scene_id for e in episodes)
    q = [0, 10, 25, 50, 75, 90, 100]
    close = int(np.sum(d < CLOSE_FAR_SPLIT))
    return {
        "episodes": len(episodes),
        "scenes": len(per_scene),
        "episodes_per_scene": dict(sorted(per_scene.items())),
        "geodesic_quantiles": {f"p{p}": float(v) for p, v in zip(q, np.percentile(d, q))},
        "geodesic_mean": float(d.mean()),
        "close": close,
        "far": len(episodes) - close,
    }


def _print_summary(path: str, s: dict, out=None) -> None:
    out = sys.stdout if out is None else out
    per = s["episodes_per_scene"]
    print(f"{path}", file=out)
    print(f"  episodes: {s['episodes']}", file=out)
    print(f"  scenes:   {s['scenes']} ({min(per.values())}-{max(per.values())} episodes each)", file=out)
    for sid, n in per.items():
        print(f"    {sid}: {n}", file=out)
    qs = "  ".join(f"{k}={v:.2f}" for k, v in s["geodesic_quantiles"].items())
    print(f"  geodesic distance (m): {qs}  mean={s['geodesic_mean']:.2f}", file=out)
    n = max(s["episodes"], 1)
    print(f"  close (< {CLOSE_FAR_SPLIT} m): {s['close']} ({100 * s['close'] / n:.1f}%)  "
          f"far: {s['far']} ({100 * s['far'] / n:.1f}%)", file=out)


def main(argv: list[str] | None = None) -> int:
    p = Parser(prog="python -m plex_ma.episodes", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="command", required=True)
    pm = sub.add_parser("make", help="sample episodes by Habitat's rules and write an episode file")
    pm.add_argument("--scenes", default="procgen", help="scene source (default: procgen)")
    pm.add_argument("--split", required=True, choices=("train", "val", "test"), help="scene split")
    pm.add_argument("--num-episodes", type=int, required=True, help="number of episodes")
    pm.add_argument("--num-scenes", type=int, default=None,
                    help="number of scenes of the split (default: the split's default count)")
    pm.add_argument("--seed", type=int, required=True, help="sampling seed (non-negative)")
    pm.add_argument("--out", required=True, type=output_path(), help="output path (.json.gz)")
    ps = sub.add_parser("show", help="summarise an episode file")
    ps.add_argument("path", help="episode file (.json.gz)")
    a = p.parse_args(argv)

    try:
        if a.command == "make":
            make(a.scenes, a.split, a.num_episodes, a.seed, a.out, a.num_scenes)
            _print_summary(a.out, summary(load_episodes(a.out)))
        else:
            _print_summary(a.path, summary(load_episodes(a.path)))
    except (EpisodeFileError, SceneError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
