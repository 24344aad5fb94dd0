"""Scenes: vector geometry shared by every scene source, and its rasterised grid.

A :class:`Scene` is what a scene source produces (the procedural generator in
:mod:`.procgen`, real floor plans in :mod:`.r2v`): wall segments with a thickness,
door segments that cut openings into walls, and axis-aligned furniture boxes, all in
metres on a flat floor. Everything the simulator needs is derived from it once by
:func:`rasterize`, which returns a :class:`SceneGrid`:

* ``kind``: per cell an index into a small table of vertical profiles (free floor of a
  room, full-height wall, door lintel, furniture of a given height). The renderer casts
  rays over this grid; walls and furniture are vertical extrusions.
* ``nav``: the cells where the *whole cell* keeps the agent's disc (radius 0.1 m) clear of
  every obstacle cell. The agent's centre is only ever inside a navigable cell, so the
  agent is never inside an obstacle.
* ``room``: room index per cell (connected free space with doors closed), used for
  per-room wall and floor colours.
* ``component``: connected component of the navigable grid under the geodesic graph's
  own connectivity (8 neighbours without corner cutting, which connects exactly what 4
  neighbours connect), used to keep sub-goals reachable.

Coordinates: x to the right, y up, headings counter-clockwise from +x. Cell ``(i, j)``
covers ``x in [x0 + j*cs, x0 + (j+1)*cs)`` and ``y in [y0 + i*cs, y0 + (i+1)*cs)``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

# Vertical layout (metres). Habitat's agent is 1.5 m tall with the camera at 1.25 m.
CEILING_HEIGHT = 2.5
DOOR_HEIGHT = 2.0
AGENT_HEIGHT = 1.5
AGENT_RADIUS = 0.1
CELL_SIZE = 0.05

# Material ids stored in the kind table.
MAT_FREE = 0
MAT_WALL = 1
MAT_DOOR = 2  # the lintel above a door opening and the door's threshold
MAT_VOID = 3  # outside the building: solid, never seen from inside
MAT_FURNITURE = 4  # furniture category c has material MAT_FURNITURE + c
NUM_FURNITURE_CATEGORIES = 8


class SceneError(ValueError):
    """A scene (or its parameters) is malformed; the message names the scene and problem."""


@dataclass
class Scene:
    """Vector description of one indoor scene.

    Attributes:
        scene_id: unique name, e.g. ``procgen-train-00012`` or a floor-plan id.
        walls: (N, 4) float segments ``x0, y0, x1, y1`` in metres.
        wall_thickness: thickness of every wall in metres.
        doors: (M, 4) float segments; each cuts an opening of the wall thickness
            through the walls it lies on, leaving a lintel above ``DOOR_HEIGHT``.
        boxes: (K, 4) axis-aligned furniture rectangles ``x_min, y_min, x_max, y_max``.
        box_heights: (K,) heights of the furniture boxes in metres.
        box_categories: (K,) integer furniture categories (for colours), < 8.
        source: where the scene came from (``procgen`` or ``r2v``).
    """

    scene_id: str
    walls: np.ndarray
    wall_thickness: float = 0.1
    doors: np.ndarray = field(default_factory=lambda: np.zeros((0, 4), np.float32))
    boxes: np.ndarray = field(default_factory=lambda: np.zeros((0, 4), np.float32))
    box_heights: np.ndarray = field(default_factory=lambda: np.zeros((0,), np.float32))
    box_categories: np.ndarray = field(default_factory=lambda: np.zeros((0,), np.int64))
    source: str = "procgen"

    def __post_init__(self) -> None:
        self.walls = _as_array(self.walls, (-1, 4), "walls", self.scene_id)
        self.doors = _as_array(self.doors, (-1, 4), "doors", self.scene_id)
        self.boxes = _as_array(self.boxes, (-1, 4), "boxes", self.scene_id)
        self.box_heights = _as_array(self.box_heights, (-1,), "box_heights", self.scene_id)
        self.box_categories = np.asarray(self.box_categories, dtype=np.int64).reshape(-1)
        if len(self.walls) == 0:
            raise SceneError(f"scene {self.scene_id!r}: has no walls")
        if not (0.0 < self.wall_thickness <= 1.0):
            raise SceneError(f"scene {self.scene_id!r}: wall_thickness {self.wall_thickness} not in (0, 1]")
        k = len(self.boxes)
        if len(self.box_heights) != k or len(self.box_categories) != k:
            raise SceneError(
                f"scene {self.scene_id!r}: {k} boxes but {len(self.box_heights)} heights and "
                f"{len(self.box_categories)} categories"
            )
        if k and (np.any(self.boxes[:, 2] <= self.boxes[:, 0]) or np.any(self.boxes[:, 3] <= self.boxes[:, 1])):
            raise SceneError(f"scene {self.scene_id!r}: a furniture box has x_max <= x_min or y_max <= y_min")
        if k and (np.any(self.box_heights <= 0) or np.any(self.box_heights > CEILING_HEIGHT)):
            raise SceneError(f"scene {self.scene_id!r}: furniture heights must lie in (0, {CEILING_HEIGHT}]")
        if k and (np.any(self.box_categories < 0) or np.any(self.box_categories >= NUM_FURNITURE_CATEGORIES)):
            raise SceneError(f"scene {self.scene_id!r}: furniture categories must lie in [0, {NUM_FURNITURE_CATEGORIES})")

    def bounds(self) -> tuple[float, float, float, float]:
        """(x_min, y_min, x_max, y_max) over all geometry."""
        pts = [self.walls[:, [0, 1]], self.walls[:, [2, 3]]]
        if len(self.boxes):
            pts += [self.boxes[:, [0, 1]], self.boxes[:, [2, 3]]]
        p = np.concatenate(pts)
        return float(p[:, 0].min()), float(p[:, 1].min()), float(p[:, 0].max()), float(p[:, 1].max())


def _as_array(a, shape, name: str, scene_id: str) -> np.ndarray:
    try:
        arr = np.asarray(a, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise SceneError(f"scene {scene_id!r}: {name} is not numeric: {e}") from None
    if arr.size == 0:
        return np.zeros((0,) + tuple(s for s in shape[1:]), np.float32)
    try:
        arr = arr.reshape(shape)
    except ValueError:
        raise SceneError(f"scene {scene_id!r}: {name} has shape {arr.shape}, expected {shape}") from None
    if not np.all(np.isfinite(arr)):
        raise SceneError(f"scene {scene_id!r}: {name} contains NaN or infinite values")
    return arr.astype(np.float32)


@dataclass
class SceneGrid:
    """The rasterised scene the simulator works on (see the module docstring)."""

    scene_id: str
    origin: tuple[float, float]  # world (x, y) of the grid's lower-left corner
    cell_size: float
    kind: np.ndarray  # (H, W) int32 index into the kind table
    kind_lo: np.ndarray  # (K,) float32 bottom of the solid part of each kind (m)
    kind_hi: np.ndarray  # (K,) float32 top of the solid part (0 for free floor)
    kind_mat: np.ndarray  # (K,) int32 material id
    kind_room: np.ndarray  # (K,) int32 room index (-1 when not a room's floor)
    nav: np.ndarray  # (H, W) bool
    room: np.ndarray  # (H, W) int32, -1 outside rooms
    component: np.ndarray  # (H, W) int32, -1 where not navigable
    num_rooms: int
    seed: int = 0  # colours are derived from it

    @property
    def shape(self) -> tuple[int, int]:
        return self.kind.shape

    def world_to_cell(self, xy: np.ndarray) -> np.ndarray:
        """(..., 2) world points -> (..., 2) integer (row, col); may lie outside the grid."""
        xy = np.asarray(xy, dtype=np.float64)
        col = np.floor((xy[..., 0] - self.origin[0]) / self.cell_size).astype(np.int64)
        row = np.floor((xy[..., 1] - self.origin[1]) / self.cell_size).astype(np.int64)
        return np.stack([row, col], axis=-1)

    def cell_center(self, rc: np.ndarray) -> np.ndarray:
        rc = np.asarray(rc)
        x = self.origin[0] + (rc[..., 1] + 0.5) * self.cell_size
        y = self.origin[1] + (rc[..., 0] + 0.5) * self.cell_size
        return np.stack([x, y], axis=-1)

    def is_navigable(self, xy: np.ndarray) -> np.ndarray:
        rc = self.world_to_cell(xy)
        h, w = self.shape
        inside = (rc[..., 0] >= 0) & (rc[..., 0] < h) & (rc[..., 1] >= 0) & (rc[..., 1] < w)
        out = np.zeros(rc.shape[:-1], bool)
        out[inside] = self.nav[rc[..., 0][inside], rc[..., 1][inside]]
        return out

    def navigable_area(self) -> float:
        return float(self.nav.sum()) * self.cell_size**2

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in (self.kind, self.nav, self.room, self.component))


def _segment_cells(seg: np.ndarray, half_width: float, origin, cs: float, shape) -> tuple[np.ndarray, np.ndarray]:
    """Rows and cols of the cells whose centres lie within ``half_width`` of a segment."""
    x0, y0, x1, y1 = (float(v) for v in seg)
    pad = half_width + cs
    c0 = int(np.floor((min(x0, x1) - pad - origin[0]) / cs))
    c1 = int(np.ceil((max(x0, x1) + pad - origin[0]) / cs))
    r0 = int(np.floor((min(y0, y1) - pad - origin[1]) / cs))
    r1 = int(np.ceil((max(y0, y1) + pad - origin[1]) / cs))
    c0, r0 = max(c0, 0), max(r0, 0)
    c1, r1 = min(c1, shape[1]), min(r1, shape[0])
    if c1 <= c0 or r1 <= r0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    rr, cc = np.mgrid[r0:r1, c0:c1]
    px = origin[0] + (cc + 0.5) * cs
    py = origin[1] + (rr + 0.5) * cs
    dx, dy = x1 - x0, y1 - y0
    L2 = dx * dx + dy * dy
    if L2 < 1e-12:
        t = np.zeros_like(px)
    else:
        t = np.clip(((px - x0) * dx + (py - y0) * dy) / L2, 0.0, 1.0)
    d2 = (px - (x0 + t * dx)) ** 2 + (py - (y0 + t * dy)) ** 2
    # A tiny epsilon makes walls that sit exactly on grid lines rasterise symmetrically.
    m = d2 <= (half_width + 1e-6) ** 2
    return rr[m], cc[m]


def rasterize(scene: Scene, cell_size: float = CELL_SIZE, agent_radius: float = AGENT_RADIUS,
              margin: float = 0.5, seed: int = 0) -> SceneGrid:
    """Turn a :class:`Scene` into the :class:`SceneGrid` the simulator uses.

    Raises :class:`SceneError` naming the scene when it has no navigable space.
    """
    if not (0.01 <= cell_size <= 0.25):
        raise SceneError(f"scene {scene.scene_id!r}: cell_size {cell_size} not in [0.01, 0.25]")
    xmin, ymin, xmax, ymax = scene.bounds()
    origin = (np.floor((xmin - margin) / cell_size) * cell_size, np.floor((ymin - margin) / cell_size) * cell_size)
    W = int(np.ceil((xmax + margin - origin[0]) / cell_size))
    H = int(np.ceil((ymax + margin - origin[1]) / cell_size))
    if H * W > 4000 * 4000:
        raise SceneError(f"scene {scene.scene_id!r}: {W * cell_size:.0f} x {H * cell_size:.0f} m is too large")
    wall, door = _walls_and_doors(scene, origin, cell_size, (H, W))
    furniture = _furniture(scene, wall, origin, cell_size)
    room, outside, num_rooms = _rooms(wall, door)
    kind, lo, hi, mat, kroom = _kinds(scene, wall, door, furniture, room, outside, num_rooms)
    nav, comp = _navigable(kind, lo, hi, cell_size, agent_radius)
    if comp.max() < 0:
        raise SceneError(f"scene {scene.scene_id!r}: no navigable space for an agent of radius {agent_radius} m")
    return SceneGrid(
        scene_id=scene.scene_id, origin=(float(origin[0]), float(origin[1])), cell_size=float(cell_size),
        kind=kind, kind_lo=lo, kind_hi=hi, kind_mat=mat, kind_room=kroom, nav=nav, room=room, component=comp,
        num_rooms=num_rooms, seed=seed,
    )


def _walls_and_doors(scene: Scene, origin, cell_size: float, shape) -> tuple[np.ndarray, np.ndarray]:
    """The cells of the walls and of the door openings cut into them (boolean grids)."""
    wall = np.zeros(shape, bool)
    half = scene.wall_thickness / 2
    for seg in scene.walls:
        r, c = _segment_cells(seg, half, origin, cell_size, shape)
        wall[r, c] = True
    door = np.zeros(shape, bool)
    for seg in scene.doors:
        # Doors cut a little wider than the wall so a slightly-off door still opens it.
        r, c = _segment_cells(seg, half + cell_size, origin, cell_size, shape)
        door[r, c] = True
    door &= wall
    wall &= ~door
    return wall, door


def _furniture(scene: Scene, wall: np.ndarray, origin, cell_size: float) -> np.ndarray:
    """Each cell's furniture box (its index in ``scene.boxes``), -1 where there is none."""
    H, W = wall.shape
    furniture = np.full(wall.shape, -1, np.int32)
    for b, (x0, y0, x1, y1) in enumerate(scene.boxes):
        c0 = max(int(np.ceil((x0 - origin[0]) / cell_size - 0.5)), 0)
        c1 = min(int(np.floor((x1 - origin[0]) / cell_size - 0.5)) + 1, W)
        r0 = max(int(np.ceil((y0 - origin[1]) / cell_size - 0.5)), 0)
        r1 = min(int(np.floor((y1 - origin[1]) / cell_size - 0.5)) + 1, H)
        if c1 > c0 and r1 > r0:
            sub = furniture[r0:r1, c0:c1]
            sub[~wall[r0:r1, c0:c1]] = b
    return furniture


def _rooms(wall: np.ndarray, door: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Rooms: connected open space with doors closed; returns each cell's room (-1 outside
    and in walls), the outside mask and the number of rooms. The component touching the
    grid's border is the outside of the building, which becomes solid void. Doors that lead
    outside are closed here (in place: they become wall)."""
    H, W = wall.shape
    open_space = ~wall & ~door
    labels, n = ndimage.label(open_space)
    border = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    outside = np.isin(labels, border[border > 0])
    # A front door is a wall here: a door is open only if every open cell next to it belongs
    # to the inside. Each door is examined in its bounding box padded by one cell (the reach
    # of its ring).
    lab_d, _ = ndimage.label(door, structure=np.ones((3, 3)))
    for d, sl in enumerate(ndimage.find_objects(lab_d), start=1):
        if sl is None:
            continue
        win = (slice(max(sl[0].start - 1, 0), min(sl[0].stop + 1, H)),
               slice(max(sl[1].start - 1, 0), min(sl[1].stop + 1, W)))
        m = lab_d[win] == d
        ring = ndimage.binary_dilation(m, structure=np.ones((3, 3))) & open_space[win]
        if np.any(outside[win] & ring) or not np.any(ring):
            door[win][m] = False
            wall[win][m] = True
    inside_labels = np.unique(labels[(labels > 0) & ~outside])
    remap = np.full(n + 1, -1, np.int32)
    remap[inside_labels] = np.arange(len(inside_labels), dtype=np.int32)
    room = remap[labels]
    room[outside] = -1
    return room, outside, len(inside_labels)


def _kinds(scene: Scene, wall, door, furniture, room, outside, num_rooms: int):
    """The kind grid and its table (lo and hi heights, material, room): free floor per room,
    door threshold, wall, void, lintel, one furniture kind per (height, category)."""
    lo, hi, mat, kroom = [], [], [], []

    def add(l, h, m, r):
        lo.append(l); hi.append(h); mat.append(m); kroom.append(r)
        return len(lo) - 1

    kind = np.zeros(wall.shape, np.int32)
    for r in range(num_rooms):
        add(0.0, 0.0, MAT_FREE, r)
    k_void = add(0.0, CEILING_HEIGHT, MAT_VOID, -1)
    k_wall = add(0.0, CEILING_HEIGHT, MAT_WALL, -1)
    k_door = add(DOOR_HEIGHT, CEILING_HEIGHT, MAT_DOOR, -1)
    kind[room >= 0] = room[room >= 0]
    kind[outside] = k_void
    kind[wall] = k_wall
    kind[door] = k_door
    fkinds: dict[tuple[float, int], int] = {}
    for b in range(len(scene.boxes)):
        key = (round(float(scene.box_heights[b]), 3), int(scene.box_categories[b]))
        if key not in fkinds:
            fkinds[key] = add(0.0, key[0], MAT_FURNITURE + key[1], -1)
    if len(scene.boxes):
        fk = np.array([fkinds[(round(float(scene.box_heights[b]), 3), int(scene.box_categories[b]))]
                       for b in range(len(scene.boxes))], np.int32)
        m = (furniture >= 0) & ~outside
        kind[m] = fk[furniture[m]]
    return (kind, np.asarray(lo, np.float32), np.asarray(hi, np.float32), np.asarray(mat, np.int32),
            np.asarray(kroom, np.int32))


def _navigable(kind, kind_lo, kind_hi, cell_size: float, agent_radius: float) -> tuple[np.ndarray, np.ndarray]:
    """The navigable cells and their connected components (-1 off the navigable space)."""
    # Anything whose solid part starts below the agent's height blocks it.
    blocking = (kind_hi[kind] > 0) & (kind_lo[kind] < AGENT_HEIGHT)
    # Exact clearance: a cell is navigable when every point of it is at least agent_radius
    # from every point of every blocking cell. Between two cells whose centres are (di, dj)
    # cells apart, that square-to-square distance is |(max(|di|-1, 0), max(|dj|-1, 0))|
    # cells: the centre distance to the nearest cell of the blocking set grown by one cell.
    near = ndimage.binary_dilation(blocking, structure=np.ones((3, 3), bool))
    edt = ndimage.distance_transform_edt(~near) * cell_size
    nav = (edt >= agent_radius - 1e-9) & ~blocking
    # Components as the geodesic search moves: a diagonal step needs both side cells free,
    # so only 4-neighbour connections join cells (a full 3x3 structure would join cells
    # that touch only at a corner, which no path can pass).
    comp, _ = ndimage.label(nav)
    return nav, comp.astype(np.int32) - 1
