"""Compiled (numba) hot loops of the simulator: ray casting, motion, geodesics, ego map.

Every kernel works on a *scene bank*: the grids of all loaded scenes concatenated into
flat arrays, with per-scene offsets and shapes (see :mod:`.bank`). A batch of worlds is
processed in one call, so Python overhead does not grow with the number of worlds.

Conventions: positions in metres, headings in radians counter-clockwise from +x; the
camera looks along the heading. Image column ``j`` has horizontal angle
``atan((W/2 - j - 0.5) / f)`` (positive = left) and row ``i`` the vertical slope
``(H/2 - i - 0.5) / f`` (positive = up), with ``f = (W/2) / tan(hfov/2)``.
Depth is *planar*: the distance along the optical axis (Habitat's convention), not the
length of the ray.
"""

from __future__ import annotations

import math
import os
import sys
import types

import numba
import numpy as np
from numba import njit, prange

# numba's on-disk cache (``cache=True``) pickles the name of the module that defined a
# kernel and re-imports it by that name when it loads the cache. This package can be
# imported as ``plex_ma.envs`` (installed) and as ``envs`` (from the repository root), so
# a cache written under one name must load under the other: register both names.
for _alias in ("plex_ma.envs.sim.kernels", "envs.sim.kernels"):
    sys.modules.setdefault(_alias, sys.modules[__name__])
del _alias

# The parallel kernels run on numba's "workqueue" threading layer, not on GNU OpenMP
# (numba's default where it finds no TBB). On OpenMP they ran inside torch's OpenMP
# runtime (torch loads its libgomp into the global symbol scope, and numba's OpenMP layer
# binds to it): with torch imported first they waited as torch's runtime had been set up
# (spinning, by default), and beside any other busy process a vector env ran up to 30x
# slower; fork() after a kernel killed the child ("fork() called from a process already
# using GNU OpenMP"), which broke gymnasium's async vector envs. workqueue's threads sleep
# on a condition variable between kernels, survive fork() and read no OMP_* setting, so
# the import order no longer matters. The layer is fixed when the first parallel kernel
# runs in the process; a layer the user chose (NUMBA_THREADING_LAYER, or numba.config set
# before this import) is kept. (Like every numba setting, this one holds for the whole
# process, so for the user's own parallel kernels too.)
if numba.config.THREADING_LAYER == "default" and "NUMBA_THREADING_LAYER" not in os.environ:
    numba.config.THREADING_LAYER = "workqueue"


def threaded(**flags):
    """``njit(cache=True, parallel=True, **flags)``, plus the same function compiled
    without threads as the kernel's ``serial`` attribute (see :func:`pick`).

    The serial twin is a copy of the Python function under its own name, so that numba's
    on-disk cache (keyed by qualified name and line, not by the ``parallel`` flag) keeps
    the two apart. Each loop iteration of these kernels writes its own outputs, so both
    give the same results (``tests/test_sim_determinism.py``)."""

    def wrap(fn):
        kernel = njit(cache=True, parallel=True, **flags)(fn)
        twin = types.FunctionType(fn.__code__, fn.__globals__, fn.__name__ + "_serial", fn.__defaults__,
                                  fn.__closure__)
        twin.__qualname__ = fn.__qualname__ + "_serial"
        twin.__doc__ = fn.__doc__
        kernel.serial = njit(cache=True, **flags)(twin)
        return kernel

    return wrap


def pick(kernel, jobs: int):
    """``kernel`` itself, or its serial twin where threads have nothing to share out (one
    job: a simulator of one world) or numba runs one thread: handing a kernel to the
    threading layer's workers costs a few tens of microseconds, as much as a one-world
    kernel takes."""
    return kernel.serial if jobs <= 1 or numba.get_num_threads() == 1 else kernel


MAX_BOUNDARIES = 16
RENDER_TILE = 16  # image columns per rendering job
INF = 1e30

# ---------------------------------------------------------------------------------------
# Grid helpers


def wrap_angle(a):
    """An angle in radians (a float or an array) wrapped to [-pi, pi)."""
    return (a + math.pi) % (2 * math.pi) - math.pi


_wrap = njit(cache=True, inline="always")(wrap_angle)


@njit(cache=True, inline="always")
def _cell(ox, oy, cs, x, y):
    return int(math.floor((y - oy) / cs)), int(math.floor((x - ox) / cs))


@njit(cache=True)
def is_nav(nav, off, h, w, ox, oy, cs, x, y):
    r, c = _cell(ox, oy, cs, x, y)
    if r < 0 or r >= h or c < 0 or c >= w:
        return False
    return nav[off + r * w + c] != 0


# ---------------------------------------------------------------------------------------
# Rendering


@njit(cache=True, inline="always")
def _shade(rgb, f):
    return (min(255.0, rgb[0] * f), min(255.0, rgb[1] * f), min(255.0, rgb[2] * f))


@threaded(fastmath=True)
def render(kind, g_off, g_h, g_w, g_ox, g_oy, cs, klo, khi, kmat, kroom,
           room_wall_rgb, room_floor_rgb, mat_rgb, scene_idx, pos, heading,
           cam_height, ceiling, hfov, max_depth, out_rgb, out_depth, active):
    """Render RGB-D for the active worlds into ``out_rgb`` (N,H,W,3) and ``out_depth`` (N,H,W,1).

    A job draws one world's tile of RENDER_TILE adjacent columns, each column by a ray
    marched through the grid and filled front to back. The tile's depth goes first into a
    column-major scratch and is copied out row by row: written straight down a column of
    ``out_depth``, whose rows lie a power of two apart at the usual sizes, every pixel would
    land in the same few cache sets and miss."""
    n = pos.shape[0]
    H = out_rgb.shape[1]
    W = out_rgb.shape[2]
    f = (W / 2.0) / math.tan(hfov / 2.0)
    nt = (W + RENDER_TILE - 1) // RENDER_TILE
    for job in prange(n * nt):
        wi = job // nt
        j0 = (job % nt) * RENDER_TILE
        if not active[wi]:
            continue
        tw = min(RENDER_TILE, W - j0)
        # depth of the tile's columns; the padding keeps its columns off each other's cache sets
        dtile = np.empty((RENDER_TILE, H + RENDER_TILE), np.float32)
        bt = np.empty(MAX_BOUNDARIES, np.float64)
        bk = np.empty(MAX_BOUNDARIES, np.int64)
        bax = np.empty(MAX_BOUNDARIES, np.int64)
        s = scene_idx[wi]
        off = g_off[s]
        gh = g_h[s]
        gw = g_w[s]
        ox = g_ox[s]
        oy = g_oy[s]
        px = pos[wi, 0]
        py = pos[wi, 1]
        orgb = out_rgb[wi].reshape(-1)  # flat: one index per byte instead of four
        for tj in range(tw):
            j = j0 + tj
            phi = math.atan((W / 2.0 - j - 0.5) / f)
            cphi = math.cos(phi)
            ang = heading[wi] + phi
            dx = math.cos(ang)
            dy = math.sin(ang)
            # --- march the horizontal ray through the grid, recording kind changes ---
            gx = (px - ox) / cs
            gy = (py - oy) / cs
            col = int(math.floor(gx))
            row = int(math.floor(gy))
            cur = kind[off + row * gw + col]
            bt[0] = 0.0
            bk[0] = cur
            bax[0] = 0
            nb = 1
            if dx > 1e-12:
                sx = 1
                tdx = cs / dx
                tmx = (col + 1 - gx) * cs / dx
            elif dx < -1e-12:
                sx = -1
                tdx = -cs / dx
                tmx = (gx - col) * cs / (-dx)
            else:
                sx = 0
                tdx = INF
                tmx = INF
            if dy > 1e-12:
                sy = 1
                tdy = cs / dy
                tmy = (row + 1 - gy) * cs / dy
            elif dy < -1e-12:
                sy = -1
                tdy = -cs / dy
                tmy = (gy - row) * cs / (-dy)
            else:
                sy = 0
                tdy = INF
                tmy = INF
            tmax = max_depth / cphi + cs
            while True:
                if tmx < tmy:
                    t = tmx
                    col += sx
                    tmx += tdx
                    axis = 0
                else:
                    t = tmy
                    row += sy
                    tmy += tdy
                    axis = 1
                if t > tmax:
                    break
                if row < 0 or row >= gh or col < 0 or col >= gw:
                    break
                k = kind[off + row * gw + col]
                if k != cur:
                    cur = k
                    bt[nb] = t
                    bk[nb] = k
                    bax[nb] = axis
                    nb += 1
                    if klo[k] <= 0.0 and khi[k] >= ceiling:  # a full-height blocker
                        break
                    if nb == MAX_BOUNDARIES:
                        break
            # --- fill the column front to back. Every kind is attached to the floor (lo == 0)
            # or to the ceiling (hi >= ceiling), so the rows not yet drawn always form one
            # interval [top, bot]; each face or surface fills rows from one of its ends. ---
            top = 0
            bot = H - 1
            hc = H / 2.0 - 0.5
            for q in range(nb):
                if top > bot:
                    break
                k = bk[q]
                z0 = bt[q] * cphi
                z1 = INF
                if q + 1 < nb:
                    z1 = bt[q + 1] * cphi
                lo = klo[k]
                hi = khi[k]
                solid = hi > lo
                m = kmat[k]
                if q > 0 and solid:
                    # vertical face at the region's entry: rows whose ray height at z0 is in [lo, hi]
                    i0 = max(top, int(math.ceil(hc - f * (hi - cam_height) / z0)))
                    i1 = min(bot, int(math.floor(hc - f * (lo - cam_height) / z0)))
                    if m <= 1 or m == 3:  # wall or void: coloured by the room it is seen from
                        pr = kroom[bk[q - 1]]
                        c3 = room_wall_rgb[pr] if pr >= 0 else mat_rgb[1]
                    else:
                        c3 = mat_rgb[m]
                    fac = 1.0 if bax[q] == 0 else 0.78
                    cr, cg, cb = _shade(c3, fac)
                    ur, ug, ub = np.uint8(cr), np.uint8(cg), np.uint8(cb)
                    dz = min(z0, max_depth) / max_depth
                    for i in range(i0, i1 + 1):
                        dtile[tj, i] = dz
                        q = (i * W + j) * 3
                        orgb[q] = ur
                        orgb[q + 1] = ug
                        orgb[q + 2] = ub
                    if i1 >= i0:
                        if lo <= 0.0 and hi >= ceiling:
                            top = bot + 1
                            break
                        if lo <= 0.0:
                            bot = i0 - 1
                        else:
                            top = i1 + 1
                # horizontal surfaces inside the region
                fl = hi if (solid and lo <= 0.0) else 0.0
                ce = lo if (solid and lo > 0.0) else ceiling
                # bottom surface (floor or furniture top): rows that descend below fl before z1
                ib = top
                if z1 < INF:
                    ib = max(top, int(math.floor(hc - f * (fl - cam_height) / z1)) + 1)
                else:
                    ib = max(top, int(math.floor(hc)) + 1)
                if fl <= 0.0:
                    rm = kroom[k]
                    c3 = room_floor_rgb[rm] if rm >= 0 else mat_rgb[m]
                    # the two checker shades, converted once per surface rather than per pixel
                    cr, cg, cb = _shade(c3, 1.0)
                    ur, ug, ub = np.uint8(cr), np.uint8(cg), np.uint8(cb)
                    cr, cg, cb = _shade(c3, 1.0 - 0.12)
                    vr, vg, vb = np.uint8(cr), np.uint8(cg), np.uint8(cb)
                    for i in range(ib, bot + 1):
                        zs = (fl - cam_height) * f / (hc - i)
                        if zs < z0:
                            zs = z0
                        d = zs / cphi
                        chk = (int(math.floor((px + d * dx) * 2.0)) + int(math.floor((py + d * dy) * 2.0))) & 1
                        dtile[tj, i] = min(zs, max_depth) / max_depth
                        q = (i * W + j) * 3
                        if chk:
                            orgb[q] = vr
                            orgb[q + 1] = vg
                            orgb[q + 2] = vb
                        else:
                            orgb[q] = ur
                            orgb[q + 1] = ug
                            orgb[q + 2] = ub
                else:
                    cr, cg, cb = _shade(mat_rgb[m], 1.2)
                    ur, ug, ub = np.uint8(cr), np.uint8(cg), np.uint8(cb)
                    for i in range(ib, bot + 1):
                        zs = (fl - cam_height) * f / (hc - i)
                        if zs < z0:
                            zs = z0
                        dtile[tj, i] = min(zs, max_depth) / max_depth
                        q = (i * W + j) * 3
                        orgb[q] = ur
                        orgb[q + 1] = ug
                        orgb[q + 2] = ub
                if ib <= bot:
                    bot = ib - 1
                # top surface (ceiling or lintel underside): rows that rise above ce before z1
                if z1 < INF:
                    it = min(bot, int(math.ceil(hc - f * (ce - cam_height) / z1)) - 1)
                else:
                    it = min(bot, int(math.ceil(hc)) - 1)
                if ce >= ceiling:
                    cr, cg, cb = 236.0, 234.0, 228.0
                else:
                    cr, cg, cb = _shade(mat_rgb[m], 0.7)
                ur, ug, ub = np.uint8(cr), np.uint8(cg), np.uint8(cb)
                for i in range(top, it + 1):
                    zs = (ce - cam_height) * f / (hc - i)
                    if zs < z0:
                        zs = z0
                    dtile[tj, i] = min(zs, max_depth) / max_depth
                    q = (i * W + j) * 3
                    orgb[q] = ur
                    orgb[q + 1] = ug
                    orgb[q + 2] = ub
                if it >= top:
                    top = it + 1
            # rows left open (march ended by range or by too many boundaries): far away
            for i in range(top, bot + 1):
                dtile[tj, i] = 1.0
                q = (i * W + j) * 3
                orgb[q] = 128
                orgb[q + 1] = 128
                orgb[q + 2] = 128
        od = out_depth[wi].reshape(-1)
        for i in range(H):  # the tile's depth, a row at a time
            p = i * W + j0
            for tj in range(tw):
                od[p + tj] = dtile[tj, i]


# ---------------------------------------------------------------------------------------
# Motion


@njit(cache=True, inline="always")
def _try_move(nav, off, h, w, ox, oy, cs, x, y, dx, dy):
    """Move from (x, y) by (dx, dy) while every sampled point is navigable and no step
    between sampled cells squeezes diagonally between two blocked cells (the move would
    leave the agent's connected component, which only 4-neighbour links form)."""
    L = math.sqrt(dx * dx + dy * dy)
    n = int(math.ceil(L / (cs * 0.25)))
    if n < 1:
        return x, y, False
    bx = x
    by = y
    br, bc = _cell(ox, oy, cs, x, y)
    for k in range(1, n + 1):
        cx = x + dx * k / n
        cy = y + dy * k / n
        if not is_nav(nav, off, h, w, ox, oy, cs, cx, cy):
            return bx, by, True
        r, c = _cell(ox, oy, cs, cx, cy)
        if r != br and c != bc and nav[off + br * w + c] == 0 and nav[off + r * w + bc] == 0:
            return bx, by, True
        bx = cx
        by = cy
        br = r
        bc = c
    return bx, by, False


@njit(cache=True)  # a few cell tests per world: cheaper on one thread than handed to the workers
def move(nav, g_off, g_h, g_w, g_ox, g_oy, cs, scene_idx, pos, heading, actions,
         forward, turn, collided):
    """Apply actions (0 stop, 1 forward, 2 left, 3 right) in place; sets ``collided``."""
    for wi in range(pos.shape[0]):
        a = actions[wi]
        collided[wi] = False
        if a == 2:
            heading[wi] = _wrap(heading[wi] + turn)
        elif a == 3:
            heading[wi] = _wrap(heading[wi] - turn)
        elif a == 1:
            s = scene_idx[wi]
            off = g_off[s]
            h = g_h[s]
            w = g_w[s]
            ox = g_ox[s]
            oy = g_oy[s]
            x = pos[wi, 0]
            y = pos[wi, 1]
            dx = forward * math.cos(heading[wi])
            dy = forward * math.sin(heading[wi])
            nx, ny, blocked = _try_move(nav, off, h, w, ox, oy, cs, x, y, dx, dy)
            if blocked:
                collided[wi] = True
                # Slide along the axis-aligned component that makes the most progress.
                rx = x + dx - nx
                ry = y + dy - ny
                ax, ay, _ = _try_move(nav, off, h, w, ox, oy, cs, nx, ny, rx, 0.0)
                bx, by, _ = _try_move(nav, off, h, w, ox, oy, cs, nx, ny, 0.0, ry)
                pa = (ax - x) * dx + (ay - y) * dy
                pb = (bx - x) * dx + (by - y) * dy
                if pa >= pb and pa > (nx - x) * dx + (ny - y) * dy:
                    nx, ny = ax, ay
                elif pb > (nx - x) * dx + (ny - y) * dy:
                    nx, ny = bx, by
            pos[wi, 0] = nx
            pos[wi, 1] = ny


@njit(cache=True)  # a few hundred cell tests per world: cheaper on one thread than handed to the workers
def straight_shortcut(nav, g_off, g_h, g_w, g_ox, g_oy, cs, scene_idx, pos, targets, rows, dist):
    """``dist[r] = min(dist[r], |targets[r] - pos[r]|)`` for each world ``r`` in ``rows``
    whose agent could move straight to its target (``_try_move``'s test, the motion's own):
    there the shortest path through free space is the straight line, which the grid's
    octile paths and their links to cell centres overestimate by up to about 10% near
    the point (0.205 m on the grid for 0.187 m in the open)."""
    for k in range(rows.shape[0]):
        wi = rows[k]
        x = pos[wi, 0]
        y = pos[wi, 1]
        dx = targets[wi, 0] - x
        dy = targets[wi, 1] - y
        e = math.sqrt(dx * dx + dy * dy)
        if e >= dist[wi]:
            continue
        s = scene_idx[wi]
        _, _, blocked = _try_move(nav, g_off[s], g_h[s], g_w[s], g_ox[s], g_oy[s], cs, x, y, dx, dy)
        if not blocked:
            dist[wi] = e


# ---------------------------------------------------------------------------------------
# Geodesic distance: Dijkstra on the 8-connected navigable grid (no corner cutting).
# A continuous point p is linked to the navigable centres of the 2x2 block of cells
# around it; its distance is min(field[c] + |p - c|). This is never below the euclidean
# distance and matches a reference Dijkstra over the same graph.


@njit(cache=True, inline="always")
def _heap_push(hk, hv, hpos, size, key, v):
    hv[size] = v
    hpos[v] = size
    _heap_decrease(hk, hv, hpos, size, key)
    return size + 1


@njit(cache=True, inline="always")
def _heap_decrease(hk, hv, hpos, i, key):
    """Set the key at heap position ``i`` to ``key`` (not above the old one) and move the
    entry up until its parent is smaller."""
    hk[i] = key
    while i > 0:
        p = (i - 1) >> 1
        if hk[p] <= hk[i]:
            break
        _swap(hk, hv, hpos, i, p)
        i = p


@njit(cache=True, inline="always")
def _heap_pop(hk, hv, hpos, size):
    key = hk[0]
    v = hv[0]
    hpos[v] = -2  # settled
    size -= 1
    if size > 0:
        hk[0] = hk[size]
        hv[0] = hv[size]
        hpos[hv[0]] = 0
        _sift_down(hk, hv, hpos, size, 0)
    return key, v, size


@njit(cache=True, inline="always")
def _sift_down(hk, hv, hpos, size, i):
    """Move the entry at heap position ``i`` down until both its children are larger."""
    while True:
        l = 2 * i + 1
        if l >= size:
            break
        m = l
        if l + 1 < size and hk[l + 1] < hk[l]:
            m = l + 1
        if hk[i] <= hk[m]:
            break
        _swap(hk, hv, hpos, i, m)
        i = m


@njit(cache=True, inline="always")
def _swap(hk, hv, hpos, i, j):
    """Swap heap positions ``i`` and ``j``, keeping ``hpos`` (cell -> position) in step."""
    hk[i], hk[j] = hk[j], hk[i]
    hv[i], hv[j] = hv[j], hv[i]
    hpos[hv[i]] = i
    hpos[hv[j]] = j


@njit(cache=True)
def _block(ox, oy, cs, x, y):
    """Row/col of the lower-left cell of the 2x2 block whose centres surround (x, y)."""
    return int(math.floor((y - oy) / cs - 0.5)), int(math.floor((x - ox) / cs - 0.5))


@njit(cache=True, inline="always")
def _link(nav, off, h, w, ox, oy, cs, r0, c0, k, x, y):
    """Cell ``k`` (0-3, row by row) of the 2x2 block whose lower-left cell is (r0, c0), as
    a link of the point (x, y) into the graph: (flat index, centre x, centre y, distance
    from the centre to the point); index -1 when the cell is off the grid or blocked."""
    r = r0 + (k >> 1)
    c = c0 + (k & 1)
    if r < 0 or r >= h or c < 0 or c >= w or nav[off + r * w + c] == 0:
        return -1, 0.0, 0.0, 0.0
    cx = ox + (c + 0.5) * cs
    cy = oy + (r + 0.5) * cs
    return r * w + c, cx, cy, math.sqrt((cx - x) ** 2 + (cy - y) ** 2)


# The one graph every search here runs on: 8-connected navigable cells, straight steps of
# one cell, diagonal steps of sqrt(2) cells that may not cut a blocked corner (both cells
# beside the diagonal must be navigable). ``move_mask`` stores it as one byte per cell:
# bit j set when the step (MOVE_DR[j], MOVE_DC[j]) is allowed.
MOVE_DR = np.array([-1, -1, -1, 0, 0, 1, 1, 1], np.int64)
MOVE_DC = np.array([-1, 0, 1, -1, 1, -1, 0, 1], np.int64)


def move_mask(nav: np.ndarray) -> np.ndarray:
    """(H, W) uint8: the allowed grid steps out of every cell of the navigability grid
    ``nav`` (bit j: the step (MOVE_DR[j], MOVE_DC[j]); none leave the grid)."""
    nav = np.asarray(nav, np.bool_)
    H, W = nav.shape
    p = np.pad(nav, 1)
    m = np.zeros((H, W), np.uint8)
    for j, (dr, dc) in enumerate(zip(MOVE_DR, MOVE_DC)):
        ok = nav & p[1 + dr: 1 + dr + H, 1 + dc: 1 + dc + W]
        if dr and dc:
            ok &= p[1 + dr: 1 + dr + H, 1: 1 + W] & p[1: 1 + H, 1 + dc: 1 + dc + W]
        m |= ok.astype(np.uint8) << j
    return m


@njit(cache=True)
def dijkstra_field(nav, moves, off, h, w, ox, oy, cs, gx, gy, dist, ring, label):
    """Fill ``dist[:h*w]`` with geodesic distances to the point (gx, gy); INF if unreachable.

    Dijkstra with a bucket queue (Dial's algorithm): bucket k holds the open cells whose
    tentative distance lies in [k cs, (k+1) cs). Every grid step is at least ``cs`` long, so
    no cell of bucket k can shorten another one's distance: all of them are final and are
    closed in any order, without a heap. Steps are at most sqrt(2) cs, so only buckets k,
    k+1 and k+2 are ever open and three rows of ``ring`` ((3, >= h*w) int32) hold them.
    ``label[v]`` ((>= h*w) int64) is the bucket that lists ``v`` (-1: none yet, -2:
    closed); a cell moved to a nearer bucket leaves a stale copy behind, skipped later.
    The distances are the same floats as a heap-ordered Dijkstra's: each cell ends as the
    minimum over its neighbours of their final distance plus the step.
    """
    n = h * w
    inv = 1.0 / cs
    diag = cs * math.sqrt(2.0)
    fill = np.zeros(3, np.int64)
    for v in range(n):
        dist[v] = INF
        label[v] = -1
    r0, c0 = _block(ox, oy, cs, gx, gy)
    for q in range(4):
        v, _, _, tail = _link(nav, off, h, w, ox, oy, cs, r0, c0, q, gx, gy)
        if v >= 0:
            dist[v] = tail
            label[v] = 0  # the seeds lie within 0.71 cs of the point: bucket 0
            ring[0, fill[0]] = v
            fill[0] += 1
    k = 0
    while fill[0] + fill[1] + fill[2] > 0:
        slot = k % 3
        i = 0
        while i < fill[slot]:
            v = ring[slot, i]
            i += 1
            if label[v] != k:
                continue  # closed already, or moved to a nearer bucket
            label[v] = -2
            d = dist[v]
            m = moves[off + v]
            for j in range(8):
                if (m >> j) & 1 == 0:
                    continue
                dr = MOVE_DR[j]
                dc = MOVE_DC[j]
                nd = d + (cs if dr == 0 or dc == 0 else diag)
                u = v + dr * w + dc
                if nd < dist[u]:
                    dist[u] = nd
                    # k+1 at least: guards against rounding of nd / cs at a bucket edge
                    b = max(int(nd * inv), k + 1)
                    if label[u] != b:
                        label[u] = b
                        bs = b % 3
                        ring[bs, fill[bs]] = u
                        fill[bs] += 1
        fill[slot] = 0
        k += 1


@njit(cache=True)
def field_lookup(nav, off, h, w, ox, oy, cs, dist, x, y):
    """Geodesic distance of the point (x, y) given a goal's field; INF if unreachable."""
    r0, c0 = _block(ox, oy, cs, x, y)
    best = INF
    for k in range(4):
        v, _, _, tail = _link(nav, off, h, w, ox, oy, cs, r0, c0, k, x, y)
        if v >= 0 and dist[v] < INF and dist[v] + tail < best:
            best = dist[v] + tail
    return best


@njit(cache=True)  # one look-up per world: cheaper on one thread than handed to the workers
def field_lookup_batch(nav, g_off, g_h, g_w, g_ox, g_oy, cs, scene_idx, fields, pos, out):
    for wi in range(pos.shape[0]):
        s = scene_idx[wi]
        out[wi] = field_lookup(nav, g_off[s], g_h[s], g_w[s], g_ox[s], g_oy[s], cs, fields[wi],
                               pos[wi, 0], pos[wi, 1])


# A* keys are f - TIE * g: among cells of (nearly) equal f the deepest goes first, so in
# open floor the search runs straight along the many equally short octile paths instead
# of flooding the parallelogram between them. A popped g is then exact up to a relative
# TIE (1e-11 m over 10 m), far below the float32 goal field's rounding.
TIE = 1e-12


# The heuristic's slack, in cells. A search starts or ends at a point linked to the
# centres of the 2x2 block of cells around it, up to sqrt(2) cells away. The octile norm
# is at most 1.0824 times the euclidean one, so from a cell centre the octile distance to
# the point overshoots the octile distance to the right centre plus the link by at most
# 0.0824 * sqrt(2) = 0.117 cells.
OCTILE_SLACK = 0.12


@njit(cache=True, inline="always")
def _heuristic(x, y, ax, ay, cs):
    """A* heuristic from a cell centre (x, y) to the point (ax, ay): the octile distance,
    the exact cost of an obstacle-free path on the 8-connected grid (so it is consistent),
    less the slack that keeps it below the true distance at the point."""
    dx = abs(x - ax)
    dy = abs(y - ay)
    return (dx + 0.41421356237309515 * dy if dx > dy else dy + 0.41421356237309515 * dx) - OCTILE_SLACK * cs


@njit(cache=True, inline="always")
def _seed(nav, off, h, w, ox, oy, cs, px, py, g, stamp, cur, hk, hv, hpos, size, ax, ay):
    """Open the navigable centres of the 2x2 block around (px, py) with g = their distance
    to it, keyed towards (ax, ay); returns the heap size."""
    r0, c0 = _block(ox, oy, cs, px, py)
    for k in range(4):
        v, cx, cy, tail = _link(nav, off, h, w, ox, oy, cs, r0, c0, k, px, py)
        if v < 0:
            continue
        stamp[v] = cur
        g[v] = tail
        hpos[v] = -1
        key = g[v] * (1.0 - TIE) + _heuristic(cx, cy, ax, ay, cs)
        size = _heap_push(hk, hv, hpos, size, key, v)
    return size


@njit(cache=True, inline="always")
def _expand(moves, off, h, w, ox, oy, cs, v, g, stamp, cur, hk, hv, hpos, size, ax, ay):
    """Relax the 8 neighbours of the closed cell ``v`` (no corner cutting); keys are
    g + heuristic towards (ax, ay). ``stamp`` marks which entries of ``g``/``hpos`` belong
    to the search ``cur``, so the scratch never needs clearing. Returns the heap size."""
    d = g[v]
    r = v // w
    c = v % w
    m = moves[off + v]
    for j in range(8):
        if (m >> j) & 1 == 0:
            continue
        dr = MOVE_DR[j]
        dc = MOVE_DC[j]
        nd = d + (cs if dr == 0 or dc == 0 else cs * math.sqrt(2.0))
        rr = r + dr
        cc = c + dc
        u = rr * w + cc
        if stamp[u] != cur:
            stamp[u] = cur
            g[u] = INF
            hpos[u] = -1
        if nd < g[u]:
            g[u] = nd
            fu = nd * (1.0 - TIE) + _heuristic(ox + (cc + 0.5) * cs, oy + (rr + 0.5) * cs, ax, ay, cs)
            if hpos[u] == -1:
                size = _heap_push(hk, hv, hpos, size, fu, u)
            elif hpos[u] >= 0:
                _heap_decrease(hk, hv, hpos, hpos[u], fu)
    return size


@njit(cache=True)
def astar(nav, moves, off, h, w, ox, oy, cs, sx, sy, gx, gy, g, stamp, cur_stamp, hk, hv, hpos):
    """Geodesic distance between two points by A* over the same graph as the fields.

    ``g``/``stamp``/``hk``/``hv``/``hpos`` are scratch arrays of at least ``h*w`` entries;
    ``stamp`` marks which entries of ``g`` and ``hpos`` are valid for this call, so the
    scratch never needs clearing. Returns INF when the points are not connected.
    """
    size = _seed(nav, off, h, w, ox, oy, cs, sx, sy, g, stamp, cur_stamp, hk, hv, hpos, 0, gx, gy)
    tr0, tc0 = _block(ox, oy, cs, gx, gy)
    best = INF
    while size > 0:
        f, v, size = _heap_pop(hk, hv, hpos, size)
        if f >= best:
            break
        r = v // w
        c = v % w
        if r - tr0 >= 0 and r - tr0 < 2 and c - tc0 >= 0 and c - tc0 < 2:
            cx = ox + (c + 0.5) * cs
            cy = oy + (r + 0.5) * cs
            t = g[v] + math.sqrt((cx - gx) ** 2 + (cy - gy) ** 2)
            if t < best:
                best = t
        size = _expand(moves, off, h, w, ox, oy, cs, v, g, stamp, cur_stamp, hk, hv, hpos, size, gx, gy)
    return best


@njit(cache=True)
def nearest_navigable(nav, comp, off, h, w, ox, oy, cs, x, y, want_comp, max_radius):
    """Nearest point to (x, y) that is a navigable cell centre of component ``want_comp``
    (or the point itself if it is already in such a cell). Returns (x, y, found)."""
    r, c = _cell(ox, oy, cs, x, y)
    if r >= 0 and r < h and c >= 0 and c < w:
        v = off + r * w + c
        if nav[v] != 0 and comp[v] == want_comp:
            return x, y, True
    R = int(math.ceil(max_radius / cs))
    best = INF
    bx = x
    by = y
    for ring in range(1, R + 1):
        # every centre on this ring is at least (ring - 1/2) cells from (x, y)
        if best <= ((ring - 0.5) * cs) ** 2:
            break
        for dr in range(-ring, ring + 1):
            for dc in range(-ring, ring + 1):
                if abs(dr) != ring and abs(dc) != ring:
                    continue
                rr = r + dr
                cc = c + dc
                if rr < 0 or rr >= h or cc < 0 or cc >= w:
                    continue
                v = off + rr * w + cc
                if nav[v] == 0 or comp[v] != want_comp:
                    continue
                cx = ox + (cc + 0.5) * cs
                cy = oy + (rr + 0.5) * cs
                d = (cx - x) ** 2 + (cy - y) ** 2
                if d < best:
                    best = d
                    bx = cx
                    by = cy
    return bx, by, best < INF


@threaded()
def snap_batch(nav, comp, g_off, g_h, g_w, g_ox, g_oy, cs, scene_idx, pos, points, rows, max_radius, out):
    """``out[r]`` = the nearest point to ``points[r]`` reachable from ``pos[r]`` (the agent's
    position itself if none is within ``max_radius``), for each ``r`` in ``rows``."""
    for k in prange(rows.shape[0]):
        r = rows[k]
        s = scene_idx[r]
        off, h, w, ox, oy = g_off[s], g_h[s], g_w[s], g_ox[s], g_oy[s]
        ar, ac = _cell(ox, oy, cs, pos[r, 0], pos[r, 1])
        want = comp[off + ar * w + ac]
        x, y, ok = nearest_navigable(nav, comp, off, h, w, ox, oy, cs, points[r, 0], points[r, 1], want, max_radius)
        if ok:
            out[r, 0] = x
            out[r, 1] = y
        else:
            out[r, 0] = pos[r, 0]
            out[r, 1] = pos[r, 1]


# ---------------------------------------------------------------------------------------
# Egocentric map (paper A.1): back-project depth with the (noisy) pose, accumulate in an
# allocentric grid, crop and rotate around the agent.

EGO_EXPLORED = 1
EGO_OBSTACLE = 2


@threaded(fastmath=True)
def egomap_update(depth, est_pose, map_origin, amap, map_cs, stride, hfov, max_depth,
                  cam_height, floor_eps, agent_height, active):
    """Accumulate back-projected depth points into each world's allocentric map ``amap``."""
    n = depth.shape[0]
    H = depth.shape[1]
    W = depth.shape[2]
    M = amap.shape[1]
    f = (W / 2.0) / math.tan(hfov / 2.0)
    for wi in prange(n):
        if not active[wi]:
            continue
        x0 = est_pose[wi, 0]
        y0 = est_pose[wi, 1]
        th = est_pose[wi, 2]
        fx = math.cos(th)
        fy = math.sin(th)
        for i in range(stride // 2, H, stride):
            up_s = (H / 2.0 - i - 0.5) / f
            for j in range(stride // 2, W, stride):
                d = depth[wi, i, j, 0]
                if d >= 0.999:
                    continue
                z = d * max_depth
                height = cam_height + up_s * z
                if height > agent_height:
                    continue  # ceiling and lintels: not an obstacle for the agent
                left = z * (W / 2.0 - j - 0.5) / f
                wx = x0 + z * fx - left * fy
                wy = y0 + z * fy + left * fx
                c = int(math.floor((wx - map_origin[wi, 0]) / map_cs))
                r = int(math.floor((wy - map_origin[wi, 1]) / map_cs))
                if r < 0 or r >= M or c < 0 or c >= M:
                    continue
                if height >= floor_eps:
                    amap[wi, r, c] |= EGO_OBSTACLE | EGO_EXPLORED
                else:
                    amap[wi, r, c] |= EGO_EXPLORED


@njit(cache=True, inline="always")
def _ego_row(amap, wi, ox, oy, map_cs, px, py, lx, ly, cells, flags):
    """``flags[m]``: the allocentric map's flags at the samples ``m`` of one row of the crop,
    the points (``px - lx[m]``, ``py + ly[m]``), 0 outside the map. ``px``, ``py`` hold the
    pose and the row's forward offset, ``lx``, ``ly`` each sample's left offset, so the sums
    are those of ``x0 + fwd * fx - left * fy`` and ``y0 + fwd * fy + left * fx``. ``cells``
    (int64 scratch of the same length) takes the map cells, computed in a loop of their own
    that the compiler vectorises; the map is read without bounds checks when every sample of
    the row lies inside it, as it does unless the agent is near the map's edge. ``map_cs``
    is a power of two (:func:`egomap_crop` checks), so a product with its inverse is exactly
    the quotient, and cheaper."""
    M = amap.shape[1]
    inv_cs = 1.0 / map_cs  # multiplying by it is the division: map_cs is a power of two
    lo = M
    hi = -1
    for m in range(flags.shape[0]):
        c = int(math.floor((px - lx[m] - ox) * inv_cs))
        r = int(math.floor((py + ly[m] - oy) * inv_cs))
        lo = min(lo, min(r, c))
        hi = max(hi, max(r, c))
        cells[m] = r * M + c
    grid = amap[wi].ravel()
    if lo >= 0 and hi < M:
        for m in range(flags.shape[0]):
            flags[m] = grid[cells[m]]
        return
    for m in range(flags.shape[0]):
        c = int(math.floor((px - lx[m] - ox) * inv_cs))
        r = int(math.floor((py + ly[m] - oy) * inv_cs))
        flags[m] = grid[r * M + c] if 0 <= r < M and 0 <= c < M else 0


@threaded()
def egomap_crop(amap, map_origin, map_cs, est_pose, ego_cs, out, rows, slots):
    """Crop ``out[slots[k]]`` (C, S, S) for world ``rows[k]``: channel 0 obstacles, channel 1
    explored free space; row 0 is ahead of the agent, column 0 to its left. Each cell samples
    4 x 4 points: channel 0 is 1 when at least a quarter of them are obstacles (so a door
    narrower than two cells stays open), channel 1 the fraction that is explored floor. With
    C = 6, channels 2-5 apply channel 0's rule to each quarter of the cell (4 x 4 points of
    its own), in the order (front left, front right, back left, back right): the obstacles
    at twice the resolution, as ``torch.nn.functional.pixel_shuffle`` unpacks them.

    The samples are read a row of the crop at a time (the cells' 4 x S samples at one
    forward offset, then the quarters' 8 x S), their left offsets computed once per call.
    ``map_cs`` must be a power of two (ValueError otherwise; the simulator's is 0.25 m)."""
    S = out.shape[2]
    sub = 4
    quarters = out.shape[1] >= 6
    if math.frexp(map_cs)[0] != 0.5:
        raise ValueError("egomap_crop: the map's cell size must be a power of two")
    # forward (row) and left (column) offsets (m) of the samples: a cell's 4 x 4, and
    # each quarter's 4 x 4 (index 2 * sub * a + sub * half + s, half = the quarter's row or column)
    off1 = np.empty((S, sub))
    off2 = np.empty((S, 2, sub))
    for a in range(S):
        for s in range(sub):
            off1[a, s] = (S / 2.0 - a - (s + 0.5) / sub) * ego_cs
            for h in range(2):
                off2[a, h, s] = (S / 2.0 - a - (h + (s + 0.5) / sub) / 2) * ego_cs
    off1 = off1.reshape(-1)
    off2 = off2.reshape(-1)
    for k in prange(rows.shape[0]):
        wi = rows[k]
        slot = slots[k]
        x0 = est_pose[wi, 0]
        y0 = est_pose[wi, 1]
        th = est_pose[wi, 2]
        fx = math.cos(th)
        fy = math.sin(th)
        ox = map_origin[wi, 0]
        oy = map_origin[wi, 1]
        lx1 = off1 * fy
        ly1 = off1 * fx
        lx2 = off2 * fy
        ly2 = off2 * fx
        flags = np.empty(off2.shape[0], np.uint8)
        cells = np.empty(off2.shape[0], np.int64)
        obs = np.zeros(S, np.int64)  # per cell of the row: samples on obstacles, on explored floor
        free = np.zeros(S, np.int64)
        qobs = np.zeros(2 * S, np.int64)  # per quarter of the half-row
        for a in range(S):
            obs[:] = 0
            free[:] = 0
            for sa in range(sub):
                fwd = off1[a * sub + sa]
                _ego_row(amap, wi, ox, oy, map_cs, x0 + fwd * fx, y0 + fwd * fy, lx1, ly1, cells, flags[:S * sub])
                for b in range(S):  # the flags are 0, EGO_EXPLORED or both bits
                    for sb in range(sub):
                        v = flags[b * sub + sb]
                        obs[b] += (v & EGO_OBSTACLE) >> 1
                        free[b] += v == EGO_EXPLORED
            for b in range(S):
                out[slot, 0, a, b] = 1.0 if obs[b] * 4 >= sub * sub else 0.0
                out[slot, 1, a, b] = free[b] * (1.0 / (sub * sub))
            if not quarters:
                continue
            for ha in range(2):
                qobs[:] = 0
                for sa in range(sub):
                    fwd = off2[(a * 2 + ha) * sub + sa]
                    _ego_row(amap, wi, ox, oy, map_cs, x0 + fwd * fx, y0 + fwd * fy, lx2, ly2, cells, flags)
                    for b in range(2 * S):
                        for sb in range(sub):
                            qobs[b] += (flags[b * sub + sb] & EGO_OBSTACLE) >> 1
                for b in range(S):
                    for hb in range(2):
                        out[slot, 2 + 2 * ha + hb, a, b] = 1.0 if qobs[2 * b + hb] * 4 >= sub * sub else 0.0
