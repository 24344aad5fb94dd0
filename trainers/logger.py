"""Metrics to ``metrics.jsonl`` (one JSON object per line) and TensorBoard, with
habitat-like keys: ``metrics/success``, ``metrics/spl``, ``reward``, ``learner/*``, ``perf/fps``,
``perf/rss_mib`` (the process's resident memory, for soak checks of long runs)."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

from torch.utils.tensorboard import SummaryWriter


def resident_memory_mib() -> float | None:
    """This process's resident set size in MiB (from Linux's /proc), or None where it cannot
    be read."""
    try:
        with open("/proc/self/statm") as f:
            pages = int(f.read().split()[1])
        return pages * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError, IndexError):
        return None


class MetricLogger:
    """``metrics.jsonl`` and TensorBoard's ``tb/`` in a run dir, opened at the first
    :meth:`log`: a run that fails before its first update leaves no run dir behind (and an
    existing one as it was).

    ``start_step`` is the step the run starts from (the resumed checkpoint's, 0 for a new
    run). Rows past it, logged by an earlier run after the checkpoint it resumes from (or
    by one that never wrote a checkpoint), are dropped from ``metrics.jsonl`` when it is
    opened, with any line cut short by a crash, so that each step appears once; TensorBoard
    hides its events past it (``purge_step``)."""

    def __init__(self, run_dir: str | Path, tensorboard: bool = True, start_step: int = 0):
        self.run_dir = Path(run_dir)
        self.tensorboard = tensorboard
        self.start_step = int(start_step)
        self._f = None
        self._tb = None

    def _open(self) -> None:
        self.run_dir.mkdir(parents=True, exist_ok=True)
        path = self.run_dir / "metrics.jsonl"
        if path.exists():
            text = path.read_text()
            lines = text.splitlines()
            keep = [line for line in lines if _row_step(line) is not None and _row_step(line) <= self.start_step]
            if keep != lines or (text and not text.endswith("\n")):
                tmp = path.with_name(".metrics.jsonl.tmp")
                tmp.write_text("".join(line + "\n" for line in keep))
                os.replace(tmp, path)
        self._f = open(path, "a", buffering=1)
        if self.tensorboard:
            tb = self.run_dir / "tb"
            self._tb = SummaryWriter(str(tb), purge_step=self.start_step + 1 if tb.exists() else None)

    def log(self, step: int, metrics: dict) -> None:
        if self._f is None:
            self._open()
        clean = {k: float(v) for k, v in metrics.items() if v is not None and math.isfinite(float(v))}
        self._f.write(json.dumps({"step": int(step), **clean}) + "\n")
        if self._tb is not None:
            for k, v in clean.items():
                self._tb.add_scalar(k, v, step)

    def close(self) -> None:
        if self._f is not None:
            self._f.close()
        if self._tb is not None:
            self._tb.close()


def _row_step(line: str) -> int | None:
    """The step of a ``metrics.jsonl`` row, or None for a line that is not one."""
    try:
        row = json.loads(line)
        return int(row["step"])
    except (json.JSONDecodeError, KeyError, TypeError, ValueError):
        return None


def read_metrics(run_dir: str | Path) -> list[dict]:
    p = Path(run_dir) / "metrics.jsonl"
    if not p.exists():
        return []
    out = []
    for line in p.read_text().splitlines():
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError:
            continue  # a line cut by a crash
    return out
