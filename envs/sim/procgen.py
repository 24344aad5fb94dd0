"""Procedural houses, deterministic from an integer seed.

A house is a rectangle between about 6 m and 25 m on its longer side, cut by binary
space partitioning into rooms of varied sizes; long cuts sometimes leave a corridor
between the two halves. Neighbouring rooms are joined by doors along a random spanning
tree of the room adjacency graph (so some rooms are dead ends), plus extra doors that
make loops. Every room gets a few pieces of furniture, placed away from doors; a piece
that would cut the house's navigable space in two is dropped. The outer walls are closed.

All coordinates are multiples of 0.05 m, so walls and furniture faces fall on grid
lines of the default 0.05 m grid and rendered depth is exact.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .scene import Scene, SceneError, rasterize

MIN_ROOM = 2.4  # metres, shortest room side
MAX_ROOM = 6.0  # metres, rooms longer than this get split
WALL_T = 0.1

# (category, height range, size range of the two sides)
FURNITURE = [
    (0, (0.7, 0.8), (0.6, 1.6), (0.5, 0.9)),   # table / desk
    (1, (0.45, 0.6), (1.4, 2.0), (0.8, 1.5)),  # bed / sofa
    (3, (0.85, 0.95), (1.0, 2.4), (0.5, 0.65)),  # counter
    (4, (1.8, 2.1), (0.8, 1.6), (0.45, 0.6)),  # wardrobe
    (5, (0.8, 1.4), (0.35, 0.5), (0.35, 0.5)),  # plant
    (7, (0.4, 0.5), (0.4, 0.6), (0.4, 0.6)),   # stool / box
]


@dataclass
class HouseParams:
    """Knobs of the generator; the defaults give the documented size range."""

    min_side: float = 6.0  # shortest possible longer side of the house (m)
    max_side: float = 25.0  # longest possible longer side of the house (m)
    loop_prob: float = 0.3  # chance that a non-tree adjacency gets a door (loops)
    corridor_prob: float = 0.35  # chance that a long cut becomes a corridor
    furniture_per_room: float = 1.6  # mean furniture pieces per room

    def validate(self) -> None:
        if not (4.0 <= self.min_side <= self.max_side <= 60.0):
            raise SceneError(
                f"house params: need 4 <= min_side ({self.min_side}) <= max_side ({self.max_side}) <= 60")
        for name in ("loop_prob", "corridor_prob"):
            v = getattr(self, name)
            if not (0.0 <= v <= 1.0):
                raise SceneError(f"house params: {name}={v} is not a probability")
        if not (0.0 <= self.furniture_per_room <= 10.0):
            raise SceneError(f"house params: furniture_per_room={self.furniture_per_room} not in [0, 10]")


def _snap(v: float, q: float = 0.1) -> float:
    return round(round(v / q) * q, 4)


def _split(rect, rng, params: HouseParams, rooms: list, depth: int = 0) -> None:
    x0, y0, x1, y1 = rect
    w, h = x1 - x0, y1 - y0
    long_side = max(w, h)
    must = long_side > MAX_ROOM or w * h > 24.0
    may = long_side > 2 * MIN_ROOM + 0.2 and rng.random() < 0.35
    if not (must or may) or long_side < 2 * MIN_ROOM + 0.2:
        rooms.append(rect)
        return
    vertical = w >= h  # cut with a vertical line when the rect is wide
    lo, hi = (x0, x1) if vertical else (y0, y1)
    corridor = (long_side > 3 * MIN_ROOM + 1.6 and rng.random() < params.corridor_prob)
    cw = _snap(rng.uniform(1.2, 1.6)) if corridor else 0.0
    a = lo + MIN_ROOM
    b = hi - MIN_ROOM - cw
    cut = _snap(rng.uniform(a, b))
    if vertical:
        first = (x0, y0, cut, y1)
        second = (cut + cw, y0, x1, y1)
        mid = (cut, y0, cut + cw, y1)
    else:
        first = (x0, y0, x1, cut)
        second = (x0, cut + cw, x1, y1)
        mid = (x0, cut, x1, cut + cw)
    _split(first, rng, params, rooms, depth + 1)
    if corridor:
        rooms.append(mid)
    _split(second, rng, params, rooms, depth + 1)


def _shared_edge(a, b):
    """The segment shared by two touching rectangles, or None."""
    ax0, ay0, ax1, ay1 = a
    bx0, by0, bx1, by1 = b
    for xa, xb in ((ax1, bx0), (ax0, bx1)):
        if abs(xa - xb) < 1e-6:
            lo, hi = max(ay0, by0), min(ay1, by1)
            if hi - lo > 1e-6:
                return (xa, lo, xa, hi)
    for ya, yb in ((ay1, by0), (ay0, by1)):
        if abs(ya - yb) < 1e-6:
            lo, hi = max(ax0, bx0), min(ax1, bx1)
            if hi - lo > 1e-6:
                return (lo, ya, hi, ya)
    return None


def generate_house(seed: int, scene_id: str | None = None, params: HouseParams | None = None) -> Scene:
    """Generate one house from ``seed``. The same seed always gives the same house."""
    params = params or HouseParams()
    params.validate()
    if not isinstance(seed, (int, np.integer)) or seed < 0:
        raise SceneError(f"house seed must be a non-negative integer, got {seed!r}")
    rng = np.random.default_rng(int(seed))
    long_side = _snap(np.exp(rng.uniform(np.log(params.min_side), np.log(params.max_side))))
    short_side = _snap(max(min(long_side * rng.uniform(0.5, 1.0), params.max_side), min(5.0, long_side)))
    W, H = (long_side, short_side) if rng.random() < 0.5 else (short_side, long_side)
    rooms: list = []
    _split((0.0, 0.0, W, H), rng, params, rooms)

    walls = [(0, 0, W, 0), (W, 0, W, H), (W, H, 0, H), (0, H, 0, 0)]
    for x0, y0, x1, y1 in rooms:
        walls += [(x0, y0, x1, y0), (x1, y0, x1, y1), (x1, y1, x0, y1), (x0, y1, x0, y0)]

    # Doors: a random spanning tree of the adjacency graph, plus loop doors.
    edges = []
    for i in range(len(rooms)):
        for j in range(i + 1, len(rooms)):
            e = _shared_edge(rooms[i], rooms[j])
            if e is not None and max(abs(e[2] - e[0]), abs(e[3] - e[1])) >= 1.6:
                edges.append((i, j, e))
    order = rng.permutation(len(edges))
    parent = list(range(len(rooms)))

    def find(a):
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    doors = []
    for k in order:
        i, j, e = edges[k]
        ri, rj = find(i), find(j)
        if ri != rj or rng.random() < params.loop_prob:
            if ri != rj:
                parent[ri] = rj
            x0, y0, x1, y1 = e
            L = max(abs(x1 - x0), abs(y1 - y0))
            dw = _snap(rng.uniform(0.8, min(1.0, L - 0.8)))
            c = _snap(rng.uniform(0.35 + dw / 2, L - 0.35 - dw / 2))
            if x0 == x1:
                lo = min(y0, y1)
                doors.append((x0, lo + c - dw / 2, x0, lo + c + dw / 2))
            else:
                lo = min(x0, x1)
                doors.append((lo + c - dw / 2, y0, lo + c + dw / 2, y0))

    boxes, heights, cats = _furnish(rooms, doors, rng, params)
    sid = scene_id or f"procgen-{seed}"
    scene = Scene(scene_id=sid, walls=np.array(walls), wall_thickness=WALL_T, doors=np.array(doors).reshape(-1, 4),
                  boxes=np.array(boxes).reshape(-1, 4), box_heights=np.array(heights),
                  box_categories=np.array(cats, np.int64), source="procgen")
    return _drop_blocking_furniture(scene)


def _furnish(rooms, doors, rng, params):
    boxes, heights, cats = [], [], []
    door_c = np.array([((d[0] + d[2]) / 2, (d[1] + d[3]) / 2) for d in doors]).reshape(-1, 2)
    for x0, y0, x1, y1 in rooms:
        w, h = x1 - x0, y1 - y0
        if min(w, h) < 2.0:  # corridors stay clear
            continue
        n = rng.poisson(params.furniture_per_room * min(2.0, w * h / 12.0))
        for _ in range(n):
            for _attempt in range(6):
                cat, hr, sa, sb = FURNITURE[rng.integers(len(FURNITURE))]
                a = _snap(rng.uniform(*sa), 0.05)
                b = _snap(rng.uniform(*sb), 0.05)
                if rng.random() < 0.5:
                    a, b = b, a
                if a > w - 1.0 or b > h - 1.0:
                    continue
                side = rng.integers(5)  # against one of four walls, or free-standing
                gap = 0.1  # leave room for the wall's half-thickness
                if side == 0:
                    bx0, by0 = x0 + gap, rng.uniform(y0 + gap, y1 - gap - b)
                elif side == 1:
                    bx0, by0 = x1 - gap - a, rng.uniform(y0 + gap, y1 - gap - b)
                elif side == 2:
                    bx0, by0 = rng.uniform(x0 + gap, x1 - gap - a), y0 + gap
                elif side == 3:
                    bx0, by0 = rng.uniform(x0 + gap, x1 - gap - a), y1 - gap - b
                else:
                    if a > w - 1.7 or b > h - 1.7:
                        continue
                    bx0, by0 = rng.uniform(x0 + 0.8, x1 - 0.8 - a), rng.uniform(y0 + 0.8, y1 - 0.8 - b)
                bx0, by0 = _snap(bx0, 0.05), _snap(by0, 0.05)
                box = (bx0, by0, round(bx0 + a, 4), round(by0 + b, 4))
                if len(door_c):
                    cx = np.clip(door_c[:, 0], box[0], box[2])
                    cy = np.clip(door_c[:, 1], box[1], box[3])
                    if np.min(np.hypot(cx - door_c[:, 0], cy - door_c[:, 1])) < 1.0:
                        continue
                if any(not (box[2] + 0.5 <= o[0] or o[2] + 0.5 <= box[0] or box[3] + 0.5 <= o[1]
                            or o[3] + 0.5 <= box[1]) for o in boxes):
                    continue
                boxes.append(box)
                heights.append(_snap(rng.uniform(*hr), 0.05))
                cats.append(cat)
                break
    return boxes, heights, cats


def _drop_blocking_furniture(scene: Scene) -> Scene:
    """Remove furniture (last placed first) until it no longer splits navigable space."""
    bare = Scene(scene.scene_id, scene.walls, scene.wall_thickness, scene.doors, source=scene.source)
    n_bare = int(rasterize(bare).component.max()) + 1
    while len(scene.boxes):
        if int(rasterize(scene).component.max()) + 1 <= n_bare:
            return scene
        scene = Scene(scene.scene_id, scene.walls, scene.wall_thickness, scene.doors, scene.boxes[:-1],
                      scene.box_heights[:-1], scene.box_categories[:-1], scene.source)
    return scene
