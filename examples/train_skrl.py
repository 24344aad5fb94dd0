"""Train ``plex_nav_v0``'s compat view with skrl's multi-agent IPPO, through
``plex_nav_v0.compat_parallel_env()``; with ``--eli`` the executor's action carries the ELI.

    pip install skrl                    # tested with skrl 2.1.1; not a dependency of plex-ma
    python examples/train_skrl.py --timesteps 2000
    python examples/train_skrl.py --timesteps 2000 --eli

skrl trains PettingZoo *parallel* envs (``skrl.envs.wrappers.torch.wrap_env(env,
wrapper="pettingzoo")``); ``compat_parallel_env()`` is the turn-based Parallel view, in
which both agents act every step and only the acting agent's action is applied
(``infos[agent]["acting"]`` names it). skrl reads the spaces from
``env.unwrapped.observation_spaces``, which the compat env answers with its own spaces
(each agent its own: ``Discrete(33)`` for the planner, ``Discrete(4)`` for the executor).

What the recipe needs beyond the wrapper:

* **Action masking.** skrl flattens each Dict observation in key order:
  ``action_mask`` (the agent's action count) first, then ``observation``. :class:`Policy`
  puts -inf on the logits the mask forbids; that matters with ``pad=True``, where the
  executor's actions 4-32 are masked and the env rejects them (``InvalidAction``).
* **No global state.** The env has no ``state()``; :class:`NoState` makes the wrapper say
  so (``None`` for each agent) instead of calling it.

**The ELI** (``--eli``): ``compat_parallel_env(eli=True, mask="none")``. The executor's
action is ``Dict(action=Discrete(4), eli=Box(128))``, which skrl carries as one flat
tensor (its keys in order: the move, then the 128 ELI values) and unflattens for the env;
the planner's observation ends with the ELI its executor sent last. :class:`EliPolicy`
samples the move from a categorical and the ELI from a diagonal Gaussian over one trunk,
and its log-probability is the sum of both, so IPPO's ratio and entropy cover the message.

As with TorchRL and Tianshou (docs/trainers.md), each step's reward is what the agent
earned in that one step, and skrl stores a transition for both agents every step, the
non-acting one's included; the planner earns during the executor's steps, so plain IPPO
credits its decisions poorly. This recipe shows the plumbing; for learning, keep each
agent's acting steps and sum its rewards up to its next turn, as
``examples/train_ippo_parallel.py`` does.
"""

from __future__ import annotations

import argparse

import numpy as np

from plex_ma.envs import plex_nav_v0
import torch
from skrl.envs.wrappers.torch.pettingzoo_envs import PettingZooWrapper
from skrl.memories.torch import RandomMemory
from skrl.models.torch import CategoricalMixin, DeterministicMixin, Model
from skrl.multi_agents.torch.ippo import IPPO
from skrl.trainers.torch import SequentialTrainer
from torch import nn
from torch.distributions import Categorical, Normal


class NoState(PettingZooWrapper):
    """skrl's PettingZoo wrapper for an env without a global state."""

    def state(self):
        return {uid: None for uid in self.possible_agents}


def mask_width(space) -> int:
    """Length of ``action_mask`` at the front of skrl's flattened observation (skrl
    flattens a Dict space in its key order, which gymnasium sorts); 0 without a mask."""
    if not hasattr(space, "spaces"):
        return 0
    assert list(space.spaces) == ["action_mask", "observation"], list(space.spaces)
    return int(space["action_mask"].shape[0])


class Policy(CategoricalMixin, Model):
    """Logits over the agent's Discrete actions, with the masked ones at -inf."""

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
        logits = self.net(obs)
        return (logits.masked_fill(mask < 0.5, float("-inf")) if self.k else logits), {}


class EliPolicy(Model):
    """The executor with the ELI: a categorical move and a Gaussian 128-float ELI from one
    trunk. Its actions are skrl's flat ``[move, eli_0 .. eli_127]``; the log-probability
    and entropy are those of both parts."""

    def __init__(self, observation_space, state_space, action_space, device, hidden: int = 64):
        Model.__init__(self, observation_space=observation_space, state_space=state_space,
                       action_space=action_space, device=device)
        n_moves, eli_dim = action_space["action"].n, action_space["eli"].shape[0]
        self.trunk = nn.Sequential(nn.Linear(self.num_observations, hidden), nn.Tanh())
        self.moves = nn.Linear(hidden, n_moves)
        self.eli_mean = nn.Linear(hidden, eli_dim)
        self.eli_log_std = nn.Parameter(torch.full((eli_dim,), -1.0))
        self._entropy = self._eli = None

    def compute(self, inputs, *, role=""):
        h = self.trunk(inputs["observations"])
        return self.moves(h), {"eli_mean": self.eli_mean(h)}

    def act(self, inputs, *, role=""):
        logits, out = self.compute(inputs, role=role)
        move, eli = Categorical(logits=logits), Normal(out["eli_mean"], self.eli_log_std.exp())
        taken = inputs.get("taken_actions")
        if taken is None:
            a, m = move.sample(), eli.sample()
        else:  # PPO's update: the log-probability of the stored actions
            a, m = taken[:, 0].long(), taken[:, 1:]
        self._entropy, self._eli = move.entropy() + eli.entropy().sum(-1), eli
        log_prob = move.log_prob(a) + eli.log_prob(m).sum(-1)
        return torch.cat([a[:, None].float(), m], dim=1), {"log_prob": log_prob[:, None]}

    def get_entropy(self, *, role=""):
        return self._entropy

    def distribution(self, *, role=""):
        return self._eli  # skrl logs its standard deviation after each update


class Value(DeterministicMixin, Model):
    def __init__(self, observation_space, state_space, action_space, device, hidden: int = 64):
        Model.__init__(self, observation_space=observation_space, state_space=state_space,
                       action_space=action_space, device=device)
        DeterministicMixin.__init__(self)
        self.k = mask_width(observation_space)
        self.net = nn.Sequential(nn.Linear(self.num_observations - self.k, hidden), nn.Tanh(), nn.Linear(hidden, 1))

    def compute(self, inputs, role=""):
        return self.net(inputs["observations"][:, self.k:]), {}


def build(env_kwargs: dict, rollouts: int = 64, seed: int = 0, eli: bool = False):
    """The wrapped env and an IPPO agent with one policy and one value network per agent;
    with ``eli`` the executor's policy also sends the ELI."""
    torch.manual_seed(seed)
    env = NoState(plex_nav_v0.compat_parallel_env(**env_kwargs, **(dict(eli=True, mask="none") if eli else {})))
    models, memories = {}, {}
    for uid in env.possible_agents:
        ob, act = env.observation_space(uid), env.action_space(uid)
        policy = EliPolicy if eli and uid == "executor" else Policy
        models[uid] = {"policy": policy(ob, None, act, env.device), "value": Value(ob, None, act, env.device)}
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
    p.add_argument("--eli", action="store_true", help="the executor's action carries the ELI to the planner")
    args = p.parse_args(argv)
    env, agent = build(dict(resolution=args.resolution, num_scenes=args.num_scenes, max_steps=args.max_steps),
                       args.rollouts, args.seed, args.eli)
    episodes = {"count": 0, "success": [], "eli": []}
    step = env.step

    def counting_step(actions):  # the episodes that end, with their success; the ELIs the planner saw
        out = step(actions)
        if args.eli and "planner" in out[0]:
            episodes["eli"].append(float(out[0]["planner"][0, -128:].abs().mean()))
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
    eli = f", mean |ELI| seen by the planner {np.mean(episodes['eli']):.3f}" if args.eli else ""
    print(f"{args.timesteps} steps, {updates} IPPO updates per agent, {episodes['count']} episodes, "
          f"success {rate:.2f}{eli}")
    return {"episodes": episodes["count"], "updates": updates, "agent": agent, "eli": episodes["eli"]}


if __name__ == "__main__":
    main()
