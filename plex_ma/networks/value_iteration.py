"""The value-iteration module over the ego map (:class:`ValueIteration`) and its Bellman
updates (:func:`bellman`): on the CPU compiled numba loops with their own gradient
(:class:`_BellmanCPU`), elsewhere the tensor version :func:`bellman_reference`, which the
loops reproduce (tests/test_value_iteration.py)."""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from plex_ma.envs.sim.core import BatchedSim

EGO_CELL = BatchedSim.ego_cell  # m: the ego map's cell size (32 x 32 cells, the agent at cell (16, 16))
SUBGOAL_REACH = 2.0  # m: the value-iteration read-out looks for its sub-goal within this distance
BELLMAN_UNREACHED = 1e4  # the distance of cells no path has reached (and of the map's outside)
DIAGONALS = ((-1, -1), (-1, 1), (1, -1), (1, 1))  # (row, column) steps, in the order the update takes them


class ValueIteration(nn.Module):
    """A planning module over the ego map: a value-iteration network (Tamar et al. 2016),
    as CMP (Gupta et al. 2017) plans on egocentric maps.

    - A learned cost per cell, ``1 + softplus(conv3x3(ego map))``, started at about 1 on
      free cells and 97 on cells seen as obstacles (unseen cells count as free).
    - ``iterations`` Bellman updates of the distance to the goal over 8 neighbours (a
      diagonal step costs sqrt 2 x the largest cost of the cell and the two cells beside
      the step, so paths do not cut a wall's corner). The goal is its cell, or, beyond the
      map, the cell where the straight line to it leaves the map. Gradients flow through
      the last ``grad_iterations`` updates only: the cost map is local, so that is where it
      learns (:func:`bellman`).
    - Read-out (:meth:`forward`): the distance field within ``SUBGOAL_REACH`` of the agent
      relative to its smallest value there, and a sub-goal: the cell nearest the goal among
      those the agent reaches within that distance (the goal's exact position stands in for
      its cell; the agent's own cell is never chosen).
    """

    def __init__(self, ego_channels: int = 2, map_size: int = 32, iterations: int = 40, grad_iterations: int = 8):
        super().__init__()
        self.s, self.iterations, self.grad_iterations = map_size, iterations, grad_iterations
        self.cost = nn.Conv2d(ego_channels, 1, 3, padding=1)
        with torch.no_grad():
            self.cost.weight.zero_()
            self.cost.weight[0, 0, 1, 1] = 100.0  # channel 0: obstacles
            self.cost.bias.fill_(-4.0)
        s, r = map_size, int(SUBGOAL_REACH / EGO_CELL)
        self.reach_cells = r
        rows = torch.arange(s, dtype=torch.float32)
        fwd = (s / 2 - rows - 0.5) * EGO_CELL  # the cell centres' offsets from the agent (m)
        self.register_buffer("centre_fwd", fwd[:, None].expand(s, s).clone(), persistent=False)
        self.register_buffer("centre_left", fwd[None, :].expand(s, s).clone(), persistent=False)
        lo, hi = s // 2 - r, s // 2 + r + 1
        self.crop = (lo, hi)
        disc = (self.centre_fwd[lo:hi, lo:hi] ** 2 + self.centre_left[lo:hi, lo:hi] ** 2) <= SUBGOAL_REACH ** 2
        self.register_buffer("disc", disc, persistent=False)
        own = torch.zeros_like(disc)
        own[r, r] = True  # the agent's own cell: never the sub-goal
        self.register_buffer("own_cell", own[disc], persistent=False)
        self.out_dim = int(disc.sum()) + 4

    def goal_cell(self, goal: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(row, column, inside) of each goal (B, 2): its cell, or where the straight line to it
        leaves the map; ``inside`` where the goal itself lies on the map."""
        s = self.s
        fwd, left = goal[:, 0] * torch.cos(goal[:, 1]), goal[:, 0] * torch.sin(goal[:, 1])
        lim = (s / 2 - 1) * EGO_CELL
        m = torch.maximum(fwd.abs(), left.abs())
        inside = m <= lim
        k = torch.where(inside, torch.ones_like(m), lim / m.clamp(min=1e-6))
        a = torch.floor(s / 2 - fwd * k / EGO_CELL).long().clamp(0, s - 1)
        b = torch.floor(s / 2 - left * k / EGO_CELL).long().clamp(0, s - 1)
        return a, b, inside

    def forward(self, ego: torch.Tensor, goal: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(features (B, out_dim), sub-goal (B, 2) = (distance m, direction rad))."""
        B, s = ego.shape[0], self.s
        cost = 1.0 + F.softplus(self.cost(ego)[:, 0])
        a, b, inside = self.goal_cell(goal)
        at_goal = torch.zeros(B, s, s, dtype=torch.bool, device=ego.device)
        at_goal[torch.arange(B, device=ego.device), a, b] = True
        to_goal = bellman(cost, at_goal, self.iterations, self.grad_iterations)
        # distances from the agent over the cells near it (its own cell: 0), a mask only: no gradient
        lo, hi = self.crop
        pad = 2  # cells round the reach that paths from the agent may pass through
        near_cost = cost[:, lo - pad:hi + pad, lo - pad:hi + pad].detach()
        # the goal's cell is always enterable: a 0.5 m cell that holds the goal and a wall is
        # an obstacle cell, and a sub-goal search that cannot enter it never sets the goal
        near_cost = torch.where(at_goal[:, lo - pad:hi + pad, lo - pad:hi + pad], torch.ones_like(near_cost), near_cost)
        at_agent = torch.zeros_like(near_cost, dtype=torch.bool)
        at_agent[:, self.reach_cells + pad, self.reach_cells + pad] = True
        from_agent = bellman(near_cost, at_agent, 2 * (self.reach_cells + pad), 0)
        from_agent = from_agent[:, pad:-pad, pad:-pad][:, self.disc]
        d = to_goal[:, lo:hi, lo:hi][:, self.disc]  # (B, cells within reach)
        # the sub-goal: the cell nearest the goal among those the agent reaches within
        # SUBGOAL_REACH (cells beyond that reach are penalised, not cut off)
        score = d + 10.0 * F.relu(from_agent - SUBGOAL_REACH / EGO_CELL) + 1e4 * self.own_cell
        least = score.min(dim=1, keepdim=True).values
        fwd = self.centre_fwd[lo:hi, lo:hi][self.disc].expand_as(d)
        left = self.centre_left[lo:hi, lo:hi][self.disc].expand_as(d)
        # the goal's own cell stands for the goal's exact position
        rows, cols = torch.nonzero(self.disc, as_tuple=True)
        is_goal = (rows[None] + lo == a[:, None]) & (cols[None] + lo == b[:, None]) & inside[:, None]
        gf, gl = goal[:, :1] * torch.cos(goal[:, 1:]), goal[:, :1] * torch.sin(goal[:, 1:])
        fwd = torch.where(is_goal, gf.expand_as(fwd), fwd)
        left = torch.where(is_goal, gl.expand_as(left), left)
        best = score.argmin(dim=1, keepdim=True)  # ties: the first in row-major order
        pf, pl = fwd.gather(1, best)[:, 0], left.gather(1, best)[:, 0]
        rho, theta = torch.hypot(pf, pl), torch.atan2(pl, pf)
        feats = torch.cat([((score - least) / 8).clamp(max=2.0), (least / 32).clamp(max=2.0), rho[:, None] / SUBGOAL_REACH,
                           torch.cos(theta)[:, None], torch.sin(theta)[:, None]], dim=1)
        return feats, torch.stack([rho, theta], dim=1)


def bellman(cost: torch.Tensor, sources: torch.Tensor, iterations: int, grad_iterations: int) -> torch.Tensor:
    """(B, H, W) distances to the nearest ``sources`` cell (B, H, W) bool after ``iterations``
    Bellman updates over 8 neighbours: a path pays ``cost`` for each of its cells but the
    source (sqrt 2 x the largest cost of the cell and the two beside the step, for a diagonal
    step); cells not reached hold 1e4. Gradients flow through the last ``grad_iterations`` updates.

    On the CPU, for float32 costs, the updates and their gradient run as compiled loops
    (:class:`_BellmanCPU`); otherwise as the tensor operations of :func:`bellman_reference`,
    which the loops reproduce: the same distances bit for bit, and the same gradient
    (torch's rule for ``minimum`` and ``maximum``: a tie splits the gradient in halves) up to
    the order of float additions. Costs must not be NaN (the loops would not pass a NaN on)."""
    if not 0 <= grad_iterations <= iterations:
        raise ValueError(f"bellman: grad_iterations={grad_iterations} must lie in [0, iterations={iterations}]")
    if cost.device.type != "cpu" or cost.dtype != torch.float32:
        return bellman_reference(cost, sources, iterations, grad_iterations)
    if grad_iterations == 0 or not (torch.is_grad_enabled() and cost.requires_grad):
        return _BellmanCPU.distances(cost, sources, iterations, 0)[0]
    return _BellmanCPU.apply(cost, sources, iterations, grad_iterations)


def bellman_reference(cost: torch.Tensor, sources: torch.Tensor, iterations: int, grad_iterations: int) -> torch.Tensor:
    """:func:`bellman` as tensor operations (any device; autograd computes the gradient)."""
    B, h, w = cost.shape
    big = BELLMAN_UNREACHED
    cp = F.pad(cost, (1, 1, 1, 1), value=big)
    sq2 = math.sqrt(2.0)
    diag = {(da, db): sq2 * torch.maximum(cost, torch.maximum(cp[:, 1 + da:1 + da + h, 1:w + 1],
                                                             cp[:, 1:h + 1, 1 + db:1 + db + w]))
            for da, db in DIAGONALS}
    d = torch.where(sources, 0.0, big)

    def update(d):
        p = F.pad(d, (1, 1, 1, 1), value=big)
        straight = torch.minimum(torch.minimum(p[:, 0:h, 1:w + 1], p[:, 2:h + 2, 1:w + 1]),
                                 torch.minimum(p[:, 1:h + 1, 0:w], p[:, 1:h + 1, 2:w + 2]))
        best = straight + cost
        for (da, db), cd in diag.items():
            best = torch.minimum(best, p[:, 1 + da:1 + da + h, 1 + db:1 + db + w] + cd)
        return torch.where(sources, 0.0, torch.minimum(d, best))

    with torch.no_grad():
        for _ in range(iterations - grad_iterations):
            d = update(d)
    for _ in range(grad_iterations):
        d = update(d)
    return d


class _BellmanCPU(torch.autograd.Function):
    """:func:`bellman` on the CPU: the updates in :func:`_bellman_forward`, the gradient in
    :func:`_bellman_backward` (replaying the last ``grad_iterations`` updates from the
    distances saved before each)."""

    @staticmethod
    def distances(cost, sources, iterations, grad_iterations) -> tuple[torch.Tensor, np.ndarray]:
        """The distances, and those before each of the last ``grad_iterations`` updates."""
        c = cost.detach().contiguous().numpy()
        out = np.empty_like(c)
        saved = np.empty((grad_iterations,) + c.shape, np.float32)
        _bellman_forward(c, sources.contiguous().numpy(), iterations, out, saved)
        return torch.from_numpy(out), saved

    @staticmethod
    def forward(ctx, cost, sources, iterations, grad_iterations):
        d, ctx.saved = _BellmanCPU.distances(cost, sources, iterations, grad_iterations)
        ctx.save_for_backward(cost, sources)
        return d

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad):
        cost, sources = ctx.saved_tensors
        g_cost = np.zeros(cost.shape, np.float32)
        _bellman_backward(cost.detach().contiguous().numpy(), sources.contiguous().numpy(), ctx.saved,
                          grad.contiguous().numpy().astype(np.float32, copy=False), g_cost)
        return torch.from_numpy(g_cost), None, None, None


@numba.njit(cache=True, nogil=True, inline="always")
def _diag_cost(c, i, j, da, db, h, w):
    """sqrt 2 x the largest cost of cell (i, j) and its two neighbours beside the diagonal step (da, db)."""
    a = c[i + da, j] if 0 <= i + da < h else np.float32(BELLMAN_UNREACHED)
    b = c[i, j + db] if 0 <= j + db < w else np.float32(BELLMAN_UNREACHED)
    return np.float32(math.sqrt(2.0)) * max(c[i, j], max(a, b))


@numba.njit(cache=True, nogil=True, inline="always")
def _diagonal(k):
    """The (row, column) step of diagonal ``k``, in the order of ``DIAGONALS``."""
    return (-1 if k < 2 else 1), (-1 if k % 2 == 0 else 1)


@numba.njit(cache=True, nogil=True)
def _diag_costs(c, cd):
    """Every cell's four diagonal step costs (:func:`_diag_cost`) into ``cd`` (4, H, W)."""
    h, w = c.shape
    for k in range(4):
        da, db = _diagonal(k)
        for i in range(h):
            for j in range(w):
                cd[k, i, j] = _diag_cost(c, i, j, da, db, h, w)


@numba.njit(cache=True, nogil=True)
def _bellman_forward(cost, sources, iterations, out, saved):
    """``iterations`` updates of every map into ``out``; the distances before each of the last
    ``len(saved)`` updates into ``saved``. Same float operations as :func:`bellman_reference`."""
    B, h, w = cost.shape
    big = np.float32(BELLMAN_UNREACHED)
    n_saved = saved.shape[0]
    p = np.full((h + 2, w + 2), big, np.float32)
    cd = np.empty((4, h, w), np.float32)
    for b in range(B):
        c, d, src = cost[b], out[b], sources[b]
        _diag_costs(c, cd)
        for i in range(h):
            for j in range(w):
                d[i, j] = np.float32(0.0) if src[i, j] else big
        for it in range(iterations):
            if it >= iterations - n_saved:
                saved[it - (iterations - n_saved), b] = d
            p[1:h + 1, 1:w + 1] = d
            for i in range(h):
                for j in range(w):
                    if src[i, j]:
                        continue
                    best = min(min(p[i, j + 1], p[i + 2, j + 1]), min(p[i + 1, j], p[i + 1, j + 2])) + c[i, j]
                    best = min(best, p[i, j] + cd[0, i, j])
                    best = min(best, p[i, j + 2] + cd[1, i, j])
                    best = min(best, p[i + 2, j] + cd[2, i, j])
                    best = min(best, p[i + 2, j + 2] + cd[3, i, j])
                    d[i, j] = min(p[i + 1, j + 1], best)


@numba.njit(cache=True, nogil=True, inline="always")
def _min_grad(x, y, g):
    """Gradients of min(x, y) for x and y (torch's ``minimum``: a tie gives each half)."""
    if x < y:
        return g, np.float32(0.0)
    if x > y:
        return np.float32(0.0), g
    return g / np.float32(2.0), g / np.float32(2.0)


@numba.njit(cache=True, nogil=True)
def _bellman_backward(cost, sources, saved, grad, g_cost):
    """The gradient of the distances after the last ``len(saved)`` updates (``grad``) with
    respect to ``cost``, into ``g_cost``: each update replayed in reverse from the distances
    before it, then the diagonal step costs."""
    B, h, w = cost.shape
    big = np.float32(BELLMAN_UNREACHED)
    n_saved = saved.shape[0]
    p = np.full((h + 2, w + 2), big, np.float32)
    g_p = np.zeros((h + 2, w + 2), np.float32)
    g_d = np.zeros((h, w), np.float32)
    cd = np.empty((4, h, w), np.float32)
    g_cd = np.zeros((4, h, w), np.float32)
    t = np.empty(4, np.float32)
    nb = np.empty(4, np.float32)
    bs = np.empty(5, np.float32)  # the running minimum through the straight and diagonal steps
    for b in range(B):
        c, src, gc = cost[b], sources[b], g_cost[b]
        _diag_costs(c, cd)
        g_cd[:] = 0.0
        g_d[:] = grad[b]
        for it in range(n_saved - 1, -1, -1):
            p[1:h + 1, 1:w + 1] = saved[it, b]
            g_p[:] = 0.0
            for i in range(h):
                for j in range(w):
                    g = g_d[i, j]
                    g_d[i, j] = 0.0
                    if src[i, j] or g == 0.0:
                        continue
                    # forward replay: straight step, then the four diagonals in order
                    m1 = min(p[i, j + 1], p[i + 2, j + 1])
                    m2 = min(p[i + 1, j], p[i + 1, j + 2])
                    b0 = min(m1, m2) + c[i, j]
                    nb[0], nb[1], nb[2], nb[3] = p[i, j], p[i, j + 2], p[i + 2, j], p[i + 2, j + 2]
                    bs[0] = b0
                    for k in range(4):
                        t[k] = nb[k] + cd[k, i, j]
                        bs[k + 1] = min(bs[k], t[k])
                    g_old, g_best = _min_grad(p[i + 1, j + 1], bs[4], g)
                    g_d[i, j] += g_old  # this cell's own distance before the update (read below)
                    for k in range(3, -1, -1):
                        g_best, g_t = _min_grad(bs[k], t[k], g_best)
                        g_cd[k, i, j] += g_t
                        da, db = _diagonal(k)
                        g_p[i + 1 + da, j + 1 + db] += g_t
                    gc[i, j] += g_best
                    g_m1, g_m2 = _min_grad(m1, m2, g_best)
                    gu, gdn = _min_grad(p[i, j + 1], p[i + 2, j + 1], g_m1)
                    gl, gr = _min_grad(p[i + 1, j], p[i + 1, j + 2], g_m2)
                    g_p[i, j + 1] += gu
                    g_p[i + 2, j + 1] += gdn
                    g_p[i + 1, j] += gl
                    g_p[i + 1, j + 2] += gr
            for i in range(h):
                for j in range(w):
                    g_d[i, j] += g_p[i + 1, j + 1]
        # the diagonal step costs: sqrt 2 x max(cost, max(cost beside, cost beside))
        for k in range(4):
            da, db = _diagonal(k)
            for i in range(h):
                for j in range(w):
                    g = g_cd[k, i, j] * np.float32(math.sqrt(2.0))
                    if g == 0.0:
                        continue
                    a = c[i + da, j] if 0 <= i + da < h else big
                    bb = c[i, j + db] if 0 <= j + db < w else big
                    g_c, g_m = _min_grad(-c[i, j], -max(a, bb), g)  # max(x, y) = -min(-x, -y)
                    gc[i, j] += g_c
                    g_a, g_b = _min_grad(-a, -bb, g_m)
                    if 0 <= i + da < h:
                        gc[i + da, j] += g_a
                    if 0 <= j + db < w:
                        gc[i, j + db] += g_b
