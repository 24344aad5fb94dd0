"""Independent PPO for PLEX (paper Algorithms 1 and 2) and flat PPO for the baselines.

PLEX runs through the rollout driver (:mod:`.driver`), per iteration:

1. *Planner decisions* (``PlexDriver.decide``). Every world whose turn is the planner's gets
   a decision (stop, or a sub-goal). A stop ends that world's episode and a new one starts,
   which needs another decision, so this repeats until every world is in an executor turn.
2. *One executor step* in all N worlds at once (``PlexDriver.step``). The executor's memory
   restarts at the first step of every turn (the env's ``executor_memory_restart`` hint).
3. After ``rollout_steps`` executor steps: a PPO update of the executor on its own rewards
   (gamma_EX per executor step). An executor turn ends at its STOP (terminal), at its
   N_EX-th action (a truncation: bootstrap from V of the observation after it, with the
   memory it had) or at the episode's end.
4. Each planner decision is one transition whose reward is everything the planner earned
   until its next decision (gamma_PL per decision). Once N_PL decisions per world have
   completed, a PPO update of the planner.

Either agent can be a stand-in that is not trained (``--planner random|oracle``,
``--executor oracle``: the shortest-path oracles use ground truth). A run can begin with
phases (:func:`phase_at`): the warm-up (the executor learns under the ``warmup_planner``
on ``warmup_scenes``), the teacher's sub-goals (the executor learns under the ``teacher``
planner: ``map``, shortest paths on the agent's own ego map, or the ground-truth
``oracle``) and the planner's imitation (the planner also learns to imitate the teacher's
decisions in the states it visits, DAgger-style).

Stop-gradient: the ELI reaches the planner through the environment as a plain array, and
the planner detaches it again inside its forward pass; the planner's optimiser holds only
the planner's parameters, so the planner's update cannot change the executor.
"""

from __future__ import annotations

import dataclasses
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch
from tqdm import tqdm

from plex_ma.config import TrainConfig
from plex_ma.envs.rules import PLANNER
from plex_ma.envs.vector import PlexVectorEnv, PointNavVectorEnv
from plex_ma.networks import Executor, FlatPolicy, Planner

from . import distributed
from .checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from .device import resolve_device
from .driver import Decision, PlexDriver, make_executor, make_planner
from .logger import MetricLogger
from .ppo import PPOConfig, RolloutBuffer, compute_gae, ppo_update

CHECKPOINT_FORMAT = 1
# Config fields added after checkpoints were first written, with the value older ones had.
LEGACY_CONFIG = {"executor_goal_skip": False}


# The settings that shape the networks: a checkpoint loads only into a run with the same.
ARCH_KEYS = ("method", "resolution", "eli", "smt_memory", "executor_hidden", "executor_goal_skip")


def saved_config(state: dict) -> dict:
    """A checkpoint's config, with the fields older checkpoints lack filled in."""
    return {**LEGACY_CONFIG, **state["config"]}


def env_kwargs(cfg: TrainConfig, split: str = "train") -> dict:
    """The env config of a training config (PLEX's env options for the PLEX methods)."""
    kw = dict(resolution=cfg.resolution, max_steps=cfg.max_steps, scenes=cfg.scenes, split=split)
    if split == "train":
        kw["num_scenes"] = cfg.num_scenes
    if cfg.method.startswith("plex"):
        kw |= dict(n_ex=cfg.n_ex, rho_max=cfg.rho_max, eli=cfg.eli, subgoal_radius=cfg.subgoal_radius,
                   executor_stop_penalty=cfg.executor_stop_penalty)
    return kw


PHASES = ("warmup", "teacher-subgoals", "planner-imitation", "main")


@dataclass(frozen=True)
class Phase:
    """A stretch of a PLEX run: which planner acts and which agents learn."""

    name: str  # one of PHASES (its index is logged as the metric "phase")
    planner: str  # the planner policy acting: learn, imitating, random or oracle
    learn_planner: bool
    learn_executor: bool
    warm_env: bool  # on --warmup-scenes with --warmup-max-steps


def phase_at(cfg: TrainConfig, step: int) -> Phase:
    """The phase of a PLEX run at an environment step. In order, each for its number of
    steps: the warm-up (``planner_warmup_steps``: the warm-up planner, the executor learns),
    the teacher's sub-goals (``teacher_subgoal_steps``: the ``teacher`` planner, the
    executor learns), the planner's imitation (``planner_imitation_steps``: the planner acts
    and learns by PPO and by imitating the teacher, beside the executor), then the main
    phase (the agents as ``--planner`` / ``--executor`` say)."""
    learn_ex = cfg.executor == "learn"
    ends = np.cumsum([cfg.planner_warmup_steps, cfg.teacher_subgoal_steps, cfg.planner_imitation_steps])
    if step < ends[0]:
        return Phase("warmup", cfg.warmup_planner, False, learn_ex, bool(cfg.warmup_scenes))
    if step < ends[1]:
        return Phase("teacher-subgoals", cfg.teacher, False, True, False)
    if step < ends[2]:
        return Phase("planner-imitation", "imitating", True, learn_ex, False)
    return Phase("main", cfg.planner, cfg.planner == "learn", learn_ex, False)


def build_policies(cfg: TrainConfig) -> dict[str, torch.nn.Module]:
    """The networks of a method: {'planner', 'executor'} for PLEX, {'policy'} for flat PPO."""
    memory = cfg.method.split("-")[1]
    if cfg.method.startswith("plex"):
        return {"planner": Planner(use_eli=cfg.eli, rho_max=cfg.rho_max),
                "executor": Executor(memory=memory, resolution=cfg.resolution, smt_memory=cfg.smt_memory,
                                     gru_hidden=cfg.executor_hidden, goal_skip=cfg.executor_goal_skip,
                                     stop_prior=cfg.executor_stop_prior)}
    return {"policy": FlatPolicy(memory=memory, resolution=cfg.resolution, smt_memory=cfg.smt_memory,
                                 gru_hidden=cfg.executor_hidden, goal_skip=cfg.executor_goal_skip)}


@dataclass
class EpisodeStats:
    """Rolling window of finished episodes for logging."""

    window: int = 100
    success: deque = field(default_factory=lambda: deque(maxlen=100))
    spl: deque = field(default_factory=lambda: deque(maxlen=100))
    reward: deque = field(default_factory=lambda: deque(maxlen=100))

    def add(self, info: dict, reward: float) -> None:
        self.success.append(info["success"])
        self.spl.append(info["spl"])
        self.reward.append(reward)

    def summary(self) -> dict:
        if not self.success:
            return {}
        return {"metrics/success": float(np.mean(self.success)), "metrics/spl": float(np.mean(self.spl)),
                "reward": float(np.mean(self.reward)), "metrics/episodes": len(self.success)}


class Trainer:
    """Shared run-dir handling: seeding, logging, checkpoints, resume, progress."""

    def __init__(self, cfg: TrainConfig, log: bool = True, record: Callable[[Trainer], object] | None = None):
        """``log``: write metrics to the run dir. ``record``: called with the trainer every
        ``cfg.record_interval`` updates on the main worker (``python -m plex_ma.train``
        passes :func:`plex_ma.viz.record.record_training_episode`)."""
        self.cfg = cfg
        self.record = record
        self.dist = distributed.context()  # rank, world size; single-process unless torchrun started a group
        self._set_threads()
        torch.manual_seed(cfg.seed)
        self.gen = torch.Generator().manual_seed(cfg.seed)
        self.device = resolve_device(cfg.device)
        if self.device.type == "cuda" and self.dist.world_size > 1:  # torchrun: each rank on its LOCAL_RANK GPU
            self.device = torch.device("cuda", self.dist.local_rank)
        self.nets = {k: m.to(self.device) for k, m in build_policies(cfg).items()}
        lrs = {"planner": cfg.planner_lr or cfg.lr}
        # fused Adam: one kernel over all parameters; a step over the planner's 6M parameters
        # takes a fifth of the per-tensor loop's time on one thread (`python -m plex_ma.bench adam`)
        self.opts = {k: torch.optim.Adam(m.parameters(), lr=lrs.get(k, cfg.lr), eps=1e-5, fused=True)
                     for k, m in self.nets.items()}
        self.ppo = PPOConfig(clip_coef=cfg.clip, vf_coef=cfg.value_coef, ent_coef=cfg.entropy_coef,
                             max_grad_norm=cfg.max_grad_norm, update_epochs=cfg.ppo_epochs,
                             num_minibatches=cfg.num_minibatches)
        self.step = 0  # environment steps (agent actions) so far
        self.updates = {k: 0 for k in self.nets}
        self.stats = EpisodeStats()
        self.logger = MetricLogger(cfg.run_dir) if log and self.dist.is_main else None  # rank 0 writes
        self.resumed_from = None
        found = distributed.find_resumable(cfg.run_dir)  # rank 0 reads, every worker gets it
        if found is not None:
            state, path = found
            self.load_state(state)
            self.resumed_from = path
            if self.dist.is_main:
                print(f"resuming from {path} at step {self.step:,}")
        elif cfg.checkpoint:
            self.load_weights(load_checkpoint(cfg.checkpoint))
            if self.dist.is_main:
                print(f"fine-tuning the networks of {cfg.checkpoint}")
        distributed.sync_start(self)  # distributed: rank 0's parameters everywhere, samplers seeded apart

    def _set_threads(self) -> None:
        """torch's intra-op threads as configured. Called again after the worlds' first
        reset: the simulator's numba kernels share torch's OpenMP runtime, and starting
        them sets its thread count to numba's."""
        if self.cfg.torch_threads:
            torch.set_num_threads(self.cfg.torch_threads)

    # ---------------------------------------------------------------- checkpoints
    def state(self) -> dict:
        return {"format": CHECKPOINT_FORMAT, "config": dataclasses.asdict(self.cfg), "step": self.step,
                "updates": dict(self.updates),
                "models": {k: m.state_dict() for k, m in self.nets.items()},
                "optimizers": {k: o.state_dict() for k, o in self.opts.items()},
                "torch_rng": torch.get_rng_state(), "sampler_rng": self.gen.get_state(),
                # actions sampled on a GPU draw from its generator
                **({"cuda_rng": torch.cuda.get_rng_state(self.device)} if self.device.type == "cuda" else {})}

    def load_weights(self, state: dict, what: str = "the checkpoint") -> None:
        """The networks' weights from a checkpoint whose architecture settings match this run's."""
        if state.get("format") != CHECKPOINT_FORMAT:
            raise CheckpointError(f"checkpoint format {state.get('format')!r} is not {CHECKPOINT_FORMAT}")
        saved = saved_config(state)
        planner = state.get("models", {}).get("planner")
        if isinstance(planner, dict) and "stop_skip.weight" not in planner:
            raise CheckpointError(f"{what} holds a planner with the linear heads, which plex-ma no longer has")
        for key in ARCH_KEYS:
            if saved.get(key) != getattr(self.cfg, key):
                raise CheckpointError(f"{what} has {key}={saved.get(key)!r} but this run asks for "
                                      f"{getattr(self.cfg, key)!r}")
        try:
            for k, m in self.nets.items():
                m.load_state_dict(state["models"][k])
        except (KeyError, RuntimeError, ValueError) as e:
            raise CheckpointError(f"checkpoint does not match the networks: {e}") from None

    def load_state(self, state: dict) -> None:
        self.load_weights(state, "the run dir's checkpoint (use another --run-dir)")
        try:
            for k, o in self.opts.items():
                o.load_state_dict(state["optimizers"][k])
        except (KeyError, RuntimeError, ValueError) as e:
            raise CheckpointError(f"checkpoint does not match the networks: {e}") from None
        self.step = int(state["step"])
        self.updates = {k: int(v) for k, v in state["updates"].items()}
        torch.set_rng_state(state["torch_rng"])
        self.gen.set_state(state["sampler_rng"])
        if "cuda_rng" in state and self.device.type == "cuda":
            torch.cuda.set_rng_state(state["cuda_rng"], self.device)

    def save(self) -> None:
        if not self.dist.is_main:
            return
        n = sum(self.updates.values())
        save_checkpoint(self.cfg.run_dir, self.state(), n, keep=self.cfg.keep_checkpoints)

    # ---------------------------------------------------------------- logging
    def log(self, metrics: dict) -> None:
        if self.logger is not None:
            self.logger.log(self.step, {**metrics, **self.stats.summary()})

    def close(self) -> None:
        if self.logger is not None:
            self.logger.close()

    def _progress(self):
        if not self.cfg.progress or not self.dist.is_main:
            return None
        return tqdm(total=self.cfg.total_steps, initial=min(self.step, self.cfg.total_steps), unit="step",
                    dynamic_ncols=True, mininterval=1.0)

    def _postfix(self, bar, sps: float) -> None:
        if bar is None:
            return
        s = self.stats.summary()
        bar.set_postfix({"sps": f"{sps:.0f}", "success": f"{s.get('metrics/success', 0):.2f}",
                         "reward": f"{s.get('reward', 0):.2f}"}, refresh=False)


    def _loop_start(self):
        """Progress bar, last logged metrics, start time and step, and the time shares."""
        return self._progress(), {}, time.perf_counter(), self.step, {"sim": 0.0, "inference": 0.0, "update": 0.0}

    def _finish(self, bar, last_log: dict) -> dict:
        """Final checkpoint; the last logged metrics with the episode statistics."""
        self.save()
        if bar is not None:
            bar.close()
        return {**last_log, **self.stats.summary()}

    def _end_of_update(self, n_updates: int, metrics: dict, timing: dict, t_start: float, s_start: int,
                       bar) -> dict | None:
        """Throughput and time shares, then logging, checkpoint, recording and progress bar
        at their intervals. Returns the metrics if they were logged."""
        cfg = self.cfg
        wall = max(time.perf_counter() - t_start, 1e-9)
        sps = (self.step - s_start) / wall
        metrics["perf/fps"] = sps
        # shares of the wall time since the start; "other" is logging, buffers, checkpoints
        for k, v in timing.items():
            metrics[f"perf/share_{k}"] = v / wall
        metrics["perf/share_other"] = max(0.0, 1.0 - sum(timing.values()) / wall)
        logged = None
        if n_updates % cfg.log_interval == 0:
            self.log(metrics)
            logged = metrics
        if n_updates % cfg.checkpoint_interval == 0:
            self.save()
        if self.record is not None and cfg.record_interval and n_updates % cfg.record_interval == 0 \
                and self.dist.is_main:
            self.record(self)
        if bar is not None:
            bar.update(min(self.step, cfg.total_steps) - bar.n)
            self._postfix(bar, sps)
        return logged


IMITATION_CAPACITY = 20_000  # planner decisions kept for imitation (DAgger's aggregate, newest kept)
IMITATION_BATCH = 128


class ImitationSet:
    """Planner observations with the teacher planner's decisions in them, in a ring of
    ``capacity``; the ego map and the ELI are kept in float16 (the ego map's values are
    multiples of 1/4, exact in float16)."""

    def __init__(self, capacity: int):
        self.capacity, self.size, self.next = capacity, 0, 0
        self.data: dict[str, torch.Tensor] = {}

    def __len__(self) -> int:
        return self.size

    def add(self, obs: dict, stop, subgoal) -> None:
        items = {**{f"obs/{k}": torch.as_tensor(v) for k, v in obs.items()},
                 "stop": torch.as_tensor(stop, dtype=torch.long), "subgoal": torch.as_tensor(subgoal, dtype=torch.float32)}
        if not self.data:
            for k, v in items.items():
                dtype = torch.float16 if k in ("obs/ego_map", "obs/eli") else v.dtype
                self.data[k] = torch.zeros((self.capacity,) + v.shape[1:], dtype=dtype)
        k = len(items["stop"])
        at = (self.next + torch.arange(k)) % self.capacity
        for key, v in items.items():
            self.data[key][at] = v.to(self.data[key].dtype)
        self.next = int((self.next + k) % self.capacity)
        self.size = min(self.size + k, self.capacity)

    def sample(self, n: int, generator: torch.Generator) -> tuple[dict, torch.Tensor, torch.Tensor]:
        """(planner obs, teacher stop, teacher sub-goal) of ``n`` decisions drawn uniformly
        (with replacement)."""
        idx = torch.randint(self.size, (n,), generator=generator)
        obs = {k[4:]: v[idx].float() if v.dtype == torch.float16 else v[idx]
               for k, v in self.data.items() if k.startswith("obs/")}
        return obs, self.data["stop"][idx], self.data["subgoal"][idx]


class PlexTrainer(Trainer):
    """Independent PPO for the planner and the executor (see the module docstring)."""

    def __init__(self, cfg: TrainConfig, log: bool = True, record: Callable[[Trainer], object] | None = None):
        super().__init__(cfg, log, record)
        self.planner: Planner = self.nets["planner"]
        self.executor: Executor = self.nets["executor"]
        self.np_rng = np.random.default_rng(cfg.seed + self.dist.seed_offset)
        self.executor_success: deque = deque(maxlen=200)  # reached / turns, over recent turns
        self.imitation = ImitationSet(IMITATION_CAPACITY)  # not checkpointed: a resumed run starts it afresh
        self._make_driver()

    def _phase(self) -> Phase:
        return phase_at(self.cfg, self.step)

    def _make_driver(self) -> None:
        """The training worlds (on ``--warmup-scenes`` in a warm-up that has them) and the
        driver with this phase's planner and executor policies."""
        cfg = self.cfg
        self.phase = self._phase()
        kw = env_kwargs(cfg)
        if self.phase.warm_env:
            kw |= {"scenes": cfg.warmup_scenes, "num_scenes": None, "max_steps": cfg.warmup_max_steps}
        self.env = PlexVectorEnv(cfg.num_envs, seed=cfg.seed + 1000 * self.updates["executor"] + self.dist.seed_offset,
                                 **kw)
        self.driver = PlexDriver(
            self.env,
            make_planner(self.phase.planner, self.env, self.planner, rng=self.np_rng, teacher=cfg.teacher,
                         max_distance=cfg.random_subgoal_distance, max_angle=cfg.random_subgoal_angle),
            make_executor(cfg.executor, self.env, self.executor))
        self.driver.reset(seed=cfg.seed + self.step + self.dist.seed_offset)
        self._set_threads()
        n = cfg.num_envs
        self.turn_d0 = np.zeros(n)
        # The planner's pending transition per world (its decision waits for its reward and
        # its successor) and the closed transitions of this planner rollout, in order.
        self.pending = np.zeros(n, np.bool_)
        self.pending_reward = np.zeros(n)
        self.pending_value = np.zeros(n, np.float32)
        self.pending_data: dict | None = None
        self.closed: list[dict] = []
        self.n_closed = 0

    # ---------------------------------------------------------------- planner transitions
    def _close(self, rows: np.ndarray, done: bool) -> None:
        rows = rows[self.pending[rows]]
        if not len(rows):
            return
        self.closed.append({"world": rows.copy(), "reward": self.pending_reward[rows].astype(np.float32),
                            "done": np.full(len(rows), done), "value": self.pending_value[rows].copy(),
                            **{k: v[rows].clone() for k, v in self.pending_data.items()}})
        self.n_closed += len(rows)
        self.pending[rows] = False

    def _on_decision(self, d: Decision) -> None:
        """Book-keeping of one round of planner decisions: episodes ended by a planner stop,
        and (when the planner learns) its transitions."""
        self._count_episodes(d.result)
        if not self._learn_planner:
            return
        rows, out = d.rows, d.out
        self._close(rows, done=False)  # the previous decision's transition is complete
        if self.pending_data is None:
            n = self.cfg.num_envs
            self.pending_data = {f"obs/{k}": torch.zeros((n,) + v.shape[1:], dtype=torch.as_tensor(v).dtype)
                                 for k, v in d.obs.items()}
            self.pending_data |= {"stop": torch.zeros(n, dtype=torch.long), "subgoal": torch.zeros(n, 2),
                                  "log_prob": torch.zeros(n)}
        idx = torch.as_tensor(rows)
        for k, v in d.obs.items():
            self.pending_data[f"obs/{k}"][idx] = torch.as_tensor(v)
        self.pending_data["stop"][idx] = torch.as_tensor(out["stop"])
        self.pending_data["subgoal"][idx] = out["raw"]
        self.pending_data["log_prob"][idx] = out["log_prob"]
        if "teacher_stop" in out:
            self.imitation.add(d.obs, out["teacher_stop"], out["teacher_subgoal"])
        self.pending_value[rows] = out["value"].numpy()
        self.pending_reward[rows] = 0.0
        self.pending[rows] = True
        self._planner_rewards(d.result)

    def _planner_rewards(self, res) -> None:
        self.pending_reward[self.pending] += res.rewards[self.pending, PLANNER]
        self._close(np.flatnonzero(res.terminated | res.truncated), done=True)

    def _count_episodes(self, res) -> None:
        for info, ret in zip(res.episode_infos, self.driver.episode_returns):
            self.stats.add(info, ret)

    def _planner_ready(self) -> bool:
        # distributed: all workers update the planner together, once every one of them is ready
        return distributed.all_true(self.n_closed >= self.cfg.n_pl * self.cfg.num_envs)

    def _update_planner(self) -> dict:
        """GAE along each world's chain of decisions, then PPO on the flattened batch."""
        cat = {k: (torch.cat if isinstance(v, torch.Tensor) else np.concatenate)([c[k] for c in self.closed])
               for k, v in self.closed[0].items()}
        self.closed, self.n_closed = [], 0
        order = np.argsort(cat["world"], kind="stable")  # each world's chain, in decision order
        world, reward, done, value = (cat[k][order] for k in ("world", "reward", "done", "value"))
        m = len(world)
        # the next transition's value within a world's chain; the chain's last one
        # bootstraps from the value of the world's pending decision
        last = np.r_[world[1:] != world[:-1], True]
        nxt = np.r_[value[1:], 0.0].astype(np.float32)
        boot = np.where(self.pending[world], self.pending_value[world], 0.0)
        nxt = np.where(last, boot, nxt)
        nxt = np.where(done, 0.0, nxt)
        g, lam = self.cfg.gamma_pl, self.cfg.gae_lambda
        delta = reward + g * nxt - value
        adv = np.zeros(m, np.float32)
        a = 0.0
        for t in range(m - 1, -1, -1):
            a = delta[t] + (0.0 if (last[t] or done[t]) else g * lam * a)
            adv[t] = a
        idx = torch.as_tensor(order)
        buf = RolloutBuffer(1, m, self.device)
        buf.add(0, obs={k[4:]: v[idx] for k, v in cat.items() if k.startswith("obs/")},
                actions={"stop": cat["stop"][idx], "subgoal": cat["subgoal"][idx]},
                log_probs=cat["log_prob"][idx], values=torch.as_tensor(value), rewards=torch.zeros(m),
                dones=torch.zeros(m, dtype=torch.bool))
        buf.data["advantages"] = torch.as_tensor(adv, device=self.device)[None]
        buf.data["returns"] = torch.as_tensor(adv + value, device=self.device)[None]
        ent = self.ppo.ent_coef if self.cfg.planner_entropy_coef is None else self.cfg.planner_entropy_coef
        ppo = dataclasses.replace(self.ppo, num_minibatches=self.cfg.planner_minibatches,
                                  target_kl=self.cfg.planner_target_kl, ent_coef=ent)
        stats = ppo_update(self.planner, buf, self.opts["planner"], ppo, self.gen)
        self.updates["planner"] += 1
        return {f"learner/planner_{k}": v for k, v in stats.items()} | {"learner/planner_batch": m}

    def _imitate(self) -> dict:
        """Imitation steps of the planner (after every executor rollout of the phase) on
        minibatches of the aggregate (DAgger): the negative log-likelihood of the teacher's
        decisions, on the planner's optimiser."""
        nll = []
        for _ in range(self.cfg.imitation_minibatches):
            obs, stop, subgoal = self.imitation.sample(IMITATION_BATCH, self.gen)
            loss = self.planner.imitation_loss(obs, stop.to(self.device), subgoal.to(self.device)).mean()
            self.opts["planner"].zero_grad()
            loss.backward()
            distributed.average_gradients(self.planner)
            torch.nn.utils.clip_grad_norm_(self.planner.parameters(), self.cfg.max_grad_norm)
            self.opts["planner"].step()
            nll.append(loss.item())
        return {"learner/planner_imitation_nll": float(np.mean(nll)), "learner/planner_imitation_set": len(self.imitation)}

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

    def train(self) -> dict:
        cfg = self.cfg
        n, T = cfg.num_envs, cfg.rollout_steps
        bar, last_log, t_start, s_start, timing = self._loop_start()
        while self.step < cfg.total_steps:
            if self.phase != self._phase():
                # A new phase: new worlds and this phase's planner. Episodes in flight are
                # dropped (their planner transitions would mix two phases' policies).
                self.env.close()
                self.stats = EpisodeStats()
                self._make_driver()
            drv = self.driver
            learn_ex = drv.executor.learns and self.phase.learn_executor
            learn_pl = self._learn_planner = drv.planner.learns and self.phase.learn_planner
            buf = RolloutBuffer(T, n, self.device)
            if learn_ex:
                buf.initial_state = drv.state.clone()
            for t in range(T):
                t0 = time.perf_counter()
                env0 = drv.env_seconds
                drv.decide(on_decision=self._on_decision)
                # sub-goal distance at the start of each turn (for the executor's success rate)
                self.turn_d0[drv.starts] = drv.executor_obs["subgoal"][drv.starts, 0]
                s = drv.step()
                res = s.result
                if learn_ex:
                    trunc = res.executor_turn_end & ~res.executor_stopped
                    buf.add(t, obs=s.obs, actions=torch.as_tensor(s.out["action"]), log_probs=s.out["log_prob"],
                            values=s.out["value"], rewards=torch.as_tensor(res.rewards[:, 1]),
                            dones=torch.as_tensor(res.executor_stopped), truncated=torch.as_tensor(trunc),
                            starts=torch.as_tensor(s.starts), bootstrap_values=torch.as_tensor(self._bootstrap(res, s.state, trunc)))
                # Success over the turns whose sub-goal was not already within reach at the start.
                counted = res.executor_turn_end & (self.turn_d0 >= self.env.config.subgoal_radius)
                self.executor_success.extend(res.executor_reached[counted].tolist())
                if learn_pl:
                    self._planner_rewards(res)
                self._count_episodes(res)
                self.step += n * self.dist.world_size  # total over all workers
                # sim: time inside env.step; inference: the networks and the bookkeeping
                sim = drv.env_seconds - env0
                timing["inference"] += time.perf_counter() - t0 - sim
                timing["sim"] += sim
            t4 = time.perf_counter()
            metrics = {"phase": PHASES.index(self.phase.name)}
            if learn_ex:
                # V(o_T) for worlds still inside a turn (their memory continues)
                rows = np.flatnonzero(drv.turn != PLANNER)
                last = np.zeros(n, np.float32)
                if len(rows):
                    last[rows] = self._values({k: v[rows] for k, v in drv.executor_obs.items()}, drv.state[rows])
                buf.compute_returns(cfg.gamma_ex, cfg.gae_lambda, last_values=torch.as_tensor(last))
                metrics |= {f"learner/executor_{k}": v for k, v in
                            ppo_update(self.executor, buf, self.opts["executor"], self.ppo, self.gen).items()}
            self.updates["executor"] += 1
            if self.executor_success:
                metrics["metrics/executor_success"] = float(np.mean(self.executor_success))
            if learn_pl and self._planner_ready():
                metrics |= self._update_planner()
            if self.phase.name == "planner-imitation" and distributed.all_true(len(self.imitation) > 0):
                metrics |= self._imitate()
            timing["update"] += time.perf_counter() - t4
            last_log = self._end_of_update(self.updates["executor"], metrics, timing, t_start, s_start, bar) or last_log
            if distributed.should_stop():  # SIGTERM / SIGINT on any worker: save below and return
                break
        return self._finish(bar, last_log)


class FlatTrainer(Trainer):
    """Recurrent PPO for the flat baselines (PPO-GRU, PPO-SMT) on PointNav."""

    def __init__(self, cfg: TrainConfig, log: bool = True, record: Callable[[Trainer], object] | None = None):
        super().__init__(cfg, log, record)
        self.env = PointNavVectorEnv(cfg.num_envs, seed=cfg.seed + 1000 * self.updates["policy"] + self.dist.seed_offset,
                                     **env_kwargs(cfg))
        self.policy: FlatPolicy = self.nets["policy"]

    def train(self) -> dict:
        cfg = self.cfg
        n, T = cfg.num_envs, cfg.rollout_steps
        obs = self.env.reset(seed=cfg.seed + self.step + self.dist.seed_offset)
        self._set_threads()
        state = self.policy.initial_state(n)
        starts = np.ones(n, np.bool_)
        ep_return = np.zeros(n)
        bar, last_log, t_start, s_start, timing = self._loop_start()
        while self.step < cfg.total_steps:
            buf = RolloutBuffer(T, n, self.device)
            buf.initial_state = state.clone()
            for t in range(T):
                t0 = time.perf_counter()
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
                timing["inference"] += t1 - t0
                timing["sim"] += t2 - t1
            t3 = time.perf_counter()
            with torch.no_grad():
                _, last, _, _ = self.policy(obs, state, torch.as_tensor(starts))
            buf.compute_returns(cfg.gamma_flat, cfg.gae_lambda, last_values=last)
            metrics = {f"learner/{k}": v for k, v in
                       ppo_update(self.policy, buf, self.opts["policy"], self.ppo, self.gen).items()}
            self.updates["policy"] += 1
            timing["update"] += time.perf_counter() - t3
            last_log = self._end_of_update(self.updates["policy"], metrics, timing, t_start, s_start, bar) or last_log
            if distributed.should_stop():  # SIGTERM / SIGINT on any worker: save below and return
                break
        return self._finish(bar, last_log)


def make_trainer(cfg: TrainConfig, log: bool = True, record: Callable[[Trainer], object] | None = None) -> Trainer:
    """The trainer of ``cfg.method``; ``log`` and ``record`` as in :class:`Trainer`."""
    return (PlexTrainer if cfg.method.startswith("plex") else FlatTrainer)(cfg, log, record)
