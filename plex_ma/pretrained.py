"""``python -m plex_ma.pretrained``: the agents shipped inside the package.

    python -m plex_ma.pretrained                      # list them: name, method, steps, how trained, and the
                                                      # command that trains their config with this code
    python -m plex_ma.pretrained export runs/x/latest.pt --name plex-gru --command "python -m plex_ma.train ..."

A shipped agent is used as ``--checkpoint pretrained:NAME`` by ``evaluate``, ``record`` and
``train`` (which fine-tunes it). The file holds float16 weights (loaded as float32), the
training config, the step count, the command that trained it and any notes (its
evaluation); it loads with ``weights_only=True``.
"""

from __future__ import annotations

import argparse
import json
import sys

from plex_ma.cli import Parser
from plex_ma.config import command
from plex_ma.trainers.base import saved_config
from plex_ma.trainers.checkpoint import (CheckpointError, export_pretrained, load_checkpoint, pretrained_dir,
                                         pretrained_names)


def _json_object(text: str) -> dict:
    """An argparse type: a JSON object."""
    try:
        value = json.loads(text)
    except json.JSONDecodeError as e:
        raise argparse.ArgumentTypeError(f"not JSON: {e}") from None
    if not isinstance(value, dict):
        raise argparse.ArgumentTypeError(f"expected a JSON object, got {type(value).__name__}")
    return value


def main(argv: list[str] | None = None) -> int:
    p = Parser(prog="python -m plex_ma.pretrained", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd")
    ex = sub.add_parser("export", help="write a checkpoint's weights-only file into the package")
    ex.add_argument("checkpoint")
    ex.add_argument("--name", required=True, help="the name it is loaded by (pretrained:NAME)")
    ex.add_argument("--command", required=True, help="the command that trained it")
    ex.add_argument("--notes", type=_json_object, default={},
                    help="JSON object stored beside the weights (e.g. its evaluation)")
    a = p.parse_args(argv)
    try:
        if a.cmd == "export":
            path = export_pretrained(a.checkpoint, pretrained_dir() / f"{a.name}.pt", a.command, a.notes)
            print(f"wrote {path} ({path.stat().st_size / 2**20:.1f} MiB)")
            return 0
        for name in pretrained_names():
            st = load_checkpoint(f"pretrained:{name}")
            print(f"pretrained:{name}  {st['config']['method']}  {st['step']:,} steps\n"
                  f"  trained by: {st['command']}\n  its config with this code: {command(saved_config(st))}")
        return 0
    except CheckpointError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
