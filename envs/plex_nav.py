"""The implementation of :mod:`plex_ma.envs.plex_nav_v0` (its module docstring is the doc
page): ``raw_env`` holds the turn logic over one :class:`~plex_ma.envs.rules.PlexWorlds`
world, ``env()`` adds PettingZoo's order-enforcing wrapper."""

from __future__ import annotations

import gymnasium
import numpy as np
from gymnasium.utils import EzPickle
from pettingzoo import AECEnv
from pettingzoo.utils import wrappers

from .rules import EXECUTOR, InvalidAction, OneWorldEnv, PlexConfig, PlexWorlds, make_config
from .sim.topdown import topdown_view
from .spaces import executor_action_space, executor_observation_space, planner_action_space, planner_observation_space
from .viewer import HumanViewer

AGENTS = ["planner", "executor"]
# The attributes that hold the episode's state, which the wrappers read through (a turn
# of agent_iter, last() and step reads them about ten times).
EPISODE_STATE = frozenset({"agents", "agent_selection", "rewards", "terminations", "truncations",
                           "_cumulative_rewards"})


def env(**kwargs) -> AECEnv:
    """:class:`raw_env` in PettingZoo's order-enforcing wrapper, its only wrapper (a step
    after the episode's end raises :class:`InvalidAction`, as ``raw_env`` does).

    PettingZoo's bounds wrappers are left out: ``raw_env`` checks every action itself and
    raises :class:`InvalidAction` naming what is wrong, where ``AssertOutOfBoundsWrapper``
    gives a bare assertion and ``ClipOutOfBoundsWrapper`` (Box spaces only) would clip
    silently."""
    e = raw_env(**kwargs)
    e = _OrderEnforcing(e)
    return e


class _OrderEnforcing(wrappers.OrderEnforcingWrapper):
    """PettingZoo's order enforcing, except that a step after the episode ended raises
    :class:`InvalidAction` (as ``raw_env`` does) instead of only logging a warning."""

    def __getattr__(self, name: str):
        # after the reset, the episode's state straight from the env, without the
        # before-reset checks of every attribute
        if name in EPISODE_STATE and self._has_reset:
            return getattr(self.env, name)
        return super().__getattr__(name)

    def step(self, action) -> None:
        if not self._has_reset:
            super().step(action)  # PettingZoo's error
            return
        if not self.env.agents:
            raise InvalidAction("step() called after the episode ended; call reset()")
        self._has_updated = True  # what PettingZoo's step does before stepping the env
        self.env.step(action)

    def last(self, observe: bool = True):
        # after the reset, the env's own last(), without a wrapper level for each of its reads
        if self._has_reset:
            return self.env.last(observe)
        return super().last(observe)


class raw_env(OneWorldEnv, AECEnv, EzPickle):
    """The PLEX Planner/Executor environment; see the module docstring."""

    metadata = {"name": "plex_nav_v0", "render_modes": ["human", "rgb_array"], "is_parallelizable": False,
                "render_fps": 10}

    def __init__(self, render_mode: str | None = None, **config):
        EzPickle.__init__(self, render_mode=render_mode, **config)
        super().__init__()
        if render_mode not in (None, *self.metadata["render_modes"]):
            raise ValueError(f"render_mode must be None, 'human' or 'rgb_array', got {render_mode!r}")
        self.render_mode = render_mode
        self._viewer = HumanViewer("plex_nav_v0", self.metadata["render_fps"]) if render_mode == "human" else None
        self.config: PlexConfig = make_config(PlexConfig, config)
        self.worlds = PlexWorlds(self.config, num_worlds=1)
        self.possible_agents = list(AGENTS)
        self.agents = []
        self.observation_spaces = {"planner": planner_observation_space(self.config),
                                   "executor": executor_observation_space(self.config)}
        self.action_spaces = {"planner": planner_action_space(self.config),
                              "executor": executor_action_space(self.config)}
        self._path: list[np.ndarray] = []
        self._seeded = False

    def observation_space(self, agent):
        return self.observation_spaces[agent]

    def action_space(self, agent):
        return self.action_spaces[agent]

    # ------------------------------------------------------------------ API
    def reset(self, seed: int | None = None, options: dict | None = None) -> None:
        if seed is not None or not self._seeded:
            self.worlds.seed(seed)
            self._seeded = True
            for k, a in enumerate(AGENTS):
                self.action_spaces[a].seed(None if seed is None else seed + k)
        episodes = None
        if options and "episode" in options:
            episodes = [options["episode"]]
        self.worlds.reset_rows([0], episodes)
        self.agents = list(AGENTS)
        self.rewards = {a: 0.0 for a in AGENTS}
        self._cumulative_rewards = {a: 0.0 for a in AGENTS}
        self.terminations = {a: False for a in AGENTS}
        self.truncations = {a: False for a in AGENTS}
        info = self.worlds.info(0)
        self.infos = {a: dict(info) for a in AGENTS}
        self.agent_selection = "planner"
        self._path = [self.worlds.sim.pos[0].copy()]
        if self._viewer is not None:
            self._viewer.show(self._frame())

    def observe(self, agent):
        if agent == "planner":
            obs = self.worlds.planner_obs([0])
        elif agent == "executor":
            obs = self.worlds.executor_obs([0])
        else:
            raise ValueError(f"unknown agent {agent!r}; agents are {AGENTS}")
        return {k: v[0] for k, v in obs.items()}

    def step(self, action) -> None:
        agent = self.agent_selection
        if not self.agents:
            raise InvalidAction("step() called after the episode ended; call reset()")
        if self.terminations[agent] or self.truncations[agent]:
            if action is not None:
                raise InvalidAction(f"{agent}: the episode has ended; the only valid action is None (dead step)")
            self._was_dead_step(action)
            return
        w = self.worlds
        if agent == "planner":
            stop, subgoal = _unpack(action, agent, ("stop", "subgoal"))
            out = w.step_one(stop=stop, subgoal=subgoal)  # _unpack checked the shapes
        else:
            act, eli = _unpack(action, agent, ("action", "eli"))
            out = w.step_one(action=act, eli=eli)
        self._cumulative_rewards[agent] = 0.0
        self.rewards = {"planner": out.planner_reward, "executor": out.executor_reward}
        self._accumulate_rewards()
        if out.acted == EXECUTOR:
            self._path.append(w.sim.pos[0].copy())
        info = w.info(0)
        self.infos = {a: dict(info) for a in self.agents}
        if out.terminated or out.truncated:
            for a in self.agents:
                self.terminations[a] = out.terminated
                self.truncations[a] = out.truncated
            self.agent_selection = agent
            self._deads_step_first()
        else:
            self.agent_selection = AGENTS[int(w.turn[0])]
        if self._viewer is not None:
            self._viewer.show(self._frame())

    def render(self):
        """``rgb_array``: the top-down view as an (H, W, 3) uint8 array. ``human``: draws it in
        the window (which every ``reset`` and ``step`` also does) and returns None."""
        if self.render_mode is None:

            gymnasium.logger.warn("render() called without render_mode; create the env with "
                                  "render_mode='rgb_array' or 'human'")
            return None
        if self.render_mode == "human":
            if self.worlds.sim.episodes[0] is not None:
                self._viewer.show(self._frame())
            return None
        return self._frame()

    def _frame(self) -> np.ndarray:
        w = self.worlds
        sim = w.sim
        grid = sim.bank.grids[int(sim.scene_idx[0])]
        show_sub = w.turn[0] == EXECUTOR or w.planner_decisions[0] > 0
        return topdown_view(grid, path=np.array(self._path), goal=sim.goal[0],
                            subgoal=w.subgoal[0] if show_sub else None,
                            subgoal_raw=w.subgoal_raw[0] if show_sub else None,
                            agent_pose=(sim.pos[0, 0], sim.pos[0, 1], sim.heading[0]))

    def close(self) -> None:
        if self._viewer is not None:
            self._viewer.close()


def _unpack(action, agent: str, keys: tuple[str, str]):
    """Check an agent's Dict action and return its two parts, with clear errors."""
    want = (2,) if agent == "planner" else (128,)
    if type(action) is dict and action.keys() == set(keys):  # the common case first
        a, b = action[keys[0]], action[keys[1]]
        if isinstance(b, np.ndarray) and b.shape == want and isinstance(a, (int, float, np.number, np.ndarray)) \
                and np.ndim(a) == 0:
            return a, b
    if action is None:
        raise InvalidAction(f"{agent}: action is None but the {agent} is alive; expected a dict with keys {keys}")
    if not isinstance(action, dict):
        raise InvalidAction(f"{agent}: expected a dict with keys {keys}, got {type(action).__name__} {action!r}")
    other = {"planner": ("action", "eli"), "executor": ("stop", "subgoal")}[agent]
    if set(action) == set(other):
        raise InvalidAction(f"{agent}: got the other agent's action format {sorted(action)}; "
                            f"it is the {agent}'s turn and its action has keys {keys}")
    missing = [k for k in keys if k not in action]
    extra = [k for k in action if k not in keys]
    if missing or extra:
        raise InvalidAction(f"{agent}: action keys {sorted(action)} (missing {missing}, unexpected {extra}); "
                            f"expected {list(keys)}")
    a, b = action[keys[0]], action[keys[1]]
    for k, v in zip(keys, (a, b)):
        if v is None:
            raise InvalidAction(f"{agent}: action {k!r} is None; expected a number or an array")
    if np.ndim(a) != 0:
        raise InvalidAction(f"{agent}: action {keys[0]!r} must be a scalar, got shape {np.shape(a)}")
    try:
        shape_b = np.shape(b)
    except ValueError:  # ragged nested sequences
        raise InvalidAction(f"{agent}: action {keys[1]!r} is a ragged sequence, expected shape {want}") from None
    if shape_b != want:
        raise InvalidAction(f"{agent}: action {keys[1]!r} has shape {shape_b}, expected {want}")
    return a, b
