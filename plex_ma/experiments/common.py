"""Helpers shared by the experiments: JSON output, run metadata, figures."""

from __future__ import annotations

import json
import math
import os
import platform
import subprocess
import tempfile
from pathlib import Path

import numba
import numpy as np

from . import repo_root


def to_jsonable(x):
    """numpy scalars/arrays to plain Python; non-finite floats to None (strict JSON)."""
    if isinstance(x, dict):
        return {str(k): to_jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [to_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return to_jsonable(x.tolist())
    if isinstance(x, (np.bool_, bool)):
        return bool(x)
    if isinstance(x, (np.integer, int)):
        return int(x)
    if isinstance(x, (np.floating, float)):
        x = float(x)
        return x if math.isfinite(x) else None
    return x


def write_json(path: str | os.PathLike, obj) -> Path:
    """Write ``obj`` as indented, strict JSON, atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    text = json.dumps(to_jsonable(obj), indent=1, allow_nan=False) + "\n"
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name, suffix=".tmp")
    with os.fdopen(fd, "w") as f:
        f.write(text)
    os.chmod(tmp, 0o644)  # mkstemp makes files private; results are data to share
    os.replace(tmp, path)
    return path


def machine() -> dict:
    info = {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version(),
            "numpy": np.__version__}
    info["numba_threads"] = numba.get_num_threads()
    return info


def provenance() -> dict:
    """The code the results came from: git commit and whether the simulator had local edits."""
    def git(*a):
        try:
            return subprocess.run(["git", *a], cwd=repo_root(), capture_output=True, text=True,
                                  timeout=10).stdout.strip()
        except (OSError, subprocess.SubprocessError):
            return ""

    return {"git_commit": git("rev-parse", "HEAD") or None,
            "simulator_locally_modified": bool(git("status", "--porcelain", "--", "envs/sim"))}


def pyplot():
    """matplotlib.pyplot with a non-interactive backend (figures go to files only)."""
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path: str | os.PathLike, dpi: int = 150) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # No timestamps in the PNG metadata, so re-running gives the same bytes.
    fig.savefig(path, dpi=dpi, bbox_inches="tight", metadata={"Software": None})
    return path


def mean_sd_se(x: np.ndarray) -> dict:
    x = np.asarray(x, np.float64)
    n = len(x)
    sd = float(x.std(ddof=1)) if n > 1 else 0.0
    return {"mean": float(x.mean()), "std": sd, "se": sd / math.sqrt(n) if n else math.nan}


def proportion(flags: np.ndarray) -> dict:
    """Share of True with its binomial standard error."""
    f = np.asarray(flags, bool)
    n = len(f)
    p = float(f.mean()) if n else math.nan
    return {"p": p, "se": math.sqrt(p * (1 - p) / n) if n else math.nan}
