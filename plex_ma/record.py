"""``python -m plex_ma.record``: record episodes to a Rerun ``.rrd`` file.

    python -m plex_ma.record --checkpoint runs/plex-gru-cpu/latest.pt --episodes 3 --out episodes.rrd
    python -m plex_ma.record --policy random --episodes 2 --out random.rrd --split val
    python -m plex_ma.record --policy random --out one.rrd --topdown-png one.png   # + a top-down PNG
    rerun episodes.rrd                        # open it in the viewer

The episodes are run by :func:`plex_ma.trainers.evaluation.run_episodes` on one world (the first
``--episodes`` episodes of the split's fixed set; generated ones for ``train``): greedily by
the ``--checkpoint``'s networks, or with ``--planner`` / ``--executor`` standing in for either
PLEX agent (``oracle``: the shortest-path oracles, ground truth; ``random``: random
sub-goals, STOP with a small probability, and random moves). ``--policy random`` is
``--planner random --executor random``. Each episode becomes one recording in the file (see ``plex_ma.viz``
for the entity paths). ``--spawn`` also streams the recordings live to a Rerun viewer
(started if none is running; needs a display).
"""

from __future__ import annotations

import argparse
import json
import re
import sys

import torch
from PIL import Image

from plex_ma.cli import Parser, fail, integer, output_path
from plex_ma.config import DEVICE_HELP, TrainConfig, replace
from plex_ma.envs.sim import EpisodeFileError, SceneError
from plex_ma.trainers.checkpoint import CheckpointError
from plex_ma.trainers.device import DeviceError, resolve_device
from plex_ma.trainers.driver import EXECUTOR_KINDS, PLANNER_KINDS
from plex_ma.trainers.evaluation import load_policies, run_episodes
from plex_ma.viz import EpisodeRecorder


def main(argv: list[str] | None = None) -> list[dict]:
    p = Parser(prog="python -m plex_ma.record", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkpoint", help="checkpoint file whose networks act (greedily), or pretrained:NAME")
    p.add_argument("--policy", choices=["random"], help="a random planner/executor pair instead of a checkpoint")
    p.add_argument("--planner", choices=PLANNER_KINDS, default=None,
                   help="PLEX planner (default: the checkpoint's; oracle = ground truth; map = shortest paths on "
                        "the agent's own ego map; vin = the value-iteration module's sub-goal)")
    p.add_argument("--executor", choices=EXECUTOR_KINDS, default=None,
                   help="PLEX executor (default: the checkpoint's; oracle = ground truth)")
    p.add_argument("--episodes", type=integer(1), default=1, help="episodes to record")
    p.add_argument("--out", required=True, type=output_path(), help="the .rrd file to write")
    p.add_argument("--split", choices=["train", "val", "test"], default="val", help="scene split")
    p.add_argument("--scenes", default=None, help="scene source (default: the checkpoint's, or procgen)")
    p.add_argument("--resolution", type=int, default=64, help="image size (--policy random only)")
    p.add_argument("--max-steps", type=int, default=500, help="episode length limit (--policy random only)")
    p.add_argument("--seed", type=int, default=0, help="seeds the random policy and the train split's episodes")
    p.add_argument("--jpeg-quality", type=int, default=None, help="store RGB images as JPEG of this quality")
    p.add_argument("--no-images", action="store_true", help="leave out the RGB, depth and ego map images")
    p.add_argument("--spawn", action="store_true", help="also stream live to a Rerun viewer (needs a display)")
    p.add_argument("--topdown-png", default=None, type=output_path(), help="also write the top-down picture of the last episode here")
    p.add_argument("--device", default="auto", help=DEVICE_HELP)
    a = p.parse_args(argv)
    try:
        device = resolve_device(a.device)
    except DeviceError as e:
        p.error(str(e))
    if a.policy == "random":
        if a.checkpoint:
            p.error("--policy random and --checkpoint exclude each other")
        a.planner = a.planner or "random"
        a.executor = a.executor or "random"
    a.planner, a.executor = a.planner or "learned", a.executor or "learned"
    if not a.checkpoint and "learned" in (a.planner, a.executor):
        p.error("--checkpoint is needed unless neither --planner nor --executor is learned")
    if not a.checkpoint:
        try:
            cfg = replace(TrainConfig(), resolution=a.resolution, max_steps=a.max_steps, scenes=a.scenes or "procgen")
            cfg.env.validate()  # the worlds' rules only: nothing is trained here
        except ValueError as e:  # e.g. "config resolution=0: must be an integer in [8, 1024]"
            p.error(re.sub(r"^config (\w+)=", lambda m: f"--{m.group(1).replace('_', '-')}=", str(e)))
    rec = EpisodeRecorder(a.out, max_episodes=a.episodes, images=not a.no_images, jpeg_quality=a.jpeg_quality,
                          spawn=a.spawn, name=None)
    # One world means batch-1 inference: more torch threads only spin (and beside other
    # busy processes made an episode several times slower).
    torch.set_num_threads(1)
    if a.checkpoint:
        try:
            cfg, nets = load_policies(a.checkpoint, device)
        except CheckpointError as e:
            fail(e)
    else:
        nets = {}
    try:  # a bad --scenes: one line, no traceback, no file written (the recorder starts with the env)
        results = run_episodes(cfg, nets, split=a.split, episodes=a.episodes, scenes=a.scenes, num_envs=1,
                               recorder=rec, planner=a.planner, executor=a.executor, seed=a.seed)
    except (SceneError, EpisodeFileError) as e:
        fail(e)
    if a.topdown_png and rec.episodes:
        Image.fromarray(rec.topdown(-1)).save(a.topdown_png)
    for r in rec.episodes:
        print(json.dumps({k: (round(v, 3) if isinstance(v, float) else v) for k, v in r.items()}))
    print(f"wrote {len(rec.episodes)} episode(s) to {a.out}; open with: rerun {a.out}")
    return results


if __name__ == "__main__":
    main(sys.argv[1:])
