"""The indoor navigation simulator: procedural and real scenes, ray-cast RGB-D, geodesic
distance, Habitat-style episodes and the planner's ego map, for N worlds per call."""

from .bank import SceneBank
from .core import ACTION_NAMES, MOVE_FORWARD, STOP, TURN_LEFT, TURN_RIGHT, BatchedSim
from .episodes import Episode, EpisodeFileError, Geodesics, generate_episodes, load_episodes, save_episodes
from .scene import Scene, SceneError, SceneGrid, rasterize
from .sources import DEFAULT_NUM_SCENES, SPLITS, load_scenes, scene_bank

__all__ = [
    "ACTION_NAMES", "BatchedSim", "DEFAULT_NUM_SCENES", "Episode", "EpisodeFileError", "Geodesics",
    "MOVE_FORWARD", "SPLITS", "STOP", "Scene", "SceneBank", "SceneError", "SceneGrid", "TURN_LEFT",
    "TURN_RIGHT", "generate_episodes", "load_episodes", "load_scenes", "rasterize", "save_episodes", "scene_bank",
]

