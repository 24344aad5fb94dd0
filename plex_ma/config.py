"""Training configuration: one dataclass, every field documented, parsed by tyro.

``TrainConfig`` holds the trainer's settings and nests the environment's own config
(:class:`plex_ma.envs.rules.PlexConfig`) as ``env``: every env setting (image size, episode
length, scenes, N_EX, rho_max, the ELI, reward weights, pose noise) is a flag of the same
name, defined and validated once, by the env. ``TrainConfig()`` is the recommended recipe,
reward-only PLEX-GRU as it learns best per CPU hour here (the ``cpu`` preset; why each value:
docs/results.md). ``--preset`` names a recipe (``smoke``, ``cpu``, ``paper``) as the fields
where it departs from those defaults; any flag on the command line overrides the preset's
value. :func:`replace` changes fields of either level by name.
"""

from __future__ import annotations

import argparse
import dataclasses
import shlex
from dataclasses import dataclass, field
from typing import Annotated, Literal, get_args

import tyro
from tyro._errors import on_parse_error  # tyro's documented hook: a bad flag as one line, not tyro's box

from plex_ma.envs.rules import PlexConfig, make_config

# The smallest image the executor's CNN takes (convolutions 8/4, 4/2, 3/1; tests check it).
CNN_MIN_RESOLUTION = 36
# Where the trainer's env defaults differ from the env's own (the env's are the paper's, docs/spec.md).
TRAIN_ENV = {"resolution": 48, "n_ex": 30, "subgoal_radius": 0.2}
CURRICULUM_START_DISTANCE = 2.5  # m: the training episodes' largest geodesic distance at step 0 of a curriculum
Method = Literal["plex-gru", "plex-smt", "ppo-gru", "ppo-smt", "ppo-gru-map"]
Preset = Literal["smoke", "cpu", "paper"]
# --device of the CLIs that load networks (evaluate, record, bench train; train has the field below)
DEVICE_HELP = "where the networks run: auto (CUDA when present), cpu, cuda, cuda:N"


@dataclass
class TrainConfig:
    """Train PLEX (planner + executor, independent PPO) or a flat PPO baseline."""

    method: Method = "plex-gru"
    """plex-gru / plex-smt (the paper's PLEX LSTM / SMT) or the flat baselines ppo-gru / ppo-smt; ppo-gru-map: flat PPO-GRU that also reads the planner's ego map through the planner's map encoder (its conv trunk, and its value-iteration module with --planner-value-iteration), the control arm for the hierarchy's gain over the map's"""
    planner: Literal["learn", "random", "oracle"] = "learn"
    """PLEX only: learn the planner, or train the executor alone under random sub-goals (distance uniform in [0.5, random_subgoal_distance], direction within +-random_subgoal_angle, never stopping) or under the shortest-path oracle planner (ground truth)"""
    executor: Literal["learn", "oracle"] = "learn"
    """PLEX only: learn the executor, or train the planner alone over the shortest-path oracle executor (ground truth)"""
    random_subgoal_distance: float = 1.5
    """largest distance (m) of the random planner's sub-goals (at most rho_max)"""
    random_subgoal_angle: float = 3.14
    """largest |direction| (rad) of the random planner's sub-goals"""
    preset: Preset = "cpu"
    """the recipe: cpu (these defaults for PLEX: best per CPU hour here), smoke (the cpu recipe in < 2 min), paper (the paper's settings)"""
    total_steps: int = 2_048_000
    """environment steps (agent actions) to train for (0: write the untrained networks, the untrained agent of every results table)"""
    num_envs: int = 32
    """worlds simulated in parallel"""
    seed: int = 0
    """seeds the worlds, the networks and the sampling"""
    run_dir: str = "runs/plex-gru"
    """where metrics, TensorBoard logs and checkpoints go; an existing checkpoint here is resumed"""
    checkpoint: str | None = None
    """start the networks from this checkpoint's weights (a file or pretrained:NAME) and fine-tune them with fresh optimisers from step 0; a checkpoint in --run-dir is resumed instead"""
    lr: float = 1e-3
    """Adam learning rate (the executor's and the flat policy's; the planner's where --planner-lr is None)"""
    planner_lr: float | None = 5e-4
    """PLEX only: the planner's Adam learning rate (None: --lr)"""
    planner_target_kl: float | None = None
    """PLEX only: end the planner's PPO epochs early, after the first whose mean approximate KL exceeds this (None: always --ppo-epochs)"""
    planner_subgoal_std: float = 0.5
    """PLEX only: the starting standard deviation of the planner's sampled sub-goal (rho in m, theta in rad)"""
    curriculum_steps: int = 400_000
    """sampled training episodes' largest start-goal geodesic distance grows linearly from CURRICULUM_START_DISTANCE (2.5 m) to Habitat's 30 m over this many steps (0: no curriculum)"""
    anneal_lr: bool = True
    """decay every learning rate linearly to zero at --total-steps (CleanRL's anneal_lr)"""
    rollout_steps: int = 32
    """executor (or flat agent) steps per world between its PPO updates"""
    n_pl: int = 8
    """planner decisions per world per planner update (N_PL)"""
    gamma_ex: float = 0.99
    """executor discount per executor step"""
    gamma_pl: float = 0.95
    """planner discount per planner decision (when --planner-step-gamma is None)"""
    planner_step_gamma: float | None = 0.99
    """PLEX only: discount the planner per executor step instead (a decision that lasted k steps: this^k, as options in an SMDP); None: gamma_pl per decision"""
    gamma_flat: float = 0.99
    """flat baselines' discount per step"""
    gae_lambda: float = 0.95
    """GAE lambda"""
    ppo_epochs: int = 4
    """PPO epochs per update"""
    num_minibatches: int = 2
    """minibatches per PPO epoch (the executor's and flat agent's split the worlds, the planner's its decisions)"""
    clip: float = 0.2
    """PPO clip range"""
    entropy_coef: float = 0.01
    """entropy bonus weight (both agents)"""
    value_coef: float = 0.5
    """value loss weight"""
    max_grad_norm: float = 0.5
    """gradient clipping norm"""
    executor_stop_bias: float = -3.0
    """PLEX only: a constant added to the untrained executor's STOP logit, the same in every state (it sets how long its first turns last)"""
    planner_subgoal_forward: float = 1.0
    """PLEX only: the untrained sub-goal mean's constant start, this many metres ahead in every state"""
    executor_no_reversal: bool = True
    """the executor (and the flat policies, which share its network) never undoes its previous turn within a sub-goal (or episode): no RIGHT right after LEFT, nor LEFT after RIGHT"""
    planner_value_iteration: bool = True
    """PLEX only: the planner also reads a value-iteration module over its ego map (networks.ValueIteration; the paper's planner has none)"""
    planner_fine_map: bool = True
    """the value-iteration module plans on the ego map's 0.25 m quarter cells (64 x 64) instead of its 0.5 m cells"""
    planner_trunk_stride: int = 1
    """the stride of the planner's second map convolution, which the map arm shares (the paper's: 1, 10,816 features; 2: 3,136)"""
    planner_goal_rbf: bool = True
    """the planner's goal features (and the map arm's) also expand the goal distance in 11 Gaussian bumps 0.1 m apart over 0-1 m, a fine reading where the stop is decided"""
    executor_hidden: int = 128
    """GRU hidden size of the executor and the flat GRU policy (512 in the paper)"""
    smt_memory: int = 128
    """memory entries kept by the scene-memory transformer (flat PPO-SMT spans the episode up to this cap)"""
    checkpoint_interval: int = 50
    """PPO updates (of the executor or flat agent) between checkpoints"""
    keep_checkpoints: int = 3
    """numbered checkpoints kept besides latest.pt"""
    log_interval: int = 1
    """updates between metric lines"""
    record_interval: int = 50
    """updates between rerun recordings of an episode into the run dir (0: never)"""
    torch_threads: int = 1
    """torch intra-op threads (0: torch's default)"""
    parallel_updates: bool = True
    """PLEX only: the planner's PPO update runs on a second thread beside the executor's (single-process runs; under torchrun they take turns)"""
    device: str = "auto"
    """where the networks, rollouts and PPO updates run: auto (CUDA when present), cpu, cuda or cuda:N (the simulator stays on the CPU)"""
    progress: bool = True
    """show a progress bar"""
    dist_timeout: float = 300.0
    """distributed runs (torchrun): seconds a worker waits for the others (start-up, each all-reduce) before it stops with an error"""
    env: Annotated[PlexConfig, tyro.conf.OmitArgPrefixes] = field(default_factory=lambda: PlexConfig(**TRAIN_ENV))
    """the training worlds' settings (the flat methods use those PointNav shares; evaluation changes the split)"""


# The env's fields, set by name beside the trainer's: the two sets of names must be disjoint.
ENV_FIELDS = frozenset(f.name for f in dataclasses.fields(PlexConfig) if f.init)
if ENV_FIELDS & {f.name for f in dataclasses.fields(TrainConfig)}:
    raise TypeError(f"TrainConfig and PlexConfig share field names: "
                    f"{sorted(ENV_FIELDS & {f.name for f in dataclasses.fields(TrainConfig)})}")


def setting(cfg: TrainConfig, name: str):
    """A field of the config by its name, the trainer's or its env's."""
    return getattr(cfg.env if name in ENV_FIELDS else cfg, name)


def replace(cfg: TrainConfig, **changes) -> TrainConfig:
    """``cfg`` with fields changed, the trainer's and the env's alike by their names."""
    env = {k: changes.pop(k) for k in list(changes) if k in ENV_FIELDS}
    if env:
        changes["env"] = dataclasses.replace(changes.get("env", cfg.env), **env)
    return dataclasses.replace(cfg, **changes)


def from_dict(d: dict) -> TrainConfig:
    """The TrainConfig of a saved dict (a checkpoint's ``config``). The env's fields may sit
    in ``d["env"]`` or, in a flat config, at the top level; keys neither level knows are
    ignored."""
    known = {f.name for f in dataclasses.fields(TrainConfig)} - {"env"}
    env = TRAIN_ENV | {k: v for k, v in (d | dict(d.get("env") or {})).items() if k in ENV_FIELDS}
    return TrainConfig(**{k: v for k, v in d.items() if k in known}, env=make_config(PlexConfig, env))


def cpu_recipe(method: str) -> dict:
    """The recommended recipe, TrainConfig's defaults: reward-only PLEX, both agents by PPO
    on the reward alone from the first step, with no hand-set term in any policy output
    (docs/spec.md section 6). The flat baselines share its images, worlds, curriculum,
    rollouts and PPO settings; PPO-SMT takes the best learning rate of its sweep
    (docs/results.md). The flat methods' update uses torch's threads on every core (PLEX's
    two updates already run side by side, one thread each)."""
    if method.startswith("plex"):
        return {}
    return dict(torch_threads=0) | (dict(lr=3e-4) if method == "ppo-smt" else {})


def smoke_recipe(method: str) -> dict:
    """The cpu recipe at a smoke test's size (fewer steps, worlds and scenes, 64 px, 2 PPO
    epochs), to finish in well under two minutes on two cores (it still writes a checkpoint)."""
    return cpu_recipe(method) | dict(total_steps=1_500, num_envs=4, resolution=64, rollout_steps=32,
                                     num_scenes=4, ppo_epochs=2, checkpoint_interval=5, keep_checkpoints=1)


def paper_recipe(method: str) -> dict:
    """The paper's settings: 256 px images, N_EX = 10, N_PL = 128, gamma_EX = 0.9, 30M steps,
    a 512-unit executor GRU at one constant learning rate, the env's own rewards, the paper's
    map trunk and a stop head, no value-iteration module and no curriculum."""
    env = {f.name: f.default for f in dataclasses.fields(PlexConfig) if f.name in TRAIN_ENV}
    return env | dict(total_steps=30_000_000, num_envs=16, resolution=256, rollout_steps=128, n_pl=128, lr=2.5e-4,
                      planner_lr=None, anneal_lr=False, ppo_epochs=4, gamma_ex=0.9, executor_hidden=512,
                      executor_no_reversal=False, executor_stop_bias=0.0, planner_subgoal_forward=0.0,
                      planner_trunk_stride=1, curriculum_steps=0,
                      planner_value_iteration=False, planner_fine_map=False, planner_step_gamma=None,
                      planner_goal_rbf=False, torch_threads=0)


# Each preset's recipe for a method: the values that differ from TrainConfig's defaults.
PRESETS = {"smoke": smoke_recipe, "cpu": cpu_recipe, "paper": paper_recipe}


def preset_defaults(preset: str, method: str = "plex-gru") -> TrainConfig:
    """A TrainConfig holding a preset's recipe for ``method`` (and a run dir named after both)."""
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; choose from {sorted(PRESETS)}")
    return replace(TrainConfig(), preset=preset, method=method, run_dir=f"runs/{method}-{preset}",
                   **PRESETS[preset](method))


def validate(cfg: TrainConfig) -> TrainConfig:
    """Raise ValueError naming the first bad field."""
    def need(cond, name, why):
        if not cond:
            raise ValueError(f"config --{name.replace('_', '-')}={setting(cfg, name)!r}: {why}")

    cfg.env.validate()  # the env's fields, by the env's own rules

    need(cfg.method in get_args(Method), "method", "unknown method")
    need(cfg.total_steps >= 0, "total_steps", "must be >= 0 (0 writes the untrained networks)")
    need(cfg.num_envs >= 1, "num_envs", "must be >= 1")
    need(cfg.env.resolution >= CNN_MIN_RESOLUTION, "resolution",
         f"must be >= {CNN_MIN_RESOLUTION} to train: the executor's CNN needs {CNN_MIN_RESOLUTION} px")
    need(cfg.executor_hidden >= 8, "executor_hidden", "must be >= 8")
    need(cfg.lr > 0, "lr", "must be positive")
    need(cfg.planner_lr is None or cfg.planner_lr > 0, "planner_lr", "must be positive")
    need(cfg.planner_target_kl is None or cfg.planner_target_kl > 0, "planner_target_kl", "must be positive")
    need(cfg.planner_subgoal_std > 0, "planner_subgoal_std", "must be positive")
    need(cfg.rollout_steps >= 2, "rollout_steps", "must be >= 2")
    need(cfg.n_pl >= 1, "n_pl", "must be >= 1")
    for g in ("gamma_ex", "gamma_pl", "gamma_flat", "gae_lambda"):
        need(0.0 <= getattr(cfg, g) <= 1.0, g, "must be in [0, 1]")
    need(cfg.planner_step_gamma is None or 0.0 < cfg.planner_step_gamma <= 1.0, "planner_step_gamma", "must be in (0, 1]")
    need(cfg.ppo_epochs >= 1, "ppo_epochs", "must be >= 1")
    need(cfg.curriculum_steps >= 0, "curriculum_steps", "must be >= 0")
    need(1 <= cfg.num_minibatches <= cfg.num_envs, "num_minibatches", "must be in [1, num_envs]")
    need(cfg.clip > 0, "clip", "must be positive")
    need(cfg.max_grad_norm > 0, "max_grad_norm", "must be positive")
    need(cfg.checkpoint_interval >= 1, "checkpoint_interval", "must be >= 1")
    need(cfg.keep_checkpoints >= 1, "keep_checkpoints", "must be >= 1")
    need(cfg.smt_memory >= 1, "smt_memory", "must be >= 1")
    need(cfg.record_interval >= 0, "record_interval", "must be >= 0")
    need(cfg.planner in ("learn", "random", "oracle"), "planner", "must be 'learn', 'random' or 'oracle'")
    need(cfg.executor in ("learn", "oracle"), "executor", "must be 'learn' or 'oracle'")
    need(not (cfg.planner != "learn" and cfg.executor == "oracle"), "executor",
         "with --executor oracle the planner must learn (nothing would be trained)")
    need(-20 <= cfg.executor_stop_bias <= 20, "executor_stop_bias", "must be in [-20, 20] logits")
    need(cfg.planner_trunk_stride in (1, 2), "planner_trunk_stride", "must be 1 or 2")
    need(0 <= cfg.planner_subgoal_forward <= cfg.env.rho_max, "planner_subgoal_forward", "must be in [0, rho_max] metres")
    need(0.5 < cfg.random_subgoal_distance <= cfg.env.rho_max, "random_subgoal_distance", "must be in (0.5, rho_max]")
    need(cfg.dist_timeout > 0, "dist_timeout", "must be positive")
    need(cfg.device in ("auto", "cpu", "cuda") or cfg.device.startswith("cuda:"), "device",
         "must be auto, cpu, cuda or cuda:N")
    return cfg


# Fields that change where a run writes and what it shows, not what it trains.
OUTPUT_FIELDS = frozenset({"run_dir", "progress", "record_interval", "log_interval", "checkpoint_interval",
                           "keep_checkpoints", "dist_timeout", "device"})


def command(cfg: TrainConfig) -> str:
    """The ``python -m plex_ma.train`` command that trains ``cfg``: its preset and method,
    then a flag for every field (the trainer's or its env's) that differs from them;
    :data:`OUTPUT_FIELDS` are left out. ``parse`` of its arguments gives ``cfg`` back."""
    base = preset_defaults(cfg.preset, cfg.method)
    flags = ["--preset", cfg.preset, "--method", cfg.method]
    names = [f.name for f in dataclasses.fields(TrainConfig) if f.name not in ("env", "preset", "method")]
    names += [f.name for f in dataclasses.fields(PlexConfig) if f.init]
    for name in names:
        value = setting(cfg, name)
        if name in OUTPUT_FIELDS or value == setting(base, name):
            continue
        flag = "--" + name.replace("_", "-")
        if isinstance(value, bool):
            flags.append(flag if value else "--no-" + name.replace("_", "-"))
        elif isinstance(value, (tuple, list)):
            flags += [flag, *map(str, value)]
        else:
            flags += [flag, str(value)]
    return "python -m plex_ma.train " + " ".join(shlex.quote(f) for f in flags)


def parse(argv: list[str] | None = None) -> TrainConfig:
    """Parse the command line: the preset first, then every flag on top of it."""
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--preset", default="cpu")
    pre.add_argument("--method", default="plex-gru")
    known, _ = pre.parse_known_args(argv)
    if known.method not in get_args(Method):
        raise ValueError(f"argument --method: invalid choice {known.method!r}; choose from {list(get_args(Method))}")
    try:
        default = preset_defaults(known.preset, known.method)
    except ValueError:
        default = TrainConfig()  # tyro reports the bad preset
    with on_parse_error(_parse_error):
        cfg = tyro.cli(TrainConfig, default=default, args=argv, prog="python -m plex_ma.train")
    return validate(cfg)


def _parse_error(event) -> None:
    """A tyro parse error as a ValueError of one line, naming the flag and the problem."""
    arg = getattr(event, "argument", None)
    where = f"argument {arg.display_name()}: " if arg is not None else ""
    if getattr(event, "message", None):
        raise ValueError(where + event.message)
    if getattr(event, "choices", None):
        raise ValueError(f"{where}invalid choice {event.value!r}; choose from {list(event.choices)}")
    if getattr(event, "tokens", None):
        raise ValueError(f"unrecognized arguments: {' '.join(event.tokens)}")
    if getattr(event, "missing_arguments", None):
        raise ValueError(f"missing arguments: {', '.join(a.arg.display_name() for a in event.missing_arguments)}")
    if getattr(event, "reason", None) == "too_few_values":
        raise ValueError(where + "expected a value")
    # any other event: tyro's own message
