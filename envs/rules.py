"""The one implementation of PLEX's turn order, rewards, episode ends and metrics.

:class:`PlexWorlds` applies docs/spec.md section 3 to N worlds of a :class:`BatchedSim`; the
AEC environment (``plex_nav_v0``) is these rules with N = 1 (stepped by
:meth:`PlexWorlds.step_one`, the executor's turns on Python numbers) and the vector env is
these rules with autoreset. :class:`PointNavWorlds` applies docs/spec.md section 4 (one flat
agent) and shares the episode handling, the goal-progress reward and the metrics.

Turn order (per world): after a reset the planner acts. A planner action either stops
the episode (both agents terminate; +``success_reward`` to the planner on success) or
sets a sub-goal, fixed in the world and snapped to the nearest point the agent can
reach. The executor then acts until it chooses STOP or has acted ``n_ex`` times, and the
turn returns to the planner. The episode truncates after ``max_steps`` executor actions.

Rewards written on every executor step:

==========  ==========================================================================
executor    geodesic progress towards the sub-goal + slack + collision
            (+ ``executor_collision_reward`` on a blocked move, + ``subgoal_reward``
            when it chooses STOP within ``subgoal_radius`` of a sub-goal that was
            farther than that when it was set, + ``executor_stop_penalty`` for a
            STOP outside it)
planner     geodesic progress towards the end goal + slack + collision
==========  ==========================================================================
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import NamedTuple

import numpy as np

from .actions import InvalidAction, discrete, real
from .sim import BatchedSim, Episode, Geodesics, SceneBank, generate_episodes, scene_bank
from .sim.scene import SceneGrid
from .sim.core import (ACTION_NAMES, NUM_ACTIONS, POSE_NOISE_RULE, RESOLUTION_RULE, STOP, check_pose_noise,
                        check_resolution)
from .sim.episodes import MAX_GEODESIC, EpisodeFileError, default_episode_file, load_episodes, sample_episode

PLANNER, EXECUTOR = 0, 1
ELI_DIM = 128
# The keys of every info dict (:meth:`_Worlds.info`), in order.
INFO_KEYS = ("scene_index", "episode_id", "geodesic_distance", "distance_to_goal", "collisions", "steps",
             "success", "spl")


@dataclass
class NavConfig:
    """Settings shared by the PLEX and the flat PointNav environments (each field's comment is
    its help text, and trainers expose every field as a command-line flag)."""

    resolution: int = 128  # square RGB-D image size in pixels
    max_steps: int = 500  # agent (executor) actions per episode before it truncates
    scenes: str = "procgen"  # scene source: procgen, r2v, open-room, procgen+r2v, or a directory of floor plans
    split: str = "train"  # scene split: train, val or test
    num_scenes: int | None = None  # scenes in the split (None: the source's default, 72 for procgen train)
    episodes_file: str | None = None  # fixed episodes to cycle through (None: the shipped file of procgen val/test, else sampled)
    pose_noise: tuple[float, float] = (0.0, 0.0)  # GPS+compass noise std: metres, radians
    slack_reward: float = -0.01  # reward added on every agent action
    collision_reward: float = -0.01  # reward added when a move is blocked
    success_reward: float = 10.0  # reward added when the episode ends by a successful stop
    success_distance: float = 0.2  # geodesic distance (m) to the goal under which a stop succeeds

    def validate(self) -> None:
        def bad(name, why):
            raise ValueError(f"config {name}={getattr(self, name)!r}: {why}")

        for name, check, rule in (("resolution", check_resolution, RESOLUTION_RULE),
                                  ("pose_noise", check_pose_noise, POSE_NOISE_RULE)):
            try:
                check(getattr(self, name))  # the simulator's rule, reported as this config's field
            except ValueError:
                bad(name, rule)
        if not isinstance(self.max_steps, (int, np.integer)) or self.max_steps < 1:
            bad("max_steps", "must be a positive integer")
        if self.split not in ("train", "val", "test"):
            bad("split", "must be 'train', 'val' or 'test'")
        if not isinstance(self.scenes, str) or not self.scenes:
            bad("scenes", "must be a source name or a directory")
        if self.num_scenes is not None and (not isinstance(self.num_scenes, (int, np.integer)) or self.num_scenes < 1):
            bad("num_scenes", "must be a positive integer or None")
        for name in ("slack_reward", "collision_reward", "success_reward"):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not math.isfinite(v):
                bad(name, "must be a finite number")
        if not (isinstance(self.success_distance, (int, float)) and 0 < self.success_distance < 5):
            bad("success_distance", "must be in (0, 5) metres")


@dataclass
class PlexConfig(NavConfig):
    """Settings of the PLEX two-agent environment (``plex_nav_v0``); the fields below NavConfig's
    do not apply to the flat PointNav environment."""

    n_ex: int = 10  # executor actions per planner decision at most (N_EX)
    rho_max: float = 4.0  # largest sub-goal distance (m)
    eli: bool = True  # pass the executor's ELI to the planner (--no-eli: zeros, the paper's ablation)
    subgoal_reward: float = 1.0  # executor reward for a STOP within subgoal_radius of its sub-goal
    subgoal_radius: float = 0.5  # distance (m) to its sub-goal within which the executor's STOP earns subgoal_reward
    executor_stop_penalty: float = 0.0  # executor reward for a STOP farther than subgoal_radius from its sub-goal (<= 0)
    executor_collision_reward: float = 0.0  # executor reward added on a blocked move, beside collision_reward (<= 0)

    def validate(self) -> None:
        super().validate()
        if not isinstance(self.n_ex, (int, np.integer)) or self.n_ex < 1:
            raise ValueError(f"config n_ex={self.n_ex!r}: must be a positive integer")
        if not (isinstance(self.rho_max, (int, float)) and 0 < self.rho_max <= 20):
            raise ValueError(f"config rho_max={self.rho_max!r}: must be in (0, 20] metres")
        if not isinstance(self.eli, (bool, np.bool_)):
            raise ValueError(f"config eli={self.eli!r}: must be True or False")
        if not (isinstance(self.subgoal_radius, (int, float)) and 0 < self.subgoal_radius < 5):
            raise ValueError(f"config subgoal_radius={self.subgoal_radius!r}: must be in (0, 5) metres")
        if not (isinstance(self.executor_stop_penalty, (int, float)) and -100 <= self.executor_stop_penalty <= 0):
            raise ValueError(f"config executor_stop_penalty={self.executor_stop_penalty!r}: must be in [-100, 0]")
        if not (isinstance(self.executor_collision_reward, (int, float)) and -100 <= self.executor_collision_reward <= 0):
            raise ValueError(f"config executor_collision_reward={self.executor_collision_reward!r}: must be in [-100, 0]")


def make_config(cls, kwargs: dict):
    """Build and validate a config from keyword arguments, naming unknown keys."""
    known = {f.name for f in fields(cls) if f.init}
    unknown = sorted(set(kwargs) - known)
    if unknown:
        raise TypeError(f"unknown config key(s) {unknown}; known: {sorted(known)}")
    cfg = cls(**kwargs)
    if isinstance(cfg.pose_noise, list):
        cfg.pose_noise = tuple(cfg.pose_noise)
    cfg.validate()
    return cfg


def progress_reward(d_prev, d_new, collided, cfg: NavConfig):
    """Geodesic progress + slack + collision penalty: the goal-side reward of every action (on
    arrays, or on Python numbers for one world, with the same float64 arithmetic)."""
    return (d_prev - d_new) + cfg.slack_reward + cfg.collision_reward * collided


def executor_reward(d_prev, d_new, d_set, collided, stopped, cfg: PlexConfig):
    """The executor's reward for one action and whether its STOP reached the sub-goal, from its
    geodesic distance to the sub-goal before and after the action and when the sub-goal was
    set (``d_set``); on arrays or on Python numbers, as :func:`progress_reward`."""
    r = progress_reward(d_prev, d_new, collided, cfg)
    # Only a sub-goal that was out of reach when it was set can be reached: a sub-goal set
    # within the radius would pay the bonus for a STOP on the spot.
    reached = stopped & (d_new < cfg.subgoal_radius) & (d_set >= cfg.subgoal_radius)
    r += cfg.subgoal_reward * reached
    if cfg.executor_stop_penalty:  # the two optional terms, 0 by default
        r += cfg.executor_stop_penalty * (stopped & (d_new >= cfg.subgoal_radius))
    if cfg.executor_collision_reward:
        r += cfg.executor_collision_reward * collided
    return r, reached


class OneWorldEnv:
    """The episode and scene properties of an env over one world (``plex_nav_v0``,
    ``plex_ma/PointNav-v0``); the env sets ``self.worlds``."""

    worlds: "_Worlds"

    @property
    def scene_id(self) -> str:
        """The string id of the current episode's scene (an info's ``scene_index`` indexes
        :attr:`scene_ids`)."""
        if self.worlds.sim.episodes[0] is None:
            raise RuntimeError("no episode yet; call reset() first")
        return self.worlds.scene_id(0)

    @property
    def scene_ids(self) -> list[str]:
        """The scenes of this env's split, in ``scene_index`` order."""
        return list(self.worlds.bank.scene_ids)

    @property
    def episode(self):
        """The current :class:`~plex_ma.envs.sim.Episode` (start, goal, ids), or None before ``reset``."""
        return self.worlds.sim.episodes[0]


def worlds_data(cfg: NavConfig) -> tuple[SceneBank, list[Episode] | None]:
    """The scene bank of a config and its fixed episodes (None: sampled). Raises SceneError or
    EpisodeFileError naming the bad scene source or episode file."""
    bank = scene_bank(cfg.scenes, cfg.split, cfg.num_scenes)
    path = cfg.episodes_file
    if path is None and cfg.split != "train":
        path = _default_episode_file(cfg.scenes, cfg.split)
    if path is None:
        return bank, None
    known = set(bank.scene_ids)
    eps = [e for e in load_episodes(path) if e.scene_id in known]
    if not eps:
        raise EpisodeFileError(f"episode file {path}: none of its scenes belong to {cfg.scenes}/{cfg.split}")
    return bank, eps


@dataclass(frozen=True)
class WorldView:
    """One world's state as a recorder or viewer draws it, copied out of the simulator.

    Positions are world-frame metres, angles radians; ``goal_polar`` and
    ``subgoal_raw_polar`` are (distance, direction) from the agent's noisy pose, as its
    sensors give them. The sub-goal fields are None in flat worlds."""

    episode: Episode
    grid: SceneGrid  # the scene's grid (its top-down map)
    position: np.ndarray  # (2,) the true position
    heading: float
    distance_to_goal: float  # geodesic
    collisions: int
    goal_polar: np.ndarray
    resolution: int  # of the images
    rgb: np.ndarray | None  # (H, W, 3) uint8; None when not asked for
    depth: np.ndarray | None  # (H, W, 1) float32
    turn: int | None = None  # PLEX: whose action the world needs next (PLANNER or EXECUTOR)
    subgoal: np.ndarray | None = None  # (2,) PLEX: the sub-goal, snapped to navigable space
    subgoal_raw: np.ndarray | None = None  # (2,) ... as the planner proposed it
    subgoal_raw_polar: np.ndarray | None = None


class _Worlds:
    """Episodes, metrics and infos of N worlds; subclasses add the agents' rules."""

    def __init__(self, cfg: NavConfig, num_worlds: int, seed: int | None, egomap: bool):
        self.cfg = cfg
        self.n = int(num_worlds)
        self.bank, self.fixed_episodes = worlds_data(cfg)
        self.sim = BatchedSim(self.bank, self.n, resolution=cfg.resolution, pose_noise=cfg.pose_noise, egomap=egomap)
        self.geo = Geodesics(self.bank)
        self._next_fixed = 0
        # sampled episodes' largest start-goal geodesic distance (m); a training curriculum lowers it
        self.max_geodesic = MAX_GEODESIC
        self.steps = np.zeros(self.n, np.int64)
        self.collisions = np.zeros(self.n, np.int64)
        self.done = np.ones(self.n, np.bool_)
        self.success = np.zeros(self.n, np.float32)
        self.spl = np.zeros(self.n, np.float32)
        self.seed(seed)

    def seed(self, seed: int | None) -> None:
        ss = np.random.SeedSequence(seed)
        self.rngs = [np.random.default_rng(s) for s in ss.spawn(self.n)]
        self.sim.rng = np.random.default_rng(ss.spawn(1)[0])
        self._next_fixed = 0

    def _new_episode(self, i: int) -> tuple[Episode, np.ndarray | None]:
        if self.fixed_episodes is not None:
            ep = self.fixed_episodes[self._next_fixed % len(self.fixed_episodes)]
            self._next_fixed += 1
            return ep, None
        rng = self.rngs[i]
        return sample_episode(self.bank, int(rng.integers(len(self.bank))), rng, self.geo,
                              max_geodesic=self.max_geodesic)

    def reset_rows(self, rows, episodes: list[Episode] | None = None) -> None:
        """Start new episodes in ``rows`` (given ones, or the next sampled/fixed ones)."""
        rows = np.asarray(rows, np.int64).reshape(-1)
        for k, i in enumerate(rows):
            ep, fld = (episodes[k], None) if episodes is not None else self._new_episode(int(i))
            self.sim.reset_world(int(i), ep, fld)
        self.steps[rows] = 0
        self.collisions[rows] = 0
        self.done[rows] = False
        self.success[rows] = 0.0
        self.spl[rows] = 0.0

    def _finish(self, rows: np.ndarray, success: np.ndarray) -> None:
        """Close the episodes of ``rows``; ``success`` (bool per row) decides S in SPL."""
        self.done[rows] = True
        self.success[rows] = success.astype(np.float32)
        l = np.array([self.sim.episodes[i].geodesic_distance for i in rows])
        p = self.sim.path_length[rows]
        self.spl[rows] = (success * l / np.maximum(np.maximum(l, p), 1e-9)).astype(np.float32)

    def info(self, i: int) -> dict:
        """The info dict of world ``i``: the keys of :data:`INFO_KEYS`, every value a Python
        number, the same keys from the reset to the end. ``success`` and ``spl`` read 0.0
        until the episode has ended; ``scene_index`` indexes ``bank.scene_ids`` (the scene's
        string id is :meth:`scene_id`)."""
        ep = self.sim.episodes[i]
        return {
            "scene_index": int(self.sim.scene_idx[i]),
            "episode_id": int(ep.episode_id),
            "geodesic_distance": float(ep.geodesic_distance),
            "distance_to_goal": float(self.sim.distance_to_goal[i]),
            "collisions": int(self.collisions[i]),
            "steps": int(self.steps[i]),
            "success": float(self.success[i]),  # 0.0 from the reset until _finish
            "spl": float(self.spl[i]),
        }

    def scene_id(self, i: int) -> str:
        """The string id of world ``i``'s current scene (``bank.scene_ids[info["scene_index"]]``)."""
        return self.sim.episodes[i].scene_id

    def goal_vector(self, rows) -> np.ndarray:
        return self.sim.polar_to(self.sim.goal[rows], rows)

    def pose(self, rows) -> np.ndarray:
        """(len(rows), 3) float64: the true x, y (m) and heading (rad) of the agents in ``rows``."""
        rows = np.asarray(rows, np.int64).reshape(-1)
        return np.concatenate([self.sim.pos[rows], self.sim.heading[rows, None]], axis=1)

    def view(self, i: int, images: bool = True) -> WorldView:
        """World ``i``'s :class:`WorldView` (its images only with ``images``)."""
        sim, row = self.sim, np.array([i])
        return WorldView(
            episode=sim.episodes[i], grid=self.bank.grids[int(sim.scene_idx[i])], position=sim.pos[i].copy(),
            heading=float(sim.heading[i]), distance_to_goal=float(sim.distance_to_goal[i]),
            collisions=int(self.collisions[i]), goal_polar=sim.polar_to(sim.goal[row], row)[0],
            resolution=sim.resolution, rgb=sim.rgb[i].copy() if images else None,
            depth=sim.depth[i].copy() if images else None, **self._agent_view(i))

    def _agent_view(self, i: int) -> dict:
        return {}

    def generate_episodes(self, n: int, seed: int) -> list[Episode]:
        """``n`` episodes over this split's scenes, the same for the same seed (what
        evaluation runs where a split has no episode file)."""
        return generate_episodes(self.bank, n, seed)


@dataclass
class PlexStep:
    """What one batched step did, per world (arrays of length N)."""

    rewards: np.ndarray  # (N, 2) float32: [planner, executor] earned this step
    acted: np.ndarray  # (N,) int8: who acted this step (PLANNER / EXECUTOR, -1: nothing)
    executor_turn_end: np.ndarray  # (N,) bool: the executor's turn ended (STOP, n_ex or episode end)
    executor_stopped: np.ndarray  # (N,) bool: ... because it chose STOP
    executor_reached: np.ndarray  # (N,) bool: ... with a STOP within subgoal_radius of a sub-goal set farther (its success)
    terminated: np.ndarray  # (N,) bool: episode ended by a planner stop
    truncated: np.ndarray  # (N,) bool: episode ended by max_steps


class OneStep(NamedTuple):
    """What :meth:`PlexWorlds.step_one` did: a :class:`PlexStep`'s one row as Python numbers
    (the rewards the float32 values that PlexStep holds)."""

    planner_reward: float
    executor_reward: float
    acted: int
    executor_turn_end: bool
    executor_stopped: bool
    executor_reached: bool
    terminated: bool
    truncated: bool

    @classmethod
    def of(cls, out: PlexStep) -> OneStep:
        """Row 0 of ``out``."""
        return cls(float(out.rewards[0, PLANNER]), float(out.rewards[0, EXECUTOR]), int(out.acted[0]),
                   bool(out.executor_turn_end[0]), bool(out.executor_stopped[0]), bool(out.executor_reached[0]),
                   bool(out.terminated[0]), bool(out.truncated[0]))


class PlexWorlds(_Worlds):
    """PLEX's rules over N worlds (see the module docstring)."""

    def __init__(self, cfg: PlexConfig, num_worlds: int = 1, seed: int | None = None):
        super().__init__(cfg, num_worlds, seed, egomap=True)
        n = self.n
        self.turn = np.zeros(n, np.int8)
        self.turn_steps = np.zeros(n, np.int64)
        self.subgoal = np.zeros((n, 2), np.float64)  # snapped, fixed in the world
        self.subgoal_raw = np.zeros((n, 2), np.float64)  # as proposed, before snapping
        self.subgoal_dist = np.zeros(n, np.float64)  # geodesic distance agent -> sub-goal
        self.subgoal_dist0 = np.zeros(n, np.float64)  # ... when the sub-goal was set
        self.eli = np.zeros((n, ELI_DIM), np.float32)  # last ELI the executor sent
        self.planner_decisions = np.zeros(n, np.int64)
        self._row0 = np.zeros(1, np.int64)  # the rows of step_one's world
        self._action0 = np.zeros(1, np.int64)  # step_one's executor action, for the simulator

    def _agent_view(self, i: int) -> dict:
        row = np.array([i])
        return {"turn": int(self.turn[i]), "subgoal": self.subgoal[i].copy(), "subgoal_raw": self.subgoal_raw[i].copy(),
                "subgoal_raw_polar": self.sim.polar_to(self.subgoal_raw[row], row)[0]}

    def reset_rows(self, rows, episodes=None) -> None:
        super().reset_rows(rows, episodes)
        rows = np.asarray(rows, np.int64).reshape(-1)
        self.turn[rows] = PLANNER
        self.turn_steps[rows] = 0
        self.eli[rows] = 0.0
        self.subgoal[rows] = self.sim.pos[rows]
        self.subgoal_raw[rows] = self.sim.pos[rows]
        self.subgoal_dist[rows] = 0.0
        self.subgoal_dist0[rows] = 0.0
        self.planner_decisions[rows] = 0

    # ------------------------------------------------------------------ observations
    def planner_obs(self, rows, out: dict | None = None) -> dict:
        """The planner's observations in the worlds ``rows``, arrays of len(rows); with ``out``
        (the same keys, arrays of N), written into its rows ``rows`` instead (the other rows
        are left as they are) and ``out`` returned."""
        rows = np.asarray(rows, np.int64).reshape(-1)
        if out is None:
            return {
                "ego_map": self.sim.egomap(rows),
                "goal": self.goal_vector(rows),
                "eli": self.eli[rows] if self.cfg.eli else np.zeros((len(rows), ELI_DIM), np.float32),  # a copy
            }
        self.sim.egomap(rows, out=out["ego_map"])
        out["goal"][rows] = self.goal_vector(rows)
        out["eli"][rows] = self.eli[rows] if self.cfg.eli else 0.0
        return out

    def executor_obs(self, rows) -> dict:
        rows = np.asarray(rows, np.int64).reshape(-1)
        return {
            "rgb": self.sim.rgb[rows],  # indexing by an array copies
            "depth": self.sim.depth[rows],
            "subgoal": self.sim.polar_to(self.subgoal[rows], rows),
        }

    # ------------------------------------------------------------------ validation
    def check_planner_action(self, stop, subgoal, who: str = "planner") -> tuple[np.ndarray, np.ndarray]:
        """Validate batched planner actions: stop (B,) in {0,1}, subgoal (B,2) finite in range."""
        b = np.size(stop)
        stop = discrete(stop, 2, f"{who}: action 'stop'", (b,))
        sg = real(subgoal, f"{who}: action 'subgoal'", (b, 2))
        rho, th = sg[:, 0], sg[:, 1]
        if np.any(rho < 0) or np.any(rho > self.cfg.rho_max):
            raise InvalidAction(f"{who}: action 'subgoal' distance must be in [0, {self.cfg.rho_max}], "
                                f"got {rho.tolist()}")
        if np.any(np.abs(th) > np.pi + 1e-6):
            raise InvalidAction(f"{who}: action 'subgoal' direction must be in [-pi, pi], got {th.tolist()}")
        return stop, sg

    @staticmethod
    def check_executor_action(action, eli, who: str = "executor") -> tuple[np.ndarray, np.ndarray]:
        """Validate batched executor actions: action (B,) in 0..3, eli (B,128) finite."""
        b = np.size(action)
        a = discrete(action, NUM_ACTIONS, f"{who}: action 'action'", (b,), ACTION_NAMES)
        e = real(eli, f"{who}: action 'eli'", (b, ELI_DIM))
        return a, e

    # ------------------------------------------------------------------ stepping
    def step(self, stop=None, subgoal=None, action=None, eli=None) -> PlexStep:
        """One action for every world that is not done: the planner's (``stop``, ``subgoal``)
        where it is the planner's turn, the executor's (``action``, ``eli``) elsewhere.
        Arrays are full length N; entries for the other agent's worlds are ignored.
        Actions are validated before anything changes."""
        n = self.n
        live = ~self.done
        pl = np.nonzero(live & (self.turn == PLANNER))[0]
        ex = np.nonzero(live & (self.turn == EXECUTOR))[0]
        # A batched caller may move one agent only: worlds of the agent it gave no action
        # for wait. With one world (the AEC env) a missing action is an error.
        if n > 1 and stop is None and subgoal is None and action is not None:
            pl = pl[:0]
        if n > 1 and action is None and eli is None and stop is not None:
            ex = ex[:0]
        if len(pl):
            if stop is None or subgoal is None:
                raise InvalidAction("planner: it is the planner's turn; its action needs 'stop' and 'subgoal'")
            stop_a, sg = self.check_planner_action(_rows_of(stop, n, (), "planner", "stop")[pl],
                                                   _rows_of(subgoal, n, (2,), "planner", "subgoal")[pl])
        if len(ex):
            if action is None or eli is None:
                raise InvalidAction("executor: it is the executor's turn; its action needs 'action' and 'eli'")
            act_a, eli_a = self.check_executor_action(_rows_of(action, n, (), "executor", "action")[ex],
                                                      _rows_of(eli, n, (ELI_DIM,), "executor", "eli")[ex])
        out = self._new_step()
        new = self._planner_step(pl, stop_a, sg, out) if len(pl) else pl
        if len(ex):
            self._executor_step(ex, act_a, eli_a, out, new)
        elif len(new):
            self._measure_subgoals(new, ex)
        return out

    def _new_step(self) -> PlexStep:
        flags = np.zeros((5, self.n), np.bool_)  # one allocation for the five flag arrays
        return PlexStep(rewards=np.zeros((self.n, 2), np.float32), acted=np.full(self.n, -1, np.int8),
                        executor_turn_end=flags[0], executor_stopped=flags[1], executor_reached=flags[2],
                        terminated=flags[3], truncated=flags[4])

    def step_one(self, stop=None, subgoal=None, action=None, eli=None) -> OneStep:
        """:meth:`step` in a PlexWorlds of one world (the AEC env's), the action's parts given
        as that world's (a number and an array each, not rows of arrays), the result as
        Python numbers. Actions of the common types (a Python or numpy integer in range, a
        finite float32 or float64 array of the right shape) skip the batched selection and
        checks, and the executor's take a scalar path through the same rules, since numpy's
        cost per call on one-element arrays is most of a turn there; any other action goes
        through :meth:`step` as one row (its conversions, checks and messages)."""
        if self.n != 1:
            raise ValueError(f"step_one needs a PlexWorlds of one world, this one has {self.n}")
        if not self.done[0]:
            if self.turn[0] == EXECUTOR:
                a = _whole(action, NUM_ACTIONS)
                if a is not None and _float_vector(eli, ELI_DIM) and np.isfinite(eli).all():
                    return self._executor_step_one(a, eli)
            else:
                s = _whole(stop, 2)
                rho, th = subgoal.tolist() if _float_vector(subgoal, 2) else (math.nan, math.nan)
                if s is not None and 0 <= rho <= self.cfg.rho_max and abs(th) <= np.pi + 1e-6:
                    # check_planner_action's rules, in float64 (NaN and infinities fail them)
                    out = self._new_step()
                    new = self._planner_step(self._row0, np.array([s]), np.asarray(subgoal, np.float64)[None], out)
                    self._measure_subgoals(new, new[:0])
                    return OneStep.of(out)
        rows = (None if x is None else np.asarray(x)[None] for x in (stop, subgoal, action, eli))
        return OneStep.of(self.step(*rows))

    def _executor_step_one(self, action: int, eli: np.ndarray) -> OneStep:
        """:meth:`_executor_step` in world 0 of one, on Python numbers: the same float64
        arithmetic, the rewards rounded to float32 as PlexStep holds them (``0 + r``)."""
        cfg = self.cfg
        sim = self.sim
        d_goal_prev = float(sim.distance_to_goal[0])
        d_sub_prev = float(self.subgoal_dist[0])
        x, y = sim.pos[0].tolist()
        self._action0[0] = action
        collided = bool(sim.step(self._action0)[0])
        if sim.pos[0, 0] != x or sim.pos[0, 1] != y:  # only a move changes the distance to the sub-goal
            self._measure_subgoals(self._row0[:0], self._row0)
        stopped = action == STOP
        ex_r, reached = executor_reward(d_sub_prev, float(self.subgoal_dist[0]), float(self.subgoal_dist0[0]),
                                        collided, stopped, cfg)
        pl_r = progress_reward(d_goal_prev, float(sim.distance_to_goal[0]), collided, cfg)
        if cfg.eli:
            self.eli[0] = eli
        self.collisions[0] += collided
        self.steps[0] += 1
        self.turn_steps[0] += 1
        turn_end = stopped or self.turn_steps[0] >= cfg.n_ex
        trunc = bool(self.steps[0] >= cfg.max_steps)
        if turn_end:
            self.turn[0] = PLANNER
        if trunc:
            self._finish(self._row0, np.zeros(1, np.bool_))
        return OneStep(float(np.float32(0.0 + pl_r)), float(np.float32(0.0 + ex_r)), EXECUTOR,
                       bool(turn_end or trunc), stopped, bool(reached), False, trunc)

    def _planner_step(self, rows, stop, sg, out: PlexStep) -> np.ndarray:
        """Apply planner actions; returns the worlds that got a new sub-goal (their
        distance to it is measured along with the executors' moves: :meth:`_measure_subgoals`)."""
        cfg = self.cfg
        out.acted[rows] = PLANNER
        self.planner_decisions[rows] += 1
        ends = rows[stop == 1]
        if len(ends):
            success = self.sim.distance_to_goal[ends] < cfg.success_distance
            out.rewards[ends, PLANNER] += cfg.success_reward * success
            out.terminated[ends] = True
            self._finish(ends, success)
        go = stop == 0
        rows, sg = rows[go], sg[go]
        if len(rows):
            # The sub-goal is set relative to the agent's (noisy) pose and then fixed in the world.
            pose = self.sim.est_pose[rows]
            ang = pose[:, 2] + sg[:, 1]
            raw = pose[:, :2] + sg[:, :1] * np.stack([np.cos(ang), np.sin(ang)], 1)
            self.subgoal_raw[rows] = raw
            self.subgoal[rows] = self.sim.snap_to_navigable(self.subgoal_raw, rows)[rows]
            self.turn[rows] = EXECUTOR
            self.turn_steps[rows] = 0
        return rows

    def _measure_subgoals(self, new, moved) -> None:
        """Geodesic distance to the sub-goal in the worlds ``new`` (which also sets their
        ``subgoal_dist0``) and in the worlds whose agent ``moved``, in one batch."""
        rows = np.concatenate([new, moved])
        if not len(rows):
            return
        d = self.sim.distance_to(self.subgoal, rows)[rows]
        if not np.isfinite(d).all():
            bad = rows[~np.isfinite(d)]
            raise RuntimeError(f"sub-goal unreachable in worlds {bad.tolist()} after snapping; this is a bug")
        self.subgoal_dist[rows] = d
        self.subgoal_dist0[new] = d[:len(new)]

    def _executor_step(self, rows, action, eli, out: PlexStep, new_subgoals) -> None:
        cfg = self.cfg
        sim = self.sim
        out.acted[rows] = EXECUTOR
        acts = np.zeros(self.n, np.int64)
        acts[rows] = action
        active = np.zeros(self.n, np.bool_)
        active[rows] = True
        d_goal_prev = sim.distance_to_goal[rows]  # indexing by an array copies
        d_sub_prev = self.subgoal_dist[rows]
        pos_prev = sim.pos[rows]
        collided = sim.step(acts, active)[rows]
        # The sub-goal is fixed during the turn, so the geodesic distance to it changes only
        # where the agent moved; turns, STOP and blocked moves keep the previous value.
        moved = (sim.pos[rows] != pos_prev).any(axis=1)
        self._measure_subgoals(new_subgoals, rows[moved])
        stopped = action == STOP
        ex_r, reached = executor_reward(d_sub_prev, self.subgoal_dist[rows], self.subgoal_dist0[rows], collided,
                                        stopped, cfg)
        pl_r = progress_reward(d_goal_prev, sim.distance_to_goal[rows], collided, cfg)
        out.rewards[rows, EXECUTOR] += ex_r  # float32(0 + r) = float32(r)
        out.rewards[rows, PLANNER] += pl_r
        if cfg.eli:
            self.eli[rows] = eli
        self.collisions[rows] += collided
        self.steps[rows] += 1
        self.turn_steps[rows] += 1
        turn_end = stopped | (self.turn_steps[rows] >= cfg.n_ex)
        trunc = self.steps[rows] >= cfg.max_steps
        out.executor_stopped[rows] = stopped
        out.executor_reached[rows] = reached
        out.executor_turn_end[rows] = turn_end | trunc
        self.turn[rows[turn_end]] = PLANNER
        tr = rows[trunc]
        if len(tr):
            out.truncated[tr] = True
            self._finish(tr, np.zeros(len(tr), np.bool_))


class PointNavWorlds(_Worlds):
    """The flat PointNav rules (docs/spec.md section 4) over N worlds: STOP ends the episode.

    ``egomap``: keep each world's ego map, and add the planner's ``ego_map`` (the same as
    :meth:`PlexWorlds.planner_obs`) to the observations (for the flat policy that reads it,
    PPO-GRU+map); off by default, where the simulator skips the map's updates."""

    def __init__(self, cfg: NavConfig, num_worlds: int = 1, seed: int | None = None, egomap: bool = False):
        super().__init__(cfg, num_worlds, seed, egomap=egomap)

    def obs(self, rows) -> dict:
        rows = np.asarray(rows, np.int64).reshape(-1)
        return {"rgb": self.sim.rgb[rows], "depth": self.sim.depth[rows],  # indexing by an array copies
                "pointgoal": self.goal_vector(rows),
                **({"ego_map": self.sim.egomap(rows)} if self.sim.use_egomap else {})}

    def step(self, actions) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Apply one action per live world. Returns (rewards, terminated, truncated)."""
        cfg = self.cfg
        a = discrete(actions, NUM_ACTIONS, "agent: actions", (self.n,), ACTION_NAMES, per="world")
        live = ~self.done
        rows = np.flatnonzero(live)
        rew = np.zeros(self.n, np.float32)
        term = np.zeros(self.n, np.bool_)
        trunc = np.zeros(self.n, np.bool_)
        d_prev = self.sim.distance_to_goal.copy()
        collided = self.sim.step(np.where(live, a, STOP), live)
        rew[rows] = progress_reward(d_prev[rows], self.sim.distance_to_goal[rows], collided[rows], cfg)
        self.collisions[rows] += collided[rows]
        self.steps[rows] += 1
        stops = rows[a[rows] == STOP]
        if len(stops):
            success = self.sim.distance_to_goal[stops] < cfg.success_distance
            rew[stops] += cfg.success_reward * success
            term[stops] = True
            self._finish(stops, success)
        tr = rows[(self.steps[rows] >= cfg.max_steps) & ~term[rows]]
        if len(tr):
            trunc[tr] = True
            self._finish(tr, np.zeros(len(tr), np.bool_))
        return rew, term, trunc


def _whole(x, k: int) -> int | None:
    """``x`` as an int if it is a Python or numpy integer (not a bool) in ``0..k-1``, else None."""
    if (type(x) is int or isinstance(x, np.integer)) and 0 <= x < k:
        return int(x)
    return None


def _float_vector(x, size: int) -> bool:
    """Whether ``x`` is a float32 or float64 array of shape (size,)."""
    return type(x) is np.ndarray and x.shape == (size,) and x.dtype.char in "fd"


def _rows_of(x, n: int, tail: tuple, who: str, key: str) -> np.ndarray:
    """``x`` as an array of shape (n, *tail), or InvalidAction naming the problem."""
    a = np.asarray(x)
    if a.dtype == object:
        raise InvalidAction(f"{who}: action {key!r} must be numeric, got {type(x).__name__}")
    if a.shape != (n,) + tail:
        raise InvalidAction(f"{who}: action {key!r} has shape {a.shape}, expected {(n,) + tail}")
    return a


def _default_episode_file(scenes: str, split: str):
    """The shipped fixed episode file of a scene source's split, or None (episodes are then sampled)."""
    try:
        return default_episode_file(scenes, split)
    except (ValueError, FileNotFoundError):
        return None
