"""Rerun stream helpers of :mod:`plex_ma.viz.recorder`: tensor columns, JPEG, the ``rerun`` CLI
(:func:`merge_rrd`), training scalars, and ``_Episode``, one recorded episode's buffered rows.
"""

from __future__ import annotations

import io
import math
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow as pa
import rerun as rr
from PIL import Image

from .layout import TIMELINE, TRAIN_TIMELINE


def tensor_column(x: np.ndarray, dim_name: str) -> rr.ComponentColumn:
    """Rows of ``x`` (T, D) float32 as one column of 1-D ``Tensor`` values, for
    ``send_columns`` (rerun's Python API converts tensors one at a time, ~0.6 ms each).
    The arrow layout is taken from a tensor rerun converted itself."""
    x = np.ascontiguousarray(x, np.float32)
    t, d = x.shape
    (sample,) = rr.Tensor(x[0], dim_names=[dim_name]).as_component_batches()
    ty = sample.as_arrow_array().type
    shape_t, names_t, buf_t = ty.field("shape").type, ty.field("names").type, ty.field("buffer").type
    rows = pa.array(np.arange(t + 1, dtype=np.int32))
    shape = pa.ListArray.from_arrays(rows, pa.array(np.full(t, d, np.uint64)), type=shape_t)
    names = pa.ListArray.from_arrays(rows, pa.array([dim_name] * t), type=names_t)
    kinds = [buf_t.field(i).name for i in range(buf_t.num_fields)]
    f32 = kinds.index("F32")
    children = [pa.ListArray.from_arrays(pa.array(np.arange(0, t * d + 1, d, dtype=np.int32)), pa.array(x.reshape(-1)),
                                         type=buf_t.field(i).type) if i == f32 else pa.array([], type=buf_t.field(i).type)
                for i in range(buf_t.num_fields)]
    codes = pa.py_buffer(np.full(t, buf_t.type_codes[f32], np.int8))
    buf = pa.Array.from_buffers(buf_t, t, [None, codes, pa.py_buffer(np.arange(t, dtype=np.int32))], children=children)
    arr = pa.StructArray.from_arrays([shape, names, buf], fields=list(ty))
    desc = sample.component_descriptor()

    class _Batch:
        def as_arrow_array(self):
            return arr

        def component_descriptor(self):
            return desc

    return rr.ComponentColumn(desc, _Batch())


def jpeg(img: np.ndarray, quality: int) -> bytes:
    """An (H, W, 3) uint8 image as JPEG bytes of ``quality``."""
    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="JPEG", quality=quality)
    return buf.getvalue()


def rerun_executable() -> str:
    """The ``rerun`` CLI that ships with rerun-sdk (falls back to the one on PATH)."""
    try:
        import rerun_cli  # optional: otherwise the rerun on PATH

        exe = Path(rerun_cli.__file__).with_name("rerun" + (".exe" if sys.platform.startswith("win") else ""))
        if exe.exists():
            return str(exe)
    except ImportError:
        pass
    found = shutil.which("rerun")
    if found is None:
        raise FileNotFoundError("the rerun CLI was not found (it ships with rerun-sdk)")
    return found


def _put_rerun_on_path() -> None:
    """``rr.spawn`` looks for ``rerun`` on PATH; the CLI of rerun-sdk is there only in an
    activated virtual environment."""
    if shutil.which("rerun") is None:
        os.environ["PATH"] = str(Path(rerun_executable()).parent) + os.pathsep + os.environ.get("PATH", "")


def merge_rrd(parts: list[Path], out: Path) -> None:
    """Write the recordings of several .rrd files into one (``rerun rrd merge``)."""
    tmp = out.with_name(f".{out.name}.merging")
    r = subprocess.run([rerun_executable(), "rrd", "merge", *map(str, parts), "-o", str(tmp)],
                       capture_output=True, text=True, check=False)
    if r.returncode != 0 or not tmp.exists():
        tmp.unlink(missing_ok=True)
        raise RuntimeError(f"rerun rrd merge failed ({r.returncode}): {r.stderr.strip()[-2000:]}")
    tmp.replace(out)


def _train_entity(key: str) -> str:
    """A metric name as an entity path below ``train/``."""
    parts = [re.sub(r"[^A-Za-z0-9_.\-]", "_", p) for p in str(key).split("/") if p]
    return "train/" + "/".join(parts or ["_"])


def send_training_scalars(rec: rr.RecordingStream, records: list[dict]) -> None:
    """Log metric lines (dicts with ``step``) to ``rec`` as ``train/<name>`` Scalars on the
    ``train_step`` timeline, one column per metric."""
    series: dict[str, tuple[list, list]] = {}
    for r in records:
        if "step" not in r:
            continue
        for k, v in r.items():
            if k == "step" or isinstance(v, bool) or not isinstance(v, (int, float, np.number)):
                continue
            v = float(v)
            if not math.isfinite(v):
                continue
            s = series.setdefault(k, ([], []))
            s[0].append(int(r["step"]))
            s[1].append(v)
    for k, (steps, values) in series.items():
        rec.send_columns(_train_entity(k), indexes=[rr.TimeColumn(TRAIN_TIMELINE, sequence=steps)],
                         columns=rr.Scalars.columns(scalars=values))


def _send(rec: rr.RecordingStream, entity: str, times: np.ndarray, columns) -> None:
    """``send_columns`` of ``columns`` to ``entity`` at ``times`` on the ``step`` timeline."""
    rec.send_columns(entity, indexes=[rr.TimeColumn(TIMELINE, sequence=times)], columns=columns)


def _cumulative(points, counts: list[int], **per_point):
    """Rows holding the first ``counts[i]`` points (Points2D columns, partitioned)."""
    pts = np.asarray(points, np.float32).reshape(-1, 2)
    idx = np.concatenate([np.arange(c) for c in counts]) if counts else np.zeros(0, np.int64)
    cols = {k: (np.asarray(v)[idx] if not isinstance(v, list) else [v[i] for i in idx])
            for k, v in per_point.items()}
    return rr.Points2D.columns(positions=pts[idx], **cols).partition(counts)


class _Episode:
    """One episode being recorded: its rerun stream, its history and the rows not yet sent.

    Rows are buffered as ``rows[key] = [(step, value), ...]`` and sent as columns
    (``send_columns``) when the episode ends or ``flush_every`` steps have gathered: one
    call per entity instead of one per entity and step. A key is a kind of row
    (``agent``, ``images``, ...) or ``scalar:<entity path>``."""

    def __init__(self, rec: rr.RecordingStream, file: Path, index: int, name: str):
        self.rec, self.file, self.index, self.name = rec, file, index, name
        self.t = 0
        self.k = -1  # index of the active sub-goal (-1: none yet)
        self.path: list[tuple[float, float]] = []
        self.subgoals: list[tuple[float, float]] = []
        self.subgoals_raw: list[tuple[float, float]] = []
        self.collision_points: list[tuple[float, float]] = []
        self.collisions = 0
        self.elis: list[np.ndarray] = []
        self.eli_k: list[int] = []
        self.returns = np.zeros(2)
        self.finished = False
        self.result: dict = {}
        self.description = ""
        self.rows: dict[str, list] = {}
        self.unsent = 0
        self.grid = None  # the scene's SceneGrid
        self.goal = None
        self.heading = 0.0

    def add(self, key: str, value) -> None:
        """Buffer ``value`` under ``key`` at the current step."""
        self.rows.setdefault(key, []).append((self.t, value))


__all__ = ["jpeg", "merge_rrd", "rerun_executable", "send_training_scalars", "tensor_column"]
