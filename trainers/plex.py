"""Independent PPO for PLEX (paper Algorithms 1 and 2): the planner and the executor learn side by side.

PLEX runs through the rollout driver (:mod:`.driver`), per iteration:

1. *Planner decisions* (``PlexDriver.decide``). Every world whose turn is the planner's gets
   a decision (stop, or a sub-goal). A stop ends that world's episode and a new one starts,
   which needs another decision, so this repeats until every world is in an executor turn.
2. *One executor step* in all N worlds at once (``PlexDriver.step``). The executor's memory
   restarts at the first step of every turn (each sub-goal).
3. After ``rollout_steps`` executor steps: a PPO update of the executor on its own rewards
   (gamma_EX per executor step). An executor turn ends at its STOP (terminal), at its
   N_EX-th action (a truncation: bootstrap from V of the observation after it, with the
   memory it had) or at the episode's end.
4. Each planner decision is one transition whose reward is everything the planner earned
   until its next decision (gamma_PL per decision, or ``planner_step_gamma`` per executor
   step it lasted; :class:`~.decisions.DecisionBuffer`).
   Once N_PL decisions per world have completed, a PPO update of the planner.

The planner's update of an iteration runs on a second thread beside the executor's update
(``parallel_updates``, single-process runs): the two agents share no parameters, each draws
its minibatches from its own generator, and both threads run the same number of torch
threads, so the networks are the same, bit for bit, as with the updates one after the other.

Either agent can be a stand-in that is not trained (``--planner random|oracle``,
``--executor oracle``: the shortest-path oracles use ground truth).

Stop-gradient: the ELI reaches the planner through the environment as a plain array, and
the planner detaches it again inside its forward pass; the planner's optimiser holds only
the planner's parameters, so the planner's update cannot change the executor.
"""

from __future__ import annotations

import dataclasses
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch

from plex_ma.config import TrainConfig
from plex_ma.envs.rules import PLANNER
from plex_ma.envs.vector import PlexVectorEnv
from plex_ma.networks import Executor, Planner

from . import distributed
from .base import RunClock, Trainer, env_kwargs
from .decisions import DecisionBuffer
from .driver import Decision, PlexDriver, make_executor, make_planner
from .ppo import RolloutBuffer, ppo_update

class PlexTrainer(Trainer):
    """Independent PPO for the planner and the executor (see the module docstring)."""

    def __init__(self, cfg: TrainConfig, log: bool = True, record: Callable[[Trainer], object] | None = None):
        self.planner_gen: torch.Generator | None = None  # the planner's minibatches
        super().__init__(cfg, log, record)
        if self.planner_gen is None or not self.dist.is_main:
            # a fresh run, or a worker besides rank 0 (whose sampler sync_start seeded apart):
            # a seed drawn from the executor's sampler
            self.planner_gen = torch.Generator().manual_seed(int(torch.randint(2**62, (1,), generator=self.gen)))
        # the planner learns on a second thread beside the executor's update (single process:
        # under torchrun both updates all-reduce over one process group, so they take turns)
        self.pool = ThreadPoolExecutor(1) if cfg.parallel_updates and self.dist.world_size == 1 else None
        self.planner: Planner = self.nets["planner"]
        self.executor: Executor = self.nets["executor"]
        self.np_rng = np.random.default_rng(cfg.seed + self.dist.seed_offset)
        self.executor_success: deque = deque(maxlen=200)  # reached / turns, over recent turns
        self._make_driver()

    def state(self) -> dict:
        return super().state() | {"planner_sampler_rng": self.planner_gen.get_state()}

    def load_state(self, state: dict) -> None:
        super().load_state(state)
        if "planner_sampler_rng" in state:
            self.planner_gen = torch.Generator()
            self.planner_gen.set_state(state["planner_sampler_rng"])

    def close(self) -> None:
        if self.pool is not None:
            self.pool.shutdown()
        super().close()

    def _make_driver(self) -> None:
        """The training worlds and the driver with the planner and executor policies."""
        cfg = self.cfg
        kw = env_kwargs(cfg)
        self.env = PlexVectorEnv(cfg.num_envs, seed=cfg.seed + 1000 * self.updates["executor"] + self.dist.seed_offset,
                                 **kw)
        self.driver = PlexDriver(
            self.env,
            make_planner(cfg.planner, self.env, self.planner, rng=self.np_rng,
                         max_distance=cfg.random_subgoal_distance, max_angle=cfg.random_subgoal_angle),
            make_executor(cfg.executor, self.env, self.executor))
        self.driver.reset(seed=cfg.seed + self.step + self.dist.seed_offset)
        self._set_threads()
        self.turn_d0 = np.zeros(cfg.num_envs)
        self.decisions = DecisionBuffer(cfg.num_envs, cfg.planner_step_gamma)  # the planner's transitions

    # ---------------------------------------------------------------- planner
    def _on_decision(self, d: Decision) -> None:
        """Book-keeping of one round of planner decisions: episodes ended by a planner stop,
        and (when the planner learns) its transitions."""
        self._count_episodes(d.result)
        if self.driver.planner.learns:
            out = d.out
            self.decisions.decide(d.rows, out["obs"], out["stop"], out["raw_subgoal"], out["log_prob"], out["value"])
            self._planner_rewards(d.result, executor_step=False)

    def _planner_rewards(self, res, executor_step: bool = True) -> None:
        self.decisions.rewards(res.rewards[:, PLANNER], res.terminated | res.truncated, executor_step)

    def _count_episodes(self, res) -> None:
        for info, ret in zip(res.episode_infos, self.driver.episode_returns):
            self.stats.add(info, ret)

    def _planner_ready(self) -> bool:
        # distributed: all workers update the planner together, once every one of them is ready
        return distributed.all_true(len(self.decisions) >= self.cfg.n_pl * self.cfg.num_envs)

    def _update_planner(self) -> dict:
        """PPO on the planner's closed decisions (GAE along each world's chain)."""
        batch = self.decisions.batch(self.cfg.gamma_pl, self.cfg.gae_lambda, self.device)
        ppo = dataclasses.replace(self.ppo, target_kl=self.cfg.planner_target_kl)
        stats = ppo_update(self.planner, batch, self.opts["planner"], ppo, self.planner_gen)
        self.updates["planner"] += 1
        return {f"learner/planner_{k}": v for k, v in stats.items()} | {"learner/planner_batch": len(batch.values)}

    def _learn_planner_step(self, update: bool, threads: int) -> tuple[dict, float]:
        """The planner's PPO update after an executor rollout (once N_PL decisions per world
        have closed), on ``threads`` torch threads (the main thread's count: CPU reductions
        split their work by it, so both paths give the same bits). Returns its metrics and
        seconds."""
        if torch.get_num_threads() != threads:
            torch.set_num_threads(threads)
        t0 = time.perf_counter()
        metrics = self._update_planner() if update else {}
        return metrics, time.perf_counter() - t0

    # ---------------------------------------------------------------- executor
    def _values(self, obs: dict, state: torch.Tensor) -> np.ndarray:
        """V of executor observations with the given memory, continuing the sequence."""
        with torch.no_grad():
            _, value, _, _ = self.executor(obs, state, torch.zeros(len(state), dtype=torch.bool))
        return value.cpu().numpy()

    def _bootstrap(self, res, state, trunc: np.ndarray) -> np.ndarray:
        """V(observation after the last action) of turns cut at N_EX or by max_steps, with
        the memory they had; for ended episodes that observation is the final one, as the
        world has already been reset."""
        n = self.cfg.num_envs
        ended = res.terminated | res.truncated
        boot = np.zeros(n, np.float32)
        rows = np.flatnonzero(trunc & ~ended)
        if len(rows):
            boot[rows] = self._values({k: v[rows] for k, v in res.executor_obs.items()}, state[rows])
        rows = np.flatnonzero(trunc & ended)
        if len(rows):
            sel = np.searchsorted(np.flatnonzero(ended), rows)
            boot[rows] = self._values({k: v[sel] for k, v in res.final_executor_obs.items()}, state[rows])
        return boot

    def _rollout(self, clock: RunClock) -> RolloutBuffer | None:
        """``rollout_steps`` executor steps in every world, with the planner's decisions
        between them; the executor's rollout (None when it does not learn)."""
        drv, n = self.driver, self.cfg.num_envs
        buf = RolloutBuffer(self.cfg.rollout_steps, n, self.device) if drv.executor.learns else None
        if buf is not None:
            buf.initial_state = drv.state.clone()
        for t in range(self.cfg.rollout_steps):
            t0 = time.perf_counter()
            env0 = drv.env_seconds
            drv.decide(on_decision=self._on_decision)
            # sub-goal distance at the start of each turn (for the executor's success rate)
            self.turn_d0[drv.starts] = drv.executor_obs["subgoal"][drv.starts, 0]
            s = drv.step()
            res = s.result
            if buf is not None:
                trunc = res.executor_turn_end & ~res.executor_stopped
                buf.add(t, obs=s.obs, actions=torch.as_tensor(s.out["action"]), log_probs=s.out["log_prob"],
                        values=s.out["value"], rewards=torch.as_tensor(res.rewards[:, 1]),
                        dones=torch.as_tensor(res.executor_stopped), truncated=torch.as_tensor(trunc),
                        starts=torch.as_tensor(s.starts), bootstrap_values=torch.as_tensor(self._bootstrap(res, s.state, trunc)))
            # Success over the turns whose sub-goal was not already within reach at the start.
            counted = res.executor_turn_end & (self.turn_d0 >= self.env.config.subgoal_radius)
            self.executor_success.extend(res.executor_reached[counted].tolist())
            if self.driver.planner.learns:
                self._planner_rewards(res)
            self._count_episodes(res)
            self.step += n * self.dist.world_size  # total over all workers
            # sim: time inside env.step; inference: the networks and the bookkeeping
            sim = drv.env_seconds - env0
            clock.timing["inference"] += time.perf_counter() - t0 - sim
            clock.timing["sim"] += sim
        return buf

    def _update_executor(self, buf: RolloutBuffer) -> dict:
        """The executor's PPO update on its rollout; V(o_T) bootstraps the worlds still inside
        a turn (their memory continues)."""
        drv = self.driver
        rows = np.flatnonzero(drv.turn != PLANNER)
        last = np.zeros(self.cfg.num_envs, np.float32)
        if len(rows):
            last[rows] = self._values({k: v[rows] for k, v in drv.executor_obs.items()}, drv.state[rows])
        buf.compute_returns(self.cfg.gamma_ex, self.cfg.gae_lambda, last_values=torch.as_tensor(last))
        stats = ppo_update(self.executor, buf, self.opts["executor"], self.ppo, self.gen)
        return {f"learner/executor_{k}": v for k, v in stats.items()}

    def train(self) -> dict:
        clock = self._loop_start()
        while self.step < self.cfg.total_steps:
            buf = self._rollout(clock)
            t0 = time.perf_counter()
            metrics = {}
            # the planner's update: on the second thread, if there is one, from here on (the
            # all_true check is a collective, so it stays on this thread)
            args = (self.driver.planner.learns and self._planner_ready(), torch.get_num_threads())
            job = self.pool.submit(self._learn_planner_step, *args) if self.pool is not None else None
            t1 = time.perf_counter()
            if buf is not None:
                metrics |= self._update_executor(buf)
            self.updates["executor"] += 1
            clock.learning["executor"] += time.perf_counter() - t1
            if self.executor_success:
                metrics["metrics/executor_success"] = float(np.mean(self.executor_success))
            planner_metrics, seconds = job.result() if job is not None else self._learn_planner_step(*args)
            clock.learning["planner"] += seconds
            metrics |= planner_metrics
            clock.timing["update"] += time.perf_counter() - t0
            self._end_of_update(self.updates["executor"], metrics, clock)
            if distributed.should_stop():  # SIGTERM / SIGINT on any worker: save below and return
                break
        return self._finish(clock)
