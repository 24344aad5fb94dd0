"""Exact geodesic distances between any two points of a scene, from its corner graph.

The search graph (:data:`kernels.MOVE_DR`): 8-connected navigable cells, straight steps
of one cell, diagonal steps of sqrt(2) cells that may not cut a blocked corner. On such a
grid, Uras, Felner & Koenig's *simple subgoal graphs* (SoCS 2013) answer shortest-path
queries exactly with a few hundred memory reads instead of a search over thousands of
cells. We call their subgoals *corners*, to keep "sub-goal" for the planner's.

* A **corner** is a navigable cell beside the convex corner of an obstacle: for some
  diagonal step, both straight steps it is made of are free and the diagonal cell is
  blocked. A procedural house has about a hundred.
* Two cells are **h-reachable** when a path between them is as short as the octile
  distance (an obstacle-free grid distance). If a shortest path has no corner on it,
  its ends are h-reachable and the path that takes all its diagonal steps first is free;
  otherwise it bends only at corners. So the distance between cells ``a`` and ``b`` is
  either their octile distance (when that diagonal-first path is free) or
  ``min over corners x, y: octile(a, x) + D[x, y] + octile(y, b)``, where ``x`` and
  ``y`` are corners *directly* h-reachable from ``a`` and ``b`` (no other corner needed
  on the way) and ``D`` is the corners' all-pairs distance table.
* :func:`_scan` finds the corners directly h-reachable from a cell by walking its 8
  rays: along the 4 straight ones and, from each cell of the 4 diagonal ones, along
  their two straight components as far as the earlier rows reached (farther cells are
  behind a corner). ``clear[v, k]``, the number of free non-corner cells after ``v`` in
  straight direction ``k``, makes each ray one memory read.
* ``D`` comes from the graph whose edges join each corner to the corners its scan
  finds, weighted by their octile distance (Floyd-Warshall; about 1 ms per house).

A point links to the navigable centres of the 2x2 block of cells around it, as in every
other search here (:func:`kernels._link`), so distances are those of :func:`kernels.astar`
and of the Dijkstra fields.
"""

from __future__ import annotations

import math
import sys

import numpy as np
from numba import njit, prange

from .kernels import INF, MOVE_DC, MOVE_DR, _block, _link, astar, pick, threaded

for _alias in ("plex_ma.envs.sim.corners", "envs.sim.corners"):  # see kernels.py
    sys.modules.setdefault(_alias, sys.modules[__name__])
del _alias

# A scene with more corners gets no table (8 bytes per pair: 8 MB at this size) and its
# queries run A* over the grid instead. Walls along the grid axes make few corners (at
# most about 300 in a procgen house, 160 in a real plan); a wall at an angle is drawn as
# a staircase with a corner at every step, about 30 per metre.
MAX_TABLE_CORNERS = 1024

# Straight directions k (clearance columns).
UP, DOWN, LEFT, RIGHT = 0, 1, 2, 3
_STRAIGHT_DR = np.array([-1, 1, 0, 0], np.int64)
_STRAIGHT_DC = np.array([0, 0, -1, 1], np.int64)
# The move mask's bit of each step (dr, dc), at [dr + 1, dc + 1] (kernels.MOVE_DR/DC).
_BIT = np.full((3, 3), -1, np.int64)
_BIT[MOVE_DR + 1, MOVE_DC + 1] = np.arange(8)
# Diagonal steps: (dr, dc), their move bit, and the straight directions they are made of.
_DIAG_DR = np.array([-1, -1, 1, 1], np.int64)
_DIAG_DC = np.array([-1, 1, -1, 1], np.int64)
_DIAG_BIT = _BIT[_DIAG_DR + 1, _DIAG_DC + 1]
_DIAG_VERT = np.where(_DIAG_DR < 0, UP, DOWN)
_DIAG_HORZ = np.where(_DIAG_DC < 0, LEFT, RIGHT)


def corner_mask(moves: np.ndarray) -> np.ndarray:
    """Which cells are corners, from the move mask (any shape): for some diagonal step,
    both its straight steps are allowed and the step itself is not."""
    m = moves.astype(np.uint16)
    corner = np.zeros(moves.shape, np.bool_)
    for dr, dc in zip(_DIAG_DR, _DIAG_DC):
        vert, horz, diag = ((m >> _BIT[i + 1, j + 1]) & 1 for i, j in ((dr, 0), (0, dc), (dr, dc)))
        corner |= (vert & horz & (1 - diag)).astype(np.bool_)
    return corner


@njit(cache=True)
def _clearances(nav, corner, off, h, w, clear):
    """``clear[off + v, k]``: free cells after ``v`` in straight direction ``k`` before the
    first blocked, off-grid or corner cell."""
    for r in range(h):
        for c in range(w):  # left: from the left edge
            v = off + r * w + c
            clear[v, LEFT] = 0 if c == 0 or nav[v - 1] == 0 or corner[v - 1] > 0 else clear[v - 1, LEFT] + 1
        for c in range(w - 1, -1, -1):
            v = off + r * w + c
            clear[v, RIGHT] = 0 if c == w - 1 or nav[v + 1] == 0 or corner[v + 1] > 0 else clear[v + 1, RIGHT] + 1
    for r in range(h):
        for c in range(w):
            v = off + r * w + c
            clear[v, UP] = 0 if r == 0 or nav[v - w] == 0 or corner[v - w] > 0 else clear[v - w, UP] + 1
    for r in range(h - 1, -1, -1):
        for c in range(w):
            v = off + r * w + c
            clear[v, DOWN] = 0 if r == h - 1 or nav[v + w] == 0 or corner[v + w] > 0 else clear[v + w, DOWN] + 1


@njit(cache=True)
def _scan(moves, corner, clear, off, h, w, cs, v, ids, costs, n):
    """Append to ``ids``/``costs`` (from index ``n``) the corners directly h-reachable from
    cell ``v`` (scene-local index, navigable; not ``v`` itself) and their octile distances;
    returns the new count."""
    diag = cs * math.sqrt(2.0)
    r0 = v // w
    c0 = v % w
    for k in range(4):  # the straight rays end at a wall or a corner
        L = clear[off + v, k] + 1
        r = r0 + _STRAIGHT_DR[k] * L
        c = c0 + _STRAIGHT_DC[k] * L
        if r >= 0 and r < h and c >= 0 and c < w and corner[off + r * w + c] > 0:
            ids[n] = corner[off + r * w + c] - 1
            costs[n] = L * cs
            n += 1
    for q in range(4):
        dr = _DIAG_DR[q]
        dc = _DIAG_DC[q]
        bit = _DIAG_BIT[q]
        kv = _DIAG_VERT[q]
        kh = _DIAG_HORZ[q]
        # how far the straight rays of the rows so far reached: a farther cell is behind
        # a corner (or cut off by a wall) and is reached through that corner instead
        mv = clear[off + v, kv]
        mh = clear[off + v, kh]
        u = v
        r = r0
        c = c0
        i = 0
        while (moves[off + u] >> bit) & 1:
            u += dr * w + dc
            r += dr
            c += dc
            i += 1
            if corner[off + u] > 0:
                ids[n] = corner[off + u] - 1
                costs[n] = i * diag
                n += 1
                break
            L = clear[off + u, kv]
            if L <= mv:
                rr = r + dr * (L + 1)
                if rr >= 0 and rr < h and corner[off + rr * w + c] > 0:
                    ids[n] = corner[off + rr * w + c] - 1
                    costs[n] = i * diag + (L + 1) * cs
                    n += 1
                mv = L
            L = clear[off + u, kh]
            if L <= mh:
                cc = c + dc * (L + 1)
                if cc >= 0 and cc < w and corner[off + r * w + cc] > 0:
                    ids[n] = corner[off + r * w + cc] - 1
                    costs[n] = i * diag + (L + 1) * cs
                    n += 1
                mh = L
    return n


@njit(cache=True)
def build_scene(nav, moves, corner, clear, cells, off, h, w, cs, D):
    """Fill scene ``off``'s clearances and its corners' distance table ``D`` (n*n, row
    major; ``cells`` are the corners' scene-local cells in id order)."""
    _clearances(nav, corner, off, h, w, clear)
    n = len(cells)
    for i in range(n * n):
        D[i] = INF
    ids = np.empty(n, np.int64)
    costs = np.empty(n)
    for a in range(n):
        D[a * n + a] = 0.0
        m = _scan(moves, corner, clear, off, h, w, cs, cells[a], ids, costs, 0)
        for j in range(m):
            b = ids[j]
            if costs[j] < D[a * n + b]:
                D[a * n + b] = costs[j]
                D[b * n + a] = costs[j]
    for k in range(n):  # Floyd-Warshall
        for a in range(n):
            dak = D[a * n + k]
            if dak >= INF:
                continue
            for b in range(n):
                t = dak + D[k * n + b]
                if t < D[a * n + b]:
                    D[a * n + b] = t


@njit(cache=True, inline="always")
def _octile(v, u, w, cs):
    dr = abs(v // w - u // w)
    dc = abs(v % w - u % w)
    lo = min(dr, dc)
    return (max(dr, dc) - lo) * cs + lo * cs * math.sqrt(2.0)


@njit(cache=True)
def _diagonal_first_free(moves, off, w, v, u):
    """Whether the path from cell ``v`` to ``u`` that takes all its diagonal steps first
    (then straight ones) is allowed, i.e. ``v`` and ``u`` are h-reachable along it."""
    dr = u // w - v // w
    dc = u % w - v % w
    sr = (dr > 0) - (dr < 0)
    sc = (dc > 0) - (dc < 0)
    nd = min(abs(dr), abs(dc))
    bit = _BIT[sr + 1, sc + 1]
    for _ in range(nd):
        if (moves[off + v] >> bit) & 1 == 0:
            return False
        v += sr * w + sc
    if abs(dr) > abs(dc):
        ns, bit, step = abs(dr) - nd, _BIT[sr + 1, 1], sr * w
    else:
        ns, bit, step = abs(dc) - nd, _BIT[1, sc + 1], sc
    for _ in range(ns):
        if (moves[off + v] >> bit) & 1 == 0:
            return False
        v += step
    return True


@njit(cache=True)
def _connect(nav, moves, corner, clear, off, h, w, ox, oy, cs, x, y, cells, tails, best, ids, scratch_ids,
             scratch_costs):
    """Link the point (x, y): its block's navigable cells and tails into ``cells``/``tails``
    (returns how many, first) and, for every corner directly h-reachable from one of them,
    ``best[corner]`` = the smallest tail + octile distance, listing each corner once in
    ``ids`` (count returned second)."""
    r0, c0 = _block(ox, oy, cs, x, y)
    m = 0
    n_ids = 0
    for k in range(4):
        v, _, _, tail = _link(nav, off, h, w, ox, oy, cs, r0, c0, k, x, y)
        if v < 0:
            continue
        cells[m] = v
        tails[m] = tail
        m += 1
        if corner[off + v] > 0:
            scratch_ids[0] = corner[off + v] - 1
            scratch_costs[0] = 0.0
            found = 1
        else:
            found = 0
        found = _scan(moves, corner, clear, off, h, w, cs, v, scratch_ids, scratch_costs, found)
        for j in range(found):
            a = scratch_ids[j]
            t = tail + scratch_costs[j]
            if best[a] >= INF:
                ids[n_ids] = a
                n_ids += 1
            if t < best[a]:
                best[a] = t
    return m, n_ids


@njit(cache=True)
def point_distance(nav, moves, corner, clear, D, n, off, h, w, ox, oy, cs, px, py, qx, qy):
    """Geodesic distance between the points p and q of one scene (INF if not connected);
    ``D`` is the scene's corner table (``n`` corners)."""
    pc = np.empty(4, np.int64)
    pt = np.empty(4)
    qc = np.empty(4, np.int64)
    qt = np.empty(4)
    bp = np.full(n, INF)
    bq = np.full(n, INF)
    ip = np.empty(n, np.int64)
    iq = np.empty(n, np.int64)
    sid = np.empty(n + 1, np.int64)
    scost = np.empty(n + 1)
    mp, n_p = _connect(nav, moves, corner, clear, off, h, w, ox, oy, cs, px, py, pc, pt, bp, ip, sid, scost)
    mq, nq = _connect(nav, moves, corner, clear, off, h, w, ox, oy, cs, qx, qy, qc, qt, bq, iq, sid, scost)
    best = INF
    for i in range(n_p):  # through the corners
        a = ip[i]
        da = bp[a]
        row = a * n
        for j in range(nq):
            b = iq[j]
            t = da + D[row + b] + bq[b]
            if t < best:
                best = t
    for i in range(mp):  # straight across, where no corner is needed
        for j in range(mq):
            t = pt[i] + _octile(pc[i], qc[j], w, cs) + qt[j]
            if t < best and _diagonal_first_free(moves, off, w, pc[i], qc[j]):
                best = t
    return best


@threaded()
def distance_batch(nav, moves, corner, clear, D, d_off, n_corners, g_off, g_h, g_w, g_ox, g_oy, cs, scene_idx, src,
                   dst, rows, out):
    """``out[r]`` = the geodesic distance from ``src[r]`` to ``dst[r]`` in world ``r``'s
    scene, for each ``r`` in ``rows`` (in parallel)."""
    for k in prange(rows.shape[0]):
        r = rows[k]
        s = scene_idx[r]
        n = n_corners[s]
        if n < 0:  # too many corners for a table: A* over the grid
            cells = g_h[s] * g_w[s]
            out[r] = astar(nav, moves, g_off[s], g_h[s], g_w[s], g_ox[s], g_oy[s], cs, src[r, 0], src[r, 1], dst[r, 0],
                           dst[r, 1], np.empty(cells), np.zeros(cells, np.int64), 1, np.empty(cells),
                           np.empty(cells, np.int64), np.empty(cells, np.int64))
            continue
        out[r] = point_distance(nav, moves, corner, clear, D[d_off[s]: d_off[s] + n * n], n, g_off[s], g_h[s], g_w[s],
                                g_ox[s], g_oy[s], cs, src[r, 0], src[r, 1], dst[r, 0], dst[r, 1])


class CornerGraphs:
    """The corner graphs of a bank's scenes (see the module docstring), each built on its
    scene's first query (about 4 ms for a procedural house): clearances (8 bytes per grid
    cell) and the corners' distance table (8 bytes per pair of corners). A scene with
    more than ``MAX_TABLE_CORNERS`` corners is answered by A* instead
    (``n_corners[s] == -1``)."""

    def __init__(self, bank):
        if int(max(bank.h.max(), bank.w.max())) >= np.iinfo(np.int16).max:
            raise ValueError("scene grids must be under 32767 cells a side for the corner graphs")
        self.bank = bank
        # zeros: the pages of scenes never queried are never touched
        self.corner = np.zeros(len(bank.nav), np.int32)  # 1 + the corner's id in its scene; 0: not a corner
        self.clear = np.zeros((len(bank.nav), 4), np.int16)
        self.n_corners = np.zeros(len(bank), np.int64)
        self.d_off = np.zeros(len(bank), np.int64)  # each scene's table in D
        self.D = np.zeros(0, np.float64)
        self.done = np.zeros(len(bank), np.bool_)

    def prepare(self, scenes) -> None:
        """Build the graphs of ``scenes`` that are not built yet."""
        scenes = np.asarray(scenes, np.int64).reshape(-1)
        if self.done[scenes].all():
            return  # the common case: every query asks
        b = self.bank
        todo = np.unique(scenes[~self.done[scenes]])
        tables = [self.D]
        size = len(self.D)
        for s in todo:
            off, h, w = int(b.off[s]), int(b.h[s]), int(b.w[s])
            cells = np.flatnonzero(corner_mask(b.moves[off: off + h * w]))
            n = len(cells)
            if n > MAX_TABLE_CORNERS:
                self.n_corners[s] = -1
                continue
            self.corner[off + cells] = np.arange(1, n + 1)
            table = np.empty(n * n)
            build_scene(b.nav, b.moves, self.corner, self.clear, cells, off, h, w, b.cell_size, table)
            self.d_off[s] = size
            self.n_corners[s] = n
            size += n * n
            tables.append(table)
        self.D = np.concatenate(tables)  # once: a bank may have hundreds of scenes
        self.done[todo] = True

    def distances(self, scene_idx: np.ndarray, src: np.ndarray, dst: np.ndarray, rows: np.ndarray,
                  out: np.ndarray) -> None:
        """``out[r]`` = the geodesic distance from ``src[r]`` to ``dst[r]`` in scene
        ``scene_idx[r]``, for ``r`` in ``rows`` (``kernels.INF`` if not connected)."""
        self.prepare(scene_idx[rows])
        b = self.bank
        pick(distance_batch, len(rows))(b.nav, b.moves, self.corner, self.clear, self.D, self.d_off, self.n_corners,
                                        b.off, b.h, b.w, b.ox, b.oy, b.cell_size, scene_idx, src, dst, rows, out)
