"""Batched environments for trainers: many worlds stepped per call, same rules.

:class:`PlexVectorEnv` is :class:`~plex_ma.envs.rules.PlexWorlds` with autoreset: each
world is at its own point of the planner/executor turn order, and one ``step`` call
applies the planner's action in the worlds where the planner is to act and the
executor's action in the others. :class:`PointNavVectorEnv` does the same for the flat
agent. Neither holds any rule of its own; the AEC env ``plex_nav_v0`` is the same rules
with one world, which a test checks step for step.

Info dicts (``info(i)``, ``episode_infos``) are those of the AEC and gym envs: the keys of
:data:`~plex_ma.envs.rules.INFO_KEYS`, every value a number; ``scene_ids[info["scene_index"]]``
is the scene's string id.

Returned image arrays are views into the simulator's buffers: copy them if you keep them
past the next ``step``, and do not write into them (a world whose agent did not move keeps
its image from one step to the next).

Both read one world through the same small API, which recorders and evaluation use instead
of the worlds' internals: ``world(i)`` (a :class:`~plex_ma.envs.rules.WorldView` copy:
episode, scene grid, pose, distance, collisions, images and, for PLEX, turn and sub-goal),
``ego_map(i)``, ``fixed_episodes`` (the episodes worlds take in order as they free up;
settable) and ``generate_episodes(n, seed)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .rules import (EXECUTOR, INFO_KEYS, PLANNER, NavConfig, PlexConfig, PlexWorlds, PointNavWorlds, WorldView,
                    make_config)
from .sim import Episode
from .spaces import (executor_action_space, executor_observation_space, planner_action_space,
                     planner_observation_space, pointnav_observation_space)


@dataclass
class PlexVecStep:
    """One batched step. ``turn`` says whose action each world needs next.

    The fields about ended episodes (``episode_infos``, ``final_executor_obs``,
    ``final_pose``) have one row per world whose episode ended in this step, in world
    order (``np.flatnonzero(terminated | truncated)``), taken before the autoreset."""

    turn: np.ndarray  # (N,) int8: PLANNER (0) or EXECUTOR (1)
    planner_obs: dict  # arrays (N, ...); valid where turn == PLANNER
    executor_obs: dict  # arrays (N, ...); the current images and sub-goal vector
    rewards: np.ndarray  # (N, 2): [planner, executor] earned during this step
    acted: np.ndarray  # (N,) int8: who acted in this step
    executor_turn_end: np.ndarray  # (N,) bool: the executor's turn ended in this step
    executor_stopped: np.ndarray  # (N,) bool: ... because it chose STOP
    executor_reached: np.ndarray  # (N,) bool: ... within the sub-goal radius (its success)
    terminated: np.ndarray  # (N,) bool: the episode ended by a planner stop (then reset)
    truncated: np.ndarray  # (N,) bool: the episode ended by max_steps (then reset)
    episode_infos: list  # one info dict (with success, spl) per world whose episode ended
    final_executor_obs: dict | None  # executor obs at the end of ended episodes (rows = ended)
    final_pose: np.ndarray | None  # (ended, 3) float64: x, y (m), heading (rad) at the end (rows = ended)


class _VectorEnv:
    """What both vector envs share: reading one world, and the episodes the worlds take."""

    worlds: PlexWorlds | PointNavWorlds

    @property
    def scene_ids(self) -> list[str]:
        """The scenes of the split, in ``scene_index`` order."""
        return list(self.worlds.bank.scene_ids)

    def world(self, i: int, images: bool = True) -> WorldView:
        """World ``i``'s state, copied (its images only with ``images``)."""
        return self.worlds.view(i, images)

    def ego_map(self, i: int) -> np.ndarray:
        """World ``i``'s planner ego map (6, 32, 32) float32 (PLEX, or flat with ``egomap``)."""
        return self.worlds.sim.egomap(np.array([i]))[0]

    @property
    def fixed_episodes(self) -> list[Episode] | None:
        """The split's fixed episodes (None: episodes are sampled). Set it to a list to make the
        worlds take those episodes in order as they free up (cycling), from the next reset."""
        return self.worlds.fixed_episodes

    @fixed_episodes.setter
    def fixed_episodes(self, episodes: list[Episode] | None) -> None:
        self.worlds.fixed_episodes = None if episodes is None else list(episodes)

    def generate_episodes(self, n: int, seed: int) -> list[Episode]:
        """``n`` episodes over the split's scenes, the same for the same seed."""
        return self.worlds.generate_episodes(n, seed)

    def close(self) -> None:
        pass


class PlexVectorEnv(_VectorEnv):
    """N PLEX worlds with autoreset (see the module docstring)."""

    def __init__(self, num_envs: int, seed: int | None = None, **config):
        self.config: PlexConfig = make_config(PlexConfig, config)
        self.num_envs = int(num_envs)
        self.worlds = PlexWorlds(self.config, self.num_envs, seed)
        self.planner_observation_space = planner_observation_space(self.config)
        self.executor_observation_space = executor_observation_space(self.config)
        self.planner_action_space = planner_action_space(self.config)
        self.executor_action_space = executor_action_space(self.config)
        self._planner_shapes = {k: ((self.num_envs,) + s.shape, s.dtype)
                                for k, s in self.planner_observation_space.spaces.items()}

    def reset(self, seed: int | None = None) -> tuple[np.ndarray, dict, dict]:
        """Reset every world. Returns (turn, planner_obs, executor_obs)."""
        if seed is not None:
            self.worlds.seed(seed)
        self.worlds.reset_rows(np.arange(self.num_envs))
        return self.worlds.turn.copy(), self._planner_obs(), self._executor_obs()

    def _planner_obs(self) -> dict:
        rows = np.flatnonzero(self.worlds.turn == PLANNER)
        out = {k: np.zeros(shape, dtype) for k, (shape, dtype) in self._planner_shapes.items()}
        if len(rows):
            self.worlds.planner_obs(rows, out=out)
        return out

    def _executor_obs(self) -> dict:
        w = self.worlds
        return {"rgb": w.sim.rgb, "depth": w.sim.depth,
                "subgoal": w.sim.polar_to(w.subgoal, None)}

    def step(self, stop=None, subgoal=None, action=None, eli=None) -> PlexVecStep:
        """Arrays of length N for both agents; each world reads its current agent's part.

        Giving only one agent's part (e.g. ``step(stop=..., subgoal=...)``) moves only the
        worlds where that agent is to act; the others wait. Trainers use this to resolve all
        planner decisions first, so that every executor step has all N worlds acting."""
        w = self.worlds
        out = w.step(stop=stop, subgoal=subgoal, action=action, eli=eli)
        ended = np.flatnonzero(out.terminated | out.truncated)
        infos = [w.info(int(i)) for i in ended]
        final = final_pose = None
        if len(ended):
            final = w.executor_obs(ended)  # copies
            final_pose = w.pose(ended)
            w.reset_rows(ended)
        return PlexVecStep(turn=w.turn.copy(), planner_obs=self._planner_obs(), executor_obs=self._executor_obs(),
                           rewards=out.rewards, acted=out.acted, executor_turn_end=out.executor_turn_end,
                           executor_stopped=out.executor_stopped, executor_reached=out.executor_reached,
                           terminated=out.terminated,
                           truncated=out.truncated, episode_infos=infos, final_executor_obs=final,
                           final_pose=final_pose)

    def info(self, i: int) -> dict:
        return self.worlds.info(i)


class PointNavVectorEnv(_VectorEnv):
    """N flat PointNav worlds with autoreset, for the baselines' trainer.

    ``step(actions)`` returns ``(obs, rewards, terminated, truncated, infos)`` where
    ``infos`` is a list of info dicts of the episodes that ended in this step, and
    ``obs`` of ended worlds is already the next episode's first observation.

    After each ``step``, ``final_pose`` holds the (ended, 3) float64 x, y (m) and heading
    (rad) of the agents whose episode ended in it, taken before the autoreset, in the
    order of ``infos`` (None if none ended): the returned 5-tuple is the gymnasium one.

    ``egomap=True`` adds the planner's ``ego_map`` (N, 6, 32, 32) to the observations
    (PPO-GRU+map reads it); without it the worlds keep no ego maps.
    """

    def __init__(self, num_envs: int, seed: int | None = None, egomap: bool = False, **config):
        self.config: NavConfig = make_config(NavConfig, config)
        self.num_envs = int(num_envs)
        self.worlds = PointNavWorlds(self.config, self.num_envs, seed, egomap=egomap)
        self.observation_space = pointnav_observation_space(self.config, ego_map=egomap)
        self.final_pose: np.ndarray | None = None

    def _obs(self) -> dict:
        w = self.worlds
        obs = {"rgb": w.sim.rgb, "depth": w.sim.depth, "pointgoal": w.goal_vector(np.arange(self.num_envs))}
        if w.sim.use_egomap:
            obs["ego_map"] = w.sim.egomap()
        return obs

    def reset(self, seed: int | None = None) -> dict:
        if seed is not None:
            self.worlds.seed(seed)
        self.worlds.reset_rows(np.arange(self.num_envs))
        self.final_pose = None
        return self._obs()

    def step(self, actions):
        w = self.worlds
        rew, term, trunc = w.step(actions)
        ended = np.flatnonzero(term | trunc)
        infos = [w.info(int(i)) for i in ended]
        self.final_pose = None
        if len(ended):
            self.final_pose = w.pose(ended)
            w.reset_rows(ended)
        return self._obs(), rew, term, trunc, infos


__all__ = ["PlexVectorEnv", "PlexVecStep", "PointNavVectorEnv", "WorldView", "PLANNER", "EXECUTOR", "INFO_KEYS"]
