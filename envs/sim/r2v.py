"""Real apartment floor plans (the Raster-to-Vector annotations) as :class:`Scene` s.

The plans are the 1,040 hand-annotated Japanese apartment floor plans of Liu, Wu, Kohli
and Furukawa, "Raster-to-Vector: Revisiting Floorplan Transformation" (ICCV 2017),
repository art-programmer/FloorplanTransformation, MIT licence. They ship with this
package as one archive, ``envs/sim/data/r2v/plans.tar.xz`` (see the README there).
docs/r2v.md describes the loader in full.

Plan file format (one plan per file, the file stem is its id; tab-separated records)::

    x_min  y_min  x_max  y_max  category  [dump_1  dump_2]

Coordinates are image pixels, y pointing down. How a plan becomes a scene:

* ``wall`` records are wall centre lines, :data:`WALL_THICKNESS` thick.
* ``door`` records are openings, each cut into the wall it lies on; doors that lead
  outside stay closed. A door that misses its wall by at most :data:`DOOR_TOLERANCE_PX`
  is projected onto the nearest (nearly parallel, overlapping) wall; one farther from
  every wall is dropped. Each door is shortened by :data:`DOOR_INSET` at both ends, as
  ``rasterize`` cuts half a wall plus one cell around a door: so a door that runs up to a
  perpendicular wall cuts it at most to its centre line (a cut through an outer wall
  would close the door), and the opening is about 4 cm narrower than the annotated door.
* Wall ends are snapped: an end that touches no other wall but lies within
  :data:`SNAP_TOLERANCE_PX` of one is extended (or trimmed) along its own line to meet
  it, or, when its line misses, moved onto the nearest point of that wall. This closes
  the apartment's outline, so its outside (connected to the grid border) becomes void.
* Icons (furniture and fixtures) become axis-aligned boxes with a height and a furniture
  category (see ``MATERIAL_RGB`` in :mod:`.bank`): :data:`ICONS`.
* Room labels (:data:`ROOM_LABELS`, including ``entrance``, the Japanese genkan, which
  is floor) only anchor a room's name; ``point`` records (zero-size markers) are ignored
  too. Any other category is a parse error.
* Pixels become metres with ``scale`` (default :data:`DEFAULT_SCALE` = 0.02 m per pixel:
  the median door is then 0.9 m wide and the median apartment 8.5 m across), y is
  flipped so that north stays up, and the plan is translated to start at (0, 0).
  ``scale="auto"`` instead sets each plan's scale so that its median door is
  :data:`AUTO_DOOR_WIDTH` wide (the plans were drawn at quite different resolutions).

**Navigable** (:func:`validate_scene`, with the simulator's 0.05 m cells and 0.1 m agent
radius): the rasterised plan, and its largest navigable component (connected as the
geodesic search moves), must each have at least :data:`MIN_NAVIGABLE_AREA` square metres
of navigable cells. A connected region of 8 m^2 is more than 3 m across, so it holds
episodes of the simulator's rules (geodesic distance 1 to 30 m). Smaller components (a
closet behind a narrow door) may remain; the episode sampler keeps connected pairs only.

Every problem with a plan, from an unreadable file to a plan with nothing navigable,
raises :class:`SceneError` whose message starts with ``plan '<id>'`` and says what is
wrong (parse errors give the line number). Nothing else escapes :func:`load_plan`.

Splits: a plan's split is fixed by its id alone (:func:`split_of`): the first 8 bytes
of SHA-256 of the id, modulo 100: below 80 is ``train``, below 90 ``val``, the rest
``test`` (about 80/10/10; the exact counts are in ``envs/sim/data/r2v/index.json``).

Sources (:data:`.sources.SOURCES`): ``"r2v"`` gives the bundled plans of a split that
load, in id order (rejects skipped); a directory loads every ``*.txt`` plan in it, any
split, with one warning listing the plans that failed and why. Scenes are cached per
process (callers share the :class:`Scene` objects: do not modify them in place).

Maintenance: ``python -m plex_ma.scenes pack DIR`` rebuilds the archive and its index
(split sizes and the plans rejected, with why) from a directory of plan files, and
``python -m plex_ma.scenes index`` the index alone after a loader change (bump
:data:`LOADER_VERSION` when the repair or the checks change which plans load).
"""
from __future__ import annotations

import hashlib
import inspect
import io
import json
import math
import os
import tarfile
import warnings
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from . import scene as _scene
from .scene import AGENT_RADIUS, CELL_SIZE, Scene, SceneError, SceneGrid, rasterize

LOADER_VERSION = 1  # bump when a change of the repair or the checks changes which plans load
DEFAULT_SCALE = 0.02  # metres per pixel
WALL_THICKNESS = 0.12  # metres
SNAP_TOLERANCE_PX = 10.0  # wall ends closer than this to another wall are joined to it
DOOR_TOLERANCE_PX = 10.0  # doors closer than this to a wall are moved onto it
DOOR_INSET = WALL_THICKNESS / 2 + CELL_SIZE  # metres trimmed off both ends of a door
MIN_DOOR = 0.1  # metres: a door is never trimmed shorter than this
AUTO_DOOR_WIDTH = 0.9  # metres: the median door of a plan under scale="auto"
AUTO_SCALE_RANGE = (0.005, 0.05)  # metres per pixel allowed under scale="auto"
MIN_NAVIGABLE_AREA = 8.0  # square metres of the largest navigable component
MAX_PLAN_PX = 20000.0  # coordinates beyond this are certainly not a plan
MAX_EXTENT = 100.0  # metres: no apartment is larger
SPLIT_PERCENT = {"train": 80, "val": 10, "test": 10}

# Icon category -> (furniture category of MATERIAL_RGB, height in metres).
ICONS: dict[str, tuple[int, float]] = {
    "bathtub": (2, 0.55),  # sanitary
    "toilet": (2, 0.75),
    "washing_basin": (2, 0.85),
    "cooking_counter": (3, 0.9),  # kitchen counter
    "closet": (4, 2.0),  # built-in storage, nearly ceiling high
    "special": (5, 1.1),  # appliance spaces (washer, fridge) and the like
    "stairs": (6, 1.2),  # a flight of stairs is an obstacle on a flat floor
    "PS": (7, 2.5),  # pipe space: a shaft from floor to ceiling
}
ROOM_LABELS = frozenset({
    "bedroom", "kitchen", "living_room", "corridor", "bathroom", "entrance", "balcony", "restroom",
    "washing_room", "dining_room", "office", "laundry_room", "garage", "storage", "room",
})
IGNORED = frozenset({"point"})

DATA_DIR = Path(__file__).resolve().parent / "data" / "r2v"
ARCHIVE_NAME = "plans.tar.xz"
INDEX_NAME = "index.json"


@dataclass
class Plan:
    """A parsed plan in pixel coordinates (y down), before any repair."""

    plan_id: str
    walls: np.ndarray  # (N, 4) x0, y0, x1, y1
    doors: np.ndarray  # (M, 4)
    icons: np.ndarray  # (K, 4) x_min, y_min, x_max, y_max
    icon_names: list[str]


def _err(plan_id: str, msg: str) -> SceneError:
    return SceneError(f"plan {plan_id!r}: {msg}")


# ----------------------------------------------------------------------------- parsing


def parse_plan(text: str | bytes, plan_id: str) -> Plan:
    """Parse the text of one plan file; :class:`SceneError` with the line number on defects."""
    if isinstance(text, (bytes, bytearray)):
        if b"\x00" in text:
            raise _err(plan_id, "not a text file (it holds NUL bytes; corrupt or binary)")
        try:
            text = bytes(text).decode("utf-8")
        except UnicodeDecodeError as e:
            raise _err(plan_id, f"not a text file (invalid UTF-8 at byte {e.start})") from None
    walls, doors, icons, names = [], [], [], []
    lines = text.split("\n")
    unterminated = not text.endswith("\n")

    def bad(n: int, msg: str) -> SceneError:
        hint = " (the file looks truncated)" if unterminated and n == len(lines) else ""
        return _err(plan_id, f"parse error at line {n}: {msg}{hint}")

    for n, line in enumerate(lines, start=1):
        fields = line.split()
        if not fields:
            continue
        if len(fields) < 5:
            raise bad(n, f"expected 'x_min y_min x_max y_max category', got {len(fields)} field(s) "
                         f"{line.strip()[:60]!r}")
        try:
            v = [float(x) for x in fields[:4]]
        except ValueError:
            raise bad(n, f"coordinates are not numbers: {' '.join(fields[:4])[:60]!r}") from None
        if not all(math.isfinite(x) and abs(x) <= MAX_PLAN_PX for x in v):
            raise bad(n, f"coordinates must be finite and within {MAX_PLAN_PX:.0f} px, got {fields[:4]}")
        cat = fields[4]
        if cat == "wall":
            walls.append(v)
        elif cat == "door":
            doors.append(v)
        elif cat in ICONS:
            icons.append([min(v[0], v[2]), min(v[1], v[3]), max(v[0], v[2]), max(v[1], v[3])])
            names.append(cat)
        elif cat not in ROOM_LABELS and cat not in IGNORED:
            raise bad(n, f"unknown category {cat[:40]!r}")
    return Plan(plan_id, np.asarray(walls, np.float64).reshape(-1, 4), np.asarray(doors, np.float64).reshape(-1, 4),
                np.asarray(icons, np.float64).reshape(-1, 4), names)


# ----------------------------------------------------------------------------- repair


def _point_segment(p: np.ndarray, segs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distances from point ``p`` to each segment, and the nearest points."""
    a, d = segs[:, :2], segs[:, 2:] - segs[:, :2]
    l2 = (d * d).sum(1)
    t = np.clip(((p - a) * d).sum(1) / np.maximum(l2, 1e-12), 0.0, 1.0)
    q = a + t[:, None] * d
    return np.hypot(*(p - q).T), q


def snap_walls(walls: np.ndarray, tol: float = SNAP_TOLERANCE_PX) -> np.ndarray:
    """Join wall ends that stop short of (or run past) another wall by at most ``tol``."""
    walls = walls.copy()
    n = len(walls)
    if n < 2:
        return walls
    # Endpoint-to-wall distances of all ends at once; only the loose ends are revisited.
    ends = np.concatenate([walls[:, :2], walls[:, 2:]])  # end k belongs to wall k % n
    a0, dv = walls[:, :2], walls[:, 2:] - walls[:, :2]
    t = np.clip(((ends[:, None, :] - a0[None]) * dv[None]).sum(-1) / np.maximum((dv * dv).sum(-1), 1e-12), 0, 1)
    dist = np.hypot(*(ends[:, None, :] - (a0[None] + t[..., None] * dv[None])).transpose(2, 0, 1))
    dist[np.arange(2 * n), np.arange(2 * n) % n] = np.inf
    near = dist.min(1)
    for k in np.flatnonzero((near > 0.5) & (near <= tol)):
        i, e = int(k % n), int(k // n)
        p = walls[i, 2 * e:2 * e + 2].copy()
        a = walls[i, 2 - 2 * e:4 - 2 * e].copy()  # the wall's other end
        others = np.delete(walls, i, axis=0)
        d, q = _point_segment(p, others)  # again: earlier snaps may have moved walls
        if d.min() <= 0.5 or d.min() > tol:
            continue  # already joined, or a free end (or a gap too wide to be a slip)
        u = p - a
        length = float(np.hypot(*u))
        best = None
        if length > 1e-9:
            u = u / length
            for j in np.flatnonzero(d <= tol):
                b0, v = others[j, :2], others[j, 2:] - others[j, :2]
                den = u[0] * v[1] - u[1] * v[0]
                lj = float(np.hypot(*v))
                if lj < 1e-9 or abs(den) < 1e-6 * lj:
                    continue  # parallel: no crossing
                w = b0 - a
                along_i = (w[0] * v[1] - w[1] * v[0]) / den  # crossing, from a along wall i
                along_j = (w[0] * u[1] - w[1] * u[0]) / den  # crossing on wall j, 0..1
                if along_i > 0 and abs(along_i - length) <= tol and -tol / lj <= along_j <= 1 + tol / lj:
                    if best is None or abs(along_i - length) < best[0]:
                        best = (abs(along_i - length), a + along_i * u)
        walls[i, 2 * e:2 * e + 2] = best[1] if best is not None else q[int(np.argmin(d))]
    return walls


def project_doors(doors: np.ndarray, walls: np.ndarray, tol: float = DOOR_TOLERANCE_PX) -> tuple[np.ndarray, int]:
    """Move each door onto the nearest nearly parallel wall it overlaps within ``tol``.

    Returns the doors (those with no wall in reach dropped) and how many were dropped.
    """
    out, kept = _project_doors(doors, walls, tol)
    return out, len(doors) - len(kept)


def _project_doors(doors: np.ndarray, walls: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """(projected doors, indices of the input doors they come from)."""
    v = walls[:, 2:] - walls[:, :2]
    lw = np.hypot(v[:, 0], v[:, 1])
    ok = lw > 1e-9
    a, v, lw = walls[ok, :2], v[ok], lw[ok]
    dl = np.hypot(doors[:, 2] - doors[:, 0], doors[:, 3] - doors[:, 1])
    src = np.flatnonzero(dl > 1e-9)
    doors = doors[src]
    if len(doors) == 0 or len(a) == 0:
        return np.zeros((0, 4)), np.zeros(0, np.int64)
    uw = v / lw[:, None]  # (N, 2) wall directions
    nw = np.stack([-uw[:, 1], uw[:, 0]], 1)  # wall normals
    ud = (doors[:, 2:] - doors[:, :2]) / dl[dl > 1e-9, None]
    p0, p1 = doors[:, None, :2] - a[None], doors[:, None, 2:] - a[None]  # (M, N, 2) relative to walls
    off0, off1 = (p0 * nw).sum(-1), (p1 * nw).sum(-1)
    t0, t1 = (p0 * uw).sum(-1), (p1 * uw).sum(-1)
    parallel = np.abs(ud[:, None, 0] * uw[None, :, 1] - ud[:, None, 1] * uw[None, :, 0]) < 0.26  # ~15 degrees
    overlap = np.minimum(np.maximum(t0, t1), lw) - np.maximum(np.minimum(t0, t1), 0.0)
    good = parallel & (np.maximum(np.abs(off0), np.abs(off1)) <= tol) & (overlap > 0)
    cost = np.where(good, np.abs(off0) + np.abs(off1), np.inf)
    j = np.argmin(cost, axis=1)
    keep = np.isfinite(cost[np.arange(len(doors)), j])
    m, j = np.flatnonzero(keep), j[keep]
    out = np.concatenate([a[j] + t0[m, j, None] * uw[j], a[j] + t1[m, j, None] * uw[j]], 1)
    return out, src[m]


def repair_stats(plan: Plan) -> dict:
    """How much :func:`plan_to_scene` repairs a plan: wall ends snapped, doors moved onto
    a wall, doors dropped (no wall within tolerance)."""
    walls = plan.walls[np.hypot(plan.walls[:, 2] - plan.walls[:, 0], plan.walls[:, 3] - plan.walls[:, 1]) > 0.5]
    snapped = snap_walls(walls, SNAP_TOLERANCE_PX)
    ends = np.concatenate([snapped[:, :2] - walls[:, :2], snapped[:, 2:] - walls[:, 2:]])
    doors, src = _project_doors(plan.doors, snapped, DOOR_TOLERANCE_PX)
    moved = np.abs(doors - plan.doors[src]).max(1) > 0.5 if len(src) else np.zeros(0, bool)
    return {"wall_ends_snapped": int((np.abs(ends).max(1) > 1e-6).sum()) if len(ends) else 0,
            "doors_projected": int(moved.sum()), "doors_dropped": int(len(plan.doors) - len(src))}


# ----------------------------------------------------------------------------- plan -> scene


def plan_scale(plan: Plan, scale: float | str = DEFAULT_SCALE) -> float:
    """Metres per pixel: ``scale`` itself, or for ``"auto"`` the scale that makes the plan's
    median door :data:`AUTO_DOOR_WIDTH` wide (clamped to :data:`AUTO_SCALE_RANGE`;
    :data:`DEFAULT_SCALE` for a plan with fewer than two doors)."""
    if isinstance(scale, str):
        if scale != "auto":
            raise _err(plan.plan_id, f"scale must be a number of metres per pixel or 'auto', got {scale!r}")
        d = plan.doors
        ln = np.hypot(d[:, 2] - d[:, 0], d[:, 3] - d[:, 1])
        ln = ln[ln > 0.5]
        if len(ln) < 2:
            return DEFAULT_SCALE
        return float(np.clip(AUTO_DOOR_WIDTH / np.median(ln), *AUTO_SCALE_RANGE))
    if isinstance(scale, bool) or not (isinstance(scale, (int, float, np.floating)) and math.isfinite(scale)
                                       and 0.001 <= scale <= 1.0):
        raise _err(plan.plan_id, f"scale {scale!r} m/px not in [0.001, 1]")
    return float(scale)


def plan_to_scene(plan: Plan, scale: float | str = DEFAULT_SCALE) -> Scene:
    """Repair a parsed plan and turn it into a :class:`Scene` in metres (no rasterising)."""
    pid = plan.plan_id
    scale = plan_scale(plan, scale)
    walls = plan.walls[np.hypot(plan.walls[:, 2] - plan.walls[:, 0], plan.walls[:, 3] - plan.walls[:, 1]) > 0.5]
    if len(walls) == 0:
        raise _err(pid, "has no walls")
    walls = snap_walls(walls, SNAP_TOLERANCE_PX)
    doors, _dropped = project_doors(plan.doors, walls, DOOR_TOLERANCE_PX)
    keep = (plan.icons[:, 2] - plan.icons[:, 0] > 0) & (plan.icons[:, 3] - plan.icons[:, 1] > 0)
    icons = plan.icons[keep]
    names = [nm for nm, k in zip(plan.icon_names, keep) if k]

    pts = np.concatenate([walls[:, :2], walls[:, 2:], icons[:, :2], icons[:, 2:]])
    x0, y1 = float(pts[:, 0].min()), float(pts[:, 1].max())
    ext = (pts.max(0) - pts.min(0)) * scale
    if ext.max() > MAX_EXTENT:
        raise _err(pid, f"plan is {ext[0]:.0f} x {ext[1]:.0f} m at {scale:g} m/px, larger than {MAX_EXTENT:g} m "
                        f"(wrong scale or stray coordinates?)")

    def seg_m(s: np.ndarray) -> np.ndarray:
        return np.stack([(s[:, 0] - x0) * scale, (y1 - s[:, 1]) * scale, (s[:, 2] - x0) * scale,
                         (y1 - s[:, 3]) * scale], 1)

    walls_m = seg_m(walls)
    doors_m = seg_m(doors)
    if len(doors_m):
        d = doors_m[:, 2:] - doors_m[:, :2]
        ln = np.hypot(d[:, 0], d[:, 1])
        inset = np.minimum(DOOR_INSET, np.maximum(ln - MIN_DOOR, 0.0) / 2)
        u = d / np.maximum(ln, 1e-12)[:, None]
        doors_m = np.concatenate([doors_m[:, :2] + inset[:, None] * u, doors_m[:, 2:] - inset[:, None] * u], 1)
    boxes = np.stack([(icons[:, 0] - x0) * scale, (y1 - icons[:, 3]) * scale, (icons[:, 2] - x0) * scale,
                      (y1 - icons[:, 1]) * scale], 1) if len(icons) else np.zeros((0, 4))
    cats = np.array([ICONS[nm][0] for nm in names], np.int64)
    heights = np.array([ICONS[nm][1] for nm in names], np.float64)
    return Scene(scene_id=pid, walls=walls_m, wall_thickness=WALL_THICKNESS, doors=doors_m, boxes=boxes,
                 box_heights=heights, box_categories=cats, source="r2v")


def validate_scene(scene: Scene, min_area: float = MIN_NAVIGABLE_AREA) -> SceneGrid:
    """Rasterise with the simulator's defaults and check the scene is navigable (see module doc)."""
    pid = scene.scene_id
    try:
        grid = rasterize(scene)
    except SceneError as e:
        msg = str(e)
        prefix = f"scene {pid!r}: "
        msg = msg[len(prefix):] if msg.startswith(prefix) else msg
        if "no navigable space" in msg:
            msg = (f"nothing navigable (no enclosed floor keeps a {AGENT_RADIUS:g} m agent clear of obstacles; "
                   f"is the outline closed?)")
        raise _err(pid, msg) from None
    comp = grid.component[grid.component >= 0]
    sizes = np.bincount(comp) * grid.cell_size**2
    largest, total = float(sizes.max()), grid.navigable_area()
    if total < min_area:
        raise _err(pid, f"navigable area too small: {total:.1f} m^2 < {min_area:g} m^2")
    if largest < min_area:
        raise _err(pid, f"largest navigable component too small: {largest:.1f} m^2 < {min_area:g} m^2 "
                        f"({total:.1f} m^2 in {len(sizes)} parts; doors too narrow or blocked?)")
    return grid


def load_plan(source: str | os.PathLike | bytes, plan_id: str | None = None, scale: float | str = DEFAULT_SCALE,
              validate: bool = True) -> Scene:
    """Load one plan as a :class:`Scene` (``scene_id`` = plan id, the file stem).

    ``source`` is a path to a plan file, or the file's content as ``bytes`` (then
    ``plan_id`` is required). ``scale`` is metres per pixel, or ``"auto"`` (see
    :func:`plan_scale`). With ``validate`` the scene is rasterised and checked to be
    navigable (see the module docstring). Every problem raises :class:`SceneError`
    naming the plan.
    """
    return load_plan_grid(source, plan_id, scale, validate)[0]


def load_plan_grid(source: str | os.PathLike | bytes, plan_id: str | None = None,
                   scale: float | str = DEFAULT_SCALE, validate: bool = True) -> tuple[Scene, SceneGrid | None]:
    """:func:`load_plan`, also returning the validated grid (None without ``validate``)."""
    if isinstance(source, (bytes, bytearray)):
        if plan_id is None:
            raise ValueError("plan_id is required when the plan is given as bytes")
        data = bytes(source)
    else:
        path = Path(source)
        plan_id = plan_id or path.stem
        try:
            data = path.read_bytes()
        except OSError as e:
            raise _err(plan_id, f"cannot read {path}: {e.strerror or e}") from None
    try:
        scene = plan_to_scene(parse_plan(data, plan_id), scale)
        return scene, (validate_scene(scene) if validate else None)
    except SceneError as e:
        if str(e).startswith(f"plan {plan_id!r}"):
            raise
        raise _err(plan_id, str(e)) from None
    except Exception as e:  # never crash on a malformed plan
        raise _err(plan_id, f"unexpected {type(e).__name__}: {e}") from None


# ----------------------------------------------------------------------------- splits and bundled data


def split_of(plan_id: str) -> str:
    """The split of a plan, fixed by its id (SHA-256 bucket: 80/10/10)."""
    b = int.from_bytes(hashlib.sha256(plan_id.encode()).digest()[:8], "big") % 100
    if b < SPLIT_PERCENT["train"]:
        return "train"
    if b < SPLIT_PERCENT["train"] + SPLIT_PERCENT["val"]:
        return "val"
    return "test"


@lru_cache(maxsize=1)
def loader_fingerprint() -> str:
    """Changes whenever a loader setting, or the rasteriser's code, that decides whether a
    plan loads changes (then the shipped index is not trusted; see :func:`r2v_scenes`)."""
    try:
        steps = (_scene.rasterize, _scene._segment_cells, _scene._walls_and_doors, _scene._furniture, _scene._rooms,
                 _scene._kinds, _scene._navigable)
        raster_code = hashlib.sha256("".join(inspect.getsource(f) for f in steps).encode()).hexdigest()
    except (OSError, TypeError):
        raster_code = "unknown"
    key = [LOADER_VERSION, raster_code, DEFAULT_SCALE, WALL_THICKNESS, SNAP_TOLERANCE_PX, DOOR_TOLERANCE_PX, DOOR_INSET,
           MIN_DOOR, MIN_NAVIGABLE_AREA, MAX_EXTENT, CELL_SIZE, AGENT_RADIUS, sorted(ICONS.items()),
           sorted(ROOM_LABELS)]
    return hashlib.sha256(json.dumps(key).encode()).hexdigest()[:16]


@lru_cache(maxsize=1)
def bundled_plans() -> dict[str, bytes]:
    """{plan id: file content} of every bundled plan (read once per process)."""
    path = DATA_DIR / ARCHIVE_NAME
    out: dict[str, bytes] = {}
    try:
        with tarfile.open(path, "r:xz") as tar:
            for m in tar:
                if m.isfile() and m.name.endswith(".txt"):
                    out[Path(m.name).stem] = tar.extractfile(m).read()
    except (OSError, tarfile.TarError, EOFError) as e:
        raise SceneError(f"bundled floor plans {path}: cannot be read ({e})") from None
    return dict(sorted(out.items()))


@lru_cache(maxsize=1)
def bundled_index() -> dict:
    """The index shipped with the plans: split and load status per plan."""
    try:
        return json.loads((DATA_DIR / INDEX_NAME).read_text())
    except (OSError, ValueError):
        return {}


def bundled_ids(split: str | None = None) -> list[str]:
    ids = list(bundled_plans())
    return ids if split is None else [i for i in ids if split_of(i) == split]


@lru_cache(maxsize=None)
def _bundled_scene(plan_id: str, validate: bool) -> Scene | SceneError:
    try:
        return load_plan(bundled_plans()[plan_id], plan_id, validate=validate)
    except SceneError as e:
        return e


def load_bundled(plan_id: str, validate: bool = True) -> Scene:
    """One bundled plan by id (cached); :class:`SceneError` if it does not load."""
    if plan_id not in bundled_plans():
        raise SceneError(f"plan {plan_id!r}: not among the {len(bundled_plans())} bundled plans")
    r = _bundled_scene(plan_id, validate)
    if isinstance(r, SceneError):
        raise r
    return r


def _known_rejects() -> set[str] | None:
    """Ids the index marks as rejected, if the index matches this loader (else None)."""
    idx = bundled_index()
    if idx.get("fingerprint") != loader_fingerprint():
        return None
    return set(idx.get("rejects", {}))


def r2v_scenes(split: str, num_scenes: int | None = None) -> list[Scene]:
    """The bundled plans of ``split`` that load, in id order (the first ``num_scenes``).

    When the shipped index was built by this loader, plans it marks as rejected are
    skipped and the others are loaded without rasterising them here (the scene bank
    rasterises them anyway); otherwise each plan is validated.
    """
    rejects = _known_rejects()
    out: list[Scene] = []
    for pid in bundled_ids(split):
        if num_scenes is not None and len(out) >= num_scenes:
            break
        if rejects is not None and pid in rejects:
            continue
        r = _bundled_scene(pid, rejects is None)
        if isinstance(r, Scene):
            out.append(r)
    if num_scenes is not None and len(out) < num_scenes:
        raise SceneError(f"scene source 'r2v' split {split!r} has {len(out)} usable plans, {num_scenes} asked for")
    return out


@lru_cache(maxsize=4096)
def _file_scene(path: str, mtime_ns: int, size: int, scale: float) -> Scene | SceneError:
    try:
        return load_plan(path, scale=scale)
    except SceneError as e:
        return e


def load_directory(directory: str | os.PathLike, scale: float = DEFAULT_SCALE) -> tuple[list[Scene], dict[str, str]]:
    """Every ``*.txt`` plan in ``directory`` (sorted by name): (scenes that load, {id: why not})."""
    d = Path(directory)
    scenes, failed = [], {}
    for f in sorted(d.glob("*.txt")):
        try:
            st = f.stat()
            r = _file_scene(str(f.resolve()), st.st_mtime_ns, st.st_size, scale)
        except OSError as e:
            r = _err(f.stem, f"cannot read {f}: {e.strerror or e}")
        if isinstance(r, Scene):
            scenes.append(r)
        else:
            failed[f.stem] = str(r)
    return scenes, failed


def directory_scenes(directory: str, split: str, num_scenes: int | None = None) -> list[Scene] | None:
    """The directory source of :func:`.sources.load_scenes`: every plan in a directory that loads, any split.

    Returns None when ``directory`` is not a directory (so the source stays unknown).
    Plans that fail are skipped with one ``warnings.warn`` listing them and why.
    """
    d = Path(os.fspath(directory)).expanduser()
    if not d.is_dir():
        return None
    if not any(d.glob("*.txt")):
        raise SceneError(f"scene directory {str(d)!r}: holds no plan files (*.txt)")
    scenes, failed = load_directory(d)
    if failed:
        lines = "\n".join(f"  {msg}" for msg in failed.values())
        warnings.warn(f"scene directory {str(d)!r}: skipped {len(failed)} of {len(failed) + len(scenes)} plans "
                      f"that do not load:\n{lines}", stacklevel=3)
    return scenes if num_scenes is None else scenes[:num_scenes]


# ----------------------------------------------------------------------------- packing


def build_index(plans: dict[str, bytes]) -> dict:
    """Which plans the loader (default scale) rejects and why, and the split sizes."""
    rejects, counts = {}, {sp: 0 for sp in SPLIT_PERCENT}
    for pid, data in sorted(plans.items()):
        counts[split_of(pid)] += 1
        try:
            load_plan(data, pid)
        except SceneError as e:
            rejects[pid] = str(e)
    return {"fingerprint": loader_fingerprint(), "num_plans": len(plans), "split_sizes": counts,
            "rejects": rejects}


def pack(src_dir: str | os.PathLike, out_dir: str | os.PathLike = DATA_DIR) -> dict:
    """Write ``plans.tar.xz`` (sorted, fixed metadata: reproducible) and ``index.json``."""
    src, out = Path(src_dir), Path(out_dir)
    files = sorted(src.glob("*.txt"))
    if not files:
        raise SceneError(f"pack: no *.txt plans in {src}")
    out.mkdir(parents=True, exist_ok=True)
    plans = {f.stem: f.read_bytes() for f in files}
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:xz", preset=9) as tar:
        for pid, data in plans.items():
            info = tarfile.TarInfo(f"plans/{pid}.txt")
            info.size, info.mtime, info.mode = len(data), 0, 0o644
            tar.addfile(info, io.BytesIO(data))
    (out / ARCHIVE_NAME).write_bytes(buf.getvalue())
    return write_index(build_index(plans), out)


def write_index(index: dict, out_dir: str | os.PathLike = DATA_DIR) -> dict:
    """Write ``index.json`` (one reject per line, so that diffs stay readable)."""
    body = ",\n".join(f"  {json.dumps(k)}: {json.dumps(v)}" for k, v in index["rejects"].items())
    head = {k: v for k, v in index.items() if k != "rejects"}
    Path(out_dir, INDEX_NAME).write_text(json.dumps(head)[:-1] + ', "rejects": {\n' + body + "\n}}\n")
    bundled_plans.cache_clear()
    bundled_index.cache_clear()
    _bundled_scene.cache_clear()
    return index

