"""PPO on the flat PointNav task, CleanRL style, over ``gymnasium.make_vec``.

    python examples/train_cleanrl_vector.py --total-timesteps 200000
    python examples/train_cleanrl_vector.py --help          # every option (the Args dataclass)

One file that reads top to bottom, after CleanRL's ``ppo.py``: the settings in a dataclass
parsed by tyro, ``gymnasium.make_vec("plex_ma/PointNav-v0", num_envs=N,
vectorization_mode="vector_entry_point", ...)`` (all N worlds stepped in one call of the
batched simulator), gymnasium's ``RecordEpisodeStatistics``, an actor-critic CNN over
RGB-D and the goal vector, rollouts, GAE and the clipped PPO update.

Autoreset: the env follows gymnasium's NEXT_STEP mode. The step after a world's episode
ends does not apply that world's action: it returns the next episode's first observation
with reward 0. The script marks those steps (``valid`` is False) and leaves them out of
the update; their observation, the ended episode's last one, gives the value that
bootstraps a truncated episode (see :func:`compute_advantages`).
"""

from __future__ import annotations

import random
import time
from dataclasses import dataclass

import gymnasium
import numpy as np

import plex_ma  # noqa: F401  (registers plex_ma/PointNav-v0)
import torch
import tyro
from torch import nn
from torch.distributions import Categorical


@dataclass
class Args:
    seed: int = 1
    """seed of the env, torch and numpy"""
    torch_deterministic: bool = True
    """torch.backends.cudnn.deterministic"""
    cuda: bool = True
    """use CUDA when it is available"""

    # the environment
    num_envs: int = 16
    """worlds stepped together by the batched simulator"""
    resolution: int = 64
    """square RGB-D image size (>= 40 for this CNN)"""
    num_scenes: int | None = None
    """training scenes (None: all of the source's)"""
    max_steps: int = 500
    """actions before an episode truncates"""

    # PPO
    total_timesteps: int = 200_000
    """environment steps in all (over all worlds)"""
    learning_rate: float = 2.5e-4
    num_steps: int = 128
    """steps per world per rollout"""
    anneal_lr: bool = True
    gamma: float = 0.99
    gae_lambda: float = 0.95
    num_minibatches: int = 4
    update_epochs: int = 4
    norm_adv: bool = True
    clip_coef: float = 0.2
    clip_vloss: bool = True
    ent_coef: float = 0.01
    vf_coef: float = 0.5
    max_grad_norm: float = 0.5
    target_kl: float | None = None


def layer_init(layer, std=np.sqrt(2), bias_const=0.0):
    torch.nn.init.orthogonal_(layer.weight, std)
    torch.nn.init.constant_(layer.bias, bias_const)
    return layer


class Agent(nn.Module):
    """A CNN over RGB-D (channels first, RGB scaled to [0, 1]) joined with the goal vector
    as (distance / 10, cos, sin of the direction); a shared 256-unit layer, then the
    policy's 4 logits and the value."""

    def __init__(self, resolution: int):
        super().__init__()
        self.cnn = nn.Sequential(
            layer_init(nn.Conv2d(4, 32, 8, stride=4)), nn.ReLU(),
            layer_init(nn.Conv2d(32, 64, 4, stride=2)), nn.ReLU(),
            layer_init(nn.Conv2d(64, 64, 3, stride=1)), nn.ReLU(),
            nn.Flatten(),
        )
        with torch.no_grad():
            n_flat = self.cnn(torch.zeros(1, 4, resolution, resolution)).shape[1]
        self.body = nn.Sequential(layer_init(nn.Linear(n_flat + 3, 256)), nn.ReLU())
        self.actor = layer_init(nn.Linear(256, 4), std=0.01)
        self.critic = layer_init(nn.Linear(256, 1), std=1.0)

    def features(self, rgb, depth, pointgoal):
        x = torch.cat([rgb.float() / 255.0, depth], dim=-1).permute(0, 3, 1, 2)
        goal = torch.stack([pointgoal[:, 0] / 10.0, torch.cos(pointgoal[:, 1]), torch.sin(pointgoal[:, 1])], 1)
        return self.body(torch.cat([self.cnn(x), goal], 1))

    def get_value(self, obs):
        return self.critic(self.features(**obs))

    def get_action_and_value(self, obs, action=None):
        h = self.features(**obs)
        dist = Categorical(logits=self.actor(h))
        if action is None:
            action = dist.sample()
        return action, dist.log_prob(action), dist.entropy(), self.critic(h)


def compute_advantages(rewards, values, terminations, truncations, next_value, gamma, gae_lambda):
    """GAE over a NEXT_STEP rollout, (T, N) tensors; ``next_value`` (N,) is the value of the
    observation after the last step.

    The value that follows step t is ``values[t + 1]`` (``next_value`` at the end): after a
    step that ended an episode it is the value of that episode's last observation, which
    bootstraps a truncation; a termination takes no bootstrap. The recursion stops at
    every episode end, so a reset step (invalid, left out of the update) adds nothing to
    the step before it."""
    T = rewards.shape[0]
    advantages = torch.zeros_like(rewards)
    lastgaelam = torch.zeros_like(next_value)
    for t in reversed(range(T)):
        following = next_value if t == T - 1 else values[t + 1]
        delta = rewards[t] + gamma * following * (1.0 - terminations[t]) - values[t]
        going_on = 1.0 - torch.maximum(terminations[t], truncations[t])
        lastgaelam = delta + gamma * gae_lambda * going_on * lastgaelam
        advantages[t] = lastgaelam
    return advantages


if __name__ == "__main__":
    args = tyro.cli(Args)
    batch_size = args.num_envs * args.num_steps
    num_iterations = max(1, args.total_timesteps // batch_size)

    random.seed(args.seed)
    np.random.seed(args.seed)
    torch.manual_seed(args.seed)
    torch.backends.cudnn.deterministic = args.torch_deterministic
    device = torch.device("cuda" if torch.cuda.is_available() and args.cuda else "cpu")

    # The env: N worlds of the batched simulator behind gymnasium's vector API.
    envs = gymnasium.make_vec("plex_ma/PointNav-v0", num_envs=args.num_envs, vectorization_mode="vector_entry_point",
                              resolution=args.resolution, num_scenes=args.num_scenes, max_steps=args.max_steps)
    envs = gymnasium.wrappers.vector.RecordEpisodeStatistics(envs)
    assert isinstance(envs.single_action_space, gymnasium.spaces.Discrete), "only discrete actions are supported"
    assert envs.metadata["autoreset_mode"] == gymnasium.vector.AutoresetMode.NEXT_STEP

    agent = Agent(args.resolution).to(device)
    optimizer = torch.optim.Adam(agent.parameters(), lr=args.learning_rate, eps=1e-5)

    # Rollout storage, (T, N, ...).
    T, N = args.num_steps, args.num_envs
    obs = {k: torch.zeros((T, N) + s.shape, dtype=torch.uint8 if k == "rgb" else torch.float32, device=device)
           for k, s in envs.single_observation_space.spaces.items()}
    actions = torch.zeros((T, N), dtype=torch.long, device=device)
    logprobs = torch.zeros((T, N), device=device)
    rewards = torch.zeros((T, N), device=device)
    terminations = torch.zeros((T, N), device=device)
    truncations = torch.zeros((T, N), device=device)
    values = torch.zeros((T, N), device=device)
    valid = torch.zeros((T, N), dtype=torch.bool, device=device)

    def to_torch(o: dict) -> dict:
        return {k: torch.as_tensor(v, device=device) for k, v in o.items()}

    global_step = 0
    start_time = time.time()
    next_obs, _ = envs.reset(seed=args.seed)
    next_obs = to_torch(next_obs)
    next_autoreset = torch.zeros(N, dtype=torch.bool, device=device)

    for iteration in range(1, num_iterations + 1):
        if args.anneal_lr:
            optimizer.param_groups[0]["lr"] = (1.0 - (iteration - 1.0) / num_iterations) * args.learning_rate

        returns, successes, spls = [], [], []
        for step in range(T):
            global_step += N
            for k in obs:
                obs[k][step] = next_obs[k]
            valid[step] = ~next_autoreset  # False: this step resets the world and ignores its action
            with torch.no_grad():
                action, logprob, _, value = agent.get_action_and_value(next_obs)
            actions[step], logprobs[step], values[step] = action, logprob, value.flatten()

            o, reward, term, trunc, infos = envs.step(action.cpu().numpy())
            next_obs = to_torch(o)
            rewards[step] = torch.as_tensor(reward, dtype=torch.float32, device=device)
            terminations[step] = torch.as_tensor(term, dtype=torch.float32, device=device)
            truncations[step] = torch.as_tensor(trunc, dtype=torch.float32, device=device)
            next_autoreset = torch.as_tensor(term | trunc, device=device)
            if "episode" in infos:  # RecordEpisodeStatistics: the episodes that ended in this step
                done = infos["_episode"]
                returns += infos["episode"]["r"][done].tolist()
                successes += infos["success"][done].tolist()
                spls += infos["spl"][done].tolist()

        with torch.no_grad():
            next_value = agent.get_value(next_obs).flatten()
            advantages = compute_advantages(rewards, values, terminations, truncations, next_value,
                                            args.gamma, args.gae_lambda)
            returns_t = advantages + values

        # Flatten the batch and keep the steps whose action the env applied.
        keep = valid.reshape(-1)
        b_obs = {k: v.reshape((-1,) + v.shape[2:])[keep] for k, v in obs.items()}
        b_actions = actions.reshape(-1)[keep]
        b_logprobs = logprobs.reshape(-1)[keep]
        b_advantages = advantages.reshape(-1)[keep]
        b_returns = returns_t.reshape(-1)[keep]
        b_values = values.reshape(-1)[keep]
        n_valid = int(keep.sum())
        minibatch_size = max(1, n_valid // args.num_minibatches)

        clipfracs = []
        for epoch in range(args.update_epochs):
            b_inds = torch.randperm(n_valid, device=device)
            for start in range(0, n_valid, minibatch_size):
                mb = b_inds[start:start + minibatch_size]
                _, newlogprob, entropy, newvalue = agent.get_action_and_value(
                    {k: v[mb] for k, v in b_obs.items()}, b_actions[mb])
                logratio = newlogprob - b_logprobs[mb]
                ratio = logratio.exp()
                with torch.no_grad():
                    approx_kl = ((ratio - 1) - logratio).mean()
                    clipfracs.append(((ratio - 1.0).abs() > args.clip_coef).float().mean().item())

                mb_advantages = b_advantages[mb]
                if args.norm_adv and len(mb) > 1:
                    mb_advantages = (mb_advantages - mb_advantages.mean()) / (mb_advantages.std() + 1e-8)

                pg_loss = torch.max(-mb_advantages * ratio,
                                    -mb_advantages * torch.clamp(ratio, 1 - args.clip_coef, 1 + args.clip_coef)).mean()
                newvalue = newvalue.view(-1)
                if args.clip_vloss:
                    v_unclipped = (newvalue - b_returns[mb]) ** 2
                    v_clipped = b_values[mb] + torch.clamp(newvalue - b_values[mb], -args.clip_coef, args.clip_coef)
                    v_loss = 0.5 * torch.max(v_unclipped, (v_clipped - b_returns[mb]) ** 2).mean()
                else:
                    v_loss = 0.5 * ((newvalue - b_returns[mb]) ** 2).mean()
                loss = pg_loss - args.ent_coef * entropy.mean() + v_loss * args.vf_coef

                optimizer.zero_grad()
                loss.backward()
                nn.utils.clip_grad_norm_(agent.parameters(), args.max_grad_norm)
                optimizer.step()
            if args.target_kl is not None and approx_kl > args.target_kl:
                break

        sps = int(global_step / (time.time() - start_time))
        mean = (lambda xs: f"{np.mean(xs):.3f}" if xs else "n/a")
        print(f"iteration {iteration}/{num_iterations} global_step={global_step} SPS={sps} "
              f"episodes={len(returns)} return={mean(returns)} success={mean(successes)} spl={mean(spls)} "
              f"loss={loss.item():.4f} value_loss={v_loss.item():.4f} entropy={entropy.mean().item():.3f} "
              f"approx_kl={approx_kl.item():.4f} clipfrac={np.mean(clipfracs):.3f}", flush=True)

    envs.close()
