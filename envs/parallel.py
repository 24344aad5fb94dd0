"""The turn-based Parallel view of ``plex_nav_v0``'s AEC envs: ``plex_nav_v0.parallel_env()``
and ``plex_nav_v0.compat_parallel_env()`` (the ``plex_nav_v0`` module docstring is the doc
page).

Every parallel step applies one AEC step: the action of the agent whose turn it is
(``agent_selection``); the other live agent's action is not used and may be left out of
the actions dict. ``infos[agent]["acting"]`` says which agent's action the step used, so a
trainer can keep only that agent's transition. PettingZoo's own
``turn_based_aec_to_parallel`` does the same stepping but names the agent whose turn comes
*next* (``infos[agent]["active_agent"]``, a string, absent after ``reset``), which is not
the one whose transition counts.
"""

from __future__ import annotations

from pettingzoo import AECEnv, ParallelEnv

from .actions import InvalidAction


class TurnParallelEnv(ParallelEnv):
    """A Parallel env over a turn-based AEC env: one AEC step per parallel step.

    ``reset`` returns every agent's observation and infos with ``acting`` False (no action
    was used yet). ``step(actions)`` takes the acting agent's action from ``actions``,
    steps the AEC env once, and returns every live agent's observation, the rewards each
    agent earned in that step, the flags, and infos with ``acting`` True for the agent
    whose action was used. When the episode ends it also takes the dead steps, so
    ``agents`` is then empty and the next call must be ``reset``."""

    def __init__(self, aec_env: AECEnv):
        self.aec_env = aec_env
        self.possible_agents = list(aec_env.possible_agents)
        self.metadata = aec_env.metadata
        self.render_mode = aec_env.render_mode
        self.agents = []

    def __str__(self) -> str:
        return f"parallel<{self.aec_env}>"

    @property
    def unwrapped(self):
        return self.aec_env.unwrapped

    def observation_space(self, agent):
        return self.aec_env.observation_space(agent)

    def action_space(self, agent):
        return self.aec_env.action_space(agent)

    def reset(self, seed=None, options=None):
        self.aec_env.reset(seed=seed, options=options)
        self.agents = list(self.aec_env.agents)
        observations = {a: self.aec_env.observe(a) for a in self.agents}
        return observations, self._infos(acting=None)

    def step(self, actions: dict):
        env = self.aec_env
        if not self.agents:
            raise InvalidAction("step() called after the episode ended; call reset()")
        if not isinstance(actions, dict):
            raise InvalidAction(f"actions must be a dict {{agent: action}}, got {type(actions).__name__}")
        unknown = sorted(set(actions) - set(self.agents))
        if unknown:
            raise InvalidAction(f"actions for {unknown}, which are not live agents {self.agents}")
        acting = env.agent_selection
        if acting not in actions:
            raise InvalidAction(f"actions has no action for the {acting}, whose turn it is "
                                f"(got actions for {sorted(actions)})")
        env.step(actions[acting])
        observations = {a: env.observe(a) for a in env.agents}
        rewards = {a: env.rewards[a] for a in self.agents}
        terminations = {a: env.terminations[a] for a in self.agents}
        truncations = {a: env.truncations[a] for a in self.agents}
        infos = self._infos(acting)
        while env.agents and (env.terminations[env.agent_selection] or env.truncations[env.agent_selection]):
            env.step(None)  # the dead steps PettingZoo's AEC API asks for
        self.agents = list(env.agents)
        return observations, rewards, terminations, truncations, infos

    def _infos(self, acting) -> dict:
        return {a: {**self.aec_env.infos[a], "acting": a == acting} for a in self.aec_env.agents}

    def render(self):
        return self.aec_env.render()

    def close(self) -> None:
        self.aec_env.close()
