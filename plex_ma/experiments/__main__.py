"""``python -m plex_ma.experiments NAME [--out DIR] [--seed S] [options]``.

``python -m plex_ma.experiments`` (or ``--list``) lists the registered experiments;
``python -m plex_ma.experiments NAME --help`` shows one experiment's options.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from types import ModuleType

from plex_ma.cli import Parser, output_path

from . import REGISTRY, Experiment, default_out_dir


def experiment_parser(exp: Experiment, mod: ModuleType) -> Parser:
    """The command line of experiment ``exp`` (its module ``mod``); its errors are one line."""
    p = Parser(prog=f"python -m plex_ma.experiments {exp.name}", description=exp.help)
    p.add_argument("--out", type=output_path(directory=True), default=None,
                   help=f"output directory (default: results/{exp.name}/ at the repository root)")
    p.add_argument("--seed", type=int, default=0, help="master seed; the results are deterministic in it")
    mod.add_arguments(p)
    return p


def list_experiments() -> str:
    width = max(len(n) for n in REGISTRY)
    lines = [f"  {name:<{width}}  {exp.help}" for name, exp in REGISTRY.items()]
    return ("usage: python -m plex_ma.experiments NAME [--out DIR] [--seed S] [options]\n\nexperiments:\n"
            + "\n".join(lines))


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if not argv or argv[0] in ("--list", "-l", "-h", "--help"):
        print(list_experiments())
        return 0
    name, rest = argv[0], argv[1:]
    if name not in REGISTRY:
        print(f"python -m plex_ma.experiments: error: unknown experiment {name!r}; known: {', '.join(REGISTRY)}",
              file=sys.stderr)
        return 2
    exp = REGISTRY[name]
    mod = exp.load()  # only this experiment's module is imported
    parser = experiment_parser(exp, mod)
    args = parser.parse_args(rest)
    try:
        mod.check(args)
    except ValueError as e:
        parser.error(str(e))
    out = (Path(args.out) if args.out is not None else default_out_dir(name)).resolve()
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    summary = mod.main(args, out)
    dt = time.perf_counter() - t0
    print(json.dumps({"experiment": name, "out": str(out), "seconds": round(dt, 1), **(summary or {})}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
