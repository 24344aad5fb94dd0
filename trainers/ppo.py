"""Generic PPO pieces shared by the PLEX and flat trainers (Schulman et al. 2017).

- ``compute_gae``: GAE(lambda) over (T, B) arrays with terminations and truncations.
- ``RolloutBuffer``: (T, B) storage of one rollout. Recurrent policies (executor, flat)
  set ``initial_state`` and get minibatches of whole env columns, so every sequence keeps
  its order, its ``starts`` and the memory it began with (as CleanRL's ppo_atari_lstm and
  habitat-lab do). Non-recurrent policies get minibatches of shuffled single transitions.
- ``Transitions``: a batch of single transitions whose returns are computed, for a
  non-recurrent policy whose transitions do not come in (T, B) rollouts (the planner: one
  transition per decision, see ``decisions.py``).
- ``ppo_loss`` / ``ppo_update``: clipped surrogate, (optionally clipped) value loss,
  entropy bonus, advantage normalisation per minibatch, gradient-norm clipping, and an
  optional early end of the epochs once the policy has moved far enough (``target_kl``).

A policy plugs in through one of two methods (see ``evaluate``):
``evaluate_sequences(obs (T, B, ...), actions (T, B), starts (T, B), initial_state)`` for
recurrent policies, or ``evaluate_actions(obs (N, ...), **actions)`` for the others; both
return (log_prob, entropy, value) with the batch shape of their input.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator

import torch
from torch import nn

from plex_ma.networks.common import as_tensor

from . import distributed as _dist

Tensors = torch.Tensor | dict[str, torch.Tensor]


@dataclass
class PPOConfig:
    """Update settings; defaults follow habitat's PointNav PPO (SPEC 6)."""

    clip_coef: float = 0.2
    vf_coef: float = 0.5
    ent_coef: float = 0.01
    clip_vloss: bool = True  # habitat's use_clipped_value_loss
    max_grad_norm: float = 0.5
    update_epochs: int = 4
    num_minibatches: int = 2
    norm_adv: bool = True
    target_kl: float | None = None  # end the epochs after one whose mean approx KL exceeds this (CleanRL's)


def compute_gae(rewards, values, dones, truncated, bootstrap_values, gamma, lam: float):
    """GAE(lambda) advantages and returns, each (T, B) float32.

    Convention, for step t of env b (all inputs (T, B), arrays or tensors):
    - ``values[t]`` = V(o_t), the value of the observation the action was taken in;
      ``rewards[t]`` = the reward that action got.
    - ``dones[t]``: the episode (or sequence) ended with this step, so step t + 1 belongs
      to a new one and nothing flows back across the boundary.
    - ``truncated[t]``: it ended by a cut-off (time limit), not a terminal state: the
      target bootstraps from ``bootstrap_values[t]`` = V(final observation after step t).
      A truncated step counts as done whether or not ``dones`` says so.
    - A terminated step (done, not truncated) bootstraps from 0.
    - The last row (t = T - 1) that is not done bootstraps from ``bootstrap_values[T-1]``
      = V(o_T), the observation after the rollout.
    ``bootstrap_values`` is only read at truncated steps and in the last row.
    ``gamma`` is a number or (T, B): each step's own discount (a planner decision that
    lasted k executor steps is discounted by gamma_step^k).

    delta_t = r_t + gamma * V_next_t - V(o_t);  A_t = delta_t + gamma * lam * (1 - done_t) * A_{t+1};
    returns = A + values.
    """
    rewards, values, bootstrap_values = (as_tensor(x, dtype=torch.float32) for x in (rewards, values, bootstrap_values))
    truncated = as_tensor(truncated, dtype=torch.bool)
    ended = as_tensor(dones, dtype=torch.bool) | truncated
    next_values = torch.cat([values[1:], bootstrap_values[-1:]], dim=0)
    next_values = torch.where(truncated, bootstrap_values, torch.where(ended, 0.0, next_values))
    scalar = isinstance(gamma, (int, float))
    gamma = float(gamma) if scalar else as_tensor(gamma, dtype=torch.float32).expand_as(values)
    deltas = rewards + gamma * next_values - values
    not_ended = (~ended).float()
    advantages = torch.zeros_like(values)
    last = torch.zeros_like(values[0])
    for t in reversed(range(values.shape[0])):
        g = gamma if scalar else gamma[t]
        last = deltas[t] + g * lam * not_ended[t] * last
        advantages[t] = last
    return advantages, advantages + values


@dataclass
class Minibatch:
    """Recurrent: tensors (T, b, ...) plus ``starts`` (T, b) and ``initial_state`` (b, ...).
    Non-recurrent: tensors (n, ...), ``starts`` and ``initial_state`` are None."""

    obs: dict[str, torch.Tensor]
    actions: Tensors
    log_probs: torch.Tensor
    values: torch.Tensor
    advantages: torch.Tensor
    returns: torch.Tensor
    starts: torch.Tensor | None = None
    initial_state: torch.Tensor | None = None


def _map(fn, x: Tensors) -> Tensors:
    return {k: fn(v) for k, v in x.items()} if isinstance(x, dict) else fn(x)


class Transitions(Minibatch):
    """``n`` single transitions with their advantages and returns: a non-recurrent
    :class:`Minibatch` (each tensor (n, ...)) that splits into shuffled smaller ones."""

    def minibatches(self, num_minibatches: int, generator: torch.Generator | None = None) -> Iterator[Minibatch]:
        """Shuffled minibatches covering the transitions once."""
        perm = torch.randperm(len(self.values), generator=generator).to(self.values.device)
        for idx in perm.chunk(num_minibatches):
            pick = lambda x: x[idx]  # noqa: E731
            yield Minibatch(obs=_map(pick, self.obs), actions=_map(pick, self.actions), log_probs=pick(self.log_probs),
                            values=pick(self.values), advantages=pick(self.advantages), returns=pick(self.returns))


class RolloutBuffer:
    """One rollout of ``num_steps`` x ``num_envs`` transitions, allocated on first ``add``.

    Rollout loop (recurrent policy)::

        buf.initial_state = state.clone()        # memory before step 0 (before starts[0] applies)
        for t in range(T):
            out, state = policy.act(obs, state, starts)
            ...step the envs...
            buf.add(t, obs=obs, actions=out["action"], log_probs=out["log_prob"],
                    values=out["value"], rewards=r, dones=d, truncated=tr, starts=starts,
                    bootstrap_values=v_final)     # v_final: V(final obs) where tr, else anything
        buf.compute_returns(gamma, lam, last_values=V(o_T))

    A non-recurrent policy leaves ``initial_state`` None and ``starts`` out.
    """

    def __init__(self, num_steps: int, num_envs: int, device: str | torch.device = "cpu"):
        self.num_steps, self.num_envs, self.device = num_steps, num_envs, torch.device(device)
        self.obs: dict[str, torch.Tensor] = {}
        self._actions: dict[str, torch.Tensor] = {}
        self._dict_actions = False
        self.data: dict[str, torch.Tensor] = {}
        self.initial_state: torch.Tensor | None = None

    @property
    def actions(self) -> Tensors:
        """As they were added: one tensor (T, B, ...) or a dict of them."""
        return self._actions if self._dict_actions else self._actions["action"]

    @property
    def recurrent(self) -> bool:
        return self.initial_state is not None

    @property
    def values(self) -> torch.Tensor:
        return self.data["values"]

    @property
    def returns(self) -> torch.Tensor:
        return self.data["returns"]

    def _alloc(self, x: torch.Tensor) -> torch.Tensor:
        return torch.zeros(self.num_steps, self.num_envs, *x.shape[1:], dtype=x.dtype, device=self.device)

    def _write(self, store: dict, key: str, t: int, x, dtype=None) -> None:
        x = as_tensor(x, self.device, dtype).detach()  # a stored tensor must never join a graph
        if key not in store:
            store[key] = self._alloc(x)
        store[key][t] = x

    def add(self, t: int, *, obs: dict, actions: Tensors, log_probs, values, rewards, dones,
            truncated=None, starts=None, bootstrap_values=None) -> None:
        for k, v in obs.items():
            self._write(self.obs, k, t, v)
        self._dict_actions = isinstance(actions, dict)
        for k, v in (actions if self._dict_actions else {"action": actions}).items():
            self._write(self._actions, k, t, v)
        zeros = torch.zeros(len(rewards))
        for key, x, dtype in [("log_probs", log_probs, torch.float32), ("values", values, torch.float32),
                              ("rewards", rewards, torch.float32), ("dones", dones, torch.bool),
                              ("truncated", zeros if truncated is None else truncated, torch.bool),
                              ("starts", zeros if starts is None else starts, torch.bool),
                              ("bootstrap_values", zeros if bootstrap_values is None else bootstrap_values, torch.float32)]:
            self._write(self.data, key, t, x, dtype)

    def compute_returns(self, gamma: float, lam: float, last_values=None) -> None:
        """Fill ``advantages`` and ``returns``; ``last_values`` (B,) = V(o_T) for the envs whose
        last step is not done (see ``compute_gae``)."""
        d = self.data
        if last_values is not None:
            last = as_tensor(last_values, self.device, torch.float32)
            ended = d["dones"][-1] | d["truncated"][-1]
            d["bootstrap_values"][-1] = torch.where(ended, d["bootstrap_values"][-1], last)
        d["advantages"], d["returns"] = compute_gae(d["rewards"], d["values"], d["dones"], d["truncated"],
                                                    d["bootstrap_values"], gamma, lam)

    def minibatches(self, num_minibatches: int, generator: torch.Generator | None = None) -> Iterator[Minibatch]:
        """Shuffled minibatches covering the rollout once: whole env columns if recurrent,
        single transitions otherwise."""
        d = self.data
        if "advantages" not in d:
            raise RuntimeError("call compute_returns() before minibatches()")
        if self.recurrent:
            perm = torch.randperm(self.num_envs, generator=generator).to(self.device)
            for idx in perm.chunk(num_minibatches):
                pick = lambda x: x[:, idx]  # noqa: E731
                yield Minibatch(obs=_map(pick, self.obs), actions=_map(pick, self.actions),
                                log_probs=pick(d["log_probs"]), values=pick(d["values"]),
                                advantages=pick(d["advantages"]), returns=pick(d["returns"]),
                                starts=pick(d["starts"]), initial_state=self.initial_state[idx])
        else:
            flat = lambda x: x.reshape(-1, *x.shape[2:])  # noqa: E731
            yield from Transitions(obs=_map(flat, self.obs), actions=_map(flat, self.actions),
                                   log_probs=flat(d["log_probs"]), values=flat(d["values"]),
                                   advantages=flat(d["advantages"]),
                                   returns=flat(d["returns"])).minibatches(num_minibatches, generator)


def evaluate(policy: nn.Module, mb: Minibatch):
    """(log_prob, entropy, value) of the minibatch's stored actions under ``policy``."""
    if mb.initial_state is not None:
        return policy.evaluate_sequences(mb.obs, mb.actions, mb.starts, mb.initial_state)
    if isinstance(mb.actions, dict):
        return policy.evaluate_actions(mb.obs, **mb.actions)
    return policy.evaluate_actions(mb.obs, mb.actions)


def ppo_loss(policy: nn.Module, mb: Minibatch, cfg: PPOConfig) -> tuple[torch.Tensor, dict]:
    """Total PPO loss of one minibatch and its (detached) parts."""
    new_log_probs, entropy, new_values = evaluate(policy, mb)
    log_ratio = new_log_probs - mb.log_probs
    ratio = log_ratio.exp()

    adv = mb.advantages
    if cfg.norm_adv and adv.numel() > 1:
        adv = (adv - adv.mean()) / (adv.std() + 1e-8)
    pg_loss = torch.max(-adv * ratio, -adv * ratio.clamp(1 - cfg.clip_coef, 1 + cfg.clip_coef)).mean()

    if cfg.clip_vloss:
        v_clipped = mb.values + (new_values - mb.values).clamp(-cfg.clip_coef, cfg.clip_coef)
        v_loss = 0.5 * torch.max((new_values - mb.returns) ** 2, (v_clipped - mb.returns) ** 2).mean()
    else:
        v_loss = 0.5 * ((new_values - mb.returns) ** 2).mean()

    entropy = entropy.mean()
    loss = pg_loss - cfg.ent_coef * entropy + cfg.vf_coef * v_loss
    with torch.no_grad():
        stats = {"policy_loss": pg_loss.item(), "value_loss": v_loss.item(), "entropy": entropy.item(),
                 # the low-variance KL estimator (ratio - 1) - log ratio (Schulman's blog, CleanRL)
                 "approx_kl": ((ratio - 1) - log_ratio).mean().item(),
                 "clip_fraction": ((ratio - 1).abs() > cfg.clip_coef).float().mean().item()}
    return loss, stats


def explained_variance(values: torch.Tensor, returns: torch.Tensor) -> float:
    """1 - Var(returns - values) / Var(returns); nan when the returns do not vary."""
    var = returns.var()
    return float("nan") if var == 0 else (1 - (returns - values).var() / var).item()


def ppo_update(policy: nn.Module, batch: RolloutBuffer | Transitions, optimizer: torch.optim.Optimizer,
               cfg: PPOConfig, generator: torch.Generator | None = None) -> dict:
    """``cfg.update_epochs`` epochs of minibatch PPO over a rollout whose returns are computed
    (or over ``Transitions``).
    Returns the mean over minibatch updates of policy_loss, value_loss, entropy, approx_kl,
    clip_fraction and grad_norm (before clipping), the explained variance of the rollout's
    values and the number of epochs run (fewer than ``update_epochs`` where ``target_kl``
    ended them: after the first epoch whose minibatches' mean approximate KL exceeds it, on
    any worker).

    After ``backward`` and before clipping, ``distributed.average_gradients`` averages the
    gradients over the workers (the DD-PPO all-reduce; a no-op unless distributed)."""
    sums: dict[str, float] = {}
    n = epochs = 0
    for _ in range(cfg.update_epochs):
        epochs += 1
        kl, n_epoch = 0.0, 0
        # distributed: every worker steps as often as the one with the most minibatches (None: none left here)
        for mb in _dist.common_length(batch.minibatches(cfg.num_minibatches, generator)):
            optimizer.zero_grad()
            stats = None
            if mb is not None:
                loss, stats = ppo_loss(policy, mb, cfg)
                loss.backward()
            _dist.average_gradients(policy)
            grad_norm = nn.utils.clip_grad_norm_(policy.parameters(), cfg.max_grad_norm).item()
            optimizer.step()
            if stats is None:
                continue
            stats["grad_norm"] = grad_norm
            for k, v in stats.items():
                sums[k] = sums.get(k, 0.0) + v
            n += 1
            kl += stats["approx_kl"]
            n_epoch += 1
        if cfg.target_kl is not None and _dist.any_true(kl / max(n_epoch, 1) > cfg.target_kl):
            break
    out = {k: v / max(n, 1) for k, v in sums.items()}
    out["explained_variance"] = explained_variance(batch.values, batch.returns)
    out["epochs"] = float(epochs)
    return out
