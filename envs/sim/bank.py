"""A scene bank: the grids of many scenes packed into flat arrays for the compiled kernels."""

from __future__ import annotations

import colorsys

import numpy as np

from .corners import CornerGraphs
from .kernels import move_mask
from .scene import MAT_FURNITURE, NUM_FURNITURE_CATEGORIES, SceneGrid

# Material colours (RGB): free, default wall, door, void, then furniture categories.
MATERIAL_RGB = np.array(
    [
        [128, 128, 128],
        [205, 200, 190],
        [122, 78, 44],
        [40, 40, 40],
        [150, 90, 60],    # 0 generic furniture: wood
        [60, 90, 150],    # 1 sofa / bed: fabric blue
        [235, 235, 235],  # 2 sanitary: white
        [90, 90, 95],     # 3 kitchen counter: dark grey
        [170, 140, 90],   # 4 closet: light wood
        [110, 150, 80],   # 5 plant / special: green
        [180, 60, 60],    # 6 stairs: red
        [200, 180, 60],   # 7 other: yellow
    ],
    np.float64,
)
assert len(MATERIAL_RGB) == MAT_FURNITURE + NUM_FURNITURE_CATEGORIES


def room_colours(seed: int, num_rooms: int) -> tuple[np.ndarray, np.ndarray]:
    """Deterministic per-room (wall, floor) colours: distinct pastel walls, varied floors."""
    rng = np.random.default_rng([seed, 7919])
    walls = np.zeros((num_rooms, 3))
    floors = np.zeros((num_rooms, 3))
    h0 = rng.random()
    for r in range(num_rooms):
        h = (h0 + r * 0.618034) % 1.0
        walls[r] = np.array(colorsys.hsv_to_rgb(h, 0.35 + 0.25 * rng.random(), 0.75 + 0.2 * rng.random())) * 255
        fh = [0.08, 0.1, 0.55, 0.0, 0.6][rng.integers(5)]
        floors[r] = np.array(colorsys.hsv_to_rgb(fh, 0.25 + 0.35 * rng.random(), 0.35 + 0.35 * rng.random())) * 255
    return walls, floors


class SceneBank:
    """Concatenation of :class:`SceneGrid` s; scene ``s`` occupies cells
    ``off[s] : off[s] + h[s] * w[s]`` of the flat arrays. All grids share one cell size."""

    def __init__(self, grids: list[SceneGrid]):
        if not grids:
            raise ValueError("a scene bank needs at least one scene")
        cs = {g.cell_size for g in grids}
        if len(cs) != 1:
            raise ValueError(f"all scenes of a bank must share one cell size, got {sorted(cs)}")
        self.grids = list(grids)
        self.cell_size = grids[0].cell_size
        self.scene_ids = [g.scene_id for g in grids]
        sizes = np.array([g.kind.size for g in grids], np.int64)
        self.off = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
        self.h = np.array([g.shape[0] for g in grids], np.int64)
        self.w = np.array([g.shape[1] for g in grids], np.int64)
        self.ox = np.array([g.origin[0] for g in grids], np.float64)
        self.oy = np.array([g.origin[1] for g in grids], np.float64)
        self.max_cells = int(sizes.max())
        kind_off = np.concatenate([[0], np.cumsum([len(g.kind_lo) for g in grids])[:-1]]).astype(np.int32)
        room_off = np.concatenate([[0], np.cumsum([g.num_rooms for g in grids])[:-1]]).astype(np.int32)
        self.kind = np.concatenate([(g.kind + ko).ravel() for g, ko in zip(grids, kind_off)]).astype(np.int32)
        self.nav = np.concatenate([g.nav.ravel() for g in grids]).astype(np.uint8)
        self.moves = np.concatenate([move_mask(g.nav).ravel() for g in grids])  # the search graph
        self.comp = np.concatenate([g.component.ravel() for g in grids]).astype(np.int32)
        self.klo = np.concatenate([g.kind_lo for g in grids]).astype(np.float64)
        self.khi = np.concatenate([g.kind_hi for g in grids]).astype(np.float64)
        self.kmat = np.concatenate([g.kind_mat for g in grids]).astype(np.int64)
        self.kroom = np.concatenate(
            [np.where(g.kind_room >= 0, g.kind_room + ro, -1) for g, ro in zip(grids, room_off)]
        ).astype(np.int64)
        walls, floors = [], []
        for g in grids:
            wc, fc = room_colours(g.seed, g.num_rooms)
            walls.append(wc)
            floors.append(fc)
        self.room_wall_rgb = np.concatenate(walls).reshape(-1, 3) if walls else np.zeros((0, 3))
        self.room_floor_rgb = np.concatenate(floors).reshape(-1, 3) if floors else np.zeros((0, 3))
        self.mat_rgb = MATERIAL_RGB.copy()
        self._corners = None

    @property
    def corners(self) -> CornerGraphs:
        """The scenes' corner graphs, for exact point-to-point geodesic distances (built
        scene by scene on first use and shared by every user of the bank)."""
        if self._corners is None:
            self._corners = CornerGraphs(self)
        return self._corners

    def __len__(self) -> int:
        return len(self.grids)

    def grid_args(self, s: int) -> tuple:
        """(nav, off, h, w, ox, oy, cs) for the single-scene kernels."""
        return (self.nav, int(self.off[s]), int(self.h[s]), int(self.w[s]), float(self.ox[s]),
                float(self.oy[s]), self.cell_size)

    def search_args(self, s: int) -> tuple:
        """(nav, moves, off, h, w, ox, oy, cs) for the single-scene search kernels."""
        return (self.nav, self.moves) + self.grid_args(s)[1:]

    @property
    def nbytes(self) -> int:
        return self.kind.nbytes + self.nav.nbytes + self.moves.nbytes + self.comp.nbytes
