"""PointGoal episodes by Habitat's generator rules, and fixed episode files.

Rules (Habitat's PointNav generator, docs/spec.md section 1): start and goal are navigable and
connected; the geodesic distance lies in [1, 30] m; an episode whose geodesic/euclidean
ratio is below 1.1 is kept only with probability ``20 * (ratio - 0.98) ** 2``; the start
heading is uniform.

Episode files are gzipped JSON: ``{"version": 1, "episodes": [record, ...]}`` with one
record per episode: ``episode_id``, ``scene_id``, ``start_position`` [x, y],
``start_heading`` (radians), ``goal_position`` [x, y], ``geodesic_distance`` (m).
Positions are 2-D floor coordinates (our floor is flat; Habitat's height axis is dropped).
"""

from __future__ import annotations

import gzip
import json
import math
import os
import tempfile
import zlib
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from numba import njit

from . import kernels as K
from .bank import SceneBank

MIN_GEODESIC = 1.0
MAX_GEODESIC = 30.0
RATIO_THRESHOLD = 1.1
FILE_VERSION = 1

DATA_DIR = Path(__file__).resolve().parent / "data" / "episodes"

#: Close (below) / far (at or above) split of the start-to-goal geodesic distance (m), paper Fig. 5b.
CLOSE_FAR_SPLIT = 5.76

#: (scenes, split) -> (number of episodes, seed) of the shipped default episode files.
DEFAULT_FILES: dict[tuple[str, str], tuple[int, int]] = {
    ("procgen", "val"): (500, 1),
    ("procgen", "test"): (1000, 2),
}


def default_episode_file(scenes: str, split: str) -> Path:
    """Path of the shipped fixed episode file of a scene source and split.

    Raises ``ValueError`` for a split other than ``val``/``test`` (training samples
    episodes on the fly) and ``FileNotFoundError`` when no file is shipped for the pair.
    """
    if split not in ("val", "test"):
        raise ValueError(f"fixed episode files exist for the 'val' and 'test' splits, not {split!r} "
                         "(training samples its episodes on the fly)")
    path = DATA_DIR / f"{scenes}_{split}.json.gz"
    if not path.is_file():
        have = sorted(p.name for p in DATA_DIR.glob("*.json.gz")) if DATA_DIR.is_dir() else []
        raise FileNotFoundError(
            f"no fixed episode file for scenes={scenes!r} split={split!r} (expected {path}; shipped: {have}); "
            f"make one with: python -m plex_ma.episodes make --scenes {scenes} --split {split} --out {path}")
    return path


class EpisodeFileError(ValueError):
    """An episode file is missing, corrupt, truncated or malformed; the message says which."""


@dataclass(frozen=True)
class Episode:
    episode_id: int
    scene_id: str
    start_position: tuple[float, float]
    start_heading: float
    goal_position: tuple[float, float]
    geodesic_distance: float

    def to_record(self) -> dict:
        d = asdict(self)
        d["start_position"] = list(self.start_position)
        d["goal_position"] = list(self.goal_position)
        return d


@njit(cache=True)
def ratio_keep_probability(ratio: float) -> float:
    """Habitat's acceptance probability for an episode with geodesic/euclidean ``ratio``."""
    if ratio >= RATIO_THRESHOLD:
        return 1.0
    return 20.0 * (ratio - 0.98) ** 2


class Geodesics:
    """Scratch space for the Dijkstra and A* kernels over one scene bank (not thread-safe)."""

    def __init__(self, bank: SceneBank):
        self.bank = bank
        n = bank.max_cells
        self.hk = np.empty(n, np.float64)
        self.hv = np.empty(n, np.int64)
        self.hpos = np.empty(n, np.int64)
        self.g = np.empty(n, np.float64)
        self.stamp = np.zeros(n, np.int64)
        self._stamp = 0
        self.ring = np.empty((3, n), np.int32)
        self.label = np.empty(n, np.int64)
        self._cells: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def field(self, s: int, goal: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """Distance field to ``goal`` over scene ``s``: (h*w,) float32, INF where unreachable."""
        nav, moves, off, h, w, ox, oy, cs = self.bank.search_args(s)
        dist = np.empty(h * w, np.float64)
        K.dijkstra_field(nav, moves, off, h, w, ox, oy, cs, float(goal[0]), float(goal[1]), dist, self.ring,
                         self.label)
        if out is None:
            return dist.astype(np.float32)
        out[: h * w] = dist
        return out

    def navigable_cells(self, s: int) -> tuple[np.ndarray, np.ndarray]:
        """Scene ``s``'s navigable cells (flat indices) and their centres (kept per scene)."""
        if s not in self._cells:
            grid = self.bank.grids[s]
            cells = np.flatnonzero(grid.nav.ravel())
            self._cells[s] = cells, grid.cell_center(np.stack(np.divmod(cells, grid.shape[1]), axis=1))
        return self._cells[s]

    def lookup(self, s: int, field: np.ndarray, p: np.ndarray) -> float:
        """Geodesic distance of point ``p`` in a field; ``math.inf`` if unreachable."""
        nav, off, h, w, ox, oy, cs = self.bank.grid_args(s)
        d = K.field_lookup(nav, off, h, w, ox, oy, cs, field, float(p[0]), float(p[1]))
        return math.inf if d >= K.INF else float(d)

    def distance(self, s: int, a: np.ndarray, b: np.ndarray) -> float:
        """Geodesic distance between two points by A*; ``math.inf`` if not connected."""
        nav, moves, off, h, w, ox, oy, cs = self.bank.search_args(s)
        self._stamp += 1
        d = K.astar(nav, moves, off, h, w, ox, oy, cs, float(a[0]), float(a[1]), float(b[0]), float(b[1]), self.g,
                    self.stamp, self._stamp, self.hk, self.hv, self.hpos)
        return math.inf if d >= K.INF else float(d)


def sample_episode(bank: SceneBank, s: int, rng: np.random.Generator, geo: Geodesics, episode_id: int = 0,
                   max_goals: int = 200, max_geodesic: float = MAX_GEODESIC) -> tuple[Episode, np.ndarray]:
    """Sample one episode in scene ``s`` by Habitat's rules (its start-goal geodesic
    distance in [MIN_GEODESIC, ``max_geodesic``]). Returns it and its goal field."""
    grid = bank.grids[s]
    nav_cells, centres = geo.navigable_cells(s)
    for _ in range(max_goals):
        gc = nav_cells[rng.integers(len(nav_cells))]
        goal = _cell_point(grid, gc, rng)
        field = geo.field(s, goal)
        d = field[nav_cells].astype(np.float64)
        ok = (d >= MIN_GEODESIC) & (d <= max_geodesic)
        if not np.any(ok):
            continue
        # Habitat draws a start uniformly and keeps it with probability
        # ratio_keep_probability(geodesic / euclidean); drawing one start with weights equal
        # to that probability gives the same distribution without the rejection loop.
        weight = _start_weights(d, centres, float(goal[0]), float(goal[1]), ok)
        if weight.sum() <= 0:
            continue
        cand = nav_cells[ok]
        for _try in range(20):
            sc = cand[rng.choice(len(cand), p=weight / weight.sum())]
            start = _cell_point(grid, sc, rng)
            dist = geo.lookup(s, field, start)
            if not (MIN_GEODESIC <= dist <= max_geodesic):
                continue
            heading = float(rng.uniform(-math.pi, math.pi))
            ep = Episode(episode_id, grid.scene_id, (float(start[0]), float(start[1])), heading,
                         (float(goal[0]), float(goal[1])), dist)
            return ep, field
    raise RuntimeError(f"scene {grid.scene_id!r}: no valid episode found after {max_goals} goals "
                       f"(navigable area {grid.navigable_area():.1f} m^2)")


@njit(cache=True)
def _start_weights(d, centres, gx, gy, ok):
    """The keep probability of each candidate start (the cells where ``ok``), from its
    geodesic ``d`` and the euclidean distance of its centre to the goal (gx, gy)."""
    out = np.empty(int(ok.sum()))
    k = 0
    for i in range(d.shape[0]):
        if ok[i]:
            out[k] = ratio_keep_probability(d[i] / max(math.hypot(centres[i, 0] - gx, centres[i, 1] - gy), 1e-9))
            k += 1
    return out


def _cell_point(grid, flat: int, rng: np.random.Generator) -> np.ndarray:
    """A uniformly random point inside navigable cell ``flat`` (rounded to mm)."""
    r, c = divmod(int(flat), grid.shape[1])
    cs = grid.cell_size
    x = grid.origin[0] + (c + rng.uniform(0.05, 0.95)) * cs
    y = grid.origin[1] + (r + rng.uniform(0.05, 0.95)) * cs
    return np.round(np.array([x, y]), 4)


def generate_episodes(bank: SceneBank, num_episodes: int, seed: int) -> list[Episode]:
    """``num_episodes`` episodes spread evenly over the bank's scenes, deterministic in ``seed``."""
    if num_episodes < 1:
        raise ValueError(f"num_episodes must be >= 1, got {num_episodes}")
    rng = np.random.default_rng(seed)
    geo = Geodesics(bank)
    eps = []
    for i in range(num_episodes):
        s = i % len(bank)
        ep, _ = sample_episode(bank, s, rng, geo, episode_id=i)
        eps.append(ep)
    return eps


def save_episodes(episodes: list[Episode], path: str | os.PathLike) -> None:
    """Write an episode file atomically (gzipped JSON)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    data = json.dumps({"version": FILE_VERSION, "episodes": [e.to_record() for e in episodes]})
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name, suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f, gzip.GzipFile(fileobj=f, mode="wb", mtime=0) as gz:
            gz.write(data.encode())
        os.chmod(tmp, 0o644)  # mkstemp makes the file private; an episode file is data to share
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


_FIELDS = {"episode_id": int, "scene_id": str, "start_position": list, "start_heading": (int, float),
           "goal_position": list, "geodesic_distance": (int, float)}


def load_episodes(path: str | os.PathLike) -> list[Episode]:
    """Read an episode file, with a clear :class:`EpisodeFileError` for any defect."""
    path = Path(path)
    if not path.is_file():
        raise EpisodeFileError(f"episode file {path}: does not exist")
    try:
        with gzip.open(path, "rb") as f:
            raw = f.read()
    except (OSError, EOFError, zlib.error) as e:
        raise EpisodeFileError(f"episode file {path}: not a complete gzip file ({e})") from None
    try:
        data = json.loads(raw)
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise EpisodeFileError(f"episode file {path}: not valid JSON ({e})") from None
    if not isinstance(data, dict) or "episodes" not in data or not isinstance(data["episodes"], list):
        raise EpisodeFileError(f"episode file {path}: expected an object with an 'episodes' list")
    if data.get("version") != FILE_VERSION:
        raise EpisodeFileError(f"episode file {path}: unsupported version {data.get('version')!r}")
    out = []
    for i, rec in enumerate(data["episodes"]):
        if not isinstance(rec, dict):
            raise EpisodeFileError(f"episode file {path}: record {i} is not an object")
        for k, t in _FIELDS.items():
            if k not in rec:
                raise EpisodeFileError(f"episode file {path}: record {i} lacks {k!r}")
            if not isinstance(rec[k], t) or isinstance(rec[k], bool):
                raise EpisodeFileError(f"episode file {path}: record {i} field {k!r} has type "
                                       f"{type(rec[k]).__name__}")
        for k in ("start_position", "goal_position"):
            v = rec[k]
            if len(v) != 2 or not all(isinstance(x, (int, float)) and math.isfinite(x) for x in v):
                raise EpisodeFileError(f"episode file {path}: record {i} field {k!r} must be two finite numbers")
        for k in ("start_heading", "geodesic_distance"):
            if not math.isfinite(rec[k]):
                raise EpisodeFileError(f"episode file {path}: record {i} field {k!r} is not finite")
        if not (0 < rec["geodesic_distance"] <= 1000):
            raise EpisodeFileError(f"episode file {path}: record {i} geodesic_distance out of range")
        out.append(Episode(int(rec["episode_id"]), rec["scene_id"], tuple(map(float, rec["start_position"])),
                           float(rec["start_heading"]), tuple(map(float, rec["goal_position"])),
                           float(rec["geodesic_distance"])))
    if not out:
        raise EpisodeFileError(f"episode file {path}: holds no episodes")
    return out
