"""Policy networks: the PLEX planner and executor (paper 4.2, SPEC 5) and the flat baselines.

Observations are dicts of tensors (numpy arrays are accepted and converted) with a
leading batch dimension:

- planner:  ``ego_map`` (B, C, 32, 32) float in [0, 1]; ``goal`` (B, 2) = (distance m,
  direction rad); ``eli`` (B, 128) float.
- executor: ``rgb`` (B, H, W, 3) uint8; ``depth`` (B, H, W, 1) float in [0, 1];
  ``subgoal`` (B, 2) = (distance m, direction rad).
- flat:     ``rgb``, ``depth`` as the executor, ``pointgoal`` (B, 2); and ``ego_map`` as the
  planner for the flat policy with the map (``FlatMapPolicy``).

Every (distance, direction) vector is fed to the networks as (distance, cos, sin) so that
directions just either side of +-pi look alike (see ``encode_polar``).

Recurrent policies (executor, flat) keep a memory *state*: one tensor whose first
dimension is the batch (``initial_state(batch)``), so a rollout buffer can store and index
it without knowing which memory it is. A ``starts`` mask (B,) says where a new sequence
begins (new sub-goal or new episode); the memory is cleared *before* that step is
processed. Initialisation follows CleanRL: orthogonal weights, zero biases, gain sqrt(2)
for hidden layers, 0.01 for policy heads, 1 for value heads.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
from torch import nn
from torch.nn import functional as F
from torch.distributions import Categorical, Normal

from plex_ma.envs.rules import ELI_DIM
from plex_ma.envs.sim.core import MOVE_FORWARD, NUM_ACTIONS, STOP, TURN_LEFT, TURN_RIGHT, BatchedSim

# float32(pi) is slightly *above* pi, so a float32 angle clamped to it can fail a float64
# `|theta| <= pi` range check; clamp to the float32 just below pi instead.
PI32 = float(np.nextafter(np.float32(np.pi), np.float32(0)))


def layer_init(layer: nn.Module, std: float = math.sqrt(2), bias: float = 0.0) -> nn.Module:
    """Orthogonal weight with gain ``std`` and constant bias (CleanRL's init)."""
    nn.init.orthogonal_(layer.weight, std)
    nn.init.constant_(layer.bias, bias)
    return layer


def encode_polar(vec: torch.Tensor) -> torch.Tensor:
    """(..., 2) = (distance, direction rad) -> (..., 3) = (distance, cos, sin)."""
    return torch.stack([vec[..., 0], torch.cos(vec[..., 1]), torch.sin(vec[..., 1])], dim=-1)


GOAL_FEATURES = 5


STOP_PRIOR_DISTANCE = 0.185  # m: an untrained planner's p(stop) is 0.5 at this goal distance
STOP_PRIOR_SLOPE = 200.0  # stop logit - continue logit per metre nearer the goal than that
OFFSET_FULL_DISTANCE = 1.0  # m: from here out the sub-goal heads' offsets count in full ...
OFFSET_ZERO_DISTANCE = 0.2  # m: ... and from here in not at all (the sub-goal is the goal), linear between
EXECUTOR_STOP_SLOPE = 20.0  # executor STOP logit per metre nearer the sub-goal than its stop prior


def planner_goal_features(goal: torch.Tensor) -> torch.Tensor:
    """(B, 2) goal (distance m, direction rad) -> (B, 5): distance / 10, cos, sin, and
    exp(-distance / 0.5) and min(distance, 2) for a fine reading near the goal (where
    the planner decides to stop)."""
    d, th = goal[..., 0], goal[..., 1]
    return torch.stack([d / 10, torch.cos(th), torch.sin(th), torch.exp(-d / 0.5), d.clamp(max=2.0)], dim=-1)


def _as_tensor(x, device: torch.device, dtype: torch.dtype | None = None) -> torch.Tensor:
    if isinstance(x, np.ndarray):
        x = torch.from_numpy(x)
    return torch.as_tensor(x, device=device, dtype=dtype)


def _conv_out_dim(convs: nn.Module, shape: tuple[int, ...]) -> int:
    with torch.no_grad():
        return convs(torch.zeros(1, *shape)).flatten(1).shape[1]


# --------------------------------------------------------------------------- planner


EGO_CELL = BatchedSim.ego_cell  # m: the ego map's cell size (32 x 32 cells, the agent at cell (16, 16))
SUBGOAL_REACH = 2.0  # m: the value-iteration read-out looks for its sub-goal within this distance


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


BELLMAN_UNREACHED = 1e4  # the distance of cells no path has reached (and of the map's outside)
DIAGONALS = ((-1, -1), (-1, 1), (1, -1), (1, 1))  # (row, column) steps, in the order the update takes them


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


class MapEncoder(nn.Module):
    """The planner's reading of the ego map, one definition for the PLEX planner (a subclass)
    and the flat PPO-GRU+map policy (:class:`FlatMapPolicy`, which holds one):

    - ``convs``: the paper's trunk, conv 4x4/2 and conv 3x3/1 (ReLU), flattened
      (``map_dim`` features);
    - ``vin`` (with ``value_iteration``, else None): a :class:`ValueIteration` module over
      the map and the goal (``vin_dim`` features, which end with its sub-goal as (distance /
      ``SUBGOAL_REACH``, cos, sin)).
    """

    def __init__(self, ego_channels: int = 2, channels: tuple[int, int] = (32, 64), map_size: int = 32,
                 value_iteration: bool = False):
        super().__init__()
        self.convs = nn.Sequential(
            layer_init(nn.Conv2d(ego_channels, channels[0], 4, stride=2)), nn.ReLU(),
            layer_init(nn.Conv2d(channels[0], channels[1], 3, stride=1)), nn.ReLU(),
            nn.Flatten(),
        )
        self.map_dim = _conv_out_dim(self.convs, (ego_channels, map_size, map_size))
        self.vin = ValueIteration(ego_channels, map_size) if value_iteration else None
        self.vin_dim = self.vin.out_dim if self.vin is not None else 0

    def read_map(self, ego: torch.Tensor, goal: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None,
                                                                          torch.Tensor | None]:
        """ego (B, C, S, S), goal (B, 2) = (distance m, direction rad) -> the trunk's features
        (B, map_dim), the value-iteration features (B, vin_dim) and its sub-goal (B, 2) =
        (distance m, direction rad) (both None without the module)."""
        if self.vin is None:
            return self.convs(ego), None, None
        return self.convs(ego), *self.vin(ego, goal)

    def forward(self, ego: torch.Tensor, goal: torch.Tensor) -> torch.Tensor:
        """(B, map_dim + vin_dim): the trunk's and the value-iteration module's features."""
        trunk, vin, _ = self.read_map(ego, goal)
        return trunk if vin is None else torch.cat([trunk, vin], dim=1)


class Planner(MapEncoder):
    """Planner: ego map CNN + ELI + goal -> 512 -> (+ goal) -> MLP heads: stop logits,
    Gaussian sub-goal, value.

    The paper gives the trunk (conv 4x4/2, conv 3x3/1, flatten, concatenate the ELI, FC 512,
    concatenate the goal vector) and leaves the heads open. Here the goal features
    (:func:`planner_goal_features`) also enter the FC layer, so that map and goal interact,
    and each head is an MLP (``head_hidden`` units) over (trunk, goal features). With linear
    heads on (distance, cos, sin), as the text reads literally, the sub-goal direction cannot
    follow the goal's, and a planner trained over the oracle executor reached success 0.00
    where these heads reached 0.83 (docs/results.md).

    The heads answer relative to the goal and start goal-directed:
    - sub-goal mean = (min(goal distance, ``prior_distance``), goal direction) + the head's
      output x a scale that rises linearly from 0 at ``OFFSET_ZERO_DISTANCE`` (0.2 m) to 1 at
      ``OFFSET_FULL_DISTANCE`` (1 m) from the goal, so an untrained planner points at the
      goal, ``prior_distance`` (1.5 m) away at most, directions wrap round the goal's
      direction rather than round +-pi, and near the goal the sub-goal is the goal up to an
      offset that shrinks to nothing (with unscaled offsets, trained planners set sub-goals
      0.1-0.17 m away when the goal was 0.2-0.3 m away, which an executor treats as reached,
      and timed out there: docs/results.md);
    - stop logits = the head's output + a linear skip from the goal features, started at
      ``STOP_PRIOR_SLOPE`` x (``STOP_PRIOR_DISTANCE`` - distance): p(stop) is 0.73 at 0.18 m,
      0.27 at 0.19 m and below 2% beyond 0.205 m, so a greedy planner stops where a stop
      succeeds (< 0.2 m); the head's learned output moves that threshold by only 5 mm per
      unit of logit.

    The map reading (the trunk's convolutions and the value-iteration module) is
    :class:`MapEncoder`'s, whose ``forward`` this class's replaces.

    Sub-goal action: the policy samples an *unbounded* raw (rho, theta) from two Gaussians
    with state-dependent means and state-independent learnable log-stds (started at std
    ``init_std``). The raw sample is what the rollout buffer stores and what ``log_prob`` is
    computed on; only the copy sent to the environment is mapped into the action box by
    ``subgoal_to_env``: rho is clipped to [0, rho_max] and theta is wrapped to [-pi, pi]
    (wrapping, unlike clipping, keeps the direction the sample points to).
    """

    def __init__(self, ego_channels: int = 2, eli_dim: int = ELI_DIM, use_eli: bool = True,
                 rho_max: float = 4.0, hidden: int = 512, channels: tuple[int, int] = (32, 64),
                 map_size: int = 32, init_std: float = 0.5, prior_distance: float = 1.5, head_hidden: int = 256,
                 value_iteration: bool = False):
        # ``convs`` and ``vin`` (the map reading) keep their names: checkpoints key on them
        super().__init__(ego_channels, channels, map_size, value_iteration)
        self.eli_dim, self.use_eli, self.rho_max = eli_dim, use_eli, rho_max
        self.prior_distance = min(prior_distance, rho_max)
        self.fc = nn.Sequential(layer_init(nn.Linear(self.map_dim + eli_dim + GOAL_FEATURES + self.vin_dim, hidden)),
                                nn.ReLU())
        feat = hidden + GOAL_FEATURES

        def mlp(out, std):
            return nn.Sequential(layer_init(nn.Linear(feat, head_hidden)), nn.ReLU(),
                                 layer_init(nn.Linear(head_hidden, out), std=std))

        self.stop_logits, self.subgoal_mean, self.critic = mlp(2, 0.01), mlp(2, 0.01), mlp(1, 1.0)
        self.stop_skip = nn.Linear(GOAL_FEATURES, 2)
        with torch.no_grad():
            self.stop_skip.weight.zero_()
            self.stop_skip.bias.zero_()
            # stop logit - continue logit ~ slope * (prior distance - min(goal distance, 2)) (goal feature 4)
            self.stop_skip.weight[1, 4] = -STOP_PRIOR_SLOPE
            self.stop_skip.bias[1] = STOP_PRIOR_SLOPE * STOP_PRIOR_DISTANCE
        self.subgoal_log_std = nn.Parameter(torch.full((2,), math.log(init_std)))

    def features(self, obs: dict) -> tuple[torch.Tensor, torch.Tensor | None]:
        """(B, hidden + GOAL_FEATURES): the trunk's output and the goal features; and the
        value-iteration module's sub-goal (B, 2) (None without the module)."""
        dev = self.convs[0].weight.device
        ego = _as_tensor(obs["ego_map"], dev, torch.float32)
        goal = planner_goal_features(_as_tensor(obs["goal"], dev, torch.float32))
        if self.use_eli:
            # Stop-gradient (paper 3, SPEC 5): the planner's loss must never reach the
            # executor's parameters, so the ELI always enters the planner detached.
            eli = _as_tensor(obs["eli"], dev, torch.float32).detach()
        else:
            eli = torch.zeros(ego.shape[0], self.eli_dim, device=dev)
        trunk, vin_features, vin_subgoal = self.read_map(ego, _as_tensor(obs["goal"], dev, torch.float32))
        parts = [trunk, eli, goal] + ([vin_features] if vin_features is not None else [])
        h = self.fc(torch.cat(parts, dim=1))
        return torch.cat([h, goal], dim=1), vin_subgoal

    def forward(self, obs: dict) -> tuple[Categorical, Normal, torch.Tensor]:
        """(stop distribution, sub-goal distribution over raw (rho, theta), value (B,))."""
        h, vin_subgoal = self.features(obs)
        goal = _as_tensor(obs["goal"], h.device, torch.float32)
        stop = Categorical(logits=self.stop_logits(h) + self.stop_skip(h[:, -GOAL_FEATURES:]))
        prior = torch.stack([goal[:, 0].clamp(max=self.prior_distance), goal[:, 1]], dim=1)
        scale = ((goal[:, :1] - OFFSET_ZERO_DISTANCE) / (OFFSET_FULL_DISTANCE - OFFSET_ZERO_DISTANCE)).clamp(0.0, 1.0)
        if vin_subgoal is not None:
            # the value-iteration module's sub-goal, blended into the goal with the same
            # scale as the offsets (its direction taken the short way round from the goal's)
            turn = torch.atan2(torch.sin(vin_subgoal[:, 1] - goal[:, 1]), torch.cos(vin_subgoal[:, 1] - goal[:, 1]))
            vin_prior = torch.stack([vin_subgoal[:, 0], goal[:, 1] + turn], dim=1)
            prior = prior + scale * (vin_prior - prior)
        mean = self.subgoal_mean(h) * scale + prior
        subgoal = Normal(mean, self.subgoal_log_std.exp().expand_as(mean))
        return stop, subgoal, self.critic(h).squeeze(-1)

    @staticmethod
    def _log_prob_entropy(stop_d: Categorical, sub_d: Normal, stop: torch.Tensor, subgoal: torch.Tensor):
        # The sub-goal only matters when the planner continues (stop == 0), so its
        # log-prob only counts then. The entropy is H(stop) + H(subgoal), not the joint's
        # exact H(stop) + p(continue) H(subgoal): the latter would let the entropy bonus
        # push p(continue) up and bias the agent against stopping.
        cont = (stop == 0).float()
        log_prob = stop_d.log_prob(stop) + cont * sub_d.log_prob(subgoal).sum(-1)
        entropy = stop_d.entropy() + sub_d.entropy().sum(-1)
        return log_prob, entropy

    def subgoal_to_env(self, subgoal: torch.Tensor) -> torch.Tensor:
        """Map raw samples into the action box: rho clipped to [0, rho_max], theta wrapped."""
        rho = subgoal[..., 0].clamp(0.0, self.rho_max)
        theta = torch.atan2(torch.sin(subgoal[..., 1]), torch.cos(subgoal[..., 1])).clamp(-PI32, PI32)
        return torch.stack([rho, theta], dim=-1)

    @torch.no_grad()
    def act(self, obs: dict, deterministic: bool = False) -> dict:
        """One decision per env: stop (B,) long, subgoal (B, 2) raw sample (store this),
        subgoal_env (B, 2) mapped into the action box (send this), log_prob (B,), value (B,)."""
        stop_d, sub_d, value = self(obs)
        if deterministic:
            stop, subgoal = stop_d.probs.argmax(-1), sub_d.mean
        else:
            stop, subgoal = stop_d.sample(), sub_d.sample()
        log_prob, _ = self._log_prob_entropy(stop_d, sub_d, stop, subgoal)
        return {"stop": stop, "subgoal": subgoal, "subgoal_env": self.subgoal_to_env(subgoal),
                "log_prob": log_prob, "value": value}

    def evaluate_actions(self, obs: dict, stop: torch.Tensor, subgoal: torch.Tensor):
        """(log_prob, entropy, value), each (B,), for stored actions (raw sub-goal samples)."""
        stop_d, sub_d, value = self(obs)
        log_prob, entropy = self._log_prob_entropy(stop_d, sub_d, stop.long(), subgoal)
        return log_prob, entropy, value

    def imitation_loss(self, obs: dict, stop: torch.Tensor, subgoal: torch.Tensor) -> torch.Tensor:
        """(B,) negative log-likelihood of a teacher's decisions: its stop (B,) and, where
        it continues, its sub-goal (B, 2) in the env's (rho, theta). Each theta is matched
        with the one of its 2 pi copies nearest the predicted mean, as raw samples are
        unbounded and only their wrapped copy reaches the env."""
        stop_d, sub_d, _ = self(obs)
        mean = sub_d.mean
        theta = subgoal[:, 1] + 2 * math.pi * torch.round((mean[:, 1].detach() - subgoal[:, 1]) / (2 * math.pi))
        target = torch.stack([subgoal[:, 0], theta], dim=1)
        log_prob, _ = self._log_prob_entropy(stop_d, sub_d, stop.long(), target)
        return -log_prob

    def example_obs(self, batch: int = 1, generator: torch.Generator | None = None) -> dict:
        c, s = self.convs[0].in_channels, 32
        return {"ego_map": torch.rand(batch, c, s, s, generator=generator),
                "goal": torch.rand(batch, 2, generator=generator) * torch.tensor([10.0, 2 * math.pi]) - torch.tensor([0.0, math.pi]),
                "eli": torch.randn(batch, self.eli_dim, generator=generator)}


# --------------------------------------------------------------------------- memories


class GRUMemory(nn.Module):
    """GRU memory. State: (B, hidden)."""

    def __init__(self, in_dim: int, hidden: int = 512):
        super().__init__()
        self.hidden = hidden
        self.out_dim = hidden
        self.gru = nn.GRU(in_dim, hidden)
        for name, p in self.gru.named_parameters():
            if "weight" in name:
                nn.init.orthogonal_(p, 1.0)
            else:
                nn.init.constant_(p, 0.0)

    def initial_state(self, batch: int, device=None) -> torch.Tensor:
        return torch.zeros(batch, self.hidden, device=device)

    def step(self, x: torch.Tensor, state: torch.Tensor, starts: torch.Tensor):
        h = state * (~starts).unsqueeze(-1)
        out, h = self.gru(x.unsqueeze(0), h.unsqueeze(0))
        return out[0], h[0]

    def sequence(self, x: torch.Tensor, state: torch.Tensor, starts: torch.Tensor) -> torch.Tensor:
        """x (T, B, D), starts (T, B) -> (T, B, hidden): the same GRU as :meth:`step`, with
        the memory cleared where ``starts``."""
        # PLEX's executor restarts its memory with every sub-goal, so some sequence starts
        # at almost every time step and cutting time into reset-free chunks for nn.GRU
        # leaves chunks of one or two steps. Instead, project all inputs in one matmul and
        # run only the recurrent half step by step (PyTorch's gate order r, z, n):
        # 1.7-2x faster forward + backward than per-chunk nn.GRU calls at T=64, B=8.
        g = self.gru
        gi = F.linear(x, g.weight_ih_l0, g.bias_ih_l0)
        keep = (~starts).unsqueeze(-1).to(x.dtype)
        h, outs = state, []
        for t in range(x.shape[0]):
            h = h * keep[t]
            i_r, i_z, i_n = gi[t].chunk(3, -1)
            h_r, h_z, h_n = F.linear(h, g.weight_hh_l0, g.bias_hh_l0).chunk(3, -1)
            r = torch.sigmoid(i_r + h_r)
            z = torch.sigmoid(i_z + h_z)
            n = torch.tanh(i_n + r * h_n)
            h = n + z * (h - n)
            outs.append(h)
        return torch.stack(outs)


class MultiHeadAttention(nn.Module):
    """Plain multi-head attention with a boolean mask (True = may attend).

    Written out with matmuls (not scaled_dot_product_attention) so that FLOP counting
    sees it and one step and a whole sequence use the same arithmetic.
    """

    def __init__(self, dim: int, heads: int):
        super().__init__()
        assert dim % heads == 0, "dim must be divisible by heads"
        self.heads, self.head_dim = heads, dim // heads
        self.q, self.k, self.v, self.o = (layer_init(nn.Linear(dim, dim), std=1.0) for _ in range(4))

    def forward(self, x: torch.Tensor, memory: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """x (B, Tq, D) attends over memory (B, S, D) where mask (B, Tq, S)."""
        B, Tq, D = x.shape
        S = memory.shape[1]
        q = self.q(x).view(B, Tq, self.heads, self.head_dim).transpose(1, 2)
        k = self.k(memory).view(B, S, self.heads, self.head_dim).transpose(1, 2)
        v = self.v(memory).view(B, S, self.heads, self.head_dim).transpose(1, 2)
        scores = (q @ k.transpose(-1, -2)) / math.sqrt(self.head_dim)
        attn = scores.masked_fill(~mask.unsqueeze(1), float("-inf")).softmax(dim=-1)
        return self.o((attn @ v).transpose(1, 2).reshape(B, Tq, D))


class SMTMemory(nn.Module):
    """Scene-memory transformer (after Fang et al. 2019, without furthest-point sampling).

    Each step's input is embedded into a memory token; the current token attends with
    ``heads`` heads over the memory of the last ``capacity`` tokens of its sequence
    (itself included), followed by a feed-forward block (pre-norm residuals). One
    attention block; Fang et al.'s separate memory encoder is left out.

    State: (B, capacity, dim + 1): the stored tokens, oldest first and the newest in the
    last slot, plus a last channel that is 1 for a filled slot and 0 for an empty one.
    """

    def __init__(self, in_dim: int, dim: int = 128, heads: int = 8, capacity: int = 128):
        super().__init__()
        self.dim, self.capacity, self.out_dim = dim, capacity, dim
        self.embed = layer_init(nn.Linear(in_dim, dim), std=1.0)
        self.norm1, self.norm2, self.norm_out = nn.LayerNorm(dim), nn.LayerNorm(dim), nn.LayerNorm(dim)
        self.attn = MultiHeadAttention(dim, heads)
        self.ff = nn.Sequential(layer_init(nn.Linear(dim, 2 * dim)), nn.ReLU(), layer_init(nn.Linear(2 * dim, dim), std=1.0))

    def initial_state(self, batch: int, device=None) -> torch.Tensor:
        return torch.zeros(batch, self.capacity, self.dim + 1, device=device)

    def _block(self, x: torch.Tensor, memory: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        kv = self.norm1(memory)
        h = x + self.attn(self.norm1(x), kv, mask)
        h = h + self.ff(self.norm2(h))
        return self.norm_out(h)

    def step(self, x: torch.Tensor, state: torch.Tensor, starts: torch.Tensor):
        tok = self.embed(x)
        mem = state * (~starts).view(-1, 1, 1)  # a start empties every slot
        new = torch.cat([tok, torch.ones_like(tok[:, :1])], dim=-1)
        mem = torch.cat([mem[:, 1:], new.unsqueeze(1)], dim=1)  # drop the oldest, append
        used = self._filled_tail(mem)  # attend over the filled slots only (cheaper, same result)
        valid = used[..., self.dim] > 0.5
        out = self._block(tok.unsqueeze(1), used[..., : self.dim], valid.unsqueeze(1))
        return out[:, 0], mem

    def _filled_tail(self, mem: torch.Tensor) -> torch.Tensor:
        """The last slots of ``mem`` that hold a token in at least one env. Filled slots are
        always a suffix, and empty ones are masked out anyway."""
        n = int((mem[..., self.dim] > 0.5).sum(dim=1).max())
        return mem[:, mem.shape[1] - n:]

    def sequence(self, x: torch.Tensor, state: torch.Tensor, starts: torch.Tensor) -> torch.Tensor:
        """x (T, B, D), starts (T, B) -> (T, B, dim), all steps in one attention call."""
        T, M = x.shape[0], self.capacity
        tok = self.embed(x).transpose(0, 1)  # (B, T, dim)
        old = self._filled_tail(state)  # stored memory slots M - K .. M - 1
        K = old.shape[1]
        keys = torch.cat([old[..., : self.dim], tok], dim=1)  # (B, K + T, dim)
        # Block-causal, sliding-window mask reproducing ``step``: step t sees step s of
        # this call if both are in the same sequence (no start in (s, t]), s <= t and
        # t - s < M; it sees slot j of the stored memory (which holds step j - M) only if
        # no start happened in [0, t], the slot is filled and t - (j - M) < M, i.e. j > t.
        seg = starts.long().cumsum(0).transpose(0, 1)  # (B, T) sequence id; 0 = continues state
        t = torch.arange(T, device=x.device)
        j = torch.arange(M - K, M, device=x.device)
        causal = (t[None, :] <= t[:, None]) & (t[:, None] - t[None, :] < M)  # (T, T) [query, key]
        new_ok = (seg[:, :, None] == seg[:, None, :]) & causal
        filled = old[..., self.dim] > 0.5  # (B, K)
        mem_ok = (seg == 0)[:, :, None] & filled[:, None, :] & (j[None, :] > t[:, None])
        out = self._block(tok, keys, torch.cat([mem_ok, new_ok], dim=-1))
        return out.transpose(0, 1)


# --------------------------------------------------------------------------- executor


class RGBDEncoder(nn.Module):
    """conv 8x8/4, 4x4/2, 3x3/1 (ReLU) over RGB-D, then FC + ReLU (habitat's SimpleCNN shape)."""

    def __init__(self, resolution: int, out_dim: int, channels: tuple[int, int, int] = (32, 64, 32)):
        super().__init__()
        self.resolution = resolution
        self.convs = nn.Sequential(
            layer_init(nn.Conv2d(4, channels[0], 8, stride=4)), nn.ReLU(),
            layer_init(nn.Conv2d(channels[0], channels[1], 4, stride=2)), nn.ReLU(),
            layer_init(nn.Conv2d(channels[1], channels[2], 3, stride=1)), nn.ReLU(),
            nn.Flatten(),
        )
        n_flat = _conv_out_dim(self.convs, (4, resolution, resolution))
        self.fc = nn.Sequential(layer_init(nn.Linear(n_flat, out_dim)), nn.ReLU())

    def forward(self, rgb: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
        """rgb (N, H, W, 3) uint8, depth (N, H, W, 1) float -> (N, out_dim)."""
        # One NHWC buffer, viewed as NCHW: the convolutions then run channels-last, and the
        # largest tensor of the update is written once (no divide-then-concatenate copies).
        x = torch.empty(*rgb.shape[:-1], 4, device=rgb.device)
        torch.div(rgb, 255.0, out=x[..., :3])
        x[..., 3:] = depth
        return self.fc(self.convs(x.permute(0, 3, 1, 2)))


class Executor(nn.Module):
    """Executor: RGB-D CNN -> FC (+ goal) -> GRU or SMT memory -> 128-d output, which is
    both the action embedding and the ELI -> 4-way action logits and a value.

    ``memory="gru"``: FC 512, GRU hidden 512, then a linear layer to the 128-d output.
    ``memory="smt"``: FC 128, SMT with ``smt_heads`` heads over up to ``smt_memory``
    tokens, then a linear layer to the 128-d output. The output goes through tanh so the
    ELI sent to the planner stays in [-1, 1].

    ``stop_prior`` (metres, or None): the STOP logit also gets a linear skip from
    min(sub-goal distance, 2 m), started at ``EXECUTOR_STOP_SLOPE`` x (``stop_prior`` -
    distance) + ln 3, so an untrained executor (three other logits near 0) has p(STOP) 0.5 at
    ``stop_prior`` m from its sub-goal, 0.9 at 0.1 m nearer and below 2% from 0.25 m
    farther. (Trained without it under the cpu preset's STOP penalty, executors never chose
    STOP and turned in place at their sub-goals: docs/results.md.)
    """

    goal_key = "subgoal"

    def __init__(self, memory: str = "gru", resolution: int = 128, eli_dim: int = ELI_DIM,
                 smt_memory: int = 128, smt_heads: int = 8, gru_hidden: int = 512, goal_skip: bool = True,
                 stop_prior: float | None = None, extra_inputs: int = 0, heading_prior: float | None = None):
        """``extra_inputs``: features a subclass's ``_inputs`` adds to the memory's input
        beside the image's and the goal's (:class:`FlatMapPolicy`'s map features).
        ``heading_prior`` (logits, or None; needs ``goal_skip``): the actor's goal inputs start
        at MOVE_FORWARD += k cos(direction), TURN_LEFT += k sin, TURN_RIGHT -= k sin, so an
        untrained policy turns towards its goal and moves when it faces it."""
        super().__init__()
        self.goal_skip = goal_skip
        if memory not in ("gru", "smt"):
            raise ValueError(f"memory must be 'gru' or 'smt', got {memory!r}")
        self.memory_kind, self.resolution, self.eli_dim = memory, resolution, eli_dim
        emb = 512 if memory == "gru" else 128
        self.encoder = RGBDEncoder(resolution, emb)
        if memory == "gru":
            self.memory = GRUMemory(emb + 3 + extra_inputs, gru_hidden)
        else:
            self.memory = SMTMemory(emb + 3 + extra_inputs, 128, smt_heads, smt_memory)
        self.eli_head = layer_init(nn.Linear(self.memory.out_dim, eli_dim))
        # goal_skip: the heads also read the encoded goal vector, so that "turn towards the
        # goal" is a simple function of their input from the first update on (through the
        # memory alone, 3 goal inputs beside 512 image features are learnt too slowly: the
        # policy's entropy collapsed before it did, README).
        head_in = eli_dim + (3 if goal_skip else 0)
        self.actor = layer_init(nn.Linear(head_in, NUM_ACTIONS), std=0.01)
        self.critic = layer_init(nn.Linear(head_in, 1), std=1.0)
        if heading_prior is not None:
            if not goal_skip:
                raise ValueError("heading_prior needs goal_skip (the actor's goal inputs)")
            with torch.no_grad():  # goal inputs: (distance, cos, sin) after the eli_dim ELI features
                self.actor.weight[MOVE_FORWARD, eli_dim + 1] += heading_prior
                self.actor.weight[TURN_LEFT, eli_dim + 2] += heading_prior
                self.actor.weight[TURN_RIGHT, eli_dim + 2] -= heading_prior
        self.stop_skip = None
        if stop_prior is not None:
            self.stop_skip = nn.Linear(1, NUM_ACTIONS)
            with torch.no_grad():
                self.stop_skip.weight.zero_()
                self.stop_skip.bias.zero_()
                self.stop_skip.weight[STOP, 0] = -EXECUTOR_STOP_SLOPE
                self.stop_skip.bias[STOP] = EXECUTOR_STOP_SLOPE * stop_prior + math.log(NUM_ACTIONS - 1)
                # facing the sub-goal, the heading prior adds k to MOVE_FORWARD: so much more for STOP
                self.stop_skip.bias[STOP] += heading_prior or 0.0

    @property
    def device(self) -> torch.device:
        return self.actor.weight.device

    def initial_state(self, batch: int) -> torch.Tensor:
        return self.memory.initial_state(batch, self.device)

    def _inputs(self, obs: dict) -> tuple[torch.Tensor, torch.Tensor]:
        """Any leading dims (...) -> memory input (..., emb + 3) and encoded goal (..., 3)."""
        dev = self.device
        rgb = _as_tensor(obs["rgb"], dev)
        depth = _as_tensor(obs["depth"], dev, torch.float32)
        goal = encode_polar(_as_tensor(obs[self.goal_key], dev, torch.float32))
        lead = rgb.shape[:-3]
        feat = self.encoder(rgb.reshape(-1, *rgb.shape[-3:]), depth.reshape(-1, *depth.shape[-3:]))
        return torch.cat([feat.view(*lead, -1), goal], dim=-1), goal

    def _heads(self, out: torch.Tensor, goal: torch.Tensor):
        eli = torch.tanh(self.eli_head(out))
        h = torch.cat([eli, goal], dim=-1) if self.goal_skip else eli
        logits = self.actor(h)
        if self.stop_skip is not None:
            logits = logits + self.stop_skip(goal[..., :1].clamp(max=2.0))
        return logits, self.critic(h).squeeze(-1), eli

    def forward(self, obs: dict, state: torch.Tensor, starts):
        """One step for a batch: (logits (B, 4), value (B,), eli (B, 128), new state)."""
        starts = _as_tensor(starts, self.device, torch.bool)
        x, goal = self._inputs(obs)
        out, state = self.memory.step(x, state, starts)
        logits, value, eli = self._heads(out, goal)
        return logits, value, eli, state

    @torch.no_grad()
    def act(self, obs: dict, state: torch.Tensor, starts, deterministic: bool = False):
        """Rollout step: (dict(action, log_prob, value, eli), new state)."""
        logits, value, eli, state = self(obs, state, starts)
        dist = Categorical(logits=logits)
        action = logits.argmax(-1) if deterministic else dist.sample()
        return {"action": action, "log_prob": dist.log_prob(action), "value": value, "eli": eli}, state

    def evaluate_sequences(self, obs_seq: dict, actions: torch.Tensor, starts: torch.Tensor,
                           initial_state: torch.Tensor):
        """Training pass over (T, B) sequences whose memory is ``initial_state`` before step 0
        and is cleared where ``starts``: (log_prob, entropy, value), each (T, B)."""
        starts = _as_tensor(starts, self.device, torch.bool)
        x, goal = self._inputs(obs_seq)
        out = self.memory.sequence(x, initial_state, starts)
        logits, value, _ = self._heads(out, goal)
        dist = Categorical(logits=logits)
        return dist.log_prob(_as_tensor(actions, self.device).long()), dist.entropy(), value

    def example_obs(self, batch: int = 1, generator: torch.Generator | None = None) -> dict:
        r = self.resolution
        return {"rgb": torch.randint(0, 256, (batch, r, r, 3), dtype=torch.uint8, generator=generator),
                "depth": torch.rand(batch, r, r, 1, generator=generator),
                self.goal_key: torch.rand(batch, 2, generator=generator) * torch.tensor([5.0, 2 * math.pi]) - torch.tensor([0.0, math.pi])}


class FlatPolicy(Executor):
    """Flat PointNav baselines: PPO-GRU (Savva et al. 2019) and PPO-SMT (Fang et al. 2019).

    The executor's network with the end goal (``pointgoal``) in place of the sub-goal; the
    trainer passes ``starts`` only at episode starts, so the memory spans the episode. The
    SMT memory keeps the last 256 steps of the episode by default (episodes run up to 500
    steps). Unlike Savva et al., the heads sit on the same 128-d output layer as the
    executor's, so the baselines and PLEX differ only in the hierarchy.
    """

    goal_key = "pointgoal"
    reads_ego_map = False  # the flat worlds need not keep ego maps (FlatMapPolicy's do)

    def __init__(self, memory: str = "gru", resolution: int = 128, smt_memory: int = 256, **kw):
        super().__init__(memory=memory, resolution=resolution, smt_memory=smt_memory, **kw)


class FlatMapPolicy(FlatPolicy):
    """PPO-GRU+map (``ppo-gru-map``): the flat PPO-GRU baseline that also reads the PLEX
    planner's ego map, the control arm that tells the hierarchy's gain from the map's.

    Observations: the flat ones and ``ego_map`` (B, C, 32, 32), the planner's (the flat worlds
    keep it when built with ``egomap=True``). The map goes through the planner's
    :class:`MapEncoder` (its trunk and, with ``value_iteration``, its value-iteration module,
    which reads the point goal as the planner reads its goal), and those features enter the
    memory beside the image features and the encoded goal; everything after the memory is
    :class:`FlatPolicy`'s.
    """

    reads_ego_map = True

    def __init__(self, memory: str = "gru", resolution: int = 128, ego_channels: int = 2,
                 value_iteration: bool = False, **kw):
        encoder = MapEncoder(ego_channels, value_iteration=value_iteration)
        super().__init__(memory=memory, resolution=resolution, extra_inputs=encoder.map_dim + encoder.vin_dim, **kw)
        self.map = encoder

    def _inputs(self, obs: dict) -> tuple[torch.Tensor, torch.Tensor]:
        x, goal = super()._inputs(obs)
        dev = self.device
        ego = _as_tensor(obs["ego_map"], dev, torch.float32)
        pointgoal = _as_tensor(obs[self.goal_key], dev, torch.float32)
        lead = ego.shape[:-3]
        feat = self.map(ego.reshape(-1, *ego.shape[-3:]), pointgoal.reshape(-1, 2))
        return torch.cat([x, feat.view(*lead, -1)], dim=-1), goal

    def example_obs(self, batch: int = 1, generator: torch.Generator | None = None) -> dict:
        c = self.map.convs[0].in_channels
        # mostly unseen cells, some free and some obstacles, as an ego map reads
        return {**super().example_obs(batch, generator),
                "ego_map": (torch.rand(batch, c, 32, 32, generator=generator) < 0.2).float()}
