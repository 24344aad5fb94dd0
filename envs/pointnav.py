"""``gymnasium.make("plex_ma/PointNav-v0", **config)``: the flat PointNav task (docs/spec.md section 4).

One agent in the same world, episodes, sensors and rewards as ``plex_nav_v0``.

* Observation: ``Dict(rgb=Box(0, 255, (H, W, 3), uint8), depth=Box(0, 1, (H, W, 1)),
  pointgoal=Box((2,)))``; ``pointgoal`` is (distance m, direction rad) to the end goal
  from GPS+compass.
* Action: ``Discrete(4)``: 0 STOP, 1 MOVE_FORWARD 0.25 m, 2 TURN_LEFT 10 deg, 3 TURN_RIGHT 10 deg.
* Reward: decrease of geodesic distance to the goal - 0.01 slack - 0.01 per collision,
  +10 on success. STOP ends the episode (success when the geodesic distance is below
  0.2 m); ``max_steps`` (500) actions truncate it.
* Info: the keys of ``plex_nav_v0``'s infos (its docstring's Infos table), from ``reset``
  on and every value a number: ``scene_index``, ``episode_id``, ``geodesic_distance``,
  ``distance_to_goal``, ``collisions``, ``steps``, ``success`` and ``spl`` (the last two
  0.0 until the episode ends). The scene's string id is ``env.unwrapped.scene_id``;
  ``scene_index`` indexes ``env.unwrapped.scene_ids``.

Arguments: those of :class:`~plex_ma.envs.rules.NavConfig` plus ``render_mode``:
"rgb_array" (``render()`` returns the top-down view) or "human" (the view in a live
window after every ``reset`` and ``step``; one warning and nothing shown without a
display, see :mod:`plex_ma.envs.viewer`).

Batched versions: ``gymnasium.make_vec("plex_ma/PointNav-v0", num_envs=N, **config)``
gives :class:`~plex_ma.envs.gym_vector.PointNavGymVectorEnv`, a gymnasium ``VectorEnv``
that steps all N worlds in one call of the batched simulator (NEXT_STEP autoreset,
batched spaces, infos as arrays with ``_key`` masks; with the same seeds and actions it
returns what ``SyncVectorEnv`` over N of these envs returns). The project's own
trainers use :class:`~plex_ma.envs.vector.PointNavVectorEnv`.
"""

from __future__ import annotations

import gymnasium
import numpy as np

from .actions import InvalidAction, discrete
from .rules import NavConfig, OneWorldEnv, PointNavWorlds, make_config
from .sim.core import ACTION_NAMES, NUM_ACTIONS
from .sim.topdown import topdown_view
from .spaces import pointnav_observation_space
from .viewer import HumanViewer


class PointNavEnv(OneWorldEnv, gymnasium.Env):
    metadata = {"render_modes": ["human", "rgb_array"], "render_fps": 10}

    def __init__(self, render_mode: str | None = None, **config):
        if render_mode not in (None, *self.metadata["render_modes"]):
            raise ValueError(f"render_mode must be None, 'human' or 'rgb_array', got {render_mode!r}")
        self.render_mode = render_mode
        self._viewer = HumanViewer("PointNav-v0", self.metadata["render_fps"]) if render_mode == "human" else None
        self.config: NavConfig = make_config(NavConfig, config)
        self.worlds = PointNavWorlds(self.config, 1)
        self.observation_space = pointnav_observation_space(self.config)
        self.action_space = gymnasium.spaces.Discrete(NUM_ACTIONS)
        self._path: list[np.ndarray] = []
        self._seeded = False

    def _obs(self) -> dict:
        return {k: v[0] for k, v in self.worlds.obs([0]).items()}

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        if seed is not None or not self._seeded:
            self.worlds.seed(seed)
            self._seeded = True
        episodes = [options["episode"]] if options and "episode" in options else None
        self.worlds.reset_rows([0], episodes)
        self._path = [self.worlds.sim.pos[0].copy()]
        if self._viewer is not None:
            self._viewer.show(self._frame())
        return self._obs(), self.worlds.info(0)

    def step(self, action):
        if self.worlds.done[0]:
            raise InvalidAction("step() called after the episode ended; call reset()")
        a = discrete(action, NUM_ACTIONS, "agent: action", (), ACTION_NAMES)
        rew, term, trunc = self.worlds.step(a.reshape(1))
        self._path.append(self.worlds.sim.pos[0].copy())
        if self._viewer is not None:
            self._viewer.show(self._frame())
        return self._obs(), float(rew[0]), bool(term[0]), bool(trunc[0]), self.worlds.info(0)

    def render(self):
        """``rgb_array``: the top-down view; ``human``: draws it in the window, returns None."""
        if self.render_mode == "human" and self.worlds.sim.episodes[0] is not None:
            self._viewer.show(self._frame())
        if self.render_mode != "rgb_array":
            return None
        return self._frame()

    def close(self) -> None:
        if self._viewer is not None:
            self._viewer.close()

    def _frame(self) -> np.ndarray:
        sim = self.worlds.sim
        grid = sim.bank.grids[int(sim.scene_idx[0])]
        return topdown_view(grid, path=np.array(self._path), goal=sim.goal[0],
                            agent_pose=(sim.pos[0, 0], sim.pos[0, 1], sim.heading[0]))
