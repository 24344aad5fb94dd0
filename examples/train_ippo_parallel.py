"""Independent PPO over a PettingZoo Parallel env, one policy per agent, trained here on
``plex_nav_v0.compat_parallel_env(mask="info")``.

    python examples/train_ippo_parallel.py --total-steps 4096

The loop knows nothing of PLEX. It reads what any Parallel env offers: ``possible_agents``,
each agent's ``observation_space(agent).shape`` (a flat Box) and ``action_space(agent).n``
(its own Discrete), ``infos[agent]["action_mask"]`` (every action allowed when absent)
and ``infos[agent]["acting"]`` (every agent acts when absent). The only PLEX line is the
constructor in :func:`make_env`, and its options are the whole of the glue.

**Turns.** PLEX is turn-based: in each parallel step only the acting agent's action is
used. The loop keeps an agent's transition only when ``acting`` says its action was used,
and adds the rewards the agent earns while the other agent acts to its last kept
transition, so each transition carries everything its action earned up to the agent's
next turn (what PettingZoo's AEC ``last()`` hands it). A transition is closed, and goes
into an update, when the agent acts again (its next value is the value there) or the
episode ends (0 if terminated; the value of the agent's last observation if truncated).
A transition still open at the end of a rollout waits for the next one, so no reward is
dropped and none is guessed.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from torch import nn
from torch.distributions import Categorical

from plex_ma.envs import plex_nav_v0


# total_steps: parallel env steps; num_steps: parallel steps per rollout; the PPO settings are CleanRL's
DEFAULTS = dict(total_steps=4096, num_steps=512, lr=2.5e-4, gamma=0.99, gae_lambda=0.95, update_epochs=4,
                minibatch_size=64, clip_coef=0.2, ent_coef=0.01, vf_coef=0.5, max_grad_norm=0.5,
                resolution=64, image_size=32, num_scenes=4, max_steps=100, seed=0)


def make_env(args):
    """The env: every trainer-facing choice is a constructor option."""
    return plex_nav_v0.compat_parallel_env(mask="info", resolution=args.resolution, image_size=args.image_size,
                                           num_scenes=args.num_scenes, max_steps=args.max_steps)


def layer(n_in: int, n_out: int, std: float = np.sqrt(2)) -> nn.Linear:
    lin = nn.Linear(n_in, n_out)
    nn.init.orthogonal_(lin.weight, std)
    nn.init.constant_(lin.bias, 0.0)
    return lin


class Agent(nn.Module):
    """CleanRL's PPO actor-critic for one agent: two 64-unit tanh MLPs over its flat observation."""

    def __init__(self, n_obs: int, n_actions: int):
        super().__init__()
        self.critic = nn.Sequential(layer(n_obs, 64), nn.Tanh(), layer(64, 64), nn.Tanh(), layer(64, 1, 1.0))
        self.actor = nn.Sequential(layer(n_obs, 64), nn.Tanh(), layer(64, 64), nn.Tanh(),
                                   layer(64, n_actions, 0.01))

    def value(self, x: torch.Tensor) -> torch.Tensor:
        return self.critic(x).squeeze(-1)

    def act(self, x: torch.Tensor, mask: torch.Tensor, action: torch.Tensor | None = None):
        dist = Categorical(logits=self.actor(x).masked_fill(~mask, float("-inf")))
        if action is None:
            action = dist.sample()
        return action, dist.log_prob(action), dist.entropy(), self.value(x)


class Transitions:
    """One agent's transitions: closed ones ready for an update, and the open one that
    still collects rewards until the agent's next turn or the episode's end."""

    def __init__(self):
        self.closed: list[dict] = []
        self.open: dict | None = None
        self.reward_total = 0.0  # every reward ever credited, to check that none is lost

    def start(self, obs, mask, action, logp, value, reward: float) -> None:
        if self.open is not None:  # the agent acts again: its previous transition ends here
            self.open.update(next_value=value, done=False)
            self.closed.append(self.open)
        self.open = dict(obs=obs, mask=mask, action=action, logp=logp, value=value, reward=reward)
        self.reward_total += reward

    def credit(self, reward: float) -> None:
        if self.open is not None:
            self.open["reward"] += reward
            self.reward_total += reward

    def end_episode(self, next_value: float) -> None:
        if self.open is not None:
            self.open.update(next_value=next_value, done=True)
            self.closed.append(self.open)
            self.open = None


def ppo_update(agent: Agent, opt, batch: list[dict], args) -> float:
    """GAE over the agent's own closed transitions, then clipped PPO. They are in time
    order and each one not done is followed by the next (the last by the open one, whose
    value is its ``next_value``)."""
    rew = torch.tensor([t["reward"] for t in batch])
    val = torch.tensor([t["value"] for t in batch])
    nxt = torch.tensor([t["next_value"] for t in batch])
    done = torch.tensor([float(t["done"]) for t in batch])
    adv = torch.zeros(len(batch))
    last = 0.0
    for i in reversed(range(len(batch))):
        delta = rew[i] + args.gamma * nxt[i] - val[i]
        last = delta + args.gamma * args.gae_lambda * (1.0 - done[i]) * last
        adv[i] = last
    ret = adv + val
    obs = torch.stack([t["obs"] for t in batch])
    mask = torch.stack([t["mask"] for t in batch])
    act = torch.tensor([t["action"] for t in batch])
    old_logp = torch.tensor([t["logp"] for t in batch])
    loss_sum, n = 0.0, 0
    for _ in range(args.update_epochs):
        for idx in torch.randperm(len(batch)).split(args.minibatch_size):
            _, logp, ent, v = agent.act(obs[idx], mask[idx], act[idx])
            a = adv[idx]
            if len(idx) > 1:
                a = (a - a.mean()) / (a.std() + 1e-8)
            ratio = (logp - old_logp[idx]).exp()
            pg = torch.max(-a * ratio, -a * ratio.clamp(1 - args.clip_coef, 1 + args.clip_coef)).mean()
            loss = pg + args.vf_coef * 0.5 * ((v - ret[idx]) ** 2).mean() - args.ent_coef * ent.mean()
            opt.zero_grad()
            loss.backward()
            nn.utils.clip_grad_norm_(agent.parameters(), args.max_grad_norm)
            opt.step()
            loss_sum, n = loss_sum + loss.item(), n + 1
    return loss_sum / max(n, 1)


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    for name, default in DEFAULTS.items():
        p.add_argument("--" + name.replace("_", "-"), type=type(default), default=default)
    args = p.parse_args(argv)
    torch.manual_seed(args.seed)

    env = make_env(args)
    agents = {a: Agent(int(np.prod(env.observation_space(a).shape)), int(env.action_space(a).n))
              for a in env.possible_agents}
    opts = {a: torch.optim.Adam(m.parameters(), lr=args.lr, eps=1e-5) for a, m in agents.items()}
    memory = {a: Transitions() for a in env.possible_agents}
    raw_total = dict.fromkeys(env.possible_agents, 0.0)  # every reward the env gave, for the check
    obs, infos = env.reset(seed=args.seed)
    episode_return = dict.fromkeys(env.possible_agents, 0.0)
    returns, lines, steps, start = [], [], 0, time.time()
    while steps < args.total_steps:
        for _ in range(min(args.num_steps, args.total_steps - steps)):
            actions, chosen = {}, {}
            with torch.no_grad():
                for a in env.agents:
                    x = torch.as_tensor(obs[a], dtype=torch.float32).reshape(-1)
                    m = infos[a].get("action_mask")
                    m = torch.ones(env.action_space(a).n, dtype=torch.bool) if m is None else torch.as_tensor(m) > 0
                    act, logp, _, v = agents[a].act(x[None], m[None])
                    actions[a] = int(act)
                    chosen[a] = (x, m, int(act), float(logp), float(v))
            obs, rewards, term, trunc, infos = env.step(actions)
            steps += 1
            for a in chosen:
                raw_total[a] += rewards[a]
                episode_return[a] += rewards[a]
                if infos[a].get("acting", True):
                    memory[a].start(*chosen[a], reward=rewards[a])
                else:
                    memory[a].credit(rewards[a])
            if not env.agents:  # the episode ended: close every agent's open transition
                with torch.no_grad():
                    for a in chosen:
                        last = torch.as_tensor(obs[a], dtype=torch.float32).reshape(1, -1)
                        memory[a].end_episode(0.0 if term[a] else float(agents[a].value(last)))
                returns.append(dict(episode_return))
                episode_return = dict.fromkeys(env.possible_agents, 0.0)
                obs, infos = env.reset()
        losses = {}
        for a, mem in memory.items():
            if mem.closed:
                losses[a] = ppo_update(agents[a], opts[a], mem.closed, args)
            losses.setdefault(a, float("nan"))
        kept = {a: len(mem.closed) for a, mem in memory.items()}
        for mem in memory.values():
            mem.closed = []
        recent = returns[-20:]
        mean = {a: float(np.mean([r[a] for r in recent])) if recent else float("nan") for a in env.possible_agents}
        line = (f"{steps} steps, {len(returns)} episodes, transitions kept planner {kept['planner']} executor "
                f"{kept['executor']}, mean return planner {mean['planner']:.2f} executor {mean['executor']:.2f} "
                f"({time.time() - start:.0f} s)")
        print(line)
        lines.append(line)
    env.close()
    return {"steps": steps, "episodes": len(returns), "lines": lines, "agents": agents, "raw_total": raw_total,
            "kept_total": {a: mem.reward_total for a, mem in memory.items()}}


if __name__ == "__main__":
    main()
