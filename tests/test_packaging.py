"""The wheel's metadata: the MIT licence file and the project URLs (what ``pip show`` and a
package index display), built by the package's own build backend."""

from __future__ import annotations

import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_wheel_metadata_carries_the_licence_and_urls(tmp_path):
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    src = tmp_path / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy(ROOT / name, src / name)
    for pkg in set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-dir"].values()):
        shutil.copytree(ROOT / pkg, src / pkg, ignore=shutil.ignore_patterns("__pycache__", "data"))
    out = tmp_path / "out"
    out.mkdir()
    done = subprocess.run([sys.executable, "-c", "import sys, setuptools.build_meta as b; "
                           "print(b.prepare_metadata_for_build_wheel(sys.argv[1]))", str(out)],
                          cwd=src, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    info = out / done.stdout.strip().splitlines()[-1]
    licence = (info / "licenses" / "LICENSE").read_text()
    assert licence.startswith("MIT License") and "plex-ma contributors" in licence
    meta = (info / "METADATA").read_text()
    assert "License-Expression: MIT" in meta
    urls = project["urls"]
    assert urls and all(f"Project-URL: {label}, {url}" in meta for label, url in urls.items())
    assert "deprecated" not in done.stderr  # e.g. the old license = {text = ...} table
