"""Train ``plex_nav_v0.compat_env`` with TorchRL's multi-agent PPO (one PPO per agent).

    pip install torchrl           # tested with torchrl 0.14.0, tensordict 0.14.3; not a dependency of plex-ma
    python examples/train_torchrl.py --iterations 20

TorchRL's ``PettingZooWrapper(env, use_mask=True)`` turns the AEC env into a TorchRL env
with one group per agent (``"planner"``, ``"executor"``). Every step's TensorDict holds,
per group, the agent's ``observation``, its ``action_mask``, a ``mask`` that is True for
the agent whose turn it is, the ``reward`` it earned in that step, its done flags and
its ``info`` (the env's numeric infos: ``success``, ``spl``, ``distance_to_goal``, ...).
Each step both policies propose an action; the wrapper applies the acting agent's.
The compat env gives each agent a flat Box observation and its own ``Discrete`` actions
(the planner's 33, the executor's 4) with an ``action_mask``, which ``MaskedCategorical``
applies (it forbids something only with ``pad=True``, where the executor's 4-32 are
masked). The
native ``plex_nav_v0.env()`` wraps too (its Dict spaces become composite specs), but
its Dict actions (a stop flag with a continuous sub-goal; an action with a 128-float
ELI) would need a composite distribution; this example keeps to the compat env.

Crediting each agent with all of its rewards
--------------------------------------------
The wrapper's ``reward`` of a group at a step is ``env.rewards[agent]``: what the agent
earned in that one AEC step, not what ``last()`` would give it. In PLEX the planner earns
nearly all of its reward (progress towards the goal, slack, collisions) during the
*executor's* steps, where the planner's ``mask`` is False. TorchRL's GAE and
``ClipPPOLoss`` would treat each step as one transition of each agent; read that way the
planner's action would be credited only with the +10 of its own successful stop.

:func:`agent_transitions` therefore rebuilds each agent's own transitions from a collected
batch before the update. For agent X acting at steps t_1 < t_2 < ... of one env, the
transition of t_k carries X's rewards summed over steps t_k .. t_(k+1) - 1: exactly what
``last()`` hands X at its next turn (PettingZoo's ``_cumulative_rewards``), credited to the
action that earned it. Its next state is X's observation at t_(k+1). If the episode ends
first (a planner stop also ends the executor's episode), the transition ends there:
terminated (value 0) or truncated (bootstrapped with the value of X's last observation).
If the batch ends first, it is cut and bootstrapped with the value of X's observation at
the batch's last step; the collector does not reset between batches, and the rewards
before X's first action in the next batch are the ones that bootstrap stands for. GAE
then runs over each agent's own transitions, as in a single-agent env, and each agent's
``ClipPPOLoss`` sees only its own transitions. ``test_credit`` in
``tests/test_torchrl.py`` checks the sums.

Networks: per agent, a small CNN over its 32x32 image part of the observation (the
planner's ego map, the executor's RGB-D) joined with its polar goal vector (distance/10,
cos, sin of the direction), a 128-unit layer, then logits (actor) or a value (critic).
The ELI channel is off in the compat env.
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np

from plex_ma.envs import plex_nav_v0
from plex_ma.envs.spaces import EGO_CHANNELS, EGO_SIZE
import torch
from torch import nn

try:
    from tensordict import TensorDict
    from tensordict.nn import TensorDictModule, TensorDictSequential
    from torchrl.collectors import Collector
    from torchrl.envs import SerialEnv
    from torchrl.envs.libs.pettingzoo import PettingZooWrapper
    from torchrl.modules import MaskedCategorical, ProbabilisticActor, ValueOperator
    from torchrl.objectives import ClipPPOLoss
except ImportError as e:  # pragma: no cover - the message is the point
    raise SystemExit(f"this example needs TorchRL: pip install torchrl ({e})") from None

AGENTS = ("planner", "executor")
OBS = ("observation", "observation")  # the flat vector, under each group (the mask is moved beside it)


# ---------------------------------------------------------------- env
def make_env(config: dict, seed: int = 0) -> PettingZooWrapper:
    """``compat_env(**config)`` in TorchRL's PettingZoo wrapper (one group per agent)."""
    with warnings.catch_warnings():  # "tested with PettingZoo 1.24.3": it works with later ones
        warnings.filterwarnings("ignore", message="PettingZoo in TorchRL is tested")
        return PettingZooWrapper(env=plex_nav_v0.compat_env(**config), use_mask=True, seed=seed)


# ---------------------------------------------------------------- networks
class Encoder(nn.Module):
    """The agent's own part of the flat compat observation -> 128 features (any leading dims)."""

    def __init__(self, agent: str, image_size: int = 32):
        super().__init__()
        self.channels = EGO_CHANNELS if agent == "planner" else 4
        self.size = EGO_SIZE if agent == "planner" else image_size
        self.vec_at = 2 + self.channels * self.size * self.size
        self.conv = nn.Sequential(nn.Conv2d(self.channels, 16, 4, stride=2), nn.ReLU(),
                                  nn.Conv2d(16, 32, 3, stride=2), nn.ReLU(), nn.Flatten())
        with torch.no_grad():
            n = self.conv(torch.zeros(1, self.channels, self.size, self.size)).shape[1]
        self.fc = nn.Sequential(nn.Linear(n + 3, 128), nn.ReLU())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        lead = x.shape[:-1]
        x = x.reshape(-1, x.shape[-1])
        img = x[:, 2:self.vec_at].reshape(-1, self.channels, self.size, self.size)
        v = x[:, self.vec_at:self.vec_at + 2]
        vec = torch.stack([v[:, 0] / 10.0, torch.cos(v[:, 1]), torch.sin(v[:, 1])], 1)
        return self.fc(torch.cat([self.conv(img), vec], 1)).reshape(*lead, 128)


def build(env: PettingZooWrapper, lr: float = 3e-4, image_size: int = 32) -> dict:
    """Per agent: a masked-categorical actor, a critic, their ClipPPOLoss and optimiser;
    plus ``policy``, both actors in sequence (what the collector runs)."""
    parts = {}
    for g in AGENTS:
        n = env.full_action_spec[g, "action"].space.n
        logits = TensorDictModule(nn.Sequential(Encoder(g, image_size), nn.Linear(128, n)),
                                  in_keys=[(g, *OBS)], out_keys=[(g, "logits")])
        actor = ProbabilisticActor(logits, in_keys={"logits": (g, "logits"), "mask": (g, "action_mask")},
                                   out_keys=[(g, "action")], spec=env.full_action_spec[g, "action"],
                                   distribution_class=MaskedCategorical, return_log_prob=True)
        critic = ValueOperator(nn.Sequential(Encoder(g, image_size), nn.Linear(128, 1)),
                               in_keys=[(g, *OBS)], out_keys=[(g, "state_value")])
        # The planner gets a larger entropy bonus: stopping at once is a tempting early
        # optimum (return 0 against the slack of a poor executor).
        loss = ClipPPOLoss(actor, critic, clip_epsilon=0.2, entropy_coeff=0.05 if g == "planner" else 0.01,
                           critic_coeff=0.5, normalize_advantage=False)
        loss.set_keys(action=(g, "action"), sample_log_prob=(g, "action_log_prob"), value=(g, "state_value"),
                      advantage=(g, "advantage"), value_target=(g, "value_target"))
        parts[g] = {"actor": actor, "critic": critic, "loss": loss,
                    "optim": torch.optim.Adam(loss.parameters(), lr=lr)}
    parts["policy"] = TensorDictSequential(*(parts[g]["actor"] for g in AGENTS))
    return parts


# ---------------------------------------------------------------- reward credit
def agent_transitions(batch: TensorDict, agent: str, critic=None, gamma: float = 0.99,
                      lam: float = 0.95) -> TensorDict:
    """The transitions of ``agent`` in a collected ``batch`` ([T] or [envs, T]), each with
    all of its rewards until the agent's next turn (see the module docstring).

    Returns a TensorDict of shape [M] (M = the agent's acting steps) with the agent's group
    entries at those steps (observation, action_mask, action, action_log_prob) and
    ``reward`` (the credited sum), ``done`` / ``terminated`` (the transition ends the
    agent's chain), ``step`` (index of the step in its env's row); with a ``critic``, also
    the group's ``advantage`` and ``value_target`` (GAE over the agent's own transitions).
    """
    rows = batch.reshape(-1, batch.shape[-1]) if batch.ndim > 1 else batch.unsqueeze(0)
    out = []
    for row in rows:
        out.append(_row_transitions(row, agent, critic, gamma, lam))
    return torch.cat(out, 0)


def _row_transitions(row: TensorDict, g: str, critic, gamma: float, lam: float) -> TensorDict:
    acting = row[g, "mask"][:, 0].numpy()
    rew = row["next", g, "reward"][:, 0, 0].double().numpy()
    term = row["next", g, "terminated"][:, 0, 0].numpy()
    trunc = row["next", g, "truncated"][:, 0, 0].numpy()
    steps = np.flatnonzero(acting)
    t_end = len(acting)
    m = len(steps)
    reward = np.zeros(m)
    terminated = np.zeros(m, bool)
    chain_ends = np.zeros(m, bool)  # the next transition is not this one's successor
    boot_at = np.full(m, -1)  # bootstrap from the agent's "next" observation at this step
    for k, t in enumerate(steps):
        nxt = steps[k + 1] if k + 1 < m else t_end
        ended = np.flatnonzero(term[t:nxt] | trunc[t:nxt])
        last = t + ended[0] if len(ended) else nxt - 1
        reward[k] = rew[t:last + 1].sum()
        if len(ended):
            chain_ends[k] = True
            terminated[k] = bool(term[last])
            if not terminated[k]:
                boot_at[k] = last
        elif k + 1 == m:  # the batch ends before the agent acts again
            chain_ends[k] = True
            boot_at[k] = last
    idx = torch.as_tensor(steps)
    own = row[g][idx].select("observation", "action_mask", "action", "action_log_prob")
    td = TensorDict({g: own, "reward": torch.as_tensor(reward, dtype=torch.float32).unsqueeze(-1),
                     "done": torch.as_tensor(chain_ends).unsqueeze(-1),
                     "terminated": torch.as_tensor(terminated).unsqueeze(-1),
                     "step": idx}, batch_size=[m])
    if critic is not None:
        value, boot_value = np.zeros(m), np.zeros(m)
        booted = np.flatnonzero(boot_at >= 0)
        with torch.no_grad():
            if m:
                v = critic(TensorDict({g: row[g][idx].select("observation")}, [m]))[g, "state_value"]
                value = v.reshape(m).double().numpy()
            if len(booted):
                obs = row["next", g][torch.as_tensor(boot_at[booted])].select("observation")
                bv = critic(TensorDict({g: obs}, [len(booted)]))[g, "state_value"]
                boot_value[booted] = bv.reshape(-1).double().numpy()
        next_value = np.where(chain_ends, boot_value, np.r_[value[1:], 0.0])
        next_value[terminated] = 0.0
        adv = np.zeros(m)
        running = 0.0
        for k in range(m - 1, -1, -1):
            delta = reward[k] + gamma * next_value[k] - value[k]
            running = delta + gamma * lam * (0.0 if chain_ends[k] else running)
            adv[k] = running
        # shaped like the group's state_value: [M, 1 agent, 1]
        td[g, "advantage"] = torch.as_tensor(adv, dtype=torch.float32).reshape(m, 1, 1)
        td[g, "value_target"] = torch.as_tensor(adv + value, dtype=torch.float32).reshape(m, 1, 1)
    return td


# ---------------------------------------------------------------- training
def episode_stats(batch: TensorDict) -> list[dict]:
    """One record per episode that ended in ``batch``: both agents' returns over the part of
    the episode inside the batch, success (from the env's infos) and length in AEC steps."""
    rows = batch.reshape(-1, batch.shape[-1]) if batch.ndim > 1 else batch.unsqueeze(0)
    out = []
    for row in rows:
        done = row["next", "done"].reshape(-1).numpy()
        rew = {g: row["next", g, "reward"].reshape(-1).numpy() for g in AGENTS}
        success = row["next", "planner", "info", "success"].reshape(-1).numpy()
        start = 0
        for t in np.flatnonzero(done):
            out.append({**{g: float(rew[g][start:t + 1].sum()) for g in AGENTS},
                        "success": float(success[t]), "length": int(t + 1 - start)})
            start = t + 1
    return out


def update(parts: dict, batch: TensorDict, epochs: int = 4, minibatch: int = 256, gamma: float = 0.99,
           lam: float = 0.95) -> dict:
    """PPO on each agent's own credited transitions; returns the last losses per agent."""
    logs = {}
    for g in AGENTS:
        p = parts[g]
        data = agent_transitions(batch, g, p["critic"], gamma, lam)
        if len(data) == 0:
            continue
        for _ in range(epochs):
            for idx in torch.randperm(len(data)).split(minibatch):
                out = p["loss"](data[idx])
                loss = out["loss_objective"] + out["loss_critic"] + out["loss_entropy"]
                p["optim"].zero_grad()
                loss.backward()
                nn.utils.clip_grad_norm_(p["loss"].parameters(), 0.5)
                p["optim"].step()
        logs[g] = {"loss": loss.item(), "transitions": len(data)}
    return logs


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--iterations", type=int, default=20, help="collect-then-update rounds")
    p.add_argument("--frames-per-batch", type=int, default=1000, help="AEC steps collected per update")
    p.add_argument("--num-envs", type=int, default=1, help="envs stepped in series by the collector")
    p.add_argument("--epochs", type=int, default=4, help="PPO passes over each batch")
    p.add_argument("--resolution", type=int, default=64)
    p.add_argument("--num-scenes", type=int, default=8)
    p.add_argument("--max-steps", type=int, default=150, help="executor actions per episode")
    p.add_argument("--lr", type=float, default=3e-4)
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args(argv)
    torch.manual_seed(a.seed)
    config = dict(resolution=a.resolution, num_scenes=a.num_scenes, max_steps=a.max_steps)
    if a.num_envs == 1:
        env = make_env(config, a.seed)
    else:
        env = SerialEnv(a.num_envs, [lambda i=i: make_env(config, a.seed + i) for i in range(a.num_envs)])
    env.reset()
    # Small batches run fastest on one thread. Set after the envs' first step: on numba's OpenMP
    # layer (NUMBA_THREADING_LAYER=omp) the kernels' pool, shared with torch, resets the count.
    torch.set_num_threads(1)
    parts = build(env if a.num_envs == 1 else make_env(config), a.lr)
    # The policies have no memory: no InitTracker transform needed.
    collector = Collector(env, parts["policy"], frames_per_batch=a.frames_per_batch,
                          total_frames=a.frames_per_batch * a.iterations, auto_register_policy_transforms=False)
    t0 = time.time()
    history, frames = [], 0
    for it, batch in enumerate(collector):
        frames += batch.numel()
        logs = update(parts, batch, epochs=a.epochs)
        done = episode_stats(batch)
        history.append({"frames": frames, "episodes": done, "losses": logs})
        msg = f"iteration {it + 1}: {frames} AEC steps"
        if done:
            msg += (f", {len(done)} episodes, mean return planner {np.mean([d['planner'] for d in done]):+.2f} "
                    f"executor {np.mean([d['executor'] for d in done]):+.2f}, "
                    f"success {np.mean([d['success'] for d in done]):.2f}")
        print(msg, flush=True)
    collector.shutdown()
    seconds = time.time() - t0
    print(f"{frames} AEC steps in {seconds:.0f} s ({frames / seconds:.0f} steps/s)")
    return {"env_steps": frames, "seconds": seconds, "history": history, "parts": parts}


if __name__ == "__main__":
    main()
