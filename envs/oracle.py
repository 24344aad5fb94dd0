"""Shortest-path oracles for PLEX (docs/spec.md section 7): ground-truth stand-ins for either agent.

They read the world's ground truth (the true pose, the navigable grid, the goal's
distance field), so they are diagnostics and upper bounds, never agents that could run
on a robot; every output that uses one says so.

- :class:`OraclePlanner`: stops once the geodesic distance to the goal is below the
  success distance; otherwise sets the sub-goal ``lookahead`` metres along the shortest
  path to the goal (the goal itself when it is nearer).
- :class:`OracleExecutor`: follows the shortest path to the current sub-goal, as
  Habitat's ``ShortestPathFollower`` does for the flat task: it turns towards a point
  ``aim`` metres further along the path until that point lies within half a turn step
  of its heading, then moves forward; it chooses STOP once it is within ``stop_distance``
  of the sub-goal.

Both act on a :class:`~plex_ma.envs.rules.PlexWorlds` (``env.worlds`` of the AEC and vector
envs) for the rows they are given, and return the arrays the env's ``step`` takes.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .rules import ELI_DIM, PlexWorlds
from .sim import kernels as K
from .sim.core import MOVE_FORWARD, STOP, TURN_LEFT, TURN_RIGHT, wrap_angle


@njit(cache=True)
def _along_path(nav, moves, off, h, w, ox, oy, cs, field, x, y, length):
    """The point ``length`` metres along the shortest path from (x, y) down the distance
    field ``field``: the cell centre reached by steepest descent once the path walked is at
    least ``length``, or the last cell before the target (its field value below one cell).
    Returns (x, y, found): found is False when (x, y) cannot reach the target."""
    r0, c0 = K._block(ox, oy, cs, x, y)
    v, best = -1, K.INF
    for k in range(4):
        u, _, _, tail = K._link(nav, off, h, w, ox, oy, cs, r0, c0, k, x, y)
        if u >= 0 and field[u] < K.INF and field[u] + tail < best:
            best = field[u] + tail
            v = u
    if v < 0:
        return x, y, False
    walked = 0.0
    diag = cs * math.sqrt(2.0)
    while walked < length:
        m = moves[off + v]
        nxt, nd = -1, field[v]
        for j in range(8):
            if (m >> j) & 1 == 0:
                continue
            u = v + K.MOVE_DR[j] * w + K.MOVE_DC[j]
            if field[u] < nd:
                nd = field[u]
                nxt = u
        if nxt < 0:
            break
        walked += cs if (nxt - v) in (1, -1, w, -w) else diag
        v = nxt
    r, c = v // w, v % w
    return ox + (c + 0.5) * cs, oy + (r + 0.5) * cs, True


class OraclePlanner:
    """Ground-truth planner (see the module docstring). ``lookahead``: metres of shortest
    path between the agent and its sub-goal (at most the env's ``rho_max``)."""

    name = "oracle"
    ground_truth = True

    def __init__(self, worlds: PlexWorlds, lookahead: float = 2.0):
        self.worlds = worlds
        self.lookahead = min(float(lookahead), worlds.cfg.rho_max)

    def decide(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(stop (len(rows),) int64, subgoal (len(rows), 2) float32) for the worlds ``rows``."""
        w, sim, b = self.worlds, self.worlds.sim, self.worlds.bank
        rows = np.asarray(rows, np.int64).reshape(-1)
        stop = (sim.distance_to_goal[rows] < w.cfg.success_distance).astype(np.int64)
        targets = sim.goal.copy()
        for i in rows:
            if sim.distance_to_goal[i] <= self.lookahead:
                continue  # the goal itself is the sub-goal
            s = int(sim.scene_idx[i])
            x, y, ok = _along_path(b.nav, b.moves, int(b.off[s]), int(b.h[s]), int(b.w[s]), float(b.ox[s]),
                                   float(b.oy[s]), b.cell_size, sim.fields[i], float(sim.pos[i, 0]),
                                   float(sim.pos[i, 1]), self.lookahead)
            if ok:
                targets[i] = (x, y)
        sub = sim.polar_to(targets[rows], rows)
        sub[:, 0] = np.minimum(sub[:, 0], w.cfg.rho_max)
        return stop, sub


class OracleExecutor:
    """Ground-truth executor (see the module docstring). It sends an all-zero ELI."""

    name = "oracle"
    ground_truth = True

    def __init__(self, worlds: PlexWorlds, aim: float = 0.3, stop_distance: float | None = None):
        self.worlds = worlds
        self.aim = float(aim)
        # STOP within 90% of the success distance, so that the planner's stop after a final
        # sub-goal at the goal succeeds.
        self.stop_distance = 0.9 * worlds.cfg.success_distance if stop_distance is None else float(stop_distance)
        n, cells = worlds.n, worlds.bank.max_cells
        self.fields = np.full((n, cells), K.INF, np.float32)  # distance field of each world's sub-goal
        self.targets = np.full((n, 2), np.nan)
        self.half_turn = worlds.sim.turn_angle / 2 + 1e-6

    def act(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(action (len(rows),) int64, eli (len(rows), 128) float32) for the worlds ``rows``."""
        w, sim, b = self.worlds, self.worlds.sim, self.worlds.bank
        rows = np.asarray(rows, np.int64).reshape(-1)
        act = np.empty(len(rows), np.int64)
        for k, i in enumerate(rows):
            s = int(sim.scene_idx[i])
            args = (b.nav, b.moves, int(b.off[s]), int(b.h[s]), int(b.w[s]), float(b.ox[s]), float(b.oy[s]),
                    b.cell_size)
            if not np.array_equal(self.targets[i], w.subgoal[i]):
                w.geo.field(s, w.subgoal[i], out=self.fields[i])
                self.targets[i] = w.subgoal[i]
            px, py = float(sim.pos[i, 0]), float(sim.pos[i, 1])
            d = K.field_lookup(b.nav, *args[2:], self.fields[i], px, py)
            if d < self.stop_distance or d >= K.INF:
                act[k] = STOP
                continue
            if d <= self.aim:
                tx, ty = w.subgoal[i]
            else:
                tx, ty, _ = _along_path(*args, self.fields[i], px, py, self.aim)
            ang = wrap_angle(math.atan2(ty - py, tx - px) - sim.heading[i])
            if abs(ang) <= self.half_turn:
                act[k] = MOVE_FORWARD
            else:
                act[k] = TURN_LEFT if ang > 0 else TURN_RIGHT
        return act, np.zeros((len(rows), ELI_DIM), np.float32)
