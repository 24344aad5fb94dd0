"""Shared helpers of the simulator tests: hand-made scenes, a reference
Dijkstra, and the exact obstacle geometry of a scene.

Hand-made scenes put every wall and box face on a multiple of 0.05 m, so the 0.05 m grid
represents them exactly and rendered depth can be compared with analytic values.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from plex_ma.envs.sim import BatchedSim, Episode, Scene, SceneBank, rasterize
from plex_ma.envs.sim.procgen import HouseParams, generate_house
from plex_ma.envs.sim.scene import CELL_SIZE


def room_walls(x0: float, y0: float, x1: float, y1: float) -> list[tuple[float, float, float, float]]:
    """The four wall segments of an axis-aligned rectangle."""
    return [(x0, y0, x1, y0), (x1, y0, x1, y1), (x1, y1, x0, y1), (x0, y1, x0, y0)]


def bank_of(*scenes: Scene) -> SceneBank:
    return SceneBank([rasterize(s) for s in scenes])


def sim_at(scene_or_bank, pos, heading: float, resolution: int = 64, goal=None, egomap: bool = True,
           **kw) -> BatchedSim:
    """A one-world simulator whose agent stands at ``pos`` facing ``heading``."""
    bank = scene_or_bank if isinstance(scene_or_bank, SceneBank) else bank_of(scene_or_bank)
    sim = BatchedSim(bank, 1, resolution=resolution, egomap=egomap, **kw)
    goal = pos if goal is None else goal
    sim.reset_world(0, Episode(0, bank.scene_ids[0], tuple(pos), heading, tuple(goal), 1.0))
    return sim


@lru_cache(maxsize=8)
def small_house(seed: int = 5) -> Scene:
    """A procedural house of 8-10 m (rooms, doors, furniture): quick to search exhaustively."""
    return generate_house(seed, params=HouseParams(min_side=8.0, max_side=10.0))


def two_rooms_no_door() -> Scene:
    """Two 3 m x 3 m rooms sharing a wall without a door: not connected."""
    walls = room_walls(0.0, 0.0, 6.0, 3.0) + [(3.0, 0.0, 3.0, 3.0)]
    return Scene("two-rooms", np.array(walls))


# ------------------------------------------------------------------ reference geodesics
def reference_field(grid, goal) -> np.ndarray:
    """Geodesic distance of every cell centre to ``goal`` by scipy's Dijkstra over the
    8-connected navigable grid without corner cutting (a diagonal step needs both cells it
    passes to be navigable), the goal linked to the navigable centres of the 2x2 block of
    cells around it. ``inf`` where unreachable. Independent of the simulator's kernels."""
    nav = grid.nav
    H, W = nav.shape
    cs = grid.cell_size
    idx = np.arange(H * W).reshape(H, W)
    src, dst, wts = [], [], []
    for dr, dc in ((0, 1), (1, 0), (1, 1), (1, -1)):
        r0, r1 = 0, H - dr
        c0, c1 = max(0, -dc), W - max(0, dc)
        ok = nav[r0:r1, c0:c1] & nav[r0 + dr:r1 + dr, c0 + dc:c1 + dc]
        if dr and dc:
            ok &= nav[r0 + dr:r1 + dr, c0:c1] & nav[r0:r1, c0 + dc:c1 + dc]
        a = idx[r0:r1, c0:c1][ok]
        b = idx[r0 + dr:r1 + dr, c0 + dc:c1 + dc][ok]
        w = cs * math.sqrt(2.0) if (dr and dc) else cs
        src += [a, b]
        dst += [b, a]
        wts += [np.full(len(a), w)] * 2
    n = H * W
    gr = int(math.floor((goal[1] - grid.origin[1]) / cs - 0.5))
    gc = int(math.floor((goal[0] - grid.origin[0]) / cs - 0.5))
    for r in (gr, gr + 1):
        for c in (gc, gc + 1):
            if 0 <= r < H and 0 <= c < W and nav[r, c]:
                centre = grid.cell_center(np.array([r, c]))
                src.append(np.array([n]))
                dst.append(np.array([r * W + c]))
                # scipy drops explicit zeros: a goal exactly on a centre gets a tiny weight
                wts.append(np.array([max(float(np.hypot(*(centre - goal))), 1e-300)]))
    m = coo_matrix((np.concatenate(wts), (np.concatenate(src), np.concatenate(dst))), shape=(n + 1, n + 1))
    return dijkstra(m.tocsr(), directed=True, indices=n)[:n]


def reference_lookup(grid, field: np.ndarray, p) -> float:
    """Distance of a point given a reference field: min over the navigable centres c of
    the 2x2 block around ``p`` of field[c] + |p - c|."""
    H, W = grid.shape
    cs = grid.cell_size
    r0 = int(math.floor((p[1] - grid.origin[1]) / cs - 0.5))
    c0 = int(math.floor((p[0] - grid.origin[0]) / cs - 0.5))
    best = math.inf
    for r in (r0, r0 + 1):
        for c in (c0, c0 + 1):
            if 0 <= r < H and 0 <= c < W and grid.nav[r, c]:
                best = min(best, field[r * W + c] + float(np.hypot(*(grid.cell_center(np.array([r, c])) - p))))
    return best


def reference_straight(grid, a, b) -> bool:
    """Whether an agent at ``a`` could move straight to ``b``: every point sampled each
    quarter cell along the segment is navigable and no step between sampled cells squeezes
    diagonally between two blocked cells (the simulator's motion rule, restated)."""
    cs = grid.cell_size
    d = np.asarray(b, float) - np.asarray(a, float)
    n = math.ceil(math.hypot(*d) / (cs * 0.25))
    prev = grid.world_to_cell(np.asarray(a, float))
    for k in range(1, n + 1):
        p = np.asarray(a, float) + d * k / n
        if not grid.is_navigable(p):
            return False
        rc = grid.world_to_cell(p)
        if rc[0] != prev[0] and rc[1] != prev[1] and not grid.nav[prev[0], rc[1]] and not grid.nav[rc[0], prev[1]]:
            return False
        prev = rc
    return True


def reference_distance(grid, field: np.ndarray, a, b) -> float:
    """The simulator's geodesic from ``a`` to ``b`` (``field`` is ``b``'s reference field):
    the grid's, or the straight line where the agent could walk straight there."""
    d = reference_lookup(grid, field, a)
    e = float(np.hypot(*(np.asarray(b, float) - np.asarray(a, float))))
    return e if e < d and reference_straight(grid, a, b) else d


def random_navigable_point(grid, rng: np.random.Generator) -> np.ndarray:
    cells = np.flatnonzero(grid.nav.ravel())
    r, c = divmod(int(cells[rng.integers(len(cells))]), grid.shape[1])
    return grid.cell_center(np.array([r, c])) + rng.uniform(-0.49, 0.49, 2) * grid.cell_size


# ------------------------------------------------------------------ exact obstacle geometry
def door_cut(scene: Scene) -> float:
    """How far beyond each end of a door its wall is opened. The rasteriser removes the
    wall cells whose centres lie within half a wall plus one cell of the door segment; for
    walls and doors on the 0.05 m grid that opens the wall exactly this far past the door."""
    return scene.wall_thickness / 2 + CELL_SIZE


def wall_pieces(scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """The walls as the rasteriser draws them, every point within half the wall thickness
    of a segment, with the door openings cut out: (rectangles, round ends). Each segment
    between door openings is a rectangle (x0, y0, x1, y1) along it, square where a door
    cuts it; the segments' own ends are round, discs of half the thickness about the
    end points (x, y) listed in ``ends``. (Square ends there would be stricter than the
    scene: the agent may pass a free wall end closer than its rectangle's corner.)"""
    h = scene.wall_thickness / 2
    ext = door_cut(scene)
    out, ends = [], []
    for x0, y0, x1, y1 in scene.walls.astype(np.float64):
        vertical = abs(x0 - x1) < 1e-9
        assert vertical or abs(y0 - y1) < 1e-9, "only axis-aligned walls are supported here"
        line = x0 if vertical else y0
        lo, hi = (min(y0, y1), max(y0, y1)) if vertical else (min(x0, x1), max(x0, x1))
        pieces = [(lo, hi)]
        for dx0, dy0, dx1, dy1 in scene.doors.astype(np.float64):
            if vertical and abs(dx0 - dx1) < 1e-9 and abs(dx0 - line) < 1e-6:
                a, b = min(dy0, dy1) - ext, max(dy0, dy1) + ext
            elif not vertical and abs(dy0 - dy1) < 1e-9 and abs(dy0 - line) < 1e-6:
                a, b = min(dx0, dx1) - ext, max(dx0, dx1) + ext
            else:
                continue
            nxt = []
            for p, q in pieces:
                if b <= p or a >= q:
                    nxt.append((p, q))
                    continue
                if a > p:
                    nxt.append((p, a))
                if b < q:
                    nxt.append((b, q))
            pieces = nxt
        for p, q in pieces:
            out.append((line - h, p, line + h, q) if vertical else (p, line - h, q, line + h))
            ends += [(line, t) if vertical else (t, line) for t in (p, q) if t in (lo, hi)]
    return np.array(out, np.float64).reshape(-1, 4), np.array(ends, np.float64).reshape(-1, 2)


def rect_distance(p, rects: np.ndarray) -> np.ndarray:
    """Distance from point ``p`` to each axis-aligned rectangle (0 inside)."""
    if len(rects) == 0:
        return np.full(1, np.inf)
    dx = np.maximum(np.maximum(rects[:, 0] - p[0], p[0] - rects[:, 2]), 0.0)
    dy = np.maximum(np.maximum(rects[:, 1] - p[1], p[1] - rects[:, 3]), 0.0)
    return np.hypot(dx, dy)


def segment_distance(p, segs: np.ndarray) -> np.ndarray:
    """Distance from point ``p`` to each segment (x0, y0, x1, y1)."""
    a = segs[:, :2].astype(np.float64)
    d = segs[:, 2:].astype(np.float64) - a
    L2 = np.maximum((d ** 2).sum(1), 1e-18)
    t = np.clip(((np.asarray(p) - a) * d).sum(1) / L2, 0.0, 1.0)
    return np.hypot(*(np.asarray(p) - (a + t[:, None] * d)).T)


def obstacle_clearance(p, scene: Scene) -> float:
    """Distance from point ``p`` to the nearest obstacle of the scene's exact geometry:
    the walls (:func:`wall_pieces`) and the furniture boxes (every box stands on the
    floor, so it blocks the agent)."""
    rects, ends = wall_pieces(scene)
    rects = np.concatenate([rects, scene.boxes.astype(np.float64).reshape(-1, 4)])
    d = float(rect_distance(p, rects).min())
    if len(ends):
        d = min(d, float(np.hypot(*(ends - np.asarray(p)).T).min()) - scene.wall_thickness / 2)
    return d

