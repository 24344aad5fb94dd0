"""The batched simulator: N worlds stepped by one call into compiled kernels.

The simulator knows nothing of agents, turns or rewards: it moves bodies, renders RGB-D,
keeps each world's ego map and answers geodesic queries. A single environment is this
core with N = 1.

Per world it holds: the scene index, the agent's pose, the episode's goal and its
geodesic distance field (computed once per episode), the allocentric map built from
depth, and the path length travelled since the episode began.

Sensors:
* RGB (H, W, 3) uint8 and depth (H, W, 1) float32: 90 degree horizontal field of view,
  camera 1.25 m above the floor, square images of any size. Depth is *planar* (distance
  along the optical axis, as in Habitat) in metres, clipped to [0, 10] and divided by 10.
* GPS+compass: the pose plus optional zero-mean Gaussian noise, drawn fresh at every
  step (``pose_noise=(sigma_position_m, sigma_heading_rad)``).
* Ego map (docs/spec.md section 2): every depth image, sub-sampled with stride
  ``max(1, R // 32)`` pixels, is back-projected with the camera intrinsics and the *noisy*
  pose into an allocentric grid of 0.25 m cells. Points between 0.1 m and the agent's height (1.5 m) mark obstacles
  (obstacles are sticky: the highest point wins), points below 0.1 m mark explored
  floor, and points above 1.5 m (ceiling, lintels) are dropped. The planner's view is a
  crop of ``ego_size`` x ``ego_size`` cells of 0.5 m around the agent, rotated so that
  row 0 is straight ahead: channel 0 obstacles, channel 1 explored free space, channels
  2-5 the obstacles of each cell's four 0.25 m quarters (the map at twice the resolution).
"""

from __future__ import annotations

import math

import numpy as np

from . import kernels as K
from .kernels import wrap_angle
from .bank import SceneBank
from .episodes import Episode, Geodesics
from .scene import AGENT_HEIGHT, CEILING_HEIGHT

STOP, MOVE_FORWARD, TURN_LEFT, TURN_RIGHT = 0, 1, 2, 3
ACTION_NAMES = ("STOP", "MOVE_FORWARD", "TURN_LEFT", "TURN_RIGHT")
NUM_ACTIONS = len(ACTION_NAMES)


MIN_RESOLUTION, MAX_RESOLUTION = 8, 1024  # px: the image sizes the renderer takes
RESOLUTION_RULE = f"must be an integer in [{MIN_RESOLUTION}, {MAX_RESOLUTION}]"
POSE_NOISE_RULE = "must be two finite non-negative numbers (position std m, heading std rad)"


def check_resolution(resolution) -> int:
    """``resolution`` as an int; ValueError unless it follows RESOLUTION_RULE."""
    if not isinstance(resolution, (int, np.integer)) or not MIN_RESOLUTION <= resolution <= MAX_RESOLUTION:
        raise ValueError(f"resolution {RESOLUTION_RULE}, got {resolution!r}")
    return int(resolution)


def check_pose_noise(pose_noise) -> tuple[float, float]:
    """``pose_noise`` as (position std, heading std); ValueError unless it follows POSE_NOISE_RULE."""
    try:
        pn = tuple(float(v) for v in pose_noise)
    except (TypeError, ValueError):
        pn = ()
    if len(pn) != 2 or not all(math.isfinite(v) and v >= 0 for v in pn):
        raise ValueError(f"pose_noise {POSE_NOISE_RULE}, got {pose_noise!r}")
    return pn


class BatchedSim:
    """N worlds over one :class:`SceneBank`.

    Args:
        bank: the scenes the worlds live in.
        num_worlds: N.
        resolution: square image size in pixels (8 to 1024).
        pose_noise: (position std in m, heading std in rad) of the GPS+compass noise.
        egomap: keep ego maps (off for the flat baselines, which never read them).
        seed: seeds the pose noise.
    """

    hfov = math.pi / 2
    camera_height = 1.25
    max_depth = 10.0
    forward_step = 0.25
    turn_angle = math.radians(10.0)
    ego_size = 32
    ego_cell = 0.5
    ego_channels = 6  # obstacles, explored floor, the obstacles of each cell's four quarters
    amap_cell = 0.25
    amap_size = 288  # 72 m around the episode start: covers any walk in a 30 m house

    def __init__(self, bank: SceneBank, num_worlds: int, resolution: int = 128,
                 pose_noise: tuple[float, float] = (0.0, 0.0), egomap: bool = True, seed: int = 0):
        if not isinstance(num_worlds, (int, np.integer)) or num_worlds < 1:
            raise ValueError(f"num_worlds must be a positive integer, got {num_worlds!r}")
        pn = check_pose_noise(pose_noise)
        self.bank = bank
        self.n = int(num_worlds)
        self.resolution = check_resolution(resolution)
        self.pose_noise = pn
        self.use_egomap = bool(egomap)
        self.rng = np.random.default_rng(seed)
        n, R = self.n, self.resolution
        self.scene_idx = np.zeros(n, np.int64)
        self.pos = np.zeros((n, 2), np.float64)
        self.heading = np.zeros(n, np.float64)
        self.goal = np.zeros((n, 2), np.float64)
        self.fields = np.full((n, bank.max_cells), K.INF, np.float32)
        self.episodes: list[Episode | None] = [None] * n
        self.path_length = np.zeros(n, np.float64)
        self.collided = np.zeros(n, np.bool_)
        self.distance_to_goal = np.zeros(n, np.float64)
        self.est_pose = np.zeros((n, 3), np.float64)
        self.rgb = np.zeros((n, R, R, 3), np.uint8)
        self.depth = np.zeros((n, R, R, 1), np.float32)
        self.amap = np.zeros((n, self.amap_size, self.amap_size) if egomap else (n, 1, 1), np.uint8)
        self.amap_origin = np.zeros((n, 2), np.float64)
        self.geo = Geodesics(bank)
        self._stride = max(1, R // 32)
        self._all = np.ones(n, np.bool_)

    # ---------------------------------------------------------------- episodes
    def reset_world(self, i: int, episode: Episode, field: np.ndarray | None = None) -> None:
        """Start ``episode`` in world ``i``; ``field`` is its goal field if already known."""
        try:
            s = self.bank.scene_ids.index(episode.scene_id)
        except ValueError:
            raise ValueError(f"episode {episode.episode_id}: scene {episode.scene_id!r} is not loaded") from None
        grid = self.bank.grids[s]
        start = np.asarray(episode.start_position, np.float64)
        goal = np.asarray(episode.goal_position, np.float64)
        if not grid.is_navigable(start):
            raise ValueError(f"episode {episode.episode_id} in {episode.scene_id}: start {start.tolist()} "
                             "is not navigable")
        self.scene_idx[i] = s
        self.pos[i] = start
        self.heading[i] = wrap_angle(episode.start_heading)
        self.goal[i] = goal
        h, w = self.bank.h[s], self.bank.w[s]
        if field is None:
            self.geo.field(s, goal, out=self.fields[i])
        else:
            self.fields[i, : h * w] = field
        self.episodes[i] = episode
        self.path_length[i] = 0.0
        self.collided[i] = False
        d = self.geo.lookup(s, self.fields[i], start)
        if not math.isfinite(d):
            raise ValueError(f"episode {episode.episode_id} in {episode.scene_id}: goal unreachable from start")
        self.distance_to_goal[i] = d
        self.shorten_to_straight_line(self.goal, np.array([i]), self.distance_to_goal)
        if self.use_egomap:
            self.amap[i] = 0
            self.amap_origin[i] = start - self.amap_size * self.amap_cell / 2
        mask = np.zeros(self.n, np.bool_)
        mask[i] = True
        self._sense(mask)

    # ---------------------------------------------------------------- stepping
    def step(self, actions: np.ndarray, active: np.ndarray | None = None) -> np.ndarray:
        """Apply one action per world (STOP moves nothing) and sense. Returns ``collided``.

        ``active`` (bool, N) limits the step to some worlds; the others are untouched.
        """
        actions = np.asarray(actions, np.int64)
        if actions.shape != (self.n,):
            raise ValueError(f"expected {self.n} actions, got shape {actions.shape}")
        if ((actions < 0) | (actions > 3)).any():
            raise ValueError(f"actions must be in 0..3, got {actions.tolist()}")
        active = self._all if active is None else np.asarray(active, np.bool_)
        acts = np.where(active, actions, STOP)
        old = self.pos.copy()
        old_heading = self.heading.copy()
        b = self.bank
        K.move(b.nav, b.off, b.h, b.w, b.ox, b.oy, b.cell_size, self.scene_idx, self.pos, self.heading, acts,
               self.forward_step, self.turn_angle, self.collided)
        self.collided &= active
        self.path_length += np.hypot(*(self.pos - old).T)
        # The image is a function of the pose alone: a world that did not move (STOP, a
        # move blocked at once) keeps its image, and only its GPS+compass reading and ego
        # map are refreshed.
        moved = active & ((self.pos != old).any(axis=1) | (self.heading != old_heading))
        self._sense(active, moved)
        return self.collided

    def _sense(self, active: np.ndarray, render: np.ndarray | None = None) -> None:
        """Read the sensors of the ``active`` worlds; images are rendered where ``render``
        (default: ``active``) is set and kept from the last step elsewhere."""
        b = self.bank
        K.pick(K.render, self.n)(b.kind, b.off, b.h, b.w, b.ox, b.oy, b.cell_size, b.klo, b.khi, b.kmat, b.kroom,
                                 b.room_wall_rgb, b.room_floor_rgb, b.mat_rgb, self.scene_idx, self.pos, self.heading,
                                 self.camera_height, CEILING_HEIGHT, self.hfov, self.max_depth, self.rgb, self.depth,
                                 active if render is None else render)
        sp, sh = self.pose_noise
        est = np.concatenate([self.pos, self.heading[:, None]], axis=1)
        if sp > 0 or sh > 0:
            noise = self.rng.normal(size=(self.n, 3)) * np.array([sp, sp, sh])
            est = est + noise
            est[:, 2] = wrap_angle(est[:, 2])
        self.est_pose[active] = est[active]
        if self.use_egomap:
            K.pick(K.egomap_update, self.n)(self.depth, self.est_pose, self.amap_origin, self.amap, self.amap_cell,
                                            self._stride, self.hfov, self.max_depth, self.camera_height, 0.1,
                                            AGENT_HEIGHT, active)
        d = np.empty(self.n)
        K.field_lookup_batch(b.nav, b.off, b.h, b.w, b.ox, b.oy, b.cell_size, self.scene_idx, self.fields, self.pos, d)
        self.distance_to_goal[active] = d[active]
        self.shorten_to_straight_line(self.goal, np.nonzero(active)[0], self.distance_to_goal)

    def shorten_to_straight_line(self, targets: np.ndarray, rows: np.ndarray, dist: np.ndarray) -> None:
        """Lower ``dist[rows]`` (grid geodesics to ``targets``) to the straight-line distance
        where the agent could walk straight there: the spec's geodesic is the shortest path
        through free space, which the grid overestimates (``kernels.straight_shortcut``, the
        one test of this rule)."""
        b = self.bank
        K.straight_shortcut(b.nav, b.off, b.h, b.w, b.ox, b.oy, b.cell_size, self.scene_idx, self.pos,
                            np.asarray(targets, np.float64).reshape(self.n, 2), np.asarray(rows, np.int64), dist)

    # ---------------------------------------------------------------- queries
    def egomap(self, rows: np.ndarray | None = None, out: np.ndarray | None = None) -> np.ndarray:
        """Planner ego maps (len(rows), 6, 32, 32) float32 in [0, 1] from the noisy pose
        (channels: :func:`~.kernels.egomap_crop`). With ``out`` (N, 6, 32, 32) float32, world
        ``r``'s map goes into ``out[r]`` instead (the other rows are left as they are), and
        ``out`` is returned."""
        if not self.use_egomap:
            raise RuntimeError("this simulator was built with egomap=False")
        rows = np.arange(self.n) if rows is None else np.asarray(rows, np.int64).reshape(-1)
        shape = (self.ego_channels, self.ego_size, self.ego_size)
        if out is None:
            out = np.empty((len(rows),) + shape, np.float32)
            slots = np.arange(len(rows))
        elif out.shape != (self.n,) + shape or out.dtype != np.float32:
            raise ValueError(f"out must be float32 of shape {(self.n,) + shape}, got {out.dtype} {out.shape}")
        else:
            slots = rows
        K.pick(K.egomap_crop, len(rows))(self.amap, self.amap_origin, self.amap_cell, self.est_pose, self.ego_cell,
                                         out, rows, slots)
        return out

    def polar_to(self, targets: np.ndarray, rows: np.ndarray | None = None, noisy: bool = True) -> np.ndarray:
        """(distance m, direction rad) from each world's (noisy) pose to world-frame targets."""
        rows = np.arange(self.n) if rows is None else np.asarray(rows, np.int64).reshape(-1)
        pose = self.est_pose[rows] if noisy else np.concatenate([self.pos[rows], self.heading[rows, None]], 1)
        d = np.asarray(targets, np.float64).reshape(-1, 2) - pose[:, :2]
        dist = np.hypot(d[:, 0], d[:, 1])
        out = np.empty((len(rows), 2), np.float32)
        out[:, 0] = dist
        out[:, 1] = wrap_angle(np.arctan2(d[:, 1], d[:, 0]) - pose[:, 2])
        return out

    def distance_to(self, targets: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """Geodesic distance from the agent of each world ``r`` in ``rows`` to the point
        ``targets[r]`` (a sub-goal): the grid's (the values of :meth:`geodesic`, A*), from the
        scene's corner graph (:mod:`.corners`) in 10-20 microseconds a world on one thread,
        lowered to the straight line where the agent could walk straight there, as
        :attr:`distance_to_goal` is. Returns (N,) with the entries of ``rows`` filled (``inf``
        if unreachable)."""
        rows = np.asarray(rows, np.int64).reshape(-1)
        out = np.full(self.n, np.inf)
        self.bank.corners.distances(self.scene_idx, self.pos, np.asarray(targets, np.float64).reshape(self.n, 2),
                                    rows, out)
        out[out >= K.INF] = np.inf
        self.shorten_to_straight_line(targets, rows, out)
        return out

    def prepare_geodesics(self, scenes=None) -> None:
        """Build the corner graphs of ``scenes`` (default: every scene of the bank) now
        instead of at each scene's first :meth:`distance_to` (about 4 ms per procedural
        house)."""
        self.bank.corners.prepare(np.arange(len(self.bank)) if scenes is None else scenes)

    def geodesic(self, i: int, a: np.ndarray, b: np.ndarray) -> float:
        """Geodesic distance between two points in world ``i``'s scene (``inf`` if not
        connected): A* over the grid, or the straight line where an agent could walk it."""
        bank = self.bank
        dist = np.array([self.geo.distance(int(self.scene_idx[i]), a, b)])
        # the straight-line rule of shorten_to_straight_line, for this one pair of points
        K.straight_shortcut(bank.nav, bank.off, bank.h, bank.w, bank.ox, bank.oy, bank.cell_size,
                            self.scene_idx[i:i + 1], np.asarray(a, np.float64).reshape(1, 2),
                            np.asarray(b, np.float64).reshape(1, 2), np.zeros(1, np.int64), dist)
        return float(dist[0])

    def snap_to_navigable(self, points: np.ndarray, rows: np.ndarray, max_radius: float = 8.0) -> np.ndarray:
        """For each world in ``rows``, the nearest point to ``points[r]`` that its agent can
        reach (a navigable cell centre of the agent's component, or the point itself if it
        is one); the agent's position if none lies within ``max_radius``. Returns (N, 2)
        with the rows filled."""
        b = self.bank
        out = np.zeros((self.n, 2))
        rows = np.asarray(rows, np.int64).reshape(-1)
        K.pick(K.snap_batch, len(rows))(b.nav, b.comp, b.off, b.h, b.w, b.ox, b.oy, b.cell_size, self.scene_idx,
                                        self.pos, np.asarray(points, np.float64).reshape(self.n, 2), rows,
                                        float(max_radius), out)
        return out

    def memory_per_world(self) -> int:
        """Bytes of per-world state (images, ego map, goal field, pose)."""
        per = (self.rgb.nbytes + self.depth.nbytes + self.amap.nbytes + self.fields.nbytes) / self.n
        return int(per + 8 * 16)
