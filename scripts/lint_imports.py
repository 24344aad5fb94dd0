"""Check the import-linter contracts of pyproject.toml (the layers import downward only).

    python scripts/lint_imports.py

plex-ma installs ``envs/``, ``trainers/`` and ``viz/`` as subpackages of ``plex_ma``
(``[tool.setuptools] package-dir``). import-linter reads a package from one directory
tree, so this copies the sources into that installed layout in a temporary directory
and runs ``lint-imports`` on it. Exits with lint-imports' status.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def stage(dest: Path) -> Path:
    """Copy the package's sources into ``dest`` in their installed layout; returns ``dest``."""
    package_dir = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-dir"]
    for name, src in sorted(package_dir.items()):  # parents before their subpackages
        target = dest.joinpath(*name.split("."))
        shutil.copytree(ROOT / src, target, dirs_exist_ok=True,
                        ignore=shutil.ignore_patterns("__pycache__", "data", "*.pyc"))
    return dest


def lint(staged: Path, capture: bool = False) -> subprocess.CompletedProcess:
    """``lint-imports`` on a staged copy, with pyproject.toml's contracts."""
    exe = Path(sys.executable).with_name("lint-imports")
    return subprocess.run([str(exe), str(ROOT / "pyproject.toml"), "--no-cache"], cwd=staged,
                          env={**os.environ, "PYTHONPATH": str(staged)}, capture_output=capture, text=True)


def main() -> int:
    with tempfile.TemporaryDirectory(prefix="plex_ma_layers_") as d:
        return lint(stage(Path(d))).returncode


if __name__ == "__main__":
    sys.exit(main())
