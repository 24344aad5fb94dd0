"""Top-down ``rgb_array`` view for people: walls, furniture, explored area, path, goal,
and optionally the current sub-goal."""

from __future__ import annotations

import numpy as np
from PIL import Image, ImageDraw

from .scene import MAT_DOOR, MAT_FREE, MAT_FURNITURE, MAT_VOID, MAT_WALL, SceneGrid

_FLOOR = np.array([236, 236, 236], np.uint8)
_UNSEEN = np.array([200, 200, 200], np.uint8)
_WALL = np.array([40, 40, 48], np.uint8)
_VOID = np.array([255, 255, 255], np.uint8)
_DOOR = np.array([170, 120, 70], np.uint8)
_FURN = np.array([150, 110, 80], np.uint8)


def topdown_view(grid: SceneGrid, path: np.ndarray | None = None, goal=None, subgoal=None,
                 agent_pose=None, explored: np.ndarray | None = None, px_per_m: float = 20.0,
                 subgoal_raw=None) -> np.ndarray:
    """Render an (H, W, 3) uint8 map of ``grid``.

    ``path`` (T, 2) world points; ``goal``/``subgoal``/``subgoal_raw`` world (x, y);
    ``agent_pose`` (x, y, heading); ``explored`` a boolean mask over the grid's cells
    (cells outside it are drawn darker). North (+y) is up.
    """
    mat = grid.kind_mat[grid.kind]
    img = np.empty(grid.shape + (3,), np.uint8)
    img[:] = _FLOOR
    if explored is not None:
        img[~explored & (mat == MAT_FREE)] = _UNSEEN
    img[mat == MAT_WALL] = _WALL
    img[mat == MAT_VOID] = _VOID
    img[mat == MAT_DOOR] = _DOOR
    img[mat >= MAT_FURNITURE] = _FURN
    img = img[::-1]  # row 0 of the grid is the lowest y
    scale = px_per_m * grid.cell_size
    h, w = grid.shape
    out = Image.fromarray(img).resize((max(1, int(round(w * scale))), max(1, int(round(h * scale)))), Image.NEAREST)
    draw = ImageDraw.Draw(out)

    def px(p):
        x = (float(p[0]) - grid.origin[0]) * px_per_m
        y = (h * grid.cell_size - (float(p[1]) - grid.origin[1])) * px_per_m
        return x, y

    r = max(2.0, 0.15 * px_per_m)
    if path is not None and len(path) > 1:
        draw.line([px(p) for p in path], fill=(30, 110, 230), width=max(1, int(0.06 * px_per_m)))
    if goal is not None:
        x, y = px(goal)
        draw.ellipse([x - r, y - r, x + r, y + r], fill=(220, 30, 30))
    if subgoal_raw is not None:
        x, y = px(subgoal_raw)
        draw.ellipse([x - r * 0.6, y - r * 0.6, x + r * 0.6, y + r * 0.6], outline=(230, 140, 0), width=2)
    if subgoal is not None:
        x, y = px(subgoal)
        draw.rectangle([x - r * 0.8, y - r * 0.8, x + r * 0.8, y + r * 0.8], fill=(250, 160, 0))
    if agent_pose is not None:
        x, y = px(agent_pose[:2])
        th = float(agent_pose[2])
        draw.ellipse([x - r, y - r, x + r, y + r], fill=(20, 160, 60))
        draw.line([(x, y), (x + 2 * r * np.cos(th), y - 2 * r * np.sin(th))], fill=(0, 80, 0), width=2)
    return np.asarray(out)
