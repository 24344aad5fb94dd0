"""Recurrent PPO for the flat baselines (PPO-GRU, PPO-SMT, PPO-GRU+map) on PointNav: one
agent acts at every step and learns from the env's reward (gamma_flat per step).
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
import torch

from plex_ma.config import TrainConfig
from plex_ma.envs.vector import PointNavVectorEnv
from plex_ma.networks import FlatPolicy

from . import distributed
from .base import Trainer, env_kwargs, reads_ego_map
from .ppo import RolloutBuffer, ppo_update


class FlatTrainer(Trainer):
    """Recurrent PPO for the flat baselines (PPO-GRU, PPO-SMT, PPO-GRU+map) on PointNav; the
    worlds keep ego maps only for a policy that reads them."""

    def __init__(self, cfg: TrainConfig, log: bool = True, record: Callable[[Trainer], object] | None = None):
        super().__init__(cfg, log, record)
        self.env = PointNavVectorEnv(cfg.num_envs, seed=cfg.seed + 1000 * self.updates["policy"] + self.dist.seed_offset,
                                     egomap=reads_ego_map(self.nets), **env_kwargs(cfg))
        self.policy: FlatPolicy = self.nets["policy"]

    def train(self) -> dict:
        cfg = self.cfg
        n, T = cfg.num_envs, cfg.rollout_steps
        obs = self.env.reset(seed=cfg.seed + self.step + self.dist.seed_offset)
        self._set_threads()
        state = self.policy.initial_state(n)
        starts = np.ones(n, np.bool_)
        ep_return = np.zeros(n)
        clock = self._loop_start()
        while self.step < cfg.total_steps:
            buf = RolloutBuffer(T, n, self.device)
            buf.initial_state = state.clone()
            for t in range(T):
                t0 = time.perf_counter()
                obs = self.policy.with_map_plan(obs)  # stored with the step: the epochs reuse it
                out, state = self.policy.act(obs, state, starts)
                obs_t = {k: np.array(v) for k, v in obs.items()}
                t1 = time.perf_counter()
                obs, rew, term, trunc, infos = self.env.step(out["action"].cpu().numpy())
                t2 = time.perf_counter()
                ended = term | trunc
                # A time-limit truncation is treated as terminal (the final observation is
                # gone after the autoreset); at 500 steps the discounted tail is negligible.
                buf.add(t, obs=obs_t, actions=out["action"], log_probs=out["log_prob"], values=out["value"],
                        rewards=torch.as_tensor(rew), dones=torch.as_tensor(ended), starts=torch.as_tensor(starts))
                ep_return += rew
                for k, i in enumerate(np.flatnonzero(ended)):
                    self.stats.add(infos[k], float(ep_return[i]))
                    ep_return[i] = 0.0
                starts = ended.copy()
                self.step += n * self.dist.world_size  # total over all workers
                clock.timing["inference"] += t1 - t0
                clock.timing["sim"] += t2 - t1
            t3 = time.perf_counter()
            with torch.no_grad():
                _, last, _, _ = self.policy(obs, state, torch.as_tensor(starts))
            buf.compute_returns(cfg.gamma_flat, cfg.gae_lambda, last_values=last)
            metrics = {f"learner/{k}": v for k, v in
                       ppo_update(self.policy, buf, self.opts["policy"], self.ppo, self.gen).items()}
            self.updates["policy"] += 1
            clock.timing["update"] += time.perf_counter() - t3
            self._end_of_update(self.updates["policy"], metrics, clock)
            if distributed.should_stop():  # SIGTERM / SIGINT on any worker: save below and return
                break
        return self._finish(clock)

