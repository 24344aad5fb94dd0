"""Rerun recordings of PLEX episodes: trajectories, maps, sub-goals, images and the ELI.

:class:`EpisodeRecorder` follows one world (``world=0`` by default) of a
:class:`~plex_ma.envs.vector.PlexVectorEnv` (or of a flat ``PointNavVectorEnv``) and logs
what happens there through rerun-sdk into an ``.rrd`` file, on the ``step`` timeline
(executor actions since the episode began; a planner decision is logged at the step
count it was taken at, before the executor's next action). ``rerun FILE.rrd`` opens it.

**One recording per episode, one file.** Every recorded episode is its own rerun
recording (application id ``plex_ma``, named e.g. ``episode 2: procgen-val-00002 #2``),
so all episodes use the same entity paths below and each one's ``step`` timeline starts
at 0; the viewer lists them in its recordings panel. Several episodes are written to
temporary files and merged into the one output file with the ``rerun rrd merge`` of the
CLI that ships with rerun-sdk. Each recording carries the default blueprint
(:func:`default_blueprint`). Only complete episodes are kept (an episode cut short by
:meth:`EpisodeRecorder.end` is dropped unless nothing else was recorded).

Entity paths (stable; ``ENTITY_PATHS`` holds this table; positions are world metres,
x east, y north):

============================  ==============================================================
``world``                     Transform3D flipping y, so that north is up in a 2-D view
                              (static)
``world/map``                 the scene's top-down map (``topdown_view`` without the path)
                              as an Image, placed in metres by its Transform3D (static)
``world/start``               start position (Points2D, static)
``world/goal``                end goal (Points2D, static)
``world/agent``               the agent's position (Points2D)
``world/agent/heading``       its heading (Arrows2D, 0.5 m long)
``world/path``                the path so far (LineStrips2D)
``world/collisions``          every place a move was blocked so far (Points2D)
``world/subgoal``             the active sub-goal, snapped to the nearest reachable point
                              (Points2D)
``world/subgoal_raw``         the active sub-goal as the planner proposed it (Points2D)
``world/subgoals``            every snapped sub-goal proposed so far, coloured by ``k``
                              (Points2D)
``world/subgoals_raw``        every raw sub-goal proposed so far (Points2D)
``world/subgoal_line``        the agent to the active sub-goal (LineStrips2D)
``planner/ego_map``           the planner's ego map, the observation it decides on (Image,
                              32 x 32: obstacles red, explored floor light, unknown dark;
                              row 0 straight ahead), logged whenever the planner is to act
``planner/ego_map/agent``     the agent on the ego map (Points2D, pixel coordinates)
``planner/ego_map/goal``      the end goal on the ego map, clamped to its border
                              (Points2D)
``planner/ego_map/subgoal``   the sub-goal the planner proposed from this map (Points2D)
``planner/subgoal_index``     index k of the sub-goal an executor step served (Scalars;
                              -1: none)
``executor/rgb``              the executor's RGB image (Image)
``executor/depth``            its depth image (DepthImage, millimetres as uint16)
``eli/tensor``                the ELI the executor sent at this step (Tensor, 128)
``eli/projection``            every ELI of the episode so far through one fixed random
                              orthonormal projection to 2-D (the same in every recording),
                              coloured by sub-goal index, the latest one larger (Points2D)
``eli/pca``                   the episode's ELIs on their first two principal components
                              (in units of the first one's standard deviation), coloured
                              from dark (first step) to yellow (last) (Points2D, static, at
                              the end)
``eli/episode``               all of the episode's ELIs, one row per executor step (Tensor
                              (steps, 128), static, at the end)
``reward/planner``            the planner's reward of each step (Scalars)
``reward/executor``           the executor's reward of each step (Scalars)
``reward/agent``              the flat baselines' reward instead of the two above
                              (Scalars)
``metrics/distance_to_goal``  geodesic distance to the end goal (Scalars, m)
``metrics/collisions``        collisions so far (Scalars)
``metrics/success``           success at the episode's end (Scalars, 0/1)
``metrics/spl``               SPL at the episode's end (Scalars)
``events``                    sub-goals, executor STOPs and the episode's end (TextLog)
``episode``                   scene, episode id, geodesic distance and the result
                              (TextDocument, static)
``train/<key>``               training metrics (``metrics/success``, ``learner/...``,
                              ``perf/fps``...) on the ``train_step`` timeline (environment
                              steps), see :meth:`EpisodeRecorder.log_training_scalars`
============================  ==============================================================

Training recordings (:func:`record_training_episode`, called by the trainers every
``record_interval`` updates) run one greedy episode with the current networks on a
separate one-world env (the first episode of the ``val`` split, so that recordings of a
run are comparable) and add the run's training curves so far (``train/...``); their RGB
images are JPEG and images are at most 128 px, to keep long runs' recordings small.

Rows are buffered and sent as columns (``send_columns``) at the end of each episode (or
every ``flush_every`` steps), which costs a small fraction of logging every entity at
every step. :meth:`EpisodeRecorder.topdown` draws a recorded episode with
``topdown_view`` (map, path, goal, sub-goal, pose) for a PNG.

``spawn=True`` also streams every recording live to a Rerun viewer (``rr.spawn``: starts
one if none listens on port 9876); it needs a display.
"""

from __future__ import annotations

import math
import re
import shutil
import subprocess
import sys
import tempfile
import warnings
import weakref
from pathlib import Path

import numpy as np

APPLICATION_ID = "plex_ma"
TIMELINE = "step"
TRAIN_TIMELINE = "train_step"
ELI_PROJECTION_SEED = 20240601

ENTITY_PATHS: dict[str, str] = {
    "world": "Transform3D flipping y (north up in 2-D views); static",
    "world/map": "top-down map image placed in metres; static",
    "world/start": "start position; static",
    "world/goal": "end goal; static",
    "world/agent": "agent position",
    "world/agent/heading": "agent heading arrow",
    "world/path": "path so far",
    "world/collisions": "blocked moves so far",
    "world/subgoal": "active sub-goal (snapped)",
    "world/subgoal_raw": "active sub-goal as proposed",
    "world/subgoals": "all snapped sub-goals so far",
    "world/subgoals_raw": "all raw sub-goals so far",
    "world/subgoal_line": "agent to active sub-goal",
    "planner/ego_map": "planner's ego map observation",
    "planner/ego_map/agent": "agent on the ego map",
    "planner/ego_map/goal": "end goal on the ego map",
    "planner/ego_map/subgoal": "proposed sub-goal on the ego map",
    "planner/subgoal_index": "sub-goal served by each executor step",
    "executor/rgb": "executor RGB image",
    "executor/depth": "executor depth image",
    "eli/tensor": "ELI (128)",
    "eli/projection": "ELIs so far, fixed random 2-D projection",
    "eli/pca": "episode's ELIs on their first two principal components",
    "eli/episode": "all of the episode's ELIs as one (steps, 128) tensor",
    "reward/planner": "planner reward per step",
    "reward/executor": "executor reward per step",
    "reward/agent": "flat agent reward per step",
    "metrics/distance_to_goal": "geodesic distance to the goal (m)",
    "metrics/collisions": "collisions so far",
    "metrics/success": "success at the end",
    "metrics/spl": "SPL at the end",
    "events": "text log of decisions and the episode end",
    "episode": "episode description and result",
    "train/<key>": "training scalars on the train_step timeline",
}

# Colours (RGB).
_GOAL = (220, 30, 30)
_START = (30, 30, 200)
_AGENT = (20, 160, 60)
_PATH = (30, 110, 230)
_SUB = (250, 160, 0)
_SUB_RAW = (230, 120, 0)
_COLLISION = (160, 0, 160)
_PALETTE = np.array([(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189),
                     (140, 86, 75), (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207)], np.uint8)


# --------------------------------------------------------------------------- blueprint


def default_blueprint(map_extent: tuple[float, float, float, float] | None = None):
    """The layout sent with every recording: the top-down map with path and sub-goals on the
    left above the plots; the ego map, RGB and depth, the ELI and the event log on the right.

    ``map_extent`` (x_min, x_max, y_min, y_max in world metres) zooms the map view onto the
    scene (sub-goals proposed outside it are then off screen until one zooms out)."""
    import rerun.blueprint as rrb

    bounds = None
    if map_extent is not None:
        x0, x1, y0, y1 = map_extent
        bounds = rrb.VisualBounds2D(x_range=[x0, x1], y_range=[-y1, -y0])  # the view shows y flipped
    top_down = rrb.Spatial2DView(name="Top-down map (world)", origin="/", contents=["world/**"],
                                 visual_bounds=bounds)
    plots = rrb.Tabs(
        rrb.TimeSeriesView(name="Rewards", origin="reward"),
        rrb.TimeSeriesView(name="Distance to goal", origin="metrics/distance_to_goal"),
        rrb.TimeSeriesView(name="Collisions", origin="metrics/collisions"),
        rrb.TimeSeriesView(name="Sub-goal index", origin="planner/subgoal_index"),
        rrb.TimeSeriesView(name="Training (timeline train_step)", origin="train"),
    )
    images = rrb.Horizontal(
        rrb.Spatial2DView(name="Planner ego map", origin="planner/ego_map"),
        rrb.Spatial2DView(name="Executor RGB", origin="executor/rgb"),
        rrb.Spatial2DView(name="Executor depth", origin="executor/depth"),
    )
    eli = rrb.Tabs(
        rrb.Spatial2DView(name="ELI projection", origin="eli/projection",  # fixed axes: comparable across runs
                          visual_bounds=rrb.VisualBounds2D(x_range=[-4.0, 4.0], y_range=[-4.0, 4.0])),
        rrb.Spatial2DView(name="ELI PCA (episode)", origin="eli/pca",
                          visual_bounds=rrb.VisualBounds2D(x_range=[-4.0, 4.0], y_range=[-4.0, 4.0])),
        rrb.TensorView(name="ELI tensor", origin="eli/tensor"),
    )
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(top_down, plots, row_shares=[3, 2]),
            rrb.Vertical(images, eli, rrb.TextLogView(name="Events", origin="events"), row_shares=[2, 2, 1]),
            column_shares=[3, 2],
        ),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="expanded", timeline=TIMELINE),
    )


# --------------------------------------------------------------------------- helpers


def ego_map_rgb(ego: np.ndarray) -> np.ndarray:
    """(..., 2, S, S) ego maps (obstacles, explored floor in [0, 1]) -> (..., S, S, 3) uint8
    pictures: obstacles red, explored floor light, the rest dark."""
    obs = np.clip(ego[..., 0, :, :], 0, 1)[..., None]
    free = np.clip(ego[..., 1, :, :], 0, 1)[..., None]
    img = np.array([60, 60, 66], np.float32) * (1 - free) + np.array([225, 225, 220], np.float32) * free
    img = img * (1 - obs) + np.array([205, 55, 40], np.float32) * obs
    return img.astype(np.uint8)


def ego_pixel(polar: np.ndarray, size: int, cell: float, clamp: bool = True) -> np.ndarray:
    """(distance m, direction rad) from the agent -> (u, v) on the ego map (column, row): the
    agent sits at the centre, row 0 is straight ahead and column 0 to the agent's left."""
    rho, th = float(polar[0]), float(polar[1])
    fwd, left = rho * math.cos(th), rho * math.sin(th)
    u, v = size / 2 - left / cell, size / 2 - fwd / cell
    if clamp:
        u, v = min(max(u, 0.0), float(size)), min(max(v, 0.0), float(size))
    return np.array([u, v], np.float32)


def eli_projection_matrix(dim: int = 128, seed: int = ELI_PROJECTION_SEED) -> np.ndarray:
    """A fixed (dim, 2) orthonormal projection, the same in every recording."""
    q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(dim, 2)))
    return q.astype(np.float32)


def pca_2d(x: np.ndarray) -> np.ndarray:
    """(T, D) -> (T, 2) coordinates on the first two principal components, in units of the
    first one's standard deviation (zeros if the points hardly vary)."""
    x = np.asarray(x, np.float64)
    out = np.zeros((len(x), 2), np.float32)
    if len(x) < 2:
        return out
    xc = x - x.mean(0)
    if not np.any(xc):
        return out
    _, _, vt = np.linalg.svd(xc, full_matrices=False)
    k = min(2, vt.shape[0])
    y = xc @ vt[:k].T
    sd = y[:, 0].std()
    if sd < 1e-6:
        return out
    out[:, :k] = (y / sd).astype(np.float32)
    return out


def _time_colours(n: int) -> np.ndarray:
    """Dark blue -> green -> yellow over n points."""
    t = np.linspace(0, 1, max(n, 1))[:, None]
    a, b, c = np.array([68, 1, 84]), np.array([33, 145, 140]), np.array([253, 231, 37])
    col = np.where(t < 0.5, a + (b - a) * (t / 0.5), b + (c - b) * ((t - 0.5) / 0.5))
    return col[:n].astype(np.uint8)


def tensor_column(x: np.ndarray, dim_name: str):
    """Rows of ``x`` (T, D) float32 as one column of 1-D ``Tensor`` values, for
    ``send_columns`` (rerun's Python API converts tensors one at a time, ~0.6 ms each).
    The arrow layout is taken from a tensor rerun converted itself."""
    import pyarrow as pa
    import rerun as rr

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


def _jpeg(img: np.ndarray, quality: int) -> bytes:
    import io

    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="JPEG", quality=quality)
    return buf.getvalue()


def _entity(key: str) -> str:
    """A metric name as an entity path below ``train/``."""
    parts = [re.sub(r"[^A-Za-z0-9_.\-]", "_", p) for p in str(key).split("/") if p]
    return "train/" + "/".join(parts or ["_"])


def rerun_executable() -> str:
    """The ``rerun`` CLI that ships with rerun-sdk (falls back to the one on PATH)."""
    try:
        import rerun_cli

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
    import os

    if shutil.which("rerun") is None:
        os.environ["PATH"] = str(Path(rerun_executable()).parent) + os.pathsep + os.environ.get("PATH", "")


def merge_rrd(parts: list[Path], out: Path) -> None:
    """Write the recordings of several .rrd files into one (``rerun rrd merge``)."""
    tmp = out.with_name(f".{out.name}.merging")
    r = subprocess.run([rerun_executable(), "rrd", "merge", *map(str, parts), "-o", str(tmp)],
                       capture_output=True, text=True)
    if r.returncode != 0 or not tmp.exists():
        tmp.unlink(missing_ok=True)
        raise RuntimeError(f"rerun rrd merge failed ({r.returncode}): {r.stderr.strip()[-2000:]}")
    tmp.replace(out)


def send_training_scalars(rec, records: list[dict]) -> None:
    """Log metric lines (dicts with ``step``) to ``rec`` as ``train/<name>`` Scalars on the
    ``train_step`` timeline, one column per metric."""
    import rerun as rr

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
        rec.send_columns(_entity(k), indexes=[rr.TimeColumn(TRAIN_TIMELINE, sequence=steps)],
                         columns=rr.Scalars.columns(scalars=values))


# --------------------------------------------------------------------------- recorder


class _Episode:
    """One episode being recorded: its rerun stream, its history and the rows not yet sent.

    Rows are buffered as ``rows[key] = [(step, value), ...]`` and sent as columns
    (``send_columns``) when the episode ends or ``flush_every`` steps have gathered: one
    call per entity instead of one per entity and step."""

    def __init__(self, rec, file: Path, index: int, name: str):
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
        self.rows.setdefault(key, []).append((self.t, value))


class EpisodeRecorder:
    """Record the episodes of one world of a vector env into ``path`` (see the module docstring).

    Args:
        path: the ``.rrd`` file to write (its directory is created).
        world: which world of the env to follow.
        max_episodes: stop recording after this many complete episodes (None: all). The
            default keeps ``evaluate --record`` files small: world 0's first 10 episodes.
        images: log the RGB, depth and ego map images (most of a recording's size).
        jpeg_quality: store RGB images as JPEG of this quality (None: raw pixels).
        spawn: also stream live to a Rerun viewer (``rr.spawn``; needs a display).
        name: prefix of the recordings' names (e.g. ``update 50``).
        flush_every: executor steps buffered before they are sent (1 with ``spawn``).
        max_image_size: subsample RGB and depth images larger than this (by a whole stride).

    The protocol (:func:`plex_ma.trainers.evaluation.run_episodes` drives it): ``begin(env)`` after
    ``env.reset()``, ``step(env, res, rows=rows)`` after a planner step,
    ``step(env, res, eli=eli)`` after an executor step (``res`` the ``PlexVecStep``; for a
    ``PointNavVectorEnv`` the tuple its ``step`` returns), and ``end()`` once, which
    writes the file. ``episodes`` then lists what was recorded.
    """

    def __init__(self, path: str | Path, world: int = 0, max_episodes: int | None = 10, images: bool = True,
                 jpeg_quality: int | None = None, spawn: bool = False, name: str | None = None,
                 flush_every: int | None = None, max_image_size: int | None = None):
        import rerun  # noqa: F401  (fail early if rerun-sdk is missing)

        self.path = Path(path)
        self.world = int(world)
        self.max_episodes = max_episodes
        self.images = images
        self.jpeg_quality = jpeg_quality
        self.spawn = spawn
        self.name = name
        self.flush_every = flush_every if flush_every is not None else (1 if spawn else 100)
        self.max_image_size = max_image_size
        self._stride = 1
        self.episodes: list[dict] = []
        self._ep: _Episode | None = None
        self._done: list[_Episode] = []
        self._count = 0
        self._env = None
        self._plex = False
        self._final_pose = None
        self._wrapper = None
        self._tmpdir: Path | None = None
        self._proj = eli_projection_matrix()
        self._spawned = False
        self._train_rec: _Episode | None = None
        self._pending_train: list[dict] = []
        self._blueprint = default_blueprint()

    # ------------------------------------------------------------------ protocol
    def begin(self, env) -> None:
        """Start following ``env``'s world (call after ``env.reset()``)."""
        if self._env is not None:
            raise RuntimeError("EpisodeRecorder.begin() called twice; use one recorder per run")
        if not 0 <= self.world < env.num_envs:
            raise ValueError(f"world {self.world} is not in an env of {env.num_envs} worlds")
        self._env = env
        self._plex = hasattr(env.worlds, "subgoal")
        self._make_tmpdir()
        # The vector env resets a world as soon as its episode ends, before this recorder
        # hears of it: keep the pose the episode ended at.
        worlds = env.worlds
        orig = worlds.reset_rows
        w = self.world

        def reset_rows(rows, *args, **kwargs):
            if w in np.asarray(rows).reshape(-1):
                self._final_pose = (worlds.sim.pos[w].copy(), float(worlds.sim.heading[w]))
            return orig(rows, *args, **kwargs)

        self._wrapper = reset_rows
        worlds.reset_rows = reset_rows
        self._start_episode()

    def step(self, env, res, rows=None, eli=None) -> None:
        """Log what the last ``env.step`` did in the followed world."""
        ep = self._ep
        if ep is None or env is not self._env:
            return
        w = self.world
        if not self._plex:
            self._flat_step(ep, res)
            return
        acted = int(res.acted[w])
        if acted < 0:
            return
        ended_rows = np.flatnonzero(res.terminated | res.truncated)
        ended = w in ended_rows
        info = res.episode_infos[int(np.searchsorted(ended_rows, w))] if ended else None
        if acted == 0:  # the planner
            self._planner_step(ep, res, ended, info)
        else:
            self._executor_step(ep, res, eli, ended, info, ended_rows)
        if ended:
            self._finish(ep, info, stopped=acted == 0)
        elif ep.unsent >= self.flush_every:
            self._flush(ep)

    def end(self) -> list[dict]:
        """Close the recordings and write the file; returns ``episodes``."""
        if self._env is not None and vars(self._env.worlds).get("reset_rows") is self._wrapper:
            del self._env.worlds.reset_rows  # the instance attribute set in begin()
        keep = list(self._done)
        if self._ep is not None:
            self._flush(self._ep)
            self._close_stream(self._ep)
            if not keep:  # nothing complete: keep what there is rather than nothing
                keep.append(self._ep)
                self.episodes.append(self._summary(self._ep))
            self._ep = None
        if self._pending_train and self._env is None:  # training scalars only
            self._make_tmpdir()
            self._training_stream()
        if self._train_rec is not None:
            self._close_stream(self._train_rec)
            keep.append(self._train_rec)
            self._train_rec = None
        if self._tmpdir is None:
            return self.episodes
        files = [e.file for e in keep if e.file.exists()]
        try:
            if len(files) == 1:
                files[0].replace(self.path)
            elif files:
                merge_rrd(files, self.path)
        finally:
            shutil.rmtree(self._tmpdir, ignore_errors=True)
            self._tmpdir = None
        return self.episodes

    # ------------------------------------------------------------------ training scalars
    def log_training_scalars(self, step: int, metrics: dict) -> None:
        """Log ``metrics`` (name -> number) as ``train/<name>`` at ``train_step = step``.

        They go into the episode being recorded; before ``begin`` they wait for the first
        episode; after the last one they go into a recording named ``training``."""
        self.log_training_history([{**metrics, "step": int(step)}])

    def log_training_history(self, records: list[dict]) -> None:
        """Log many metric lines at once (dicts with ``step``, as in ``metrics.jsonl``)."""
        if self._env is None:
            self._pending_train.extend(records)
            return
        rec = self._ep.rec if self._ep is not None else self._training_stream()
        send_training_scalars(rec, records)

    def _training_stream(self):
        if self._train_rec is None:
            self._train_rec = self._open("training")
        return self._train_rec.rec

    # ------------------------------------------------------------------ streams
    def _make_tmpdir(self) -> None:
        if self._tmpdir is None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._tmpdir = Path(tempfile.mkdtemp(prefix=f".{self.path.name}.", dir=self.path.parent))

    def _open(self, name: str, blueprint=None) -> _Episode:
        import uuid

        import rerun as rr

        n = self._count
        self._count += 1
        rec = rr.RecordingStream(APPLICATION_ID, recording_id=f"{self.path.stem}-{n:04d}-{uuid.uuid4().hex[:12]}")
        rec.set_log_time_enabled(False)
        rec.set_log_tick_enabled(False)
        file = self._tmpdir / f"part_{n:04d}.rrd"
        if self.spawn:
            if not self._spawned:
                _put_rerun_on_path()
                rec.spawn(connect=False)
                self._spawned = True
            rec.set_sinks(rr.FileSink(str(file)), rr.GrpcSink(), default_blueprint=blueprint or self._blueprint)
        else:
            rec.save(file, default_blueprint=blueprint or self._blueprint)
        full = f"{self.name}: {name}" if self.name else name
        rec.send_recording_name(full)
        if self._pending_train:
            send_training_scalars(rec, self._pending_train)
        return _Episode(rec, file, n, full)

    @staticmethod
    def _close_stream(ep: _Episode) -> None:
        ep.rec.flush()
        ep.rec.disconnect()

    # ------------------------------------------------------------------ episodes
    def _start_episode(self) -> None:
        import rerun as rr

        if self.max_episodes is not None and len(self._done) >= self.max_episodes:
            self._ep = None
            return
        env, w = self._env, self.world
        worlds = env.worlds
        sim = worlds.sim
        episode = sim.episodes[w]
        grid = worlds.bank.grids[int(sim.scene_idx[w])]
        (ox, oy), (h, wd) = grid.origin, grid.shape
        m = 0.5
        extent = (ox - m, ox + wd * grid.cell_size + m, oy - m, oy + h * grid.cell_size + m)
        ep = self._open(f"episode {len(self._done)}: {episode.scene_id} #{episode.episode_id}",
                        default_blueprint(extent))
        self._ep = ep
        rec = ep.rec
        ep.description = (f"**scene** `{episode.scene_id}`, **episode** {episode.episode_id}, "
                          f"**geodesic distance** {episode.geodesic_distance:.2f} m, "
                          f"**agent** {'PLEX (planner + executor)' if self._plex else 'flat PointNav'}")
        rec.log("episode", rr.TextDocument(ep.description, media_type="text/markdown"), static=True)
        ep.grid, ep.goal = grid, np.asarray(episode.goal_position)
        r = sim.resolution
        self._stride = max(1, -(-r // self.max_image_size)) if self.max_image_size else 1
        self._log_static(rec, ep.grid, episode, len(range(0, r, self._stride)))
        pos = sim.pos[w].copy()
        ep.path.append((float(pos[0]), float(pos[1])))
        ep.heading = float(sim.heading[w])
        ep.add("agent", (pos, ep.heading))
        ep.add("scalar:metrics/distance_to_goal", float(sim.distance_to_goal[w]))
        ep.add("scalar:metrics/collisions", 0.0)
        if self.images:
            ep.add("images", (sim.rgb[w].copy(), sim.depth[w].copy()))
        if self._plex and int(worlds.turn[w]) == 0:
            self._add_ego_map(ep, sim.egomap(np.array([w]))[0])
        if self.flush_every <= 1:
            self._flush(ep)

    def _log_static(self, rec, grid, episode, resolution: int) -> None:
        """What does not change during an episode: the map, start and goal, and the styles
        (colours, sizes, image formats) of the entities logged as columns later."""
        import rerun as rr

        from plex_ma.envs.sim.topdown import topdown_view

        ppm = 20.0  # map pixels per metre
        img = topdown_view(grid, px_per_m=ppm)
        h_m = grid.shape[0] * grid.cell_size
        log = lambda path, *a: rec.log(path, *a, static=True)  # noqa: E731
        log("world", rr.Transform3D(scale=[1.0, -1.0, 1.0]))
        log("world/map", rr.Transform3D(translation=[grid.origin[0], grid.origin[1] + h_m, 0.0],
                                        scale=[1.0 / ppm, -1.0 / ppm, 1.0]))
        log("world/map", rr.Image(img))
        log("world/start", rr.Points2D([episode.start_position], radii=0.15, colors=[_START], labels=["start"]))
        log("world/goal", rr.Points2D([episode.goal_position], radii=0.2, colors=[_GOAL], labels=["goal"]))
        log("world/agent", rr.Points2D.from_fields(radii=0.15, colors=[_AGENT]))
        log("world/agent/heading", rr.Arrows2D.from_fields(radii=0.04, colors=[_AGENT]))
        log("world/path", rr.LineStrips2D.from_fields(radii=0.04, colors=[_PATH]))
        log("world/collisions", rr.Points2D.from_fields(radii=0.07, colors=[_COLLISION]))
        log("metrics/distance_to_goal", rr.SeriesLines(names="distance to goal (m)", colors=[_GOAL]))
        log("metrics/collisions", rr.SeriesLines(names="collisions", colors=[_COLLISION]))
        log("metrics/success", rr.SeriesPoints(names="success", colors=[_AGENT]))
        log("metrics/spl", rr.SeriesPoints(names="SPL", colors=[_PATH]))
        if self.images:
            if not self.jpeg_quality:
                log("executor/rgb", rr.Image.from_fields(format=rr.components.ImageFormat(
                    width=resolution, height=resolution, color_model="RGB", channel_datatype="U8")))
            log("executor/depth", rr.DepthImage.from_fields(format=rr.components.ImageFormat(
                width=resolution, height=resolution, channel_datatype="U16"), meter=1000.0))
        if self._plex:
            log("world/subgoal", rr.Points2D.from_fields(radii=0.12, colors=[_SUB]))
            log("world/subgoal_raw", rr.Points2D.from_fields(radii=0.08, colors=[_SUB_RAW]))
            log("world/subgoals", rr.Points2D.from_fields(radii=0.08))
            log("world/subgoals_raw", rr.Points2D.from_fields(radii=0.05))
            log("world/subgoal_line", rr.LineStrips2D.from_fields(radii=0.02, colors=[_SUB]))
            log("reward/planner", rr.SeriesLines(names="planner", colors=[_PATH]))
            log("reward/executor", rr.SeriesLines(names="executor", colors=[_SUB]))
            log("planner/subgoal_index", rr.SeriesLines(names="sub-goal index", colors=[_SUB_RAW]))
            if self.images:
                s = 32
                log("planner/ego_map", rr.Image.from_fields(format=rr.components.ImageFormat(
                    width=s, height=s, color_model="RGB", channel_datatype="U8")))
                log("planner/ego_map/agent", rr.Points2D([[s / 2, s / 2]], radii=0.8, colors=[_AGENT]))
                log("planner/ego_map/goal", rr.Points2D.from_fields(radii=0.8, colors=[_GOAL]))
                log("planner/ego_map/subgoal", rr.Points2D.from_fields(radii=0.8, colors=[_SUB]))
        else:
            log("reward/agent", rr.SeriesLines(names="agent", colors=[_PATH]))

    def _add_ego_map(self, ep: _Episode, ego: np.ndarray) -> None:
        if not self.images:
            return
        sim, w = self._env.worlds.sim, self.world
        polar = sim.polar_to(sim.goal[w:w + 1], np.array([w]))[0]
        ep.add("ego", (np.array(ego, np.float32), ego_pixel(polar, ego.shape[-1], sim.ego_cell)))

    def _planner_step(self, ep: _Episode, res, ended: bool, info) -> None:
        w = self.world
        r = float(res.rewards[w, 0])
        ep.returns[0] += r
        if ended:  # the planner chose STOP
            ep.add("scalar:reward/planner", r)
            ep.add("events", (f"step {ep.t}: planner STOP, {info['distance_to_goal']:.2f} m from the goal", "INFO"))
            return
        worlds = self._env.worlds
        sim = worlds.sim
        sg, raw = worlds.subgoal[w].copy(), worlds.subgoal_raw[w].copy()
        ep.k += 1
        ep.subgoals.append((float(sg[0]), float(sg[1])))
        ep.subgoals_raw.append((float(raw[0]), float(raw[1])))
        ep.add("subgoals", len(ep.subgoals))
        pos = sim.pos[w].copy()
        ep.add("subgoal_line", np.stack([pos, sg]).astype(np.float32))
        if self.images:
            polar = sim.polar_to(raw[None], np.array([w]))[0]
            ep.add("ego_subgoal", ego_pixel(polar, sim.ego_size, sim.ego_cell))
        d = float(np.hypot(*(raw - pos)))
        snap = float(np.hypot(*(raw - sg)))
        ep.add("events", (f"step {ep.t}: sub-goal #{ep.k} at ({sg[0]:.2f}, {sg[1]:.2f}), {d:.2f} m from the agent"
                          + (f", snapped {snap:.2f} m from the proposed ({raw[0]:.2f}, {raw[1]:.2f})"
                             if snap > 1e-3 else ""), "INFO"))

    def _moved(self, ep: _Episode, ended: bool, info) -> tuple[np.ndarray, float, int]:
        """After an action: log the pose, path, distance and collisions; returns them."""
        worlds, w = self._env.worlds, self.world
        sim = worlds.sim
        ep.t += 1
        if ended:
            pos, heading = self._final_pose if self._final_pose is not None else (sim.pos[w].copy(),
                                                                                  float(sim.heading[w]))
            dist, coll = float(info["distance_to_goal"]), int(info["collisions"])
        else:
            pos, heading = sim.pos[w].copy(), float(sim.heading[w])
            dist, coll = float(sim.distance_to_goal[w]), int(worlds.collisions[w])
        ep.path.append((float(pos[0]), float(pos[1])))
        ep.heading = heading
        ep.add("agent", (pos, heading))
        ep.add("scalar:metrics/distance_to_goal", dist)
        ep.add("scalar:metrics/collisions", float(coll))
        if coll != ep.collisions:
            ep.collision_points.append((float(pos[0]), float(pos[1])))
            ep.collisions = coll
            ep.add("collisions", len(ep.collision_points))
        ep.unsent += 1
        return pos, dist, coll

    def _executor_step(self, ep: _Episode, res, eli, ended: bool, info, ended_rows) -> None:
        w = self.world
        pos, _, _ = self._moved(ep, ended, info)
        if ended:
            j = int(np.searchsorted(ended_rows, w))
            rgb, depth = res.final_executor_obs["rgb"][j], res.final_executor_obs["depth"][j]
        else:
            rgb, depth = res.executor_obs["rgb"][w], res.executor_obs["depth"][w]
        r_pl, r_ex = float(res.rewards[w, 0]), float(res.rewards[w, 1])
        ep.returns += (r_pl, r_ex)
        ep.add("scalar:reward/planner", r_pl)
        ep.add("scalar:reward/executor", r_ex)
        ep.add("scalar:planner/subgoal_index", float(ep.k))
        if ep.k >= 0:
            ep.add("subgoal_line", None if res.executor_turn_end[w] else
                   np.stack([pos, np.asarray(ep.subgoals[-1])]).astype(np.float32))
        if self.images:
            ep.add("images", (np.array(rgb), np.array(depth)))
        if eli is not None:
            ep.elis.append(np.asarray(eli, np.float32)[w].copy())
            ep.eli_k.append(ep.k)
            ep.add("eli", len(ep.elis))
        if res.executor_stopped[w]:
            d_sub = float(np.hypot(*(pos - np.asarray(ep.subgoals[-1])))) if ep.k >= 0 else float("nan")
            reached = getattr(res, "executor_reached", None)
            note = "" if reached is None else (" (reached)" if reached[w] else " (not reached)")
            ep.add("events", (f"step {ep.t}: executor STOP for sub-goal #{ep.k}, {d_sub:.2f} m from it{note}",
                              "INFO"))
        if not ended and int(res.turn[w]) == 0:
            self._add_ego_map(ep, res.planner_obs["ego_map"][w])

    def _flat_step(self, ep: _Episode, res) -> None:
        obs, rew, term, trunc, infos = res
        w = self.world
        ended_rows = np.flatnonzero(np.asarray(term) | np.asarray(trunc))
        ended = w in ended_rows
        info = infos[int(np.searchsorted(ended_rows, w))] if ended else None
        self._moved(ep, ended, info)
        r = float(rew[w])
        ep.returns[0] += r
        ep.add("scalar:reward/agent", r)
        if self.images and not ended:  # the flat env keeps no final images of an ended episode
            ep.add("images", (np.array(obs["rgb"][w]), np.array(obs["depth"][w])))
        if ended:
            self._finish(ep, info, stopped=bool(np.asarray(term)[w]))
        elif ep.unsent >= self.flush_every:
            self._flush(ep)

    def _finish(self, ep: _Episode, info: dict, stopped: bool) -> None:
        import rerun as rr

        success, spl = float(info["success"]), float(info["spl"])
        ep.add("scalar:metrics/success", success)
        ep.add("scalar:metrics/spl", spl)
        how = "stopped" if stopped else "truncated"
        ep.add("events", (f"step {ep.t}: episode {how}: success {success:.0f}, SPL {spl:.3f}, "
                          f"{info['distance_to_goal']:.2f} m from the goal, {info['collisions']} collisions",
                          "INFO" if success else "WARN"))
        self._flush(ep)
        rec = ep.rec
        if ep.elis:
            x = np.stack(ep.elis)
            rec.log("eli/episode", rr.Tensor(x, dim_names=["step", "eli"]), static=True)
            if len(x) >= 2:
                rec.log("eli/pca", rr.Points2D(pca_2d(x), colors=_time_colours(len(x)),
                                               radii=rr.Radius.ui_points(3.0)), static=True)
        ep.finished = True
        ep.result = {"success": success, "spl": spl, "distance_to_goal": float(info["distance_to_goal"]),
                     "collisions": int(info["collisions"]), "steps": int(info["steps"]), "ended_by": how}
        rec.log("episode", rr.TextDocument(
            ep.description + f"\n\n**result**: {how} after {ep.t} steps, success {success:.0f}, SPL {spl:.3f}, "
            f"{ep.k + 1} sub-goals, {ep.result['collisions']} collisions", media_type="text/markdown"), static=True)
        self._close_stream(ep)
        self._done.append(ep)
        self.episodes.append(self._summary(ep))
        self._final_pose = None
        self._start_episode()

    def _summary(self, ep: _Episode) -> dict:
        out = {"recording": ep.name, "steps": ep.t, "subgoals": ep.k + 1, "finished": ep.finished, **ep.result}
        if self._plex:
            out["return_planner"], out["return_executor"] = float(ep.returns[0]), float(ep.returns[1])
        else:
            out["return"] = float(ep.returns[0])
        return out

    def topdown(self, index: int = -1, px_per_m: float = 40.0) -> np.ndarray:
        """The top-down picture (``topdown_view``) of recorded episode ``index``: the map,
        the whole path, the goal, the last sub-goal (raw and snapped) and the final pose."""
        from plex_ma.envs.sim.topdown import topdown_view

        eps = self._done + ([self._ep] if self._ep is not None else [])
        ep = eps[index]
        last = ep.path[-1]
        return topdown_view(ep.grid, path=np.asarray(ep.path), goal=ep.goal,
                            subgoal=ep.subgoals[-1] if ep.subgoals else None,
                            subgoal_raw=ep.subgoals_raw[-1] if ep.subgoals_raw else None,
                            agent_pose=(last[0], last[1], ep.heading), px_per_m=px_per_m)

    # ------------------------------------------------------------------ sending
    def _flush(self, ep: _Episode) -> None:
        """Send the buffered rows as columns, one ``send_columns`` per entity."""
        import rerun as rr

        rows, ep.rows, ep.unsent = ep.rows, {}, 0
        rec = ep.rec

        def send(entity, times, columns):
            rec.send_columns(entity, indexes=[rr.TimeColumn(TIMELINE, sequence=times)], columns=columns)

        def cumulative(points, counts, **per_point):
            """Rows holding the first ``counts[i]`` points (Points2D columns, partitioned)."""
            pts = np.asarray(points, np.float32).reshape(-1, 2)
            idx = np.concatenate([np.arange(c) for c in counts]) if counts else np.zeros(0, np.int64)
            cols = {k: (np.asarray(v)[idx] if not isinstance(v, list) else [v[i] for i in idx])
                    for k, v in per_point.items()}
            return rr.Points2D.columns(positions=pts[idx], **cols).partition(counts)

        for key, items in rows.items():
            times = np.array([t for t, _ in items], np.int64)
            vals = [v for _, v in items]
            if key.startswith("scalar:"):
                send(key[7:], times, rr.Scalars.columns(scalars=np.asarray(vals, np.float64)))
            elif key == "agent":
                pos = np.array([p for p, _ in vals], np.float32)
                h = np.array([a for _, a in vals])
                send("world/agent", times, rr.Points2D.columns(positions=pos))
                send("world/agent/heading", times, rr.Arrows2D.columns(
                    origins=pos, vectors=0.5 * np.stack([np.cos(h), np.sin(h)], 1).astype(np.float32)))
                # the path so far: every row repeats the path up to its step
                path = np.asarray(ep.path, np.float32)
                first = len(ep.path) - len(vals)  # each row added one point to the path
                send("world/path", times, rr.LineStrips2D.columns(
                    strips=[path[: first + i + 1] for i in range(len(vals))]))
            elif key == "images":
                k = self._stride
                rgb = np.ascontiguousarray(np.stack([a for a, _ in vals])[:, ::k, ::k])
                depth = np.stack([d for _, d in vals])[:, ::k, ::k, 0]
                if self.jpeg_quality:
                    blobs = [_jpeg(im, int(self.jpeg_quality)) for im in rgb]
                    send("executor/rgb", times, rr.EncodedImage.columns(blob=blobs,
                                                                        media_type=["image/jpeg"] * len(blobs)))
                else:
                    send("executor/rgb", times, rr.Image.columns(buffer=rgb.reshape(len(rgb), -1)))
                mm = np.round(depth * 10000.0).astype(np.uint16)  # depth is metres / 10 -> millimetres
                send("executor/depth", times, rr.DepthImage.columns(buffer=mm.reshape(len(mm), -1).view(np.uint8)))
            elif key == "ego":
                ego = ego_map_rgb(np.stack([a for a, _ in vals]))
                send("planner/ego_map", times, rr.Image.columns(buffer=ego.reshape(len(ego), -1)))
                send("planner/ego_map/goal", times, rr.Points2D.columns(positions=np.stack([g for _, g in vals])))
            elif key == "ego_subgoal":
                send("planner/ego_map/subgoal", times, rr.Points2D.columns(positions=np.stack(vals)))
            elif key == "subgoals":
                counts = [int(c) for c in vals]
                send("world/subgoal", times, rr.Points2D.columns(
                    positions=np.asarray([ep.subgoals[c - 1] for c in counts], np.float32),
                    labels=[f"#{c - 1}" for c in counts]))
                send("world/subgoal_raw", times, rr.Points2D.columns(
                    positions=np.asarray([ep.subgoals_raw[c - 1] for c in counts], np.float32)))
                n = max(counts)
                colours = _PALETTE[np.arange(n) % len(_PALETTE)]
                send("world/subgoals", times, cumulative(ep.subgoals[:n], counts, colors=colours))
                send("world/subgoals_raw", times, cumulative(ep.subgoals_raw[:n], counts, colors=colours))
            elif key == "subgoal_line":
                strips = [s for s in vals if s is not None]
                send("world/subgoal_line", times, rr.LineStrips2D.columns(strips=strips).partition(
                    [0 if s is None else 1 for s in vals]))
            elif key == "collisions":
                counts = [int(c) for c in vals]
                send("world/collisions", times, cumulative(ep.collision_points[:max(counts)], counts))
            elif key == "eli":
                counts = [int(c) for c in vals]
                n = max(counts)
                x = np.stack(ep.elis[:n])
                rows_x = x[np.asarray(counts) - 1]
                try:
                    send("eli/tensor", times, [tensor_column(rows_x, "eli")])
                except Exception:  # an arrow layout this code does not know: one call per step
                    for t, e in zip(times, rows_x):
                        rec.set_time(TIMELINE, sequence=int(t))
                        rec.log("eli/tensor", rr.Tensor(e, dim_names=["eli"]))
                    rec.reset_time()
                colours = _PALETTE[np.maximum(np.asarray(ep.eli_k[:n]), 0) % len(_PALETTE)]
                pts = x @ self._proj
                idx = np.concatenate([np.arange(c) for c in counts])
                last = np.concatenate([np.arange(c) == c - 1 for c in counts])
                send("eli/projection", times, rr.Points2D.columns(  # radii in UI points (negative)
                    positions=pts[idx], colors=colours[idx], radii=np.where(last, -6.0, -2.5).astype(np.float32),
                ).partition(counts))
            elif key == "events":
                send("events", times, rr.TextLog.columns(text=[s for s, _ in vals], level=[lv for _, lv in vals]))
            else:  # pragma: no cover
                raise KeyError(key)


# --------------------------------------------------------------------------- training hook

_train_state: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def record_training_episode(trainer, path: str | Path | None = None, raise_errors: bool = False) -> Path | None:
    """Record one greedy episode of ``trainer``'s current networks into its run dir.

    Writes ``run_dir/recordings/update_<updates>.rrd`` (or ``path``): the first episode of
    the ``val`` split (``train`` if the scene source has no val split) on a separate
    one-world env, run by :func:`plex_ma.trainers.evaluation.run_episodes`, with the run's training
    curves so far (``train/...`` from ``metrics.jsonl``) in the same recording. Training
    is not disturbed: the actions are greedy (no sampling, so no RNG is drawn from) and
    the env is the recorder's own. A failure is reported as a warning and training goes
    on (``raise_errors=True`` raises instead). Returns the file, or None after a failure.
    """
    from plex_ma.trainers.evaluation import run_episodes
    from plex_ma.trainers.logger import read_metrics

    import torch

    cfg = trainer.cfg
    updates = int(trainer.updates.get("executor", trainer.updates.get("policy", 0)))
    out = Path(path) if path is not None else Path(cfg.run_dir) / "recordings" / f"update_{updates:06d}.rrd"
    state = _train_state.setdefault(trainer, {})
    nets = trainer.nets
    modes = {k: m.training for k, m in nets.items()}
    threads = torch.get_num_threads()
    # Batch-1 inference gains nothing from more threads, and their spin-waiting beside
    # other busy processes made one episode up to ten times slower.
    torch.set_num_threads(1)
    try:
        rec = EpisodeRecorder(out, max_episodes=1, name=f"update {updates} (step {trainer.step:,})",
                              jpeg_quality=85, max_image_size=128)
        try:
            rec.log_training_history(read_metrics(cfg.run_dir))
        except OSError:
            pass
        for m in nets.values():
            m.eval()
        splits = [state["split"]] if "split" in state else ["val", "train"]
        for split in splits:
            try:
                run_episodes(cfg, nets, split=split, episodes=1, num_envs=1, recorder=rec)
            except (ValueError, FileNotFoundError, KeyError):
                if rec._env is not None or split == splits[-1]:
                    raise
                continue  # no such split for this scene source: the env was never built
            state["split"] = split
            break
        return out
    except Exception as e:  # a recording must not end a long training run
        if raise_errors:
            raise
        warnings.warn(f"recording an episode at update {updates} failed: {type(e).__name__}: {e}", stacklevel=2)
        return None
    finally:
        for k, m in nets.items():
            m.train(modes[k])
        torch.set_num_threads(threads)


__all__ = ["APPLICATION_ID", "ENTITY_PATHS", "EpisodeRecorder", "TIMELINE", "TRAIN_TIMELINE", "default_blueprint",
           "ego_map_rgb", "eli_projection_matrix", "merge_rrd", "pca_2d", "record_training_episode",
           "send_training_scalars"]
