"""The value-iteration module over the ego map (:class:`ValueIteration`) and its Bellman
updates (:func:`bellman`): on the CPU compiled numba loops, elsewhere the tensor version
:func:`bellman_reference`, which the loops reproduce bit for bit
(tests/test_value_iteration.py). The module has no parameters: it is a fixed planning
step whose read-out the planner's layers learn from."""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from plex_ma.envs.sim.core import BatchedSim
from plex_ma.envs.sim.kernels import pick, prange, threaded

EGO_CELL = BatchedSim.ego_cell  # m: the ego map's cell size (32 x 32 cells, the agent at cell (16, 16))
ITERATIONS = {False: 40, True: 80}  # Bellman updates on the 32 x 32 map and on the fine 64 x 64 one
SUBGOAL_REACH = 2.0  # m: the value-iteration read-out looks for its sub-goal within this distance
OBSTACLE_LOGIT, FREE_LOGIT = 100.0, -4.0  # a cell's cost: 1 + softplus(OBSTACLE_LOGIT x obstacle + FREE_LOGIT)
BELLMAN_UNREACHED = 1e4  # the distance of cells no path has reached (and of the map's outside)
DIAGONALS = ((-1, -1), (-1, 1), (1, -1), (1, 1))  # (row, column) steps, in the order the update takes them


class ValueIteration(nn.Module):
    """A planning module over the ego map: a value-iteration network (Tamar et al. 2016),
    as CMP (Gupta et al. 2017) plans on egocentric maps.

    - A cost per cell, ``1 + softplus(OBSTACLE_LOGIT x obstacle + FREE_LOGIT)``: about 1.02 on
      free and unseen cells (unseen cells count as free) and 97 on cells seen as obstacles.
      It was a learned 3x3 convolution started at these values; training left it where it
      started (docs/results.md), so it is fixed and no gradient flows through the module.
    - The map it plans on: the ego map's obstacle channel (32 x 32 cells of 0.5 m), or with
      ``fine`` its quarter cells' (channels 2-5 unpacked to 64 x 64 cells of 0.25 m, where
      a narrow door that closes a 0.5 m cell stays open).
    - ``iterations`` Bellman updates (default ``ITERATIONS``: 40, or 80 on the fine map) of
      the distance to the goal over 8 neighbours (a diagonal step costs sqrt 2 x the largest cost of the cell and the two cells beside
      the step, so paths do not cut a wall's corner). The goal is its cell, or, beyond the
      map, the cell where the straight line to it leaves the map (:func:`bellman`).
    - Read-out (:meth:`forward`): the distance field within ``SUBGOAL_REACH`` of the agent
      relative to its smallest value there, and a sub-goal: the cell nearest the goal among
      those the agent reaches within that distance (the goal's exact position stands in for
      its cell; the agent's own cell is never chosen).
    """

    def __init__(self, fine: bool = False, iterations: int | None = None):
        super().__init__()
        self.fine = fine
        self.cell = EGO_CELL / 2 if fine else EGO_CELL
        self.s = 2 * BatchedSim.ego_size if fine else BatchedSim.ego_size
        self.iterations = ITERATIONS[fine] if iterations is None else iterations
        s, r = self.s, int(SUBGOAL_REACH / self.cell)
        self.reach_cells = r
        rows = torch.arange(s, dtype=torch.float32)
        fwd = (s / 2 - rows - 0.5) * self.cell  # the cell centres' offsets from the agent (m)
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
        s, cell = self.s, self.cell
        fwd, left = goal[:, 0] * torch.cos(goal[:, 1]), goal[:, 0] * torch.sin(goal[:, 1])
        lim = (s / 2 - 1) * cell
        m = torch.maximum(fwd.abs(), left.abs())
        inside = m <= lim
        k = torch.where(inside, torch.ones_like(m), lim / m.clamp(min=1e-6))
        a = torch.floor(s / 2 - fwd * k / cell).long().clamp(0, s - 1)
        b = torch.floor(s / 2 - left * k / cell).long().clamp(0, s - 1)
        return a, b, inside

    @torch.no_grad()
    def forward(self, ego: torch.Tensor, goal: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """ego maps (B, C, 32, 32) and goals (B, 2) -> (features (B, out_dim), sub-goal (B, 2) =
        (distance m, direction rad)); no gradient."""
        B, s = ego.shape[0], self.s
        obstacles = F.pixel_shuffle(ego[:, 2:6], 2)[:, 0] if self.fine else ego[:, 0]
        cost = 1.0 + F.softplus(OBSTACLE_LOGIT * obstacles + FREE_LOGIT)
        a, b, inside = self.goal_cell(goal)
        at_goal = torch.zeros(B, s, s, dtype=torch.bool, device=ego.device)
        at_goal[torch.arange(B, device=ego.device), a, b] = True
        to_goal = bellman(cost, at_goal, self.iterations)
        # distances from the agent over the cells near it (its own cell: 0)
        lo, hi = self.crop
        pad = 2  # cells round the reach that paths from the agent may pass through
        near_cost = cost[:, lo - pad:hi + pad, lo - pad:hi + pad]
        # the goal's cell is always enterable: a 0.5 m cell that holds the goal and a wall is
        # an obstacle cell, and a sub-goal search that cannot enter it never sets the goal
        near_cost = torch.where(at_goal[:, lo - pad:hi + pad, lo - pad:hi + pad], torch.ones_like(near_cost), near_cost)
        at_agent = torch.zeros_like(near_cost, dtype=torch.bool)
        at_agent[:, self.reach_cells + pad, self.reach_cells + pad] = True
        from_agent = bellman(near_cost, at_agent, 2 * (self.reach_cells + pad))
        from_agent = from_agent[:, pad:-pad, pad:-pad][:, self.disc]
        d = to_goal[:, lo:hi, lo:hi][:, self.disc]  # (B, cells within reach)
        # the sub-goal: the cell nearest the goal among those the agent reaches within
        # SUBGOAL_REACH (cells beyond that reach are penalised, not cut off)
        score = d + 10.0 * F.relu(from_agent - SUBGOAL_REACH / self.cell) + 1e4 * self.own_cell
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
        # distances in metres / 4 (near the agent) and / 16 (the nearest to the goal)
        feats = torch.cat([((score - least) * (self.cell / 4)).clamp(max=2.0), (least * (self.cell / 16)).clamp(max=2.0),
                           rho[:, None] / SUBGOAL_REACH,
                           torch.cos(theta)[:, None], torch.sin(theta)[:, None]], dim=1)
        return feats, torch.stack([rho, theta], dim=1)


def bellman(cost: torch.Tensor, sources: torch.Tensor, iterations: int) -> torch.Tensor:
    """(B, H, W) distances to the nearest ``sources`` cell (B, H, W) bool after ``iterations``
    Bellman updates over 8 neighbours: a path pays ``cost`` for each of its cells but the
    source (sqrt 2 x the largest cost of the cell and the two beside the step, for a diagonal
    step); cells not reached hold 1e4. No gradient.

    On the CPU, for float32 costs, the updates run as compiled loops
    (:func:`_bellman_forward`); otherwise as the tensor operations of
    :func:`bellman_reference`: the same distances bit for bit. Costs must not be NaN (the
    loops would not pass a NaN on)."""
    if cost.device.type != "cpu" or cost.dtype != torch.float32:
        return bellman_reference(cost, sources, iterations)
    c = cost.detach().contiguous().numpy()
    out = np.empty_like(c)
    pick(_bellman_forward, c.shape[0])(c, sources.contiguous().numpy(), iterations, out)
    return torch.from_numpy(out)


@torch.no_grad()
def bellman_reference(cost: torch.Tensor, sources: torch.Tensor, iterations: int) -> torch.Tensor:
    """:func:`bellman` as tensor operations (any device)."""
    B, h, w = cost.shape
    big = BELLMAN_UNREACHED
    cp = F.pad(cost, (1, 1, 1, 1), value=big)
    sq2 = math.sqrt(2.0)
    diag = {(da, db): sq2 * torch.maximum(cost, torch.maximum(cp[:, 1 + da:1 + da + h, 1:w + 1],
                                                             cp[:, 1:h + 1, 1 + db:1 + db + w]))
            for da, db in DIAGONALS}
    d = torch.where(sources, 0.0, big)
    for _ in range(iterations):
        p = F.pad(d, (1, 1, 1, 1), value=big)
        straight = torch.minimum(torch.minimum(p[:, 0:h, 1:w + 1], p[:, 2:h + 2, 1:w + 1]),
                                 torch.minimum(p[:, 1:h + 1, 0:w], p[:, 1:h + 1, 2:w + 2]))
        best = straight + cost
        for (da, db), cd in diag.items():
            best = torch.minimum(best, p[:, 1 + da:1 + da + h, 1 + db:1 + db + w] + cd)
        d = torch.where(sources, 0.0, torch.minimum(d, best))
    return d


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


@threaded(nogil=True)
def _bellman_forward(cost, sources, iterations, out):
    """``iterations`` updates of every map into ``out``, with the same float operations as
    :func:`bellman_reference`; a map's updates stop early once one changes no cell (the
    fixed point: the rest would change nothing). The maps are shared out over threads."""
    B, h, w = cost.shape
    big = np.float32(BELLMAN_UNREACHED)
    for b in prange(B):
        p = np.full((h + 2, w + 2), big, np.float32)
        cd = np.empty((4, h, w), np.float32)
        c, d, src = cost[b], out[b], sources[b]
        _diag_costs(c, cd)
        for i in range(h):
            for j in range(w):
                d[i, j] = np.float32(0.0) if src[i, j] else big
        for _ in range(iterations):
            p[1:h + 1, 1:w + 1] = d
            changed = False
            for i in range(h):
                for j in range(w):
                    if src[i, j]:
                        continue
                    best = min(min(p[i, j + 1], p[i + 2, j + 1]), min(p[i + 1, j], p[i + 1, j + 2])) + c[i, j]
                    best = min(best, p[i, j] + cd[0, i, j])
                    best = min(best, p[i, j + 2] + cd[1, i, j])
                    best = min(best, p[i + 2, j] + cd[2, i, j])
                    best = min(best, p[i + 2, j + 2] + cd[3, i, j])
                    if best < p[i + 1, j + 1]:
                        d[i, j] = best
                        changed = True
            if not changed:
                break
