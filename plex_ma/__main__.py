"""``python -m plex_ma``: the package's commands.

    python -m plex_ma                     # list the commands, one line each
    python -m plex_ma COMMAND [options]   # the same as python -m plex_ma.COMMAND [options]
    python -m plex_ma COMMAND --help      # one command's options

Each command is a module of the package with its own command line; :data:`COMMANDS`
names them, in the order a new user meets them.
"""

from __future__ import annotations

import runpy
import sys

# command -> what it does (each is the module plex_ma.<command>)
COMMANDS = {
    "train": "train PLEX or a flat baseline with PPO; a run dir that holds a checkpoint resumes",
    "evaluate": "evaluate a checkpoint greedily on the fixed val/test episodes (table, JSON)",
    "record": "record episodes of a checkpoint or of stand-in agents to a Rerun .rrd file",
    "pretrained": "list the agents shipped in the package, or export a checkpoint as one",
    "experiments": "run the paper's experiments (Table 1, Fig. 3, ...); with no name, list them",
    "bench": "benchmarks: simulator, environments, gymnasium vector env, geodesics, training and recording speed",
    "episodes": "make or summarise fixed evaluation episode files",
    "scenes": "check scene sources (procgen, r2v, a directory of plans) or render them top-down",
}


def usage() -> str:
    width = max(map(len, COMMANDS))
    lines = ["usage: python -m plex_ma COMMAND [options]", "", "commands:"]
    lines += [f"  {name:<{width}}  {text}" for name, text in COMMANDS.items()]
    lines += ["", "python -m plex_ma COMMAND --help shows a command's options."]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(usage())
        return 0
    name, rest = argv[0], argv[1:]
    if name not in COMMANDS:
        print(f"error: unknown command {name!r}\n\n{usage()}", file=sys.stderr)
        return 2
    saved = sys.argv
    sys.argv = [f"python -m plex_ma.{name}", *rest]
    try:
        runpy.run_module(f"plex_ma.{name}", run_name="__main__", alter_sys=True)
    finally:
        sys.argv = saved
    return 0


if __name__ == "__main__":
    sys.exit(main())
