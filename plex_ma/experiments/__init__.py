"""The paper's experiments, re-run in our own world: ``python -m plex_ma.experiments NAME``.

Every experiment is a module with three functions:

* ``add_arguments(parser)``: its own command-line options (``--out`` and ``--seed`` are
  added for every experiment by the runner);
* ``check(args)``: raise ValueError naming the first bad option (the runner prints it as one
  line, exit status 2, before it creates ``out_dir``);
* ``main(args, out_dir) -> dict``: run it, write its JSON results and PNG figures under
  ``out_dir`` (a :class:`pathlib.Path` that already exists) and return a short summary.

Adding an experiment is one line in the registry below, e.g.
``register("table1", "plex_ma.experiments.table1", "Table 1: ...")``. Modules are
imported lazily, so a heavy experiment never slows down another one's start.

Results go to ``results/NAME/`` at the repository root by default (``--out DIR``
overrides it).
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType


@dataclass(frozen=True)
class Experiment:
    name: str
    module: str  # dotted module path with add_arguments(parser), check(args) and main(args, out_dir)
    help: str

    def load(self) -> ModuleType:
        mod = importlib.import_module(self.module)
        for fn in ("add_arguments", "check", "main"):
            if not callable(getattr(mod, fn, None)):
                raise TypeError(f"experiment {self.name!r}: module {self.module} lacks a {fn}() function")
        return mod


REGISTRY: dict[str, Experiment] = {}


def register(name: str, module: str, help: str = "") -> None:
    """Make ``python -m plex_ma.experiments NAME`` run ``module``'s ``main``."""
    if not name or not name.replace("_", "").replace("-", "").isalnum():
        raise ValueError(f"experiment name must be alphanumeric (with - or _), got {name!r}")
    if name in REGISTRY:
        raise ValueError(f"experiment {name!r} is already registered (by {REGISTRY[name].module})")
    REGISTRY[name] = Experiment(name, module, help)


def repo_root() -> Path:
    """The repository root when running from a checkout, else the current directory."""
    here = Path(__file__).resolve().parents[2]
    if (here / "pyproject.toml").is_file() and (here / "plex_ma").is_dir():
        return here
    return Path.cwd()


def default_out_dir(name: str) -> Path:
    return repo_root() / "results" / name


# ----------------------------------------------------------------------- the registry
register("fig3", "plex_ma.experiments.fig3", "Fig. 3: distance covered by a random policy vs. number of actions")
register("prop1", "plex_ma.experiments.prop1", "Proposition 1: random-walk tail probabilities vs. Chernoff bounds")
register("table1", "plex_ma.experiments.table1",
         "Table 1, Fig. 4, Fig. 5a/b: PLEX, the flat baselines, the no-ELI ablation and the map control at one budget")
