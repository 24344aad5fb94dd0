"""Observation and action spaces of the PLEX agents and the flat agent (docs/spec.md sections 3-4).

Angles are radians, counter-clockwise, 0 = the agent's heading. Every space is built once
per environment, so ``observation_space(agent)`` returns the same object on every call.
"""

from __future__ import annotations

import numpy as np
from gymnasium import spaces

from .rules import ELI_DIM, NavConfig, PlexConfig
from .sim.core import NUM_ACTIONS, BatchedSim

# The ego map's geometry, as the simulator draws it: channels (obstacles, explored free
# space, the obstacles of each cell's four 0.25 m quarters), cells per side, cell size (m).
EGO_CHANNELS, EGO_SIZE, EGO_CELL = BatchedSim.ego_channels, BatchedSim.ego_size, BatchedSim.ego_cell
MAX_GOAL_DISTANCE = 100.0  # metres; bounds of the polar goal vectors


def polar_space(max_distance: float) -> spaces.Box:
    return spaces.Box(low=np.array([0.0, -np.pi], np.float32), high=np.array([max_distance, np.pi], np.float32),
                      dtype=np.float32)


def image_spaces(resolution: int) -> dict:
    return {
        "rgb": spaces.Box(0, 255, (resolution, resolution, 3), np.uint8),
        "depth": spaces.Box(0.0, 1.0, (resolution, resolution, 1), np.float32),
    }


def ego_map_space() -> spaces.Box:
    return spaces.Box(0.0, 1.0, (EGO_CHANNELS, EGO_SIZE, EGO_SIZE), np.float32)


def planner_observation_space(cfg: PlexConfig) -> spaces.Dict:
    return spaces.Dict({
        "ego_map": ego_map_space(),
        "goal": polar_space(MAX_GOAL_DISTANCE),
        "eli": spaces.Box(-np.inf, np.inf, (ELI_DIM,), np.float32),
    })


def planner_action_space(cfg: PlexConfig) -> spaces.Dict:
    return spaces.Dict({
        "stop": spaces.Discrete(2),
        "subgoal": spaces.Box(np.array([0.0, -np.pi], np.float32), np.array([cfg.rho_max, np.pi], np.float32),
                              dtype=np.float32),
    })


def executor_observation_space(cfg: PlexConfig) -> spaces.Dict:
    return spaces.Dict({**image_spaces(cfg.resolution), "subgoal": polar_space(MAX_GOAL_DISTANCE)})


def executor_action_space(cfg: PlexConfig) -> spaces.Dict:
    return spaces.Dict({
        "action": spaces.Discrete(NUM_ACTIONS),
        "eli": spaces.Box(-np.inf, np.inf, (ELI_DIM,), np.float32),
    })


def pointnav_observation_space(cfg: NavConfig, ego_map: bool = False) -> spaces.Dict:
    """The flat agent's observations; with ``ego_map``, also the planner's ego map."""
    return spaces.Dict({**image_spaces(cfg.resolution), "pointgoal": polar_space(MAX_GOAL_DISTANCE),
                        **({"ego_map": ego_map_space()} if ego_map else {})})
