"""Train ``plex_nav_v0.compat_env`` with Tianshou's multi-agent PPO (one PPO per agent).

    pip install tianshou          # tested with tianshou 2.0.1; not a dependency of plex-ma
    python examples/train_compat_tianshou.py --epochs 20

Tianshou's ``PettingZooEnv`` wraps the AEC env for its vector envs and collector, and
``MultiAgentOnPolicyAlgorithm`` routes every transition to the PPO of the agent that
acted in it. Tianshou needs identical spaces for all agents, so the example asks the
compat env for ``pad=True``: one Box observation and one Discrete(33) action space for
both agents, and an action mask (the executor may only use actions 0-3), which the
networks below apply to their logits.

Crediting each agent with all of its rewards
--------------------------------------------
Tianshou's ``PettingZooEnv.step`` returns ``env.rewards``: what each agent earned in that
one AEC step, not what ``last()`` would give it. In PLEX the planner earns nearly all of
its reward (progress towards the goal, slack, collisions) during the *executor's* steps,
and Tianshou trains the planner only on the transitions in which the planner acted, so
read naively the planner would see almost nothing but its +10 success bonus. The
executor has the mirror problem for ``obs_next``: after its last action of a turn the next
observation Tianshou stores is the planner's.

:class:`TurnCreditPPO` fixes both before each update, on the whole collected batch: for
each transition of agent X it adds up X's column of the reward vectors from that
transition up to (not including) X's next transition in the same episode, which is
exactly the reward ``last()`` hands X at its next turn (PettingZoo's
``_cumulative_rewards``), but credited to the action that earned it; it makes X's
``obs_next`` X's own next observation, and marks the transition terminal or truncated when
the episode ended before X acted again (a planner stop ends the executor's episode too).
Then GAE runs per agent over that agent's own transitions, as it would in a
single-agent env. ``test_credit`` in ``tests/test_compat_example.py`` checks the sums.

Networks: per agent, a small CNN over its 32x32 image part of the observation (the
planner's ego map, the executor's RGB-D) joined with its polar goal vector (distance/10,
cos, sin of the direction), a 128-unit layer, then masked logits (actor) or a value
(critic). The ELI channel is off in the compat env.
"""

from __future__ import annotations

import argparse
import logging
import time

import numpy as np

from plex_ma.envs import plex_nav_v0
from plex_ma.envs.spaces import EGO_CHANNELS, EGO_SIZE
import torch
from torch import nn

try:
    from tianshou.algorithm import PPO
    from tianshou.algorithm.modelfree.reinforce import DiscreteActorPolicy
    from tianshou.algorithm.multiagent.marl import MultiAgentOnPolicyAlgorithm
    from tianshou.algorithm.optim import AdamOptimizerFactory
    from tianshou.data import Collector, VectorReplayBuffer
    from tianshou.env import DummyVectorEnv, PettingZooEnv
    from tianshou.trainer import OnPolicyTrainerParams
except ImportError as e:  # pragma: no cover - the message is the point
    raise SystemExit(f"this example needs Tianshou 2.x: pip install tianshou ({e})") from None

AGENTS = ("planner", "executor")
GOAL_DISTANCE_INDEX = 2 + EGO_CHANNELS * EGO_SIZE * EGO_SIZE  # in the planner's compat observation: one-hot id, ego map, goal


# ---------------------------------------------------------------- reward credit
def credit_turns(batch, buffer, indices: np.ndarray, agent_idx: dict) -> None:
    """Rewrite ``batch`` (= ``buffer[indices]``, whole episodes in order) in place so that
    each transition of agent X carries all of X's reward until X's next transition, X's
    own next observation, and the episode's end if it came first (see the module
    docstring)."""
    n = len(indices)
    where = {int(b): p for p, b in enumerate(indices)}
    nxt = buffer.next(indices)
    agents = np.asarray(batch.obs.agent_id)
    rew = np.asarray(batch.rew, np.float64)
    term = np.asarray(batch.terminated, bool)
    trunc = np.asarray(batch.truncated, bool)
    ended = term | trunc
    new_rew, new_term, new_trunc = rew.copy(), term.copy(), trunc.copy()
    next_from_obs = np.full(n, -1)  # obs_next[p] := obs[q] (the agent's own next observation)
    next_from_next = np.arange(n)  # obs_next[p] := obs_next[q] (the episode's last observation)
    for p in range(n):
        a = agents[p]
        col = agent_idx[a]
        total = rew[p, col]
        q = p
        while True:
            q_next = int(nxt[q])
            if ended[q] or q_next == int(indices[q]) or q_next not in where:
                # The episode ended (or the collected data stops) before X acted again.
                new_term[p] = term[q]
                new_trunc[p] = trunc[q] or not ended[q]  # data stops: cut and bootstrap there
                next_from_next[p] = q
                break
            q = where[q_next]
            if agents[q] == a:
                new_term[p] = new_trunc[p] = False
                next_from_obs[p] = q
                break
            total += rew[q, col]  # what X earned during the other agent's step
        new_rew[p, col] = total
    own = next_from_obs >= 0
    for key in batch.obs_next.get_keys():
        vals = np.array(batch.obs_next[key])
        src = np.asarray(batch.obs[key])
        vals[own] = src[next_from_obs[own]]
        vals[~own] = np.asarray(batch.obs_next[key])[next_from_next[~own]]
        batch.obs_next[key] = vals
    batch.rew = new_rew.astype(np.asarray(batch.rew).dtype)
    batch.terminated = new_term
    batch.truncated = new_trunc
    if "done" in batch.get_keys():
        batch.done = new_term | new_trunc


class TurnCreditPPO(MultiAgentOnPolicyAlgorithm):
    """One PPO per agent, with each agent's rewards credited as ``last()`` would
    (:func:`credit_turns`) before the per-agent GAE."""

    def _preprocess_batch(self, batch, buffer, indices):
        credit_turns(batch, buffer, indices, self._dispatcher.agent_idx)
        # Tianshou reads "is obs_next terminal" from the buffer, so patch it there while
        # the per-agent returns are computed (the on-policy buffer is emptied afterwards).
        saved_term = buffer.terminated[indices].copy()
        saved_rew = buffer.rew[indices].copy()
        buffer.terminated[indices] = batch.terminated
        buffer.rew[indices] = batch.rew
        try:
            return super()._preprocess_batch(batch, buffer, indices)
        finally:
            buffer.terminated[indices] = saved_term
            buffer.rew[indices] = saved_rew


# ---------------------------------------------------------------- networks
class Encoder(nn.Module):
    """The agent's own part of the flat compat observation -> 128 features."""

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
        img = x[:, 2:self.vec_at].reshape(-1, self.channels, self.size, self.size)
        v = x[:, self.vec_at:self.vec_at + 2]
        vec = torch.stack([v[:, 0] / 10.0, torch.cos(v[:, 1]), torch.sin(v[:, 1])], 1)
        return self.fc(torch.cat([self.conv(img), vec], 1))


def _obs_tensors(obs):
    x = torch.as_tensor(np.asarray(obs.obs), dtype=torch.float32)
    mask = torch.as_tensor(np.asarray(obs.mask), dtype=torch.bool)
    return x, mask


class Actor(nn.Module):
    def __init__(self, agent: str, num_actions: int, image_size: int = 32):
        super().__init__()
        self.enc = Encoder(agent, image_size)
        self.head = nn.Linear(128, num_actions)

    def forward(self, obs, state=None, info=None):
        x, mask = _obs_tensors(obs)
        logits = self.head(self.enc(x))
        return logits.masked_fill(~mask, -1e9), state  # the action mask: other agent's actions


class Critic(nn.Module):
    def __init__(self, agent: str, image_size: int = 32):
        super().__init__()
        self.enc = Encoder(agent, image_size)
        self.head = nn.Linear(128, 1)

    def forward(self, obs, **kwargs):
        x, _ = _obs_tensors(obs)
        return self.head(self.enc(x))


# ---------------------------------------------------------------- training
class LoggedPettingZooEnv(PettingZooEnv):
    """Tianshou's wrapper, plus a log of each finished episode: every agent's return (the
    sum of its per-step rewards, all of them), success and length."""

    def __init__(self, env, log: list | None = None, stop_within: float | None = None):
        self.log = log
        self.stop_within = stop_within
        self._returns = np.zeros(2)
        self._length = 0
        super().__init__(env)

    def _restrict(self, obs: dict) -> dict:
        # Optional curriculum (--stop-within): the planner may only STOP once its own
        # GPS+compass goal vector (part of its observation) says the goal is that close.
        if self.stop_within is not None and obs["agent_id"] == "planner":
            if obs["obs"][GOAL_DISTANCE_INDEX] > self.stop_within:
                obs["mask"] = [False] + list(obs["mask"][1:])
        return obs

    def reset(self, *args, **kwargs):
        self._returns[:] = 0.0
        self._length = 0
        obs, info = super().reset(*args, **kwargs)
        return self._restrict(obs), info

    def step(self, action):
        obs, rew, term, trunc, info = super().step(action)
        self._returns += [self.env.rewards.get(a, 0.0) for a in self.agents]
        self._length += 1
        if (term or trunc) and self.log is not None:
            self.log.append({"planner": self._returns[0], "executor": self._returns[1], "length": self._length,
                             "success": float(info.get("success", 0.0))})
        return self._restrict(obs), rew, term, trunc, info


def make_env(config: dict, seed: int, log: list | None = None, stop_within: float | None = None) -> PettingZooEnv:
    env = LoggedPettingZooEnv(plex_nav_v0.compat_env(pad=True, **config), log, stop_within)
    env.reset(seed=seed)
    return env


def build(config: dict, num_envs: int, seed: int, lr: float = 3e-4, log: list | None = None,
          stop_within: float | None = None):
    """The multi-agent PPO and its train and test envs; finished training episodes go to ``log``."""
    probe = make_env(config, seed)
    algorithms = []
    for agent in probe.agents:
        actor = Actor(agent, probe.action_space.n)
        policy = DiscreteActorPolicy(actor=actor, action_space=probe.action_space,
                                     observation_space=probe.observation_space)
        # No advantage normalisation: an agent may have a single transition in an update
        # (a planner that stops at once leaves the executor nothing), and the std of one
        # advantage is NaN. The planner gets a larger entropy bonus: stopping at once is a
        # tempting early optimum (return 0 against the slack of a poor executor).
        algorithms.append(PPO(policy=policy, critic=Critic(agent), optim=AdamOptimizerFactory(lr=lr),
                              gamma=0.99, gae_lambda=0.95, ent_coef=0.05 if agent == "planner" else 0.01,
                              max_grad_norm=0.5, advantage_normalization=False))
    algorithm = TurnCreditPPO(algorithms=algorithms, env=probe)
    train_envs = DummyVectorEnv([lambda i=i: make_env(config, seed + 1 + i, log, stop_within)
                                 for i in range(num_envs)])
    test_envs = DummyVectorEnv([lambda i=i: make_env(config, seed + 1000 + i, None, stop_within)
                                for i in range(num_envs)])
    return algorithm, train_envs, test_envs


def evaluate(algorithm, envs, episodes: int) -> dict:
    """Mean episode return per agent (the planner's is Table 1's episode reward)."""
    collector = Collector(algorithm, envs)
    collector.reset()
    stats = collector.collect(n_episode=episodes, reset_before_collect=True)
    returns = np.asarray(stats.returns).reshape(-1, len(AGENTS))
    return {"planner_return": float(returns[:, 0].mean()), "executor_return": float(returns[:, 1].mean()),
            "episode_length": float(np.mean(stats.lens)), "episodes": len(returns)}


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--epochs", type=int, default=20)
    p.add_argument("--steps-per-epoch", type=int, default=4000, help="AEC steps collected per epoch")
    p.add_argument("--steps-per-collect", type=int, default=1000, help="AEC steps per PPO update")
    p.add_argument("--num-envs", type=int, default=4)
    p.add_argument("--eval-episodes", type=int, default=8)
    p.add_argument("--resolution", type=int, default=64)
    p.add_argument("--num-scenes", type=int, default=8)
    p.add_argument("--max-steps", type=int, default=150, help="executor actions per episode")
    p.add_argument("--lr", type=float, default=3e-4)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--stop-within", type=float, default=None,
                   help="curriculum: mask the planner's STOP until its goal vector reads below this many metres "
                        "(without it an untrained pair soon learns that stopping at once beats the slack)")
    a = p.parse_args(argv)
    logging.getLogger("tianshou.data.stats").setLevel(logging.ERROR)  # per-agent return vectors are fine
    torch.manual_seed(a.seed)
    torch.set_num_threads(1)
    config = dict(resolution=a.resolution, num_scenes=a.num_scenes, max_steps=a.max_steps)

    log: list = []
    algorithm, train_envs, test_envs = build(config, a.num_envs, a.seed, a.lr, log, a.stop_within)
    before = evaluate(algorithm, test_envs, a.eval_episodes)
    print("before training:", before)
    t0 = time.time()
    buffer = VectorReplayBuffer(max(a.steps_per_collect, 1000) * 2, a.num_envs)
    train_collector = Collector(algorithm, train_envs, buffer)
    trainer = algorithm.create_trainer(OnPolicyTrainerParams(
        training_collector=train_collector, test_collector=None, max_epochs=a.epochs,
        epoch_num_steps=a.steps_per_epoch, collection_step_num_env_steps=a.steps_per_collect,
        # Each agent's whole share of the collected steps is one batch, used 6 times.
        update_step_num_repetitions=6, batch_size=None,
        multi_agent_return_reduction=lambda r: r[:, 0],  # log the planner's return
        verbose=False, show_progress=False))
    trainer.reset()
    for epoch in range(a.epochs):
        seen = len(log)
        trainer.execute_epoch()
        done = log[seen:]
        if done:
            print(f"epoch {epoch + 1}: {len(done)} episodes, mean return planner "
                  f"{np.mean([d['planner'] for d in done]):+.2f} executor {np.mean([d['executor'] for d in done]):+.2f}, "
                  f"success {np.mean([d['success'] for d in done]):.2f}, length {np.mean([d['length'] for d in done]):.0f}")
    seconds = time.time() - t0
    steps = int(trainer._env_step)
    after = evaluate(algorithm, test_envs, a.eval_episodes)
    print("after training: ", after)
    print(f"{steps} AEC steps in {seconds:.0f} s ({steps / seconds:.0f} steps/s)")
    return {"before": before, "after": after, "env_steps": steps, "seconds": seconds, "episodes": log}


if __name__ == "__main__":
    main()
