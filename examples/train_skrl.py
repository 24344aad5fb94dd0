"""Train ``plex_nav_v0.compat_env`` with skrl's multi-agent IPPO, through PettingZoo's
turn-based parallel conversion.

    pip install skrl                    # tested with skrl 2.1.1; not a dependency of plex-ma
    python examples/train_skrl.py --timesteps 2000

skrl trains PettingZoo *parallel* envs (``skrl.envs.wrappers.torch.wrap_env(env,
wrapper="pettingzoo")``); PLEX's env is turn-based (AEC), so
``pettingzoo.utils.conversions.turn_based_aec_to_parallel`` presents it as a parallel env
in which both agents act every step and only the acting agent's action is applied
(``infos[agent]["active_agent"]`` names it). skrl reads the spaces from
``env.unwrapped.observation_spaces``, which the compat env answers with its own spaces.

What the recipe needs beyond the wrapper:

* **Action masking.** skrl flattens each Dict observation in key order:
  ``action_mask`` (33 values) first, then ``observation`` (6,148). The executor may use
  only actions 0-3, and the env rejects a masked action (``InvalidAction``), so
  :class:`Policy` puts -inf on the logits the mask forbids.
* **No global state.** The env has no ``state()``; :class:`NoState` makes the wrapper say
  so (``None`` for each agent) instead of calling it.

As with TorchRL and Tianshou (docs/trainers.md), each step's reward is what the agent
earned in that one step; the planner earns during the executor's steps, so plain IPPO
credits its decisions poorly. This recipe shows the plumbing; for learning, sum each
agent's rewards up to its next turn as ``examples/train_torchrl.py`` does.
"""

from __future__ import annotations

import argparse

import numpy as np

from plex_ma.envs import plex_nav_v0
import torch
from pettingzoo.utils.conversions import turn_based_aec_to_parallel
from skrl.envs.wrappers.torch.pettingzoo_envs import PettingZooWrapper
from skrl.memories.torch import RandomMemory
from skrl.models.torch import CategoricalMixin, DeterministicMixin, Model
from skrl.multi_agents.torch.ippo import IPPO
from skrl.trainers.torch import SequentialTrainer
from torch import nn


class NoState(PettingZooWrapper):
    """skrl's PettingZoo wrapper for an env without a global state."""

    def state(self):
        return {uid: None for uid in self.possible_agents}


def mask_width(space) -> int:
    """Length of ``action_mask`` at the front of skrl's flattened observation (skrl
    flattens a Dict space in its key order, which gymnasium sorts)."""
    assert list(space.spaces) == ["action_mask", "observation"], list(space.spaces)
    return int(space["action_mask"].shape[0])


class Policy(CategoricalMixin, Model):
    """Logits over the Discrete(33) actions, with the masked ones at -inf."""

    def __init__(self, observation_space, state_space, action_space, device, hidden: int = 64):
        Model.__init__(self, observation_space=observation_space, state_space=state_space,
                       action_space=action_space, device=device)
        CategoricalMixin.__init__(self, unnormalized_log_prob=True)
        self.k = mask_width(observation_space)
        self.net = nn.Sequential(nn.Linear(self.num_observations - self.k, hidden), nn.Tanh(),
                                 nn.Linear(hidden, self.num_actions))

    def compute(self, inputs, role=""):
        x = inputs["observations"]
        mask, obs = x[:, :self.k], x[:, self.k:]
        return self.net(obs).masked_fill(mask < 0.5, float("-inf")), {}


class Value(DeterministicMixin, Model):
    def __init__(self, observation_space, state_space, action_space, device, hidden: int = 64):
        Model.__init__(self, observation_space=observation_space, state_space=state_space,
                       action_space=action_space, device=device)
        DeterministicMixin.__init__(self)
        self.k = mask_width(observation_space)
        self.net = nn.Sequential(nn.Linear(self.num_observations - self.k, hidden), nn.Tanh(), nn.Linear(hidden, 1))

    def compute(self, inputs, role=""):
        return self.net(inputs["observations"][:, self.k:]), {}


def build(env_kwargs: dict, rollouts: int = 64, seed: int = 0):
    """The wrapped env and an IPPO agent with one policy and one value network per agent."""
    torch.manual_seed(seed)
    env = NoState(turn_based_aec_to_parallel(plex_nav_v0.compat_env(**env_kwargs)))
    models, memories = {}, {}
    for uid in env.possible_agents:
        ob, act = env.observation_space(uid), env.action_space(uid)
        models[uid] = {"policy": Policy(ob, None, act, env.device), "value": Value(ob, None, act, env.device)}
        memories[uid] = RandomMemory(memory_size=rollouts, num_envs=env.num_envs, device=env.device)
    per_agent = {uid: {} for uid in env.possible_agents}  # skrl 2.1 wants the *_kwargs dicts keyed by agent
    cfg = {"rollouts": rollouts, "learning_epochs": 2, "mini_batches": 2, "learning_rate": 3e-4,
           "experiment": {"write_interval": 0, "checkpoint_interval": 0},
           **{f"{k}_kwargs": per_agent for k in ("learning_rate_scheduler", "observation_preprocessor",
                                                 "state_preprocessor", "value_preprocessor")}}
    agent = IPPO(possible_agents=env.possible_agents, models=models, memories=memories,
                 observation_spaces=env.observation_spaces, state_spaces={uid: None for uid in env.possible_agents},
                 action_spaces=env.action_spaces, device=env.device, cfg=cfg)
    return env, agent


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--timesteps", type=int, default=2000, help="parallel steps (each applies one agent's action)")
    p.add_argument("--rollouts", type=int, default=64, help="steps between updates")
    p.add_argument("--resolution", type=int, default=64)
    p.add_argument("--num-scenes", type=int, default=4)
    p.add_argument("--max-steps", type=int, default=100)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    env, agent = build(dict(resolution=args.resolution, num_scenes=args.num_scenes, max_steps=args.max_steps),
                       args.rollouts, args.seed)
    episodes = {"count": 0, "success": []}
    step = env.step

    def counting_step(actions):  # the episodes that end, with their success
        out = step(actions)
        if not env.agents:
            episodes["count"] += 1
            episodes["success"].append(float(out[4]["planner"]["success"]))
        return out

    env.step = counting_step
    trainer = SequentialTrainer(env=env, agents=agent, cfg={"timesteps": args.timesteps, "headless": True,
                                                           "disable_progressbar": True,
                                                           "close_environment_at_exit": False})
    trainer.train()
    env.close()
    updates = args.timesteps // args.rollouts
    rate = float(np.mean(episodes["success"])) if episodes["success"] else float("nan")
    print(f"{args.timesteps} steps, {updates} IPPO updates per agent, {episodes['count']} episodes, "
          f"success {rate:.2f}")
    return {"episodes": episodes["count"], "updates": updates, "agent": agent}


if __name__ == "__main__":
    main()
