"""What the PLEX and flat trainers share: the networks of a method, its env settings, and
the run-dir life of a training run (seeding, devices, optimisers, checkpoints, resume,
metrics, progress and the time shares of each update).

:class:`Trainer` is the base class; :class:`~plex_ma.trainers.plex.PlexTrainer` and
:class:`~plex_ma.trainers.flat.FlatTrainer` hold the training loops.
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from collections import defaultdict, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
import torch
from tqdm import tqdm

from plex_ma.config import CURRICULUM_START_DISTANCE, TrainConfig, from_dict, setting
from plex_ma.envs.rules import NavConfig
from plex_ma.envs.sim.episodes import MAX_GEODESIC
from plex_ma.networks import Executor, FlatMapPolicy, FlatPolicy, Planner

from . import distributed
from .checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from .device import resolve_device
from .logger import MetricLogger, resident_memory_mib
from .ppo import PPOConfig

CHECKPOINT_FORMAT = 2  # 2: the networks hold no hand-set priors (format 1's could)


# The settings that shape the networks (and their action mask): a checkpoint loads only into a run with the same.
ARCH_KEYS = ("method", "resolution", "eli", "smt_memory", "executor_hidden", "executor_no_reversal")
PLEX_ARCH_KEYS = ("planner_value_iteration", "planner_fine_map",
                  "planner_trunk_stride", "planner_goal_rbf")  # ... and for the methods that read the ego map (the planner's)
NAV_FIELDS = tuple(f.name for f in dataclasses.fields(NavConfig) if f.init)


def saved_config(state: dict) -> TrainConfig:
    """A checkpoint's config (a checkpoint of another format is refused: its networks may differ)."""
    if state.get("format") != CHECKPOINT_FORMAT:
        raise CheckpointError(f"checkpoint format {state.get('format')!r} is not {CHECKPOINT_FORMAT} (this version's): "
                              "another version of plex-ma wrote it; retrain it")
    try:
        config = dict(state["config"])
        if str(config.get("method")).startswith("plex") and config.get("planner_stop_radius") is not None:
            raise CheckpointError("checkpoint's planner stops by its sub-goal's distance (--planner-stop-radius, "
                                  "since removed) and has no stop head: retrain it")
        return from_dict(config)
    except (KeyError, TypeError, ValueError) as e:
        raise CheckpointError(f"checkpoint config is not valid: {e}") from None


def env_kwargs(cfg: TrainConfig, split: str | None = None) -> dict:
    """The env settings of a training config, as keyword arguments of the PLEX env (the PointNav
    env's for the flat methods). ``split``, when it is not the config's own, selects that
    split's default scenes and fixed episodes (evaluation)."""
    names = [f.name for f in dataclasses.fields(cfg.env) if f.init] if cfg.method.startswith("plex") else NAV_FIELDS
    kw = {k: getattr(cfg.env, k) for k in names}
    if split is not None and split != cfg.env.split:
        kw |= {"split": split, "num_scenes": None, "episodes_file": None}
    return kw


def curriculum_distance(step: int, curriculum_steps: int) -> float:
    """The largest start-goal geodesic distance (m) of the training episodes sampled at
    ``step``: CURRICULUM_START_DISTANCE at step 0, growing linearly to Habitat's
    MAX_GEODESIC at ``curriculum_steps``. Short episodes first give the planner's stop
    (which only succeeds within 0.2 m of the goal) outcomes to learn from."""
    frac = min(step / curriculum_steps, 1.0)
    return CURRICULUM_START_DISTANCE + frac * (MAX_GEODESIC - CURRICULUM_START_DISTANCE)


def build_policies(cfg: TrainConfig) -> dict[str, torch.nn.Module]:
    """The networks of a method: {'planner', 'executor'} for PLEX, {'policy'} for flat PPO
    (ppo-gru-map: the flat GRU policy that also reads the ego map, with the planner's map
    encoder as --planner-value-iteration sets it)."""
    memory = cfg.method.split("-")[1]
    if cfg.method.startswith("plex"):
        kw = dict(use_eli=cfg.env.eli, rho_max=cfg.env.rho_max, subgoal_radius=cfg.env.subgoal_radius,
                  init_std=cfg.planner_subgoal_std, value_iteration=cfg.planner_value_iteration,
                  fine_map=cfg.planner_fine_map, trunk_stride=cfg.planner_trunk_stride, goal_rbf=cfg.planner_goal_rbf)
        planner = Planner(subgoal_forward=cfg.planner_subgoal_forward, **kw)
        return {"planner": planner,
                "executor": Executor(memory=memory, resolution=cfg.env.resolution, smt_memory=cfg.smt_memory,
                                     gru_hidden=cfg.executor_hidden, no_reversal=cfg.executor_no_reversal, stop_bias=cfg.executor_stop_bias)}
    flat = dict(memory=memory, resolution=cfg.env.resolution, smt_memory=cfg.smt_memory,
                gru_hidden=cfg.executor_hidden, no_reversal=cfg.executor_no_reversal)
    if cfg.method == "ppo-gru-map":
        return {"policy": FlatMapPolicy(value_iteration=cfg.planner_value_iteration, fine_map=cfg.planner_fine_map,
                                        trunk_stride=cfg.planner_trunk_stride, goal_rbf=cfg.planner_goal_rbf,
                                        **flat)}
    return {"policy": FlatPolicy(**flat)}


def reads_ego_map(nets: dict[str, torch.nn.Module]) -> bool:
    """Whether a method's networks read the ego map (then its worlds must keep it)."""
    return "planner" in nets or getattr(nets.get("policy"), "reads_ego_map", False)


@dataclass
class EpisodeStats:
    """Rolling window of finished episodes for logging."""

    window: ClassVar[int] = 100  # episodes kept
    success: deque = field(default_factory=lambda: deque(maxlen=EpisodeStats.window))
    spl: deque = field(default_factory=lambda: deque(maxlen=EpisodeStats.window))
    reward: deque = field(default_factory=lambda: deque(maxlen=EpisodeStats.window))

    def add(self, info: dict, reward: float) -> None:
        self.success.append(info["success"])
        self.spl.append(info["spl"])
        self.reward.append(reward)

    def state(self) -> dict:
        """The window as plain lists, for a checkpoint: a resumed run's logged metrics go on
        from where they stopped."""
        return {f.name: [float(x) for x in getattr(self, f.name)] for f in dataclasses.fields(self)}

    @classmethod
    def from_state(cls, state: dict) -> EpisodeStats:
        stats = cls()
        for k, values in state.items():
            getattr(stats, k).extend(values)
        return stats

    def summary(self) -> dict:
        if not self.success:
            return {}
        return {"metrics/success": float(np.mean(self.success)), "metrics/spl": float(np.mean(self.spl)),
                "reward": float(np.mean(self.reward)), "metrics/episodes": len(self.success)}


@dataclass
class RunClock:
    """A training loop's progress bar, its last logged metrics, when and at which step it
    started, and the seconds spent so far in each part of an update."""

    bar: object
    start_time: float
    start_step: int
    last_log: dict = field(default_factory=dict)
    timing: dict = field(default_factory=lambda: {"sim": 0.0, "inference": 0.0, "update": 0.0})
    # seconds each agent's learning took inside the updates (PLEX: they run side by side, so
    # these overlap and are not parts of the wall time)
    learning: defaultdict = field(default_factory=lambda: defaultdict(float))


class Trainer:
    """Shared run-dir handling: seeding, logging, checkpoints, resume, progress."""

    def __init__(self, cfg: TrainConfig, log: bool = True, record: Callable[[Trainer], object] | None = None):
        """``log``: write metrics to the run dir. ``record``: called with the trainer every
        ``cfg.record_interval`` updates on the main worker (``python -m plex_ma.train``
        passes :func:`plex_ma.viz.record_training_episode`)."""
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
        self.base_lr = {k: lrs.get(k, cfg.lr) for k in self.nets}
        self.ppo = PPOConfig(clip_coef=cfg.clip, vf_coef=cfg.value_coef, ent_coef=cfg.entropy_coef,
                             max_grad_norm=cfg.max_grad_norm, update_epochs=cfg.ppo_epochs,
                             num_minibatches=cfg.num_minibatches)
        self.step = 0  # environment steps (agent actions) so far
        self.updates = {k: 0 for k in self.nets}
        self.stats = EpisodeStats()
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
        # rank 0 writes, from its first log on; rows an earlier run logged past this step go
        self.logger = MetricLogger(cfg.run_dir, start_step=self.step) if log and self.dist.is_main else None
        distributed.sync_start(self)  # distributed: rank 0's parameters everywhere, samplers seeded apart

    def _set_threads(self) -> None:
        """torch's intra-op threads as configured. Called again after the worlds' first
        reset: with ``NUMBA_THREADING_LAYER=omp`` (the default layer is workqueue,
        envs/sim/kernels.py) the simulator's numba kernels share torch's OpenMP runtime,
        and starting them sets its thread count to numba's."""
        if self.cfg.torch_threads:
            torch.set_num_threads(self.cfg.torch_threads)

    # ---------------------------------------------------------------- checkpoints
    def state(self) -> dict:
        return {"format": CHECKPOINT_FORMAT, "config": dataclasses.asdict(self.cfg), "step": self.step,
                "updates": dict(self.updates),
                "models": {k: m.state_dict() for k, m in self.nets.items()},
                "optimizers": {k: o.state_dict() for k, o in self.opts.items()},
                "torch_rng": torch.get_rng_state(), "sampler_rng": self.gen.get_state(),
                "episodes": self.stats.state(),
                # actions sampled on a GPU draw from its generator
                **({"cuda_rng": torch.cuda.get_rng_state(self.device)} if self.device.type == "cuda" else {})}

    def load_weights(self, state: dict, what: str = "the checkpoint") -> None:
        """The networks' weights from a checkpoint whose architecture settings match this run's."""
        saved = saved_config(state)
        for key in ARCH_KEYS + (PLEX_ARCH_KEYS if reads_ego_map(self.nets) else ()):
            if setting(saved, key) != setting(self.cfg, key):
                raise CheckpointError(f"{what} has {key}={setting(saved, key)!r} but this run asks for "
                                      f"{setting(self.cfg, key)!r}")
        try:
            for k, m in self.nets.items():
                m.load_state_dict(state["models"][k])
        except (KeyError, RuntimeError, ValueError) as e:
            raise CheckpointError(f"checkpoint does not match the networks: {e}") from None

    def load_state(self, state: dict) -> None:
        self.load_weights(state, "the run dir's checkpoint (use another --run-dir)")
        if "optimizers" not in state:  # a numbered checkpoint (latest.pt was corrupt): see checkpoint.py
            warnings.warn("this checkpoint holds no optimiser state (only latest.pt does): the optimisers "
                          "restart from zero moments", stacklevel=2)
        else:
            try:
                for k, o in self.opts.items():
                    o.load_state_dict(state["optimizers"][k])
            except (KeyError, RuntimeError, ValueError) as e:
                raise CheckpointError(f"checkpoint does not match the networks: {e}") from None
        self.step = int(state["step"])
        self.updates = {k: int(v) for k, v in state["updates"].items()}
        torch.set_rng_state(state["torch_rng"])
        self.gen.set_state(state["sampler_rng"])
        self.stats = EpisodeStats.from_state(state.get("episodes", {}))  # older checkpoints: empty
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


    def _loop_start(self) -> RunClock:
        self._anneal()
        return RunClock(self._progress(), time.perf_counter(), self.step)

    def _anneal(self) -> None:
        """Set before every rollout and update: with ``anneal_lr``, each optimiser's learning
        rate falls linearly from its base value at step 0 to zero at ``total_steps`` (CleanRL's
        schedule); with ``curriculum_steps``, the training worlds' largest episode distance
        (:func:`curriculum_distance`)."""
        if self.cfg.curriculum_steps:
            self.env.worlds.max_geodesic = curriculum_distance(self.step, self.cfg.curriculum_steps)
        if self.cfg.anneal_lr:
            frac = max(1.0 - self.step / self.cfg.total_steps, 0.0) if self.cfg.total_steps else 1.0
            for k, o in self.opts.items():
                for group in o.param_groups:
                    group["lr"] = self.base_lr[k] * frac

    def _finish(self, clock: RunClock) -> dict:
        """Final checkpoint; the last logged metrics with the episode statistics."""
        self.save()
        if clock.bar is not None:
            clock.bar.close()
        return {**clock.last_log, **self.stats.summary()}

    def _end_of_update(self, n_updates: int, metrics: dict, clock: RunClock) -> None:
        """Throughput and time shares, then logging, checkpoint, recording and progress bar
        at their intervals (the logged metrics become ``clock.last_log``)."""
        cfg = self.cfg
        timing, bar = clock.timing, clock.bar
        wall = max(time.perf_counter() - clock.start_time, 1e-9)
        sps = (self.step - clock.start_step) / wall
        metrics["perf/fps"] = sps
        # shares of the wall time since the start; "other" is logging, buffers, checkpoints
        for k, v in timing.items():
            metrics[f"perf/share_{k}"] = v / wall
        metrics["perf/share_other"] = max(0.0, 1.0 - sum(timing.values()) / wall)
        for k, v in clock.learning.items():
            metrics[f"perf/share_learn_{k}"] = v / wall
        metrics["perf/rss_mib"] = resident_memory_mib()  # None (not logged) off Linux
        self._anneal()  # the next update's learning rates
        metrics |= {f"learner/{k}_lr": o.param_groups[0]["lr"] for k, o in self.opts.items()}
        if n_updates % cfg.log_interval == 0:
            self.log(metrics)
            clock.last_log = metrics
        if n_updates % cfg.checkpoint_interval == 0:
            self.save()
        if self.record is not None and cfg.record_interval and n_updates % cfg.record_interval == 0 \
                and self.dist.is_main:
            self.record(self)
        if bar is not None:
            bar.update(min(self.step, cfg.total_steps) - bar.n)
            self._postfix(bar, sps)

