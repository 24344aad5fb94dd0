"""A classical planner on the agent's own ego map: PLEX's planner observation, no ground truth.

:class:`MapPlanner` reads only what the learned planner sees: the 32 x 32 ego map (0.5 m
cells, row 0 ahead of the agent, column 0 to its left; channel 0 obstacles) and the goal
vector (distance, direction). It plans optimistically, as frontier-free map-based
navigation does: cells never seen count as free, observed obstacle cells are blocked.

- It stops once the goal is nearer than ``stop_distance`` (Euclidean, from the goal
  vector).
- Otherwise it runs Dijkstra (8-connected, diagonal steps cost sqrt 2; a diagonal step
  passes only where both cells beside it are free, so no path cuts a wall's corner) from
  the goal's cell, or from the point where the straight line to the goal leaves the map when the goal
  lies beyond it, and sets the sub-goal at the cell ``lookahead`` metres along the shortest
  path from the agent's cell (by steepest descent, so on the grid's 45-degree steps: its
  direction can differ from the goal's by up to about 0.5 rad in open space), or at the
  goal itself when it is nearer than that.
- When the agent's cell cannot reach the target on the map, it falls back to a sub-goal
  1.5 m towards the goal.
- With ``line_of_sight`` (the ``map-los`` planner) the sub-goal is the farthest cell of
  that path, within ``lookahead``, that a straight line from the agent reaches over cells
  seen as floor and free of obstacles (the first cell of the path when none is): a
  sub-goal a learned executor can walk straight to, never one behind a wall or in space
  it has not seen. A goal nearer than ``lookahead`` is the sub-goal only when such a line
  reaches it; otherwise the path is planned as for a far goal.

It is a baseline and a diagnostic: ``python -m plex_ma.evaluate --planner map --executor oracle``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

STOP_DISTANCE = 0.19  # m: the stand-in planners stop nearer the goal than this (success is < 0.2 m)
_NEIGHBOURS = np.array([(-1, 0), (1, 0), (0, -1), (0, 1), (-1, -1), (-1, 1), (1, -1), (1, 1)], np.int64)


@njit(cache=True)
def _cuts_corner(blocked, a, b, x, y, k):
    """True if step ``k`` of ``_NEIGHBOURS`` from cell (a, b) to (x, y) is diagonal and passes
    a blocked cell beside it (it would cut a wall's corner)."""
    return k >= 4 and (blocked[a, y] or blocked[x, b])


@njit(cache=True)
def _distances(blocked, ga, gb, nb):
    """Dijkstra distances (in cells) from cell (ga, gb) over the free cells of ``blocked``."""
    s = blocked.shape[0]
    dist = np.full((s, s), np.inf)
    done = np.zeros((s, s), np.bool_)
    dist[ga, gb] = 0.0
    for _ in range(s * s):  # O(n^2) Dijkstra: 1,024 cells, no heap needed
        best, a, b = np.inf, -1, -1
        for i in range(s):
            for j in range(s):
                if not done[i, j] and dist[i, j] < best:
                    best, a, b = dist[i, j], i, j
        if a < 0:
            break
        done[a, b] = True
        for k in range(nb.shape[0]):
            x, y = a + nb[k, 0], b + nb[k, 1]
            if 0 <= x < s and 0 <= y < s and not blocked[x, y]:
                if _cuts_corner(blocked, a, b, x, y, k):
                    continue
                c = best + (1.4142135623730951 if k >= 4 else 1.0)
                if c < dist[x, y]:
                    dist[x, y] = c
    return dist


@njit(cache=True)
def _seen_free_line(obstacles, explored, a0, b0, a1, b1):
    """True if the straight line between the centres of cells (a0, b0) and (a1, b1)
    crosses only cells seen as floor and free of obstacles (sampled every quarter cell)."""
    n = int(4 * max(abs(a1 - a0), abs(b1 - b0))) + 1
    for k in range(1, n + 1):
        t = k / n
        a = int(math.floor(a0 + 0.5 + t * (a1 - a0)))
        b = int(math.floor(b0 + 0.5 + t * (b1 - b0)))
        if obstacles[a, b] > 0.5 or explored[a, b] <= 0.0:
            return False
    return True


@njit(cache=True)
def _cell_of(d, th, cell, s):
    """The ego-map cell (row, column) of the point ``d`` metres away at bearing ``th``."""
    a = int(round(s / 2 - d * math.cos(th) / cell - 0.5))
    b = int(round(s / 2 - d * math.sin(th) / cell - 0.5))
    return min(max(a, 0), s - 1), min(max(b, 0), s - 1)


@njit(cache=True)
def _plan(obstacles, explored, d, th, cell, lookahead, nb, line_of_sight):
    """(rho, theta) of the sub-goal for one ego map (see the module docstring)."""
    s = obstacles.shape[0]
    if d <= lookahead:
        ga, gb = _cell_of(d, th, cell, s)
        if not line_of_sight or _seen_free_line(obstacles, explored, s // 2, s // 2, ga, gb):
            return d, th
    fwd, left = d * math.cos(th), d * math.sin(th)
    lim = (s / 2 - 1) * cell
    m = max(abs(fwd), abs(left))
    if m > lim:
        fwd, left = fwd * lim / m, left * lim / m
    ga = min(max(int(s / 2 - fwd / cell), 0), s - 1)
    gb = min(max(int(s / 2 - left / cell), 0), s - 1)
    blocked = obstacles > 0.5
    blocked[ga, gb] = False
    dist = _distances(blocked, ga, gb, nb)
    a, b = s // 2, s // 2
    if not np.isfinite(dist[a, b]):
        # the agent's own cell may be marked (an obstacle within its 0.5 m): step off it
        best, bx, by = np.inf, a, b
        for k in range(nb.shape[0]):
            x, y = a + nb[k, 0], b + nb[k, 1]
            if dist[x, y] < best:
                best, bx, by = dist[x, y], x, y
        if not np.isfinite(best):
            return min(d, 1.5), th
        a, b = bx, by
    a0, b0 = a, b
    walked = 0.0
    first_a, first_b = -1, -1  # the path's first cell
    seen_a, seen_b = -1, -1  # the farthest path cell so far in a straight line over seen floor
    while walked < lookahead / cell and dist[a, b] > 0:
        best, bx, by, step = dist[a, b], a, b, 0.0
        for k in range(nb.shape[0]):
            x, y = a + nb[k, 0], b + nb[k, 1]
            if (0 <= x < s and 0 <= y < s and dist[x, y] < best
                    and not _cuts_corner(blocked, a, b, x, y, k)):
                best, bx, by, step = dist[x, y], x, y, (1.4142135623730951 if k >= 4 else 1.0)
        if step == 0.0:
            break
        a, b = bx, by
        walked += step
        if first_a < 0:
            first_a, first_b = a, b
        if line_of_sight:
            if _seen_free_line(obstacles, explored, a0, b0, a, b):
                seen_a, seen_b = a, b
            else:
                break
    if line_of_sight:
        a, b = (seen_a, seen_b) if seen_a >= 0 else (first_a, first_b) if first_a >= 0 else (a, b)
    f, l = (s / 2 - a - 0.5) * cell, (s / 2 - b - 0.5) * cell
    return math.hypot(f, l), math.atan2(l, f)


class MapPlanner:
    """Shortest paths on the planner's own ego map (module docstring). ``decide`` takes
    planner observations (``ego_map`` (k, C, S, S), ``goal`` (k, 2)) and returns the
    arrays the env's ``step`` takes for those worlds."""

    name = "map"
    ground_truth = False

    def __init__(self, cell: float = 0.5, lookahead: float = 2.0, stop_distance: float = STOP_DISTANCE,
                 line_of_sight: bool = False):
        self.cell, self.lookahead, self.stop_distance = float(cell), float(lookahead), float(stop_distance)
        self.line_of_sight = bool(line_of_sight)

    def decide(self, obs: dict) -> tuple[np.ndarray, np.ndarray]:
        """(stop (k,) int64, subgoal (k, 2) float32)."""
        ego = np.asarray(obs["ego_map"], np.float32)
        goal = np.asarray(obs["goal"], np.float64)
        stop = (goal[:, 0] < self.stop_distance).astype(np.int64)
        sub = np.zeros((len(goal), 2), np.float32)
        for k in range(len(goal)):
            sub[k] = _plan(ego[k, 0], ego[k, 1], goal[k, 0], goal[k, 1], self.cell, self.lookahead, _NEIGHBOURS,
                           self.line_of_sight)
        return stop, sub
