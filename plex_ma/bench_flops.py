"""FLOP counts of the policies and this machine's matmul speed, for ``python -m plex_ma.bench train``.

FLOPs count 2 per multiply-add (torch's convention), so MACs = FLOPs / 2. A PPO update
costs roughly 3x the forward FLOPs per sample per epoch (forward + backward).
"""

from __future__ import annotations

import time

import torch
from torch.utils.flop_counter import FlopCounterMode


def model_flops_per_step(model: torch.nn.Module, batch: int = 1, by_module: bool = False,
                         memory_filled: int | None = None):
    """FLOPs of one ``act`` call per env (one decision for the planner, one action for the
    executor / flat policy), counted over conv, linear, GRU and attention matmuls.

    An SMT's cost grows with the number of tokens in its memory: ``memory_filled`` of them
    before the step (default: a full memory; a PLEX executor holds at most N_EX = 10).
    With ``by_module`` returns (total, {module name: FLOPs}) instead.
    """
    obs = model.example_obs(batch)
    counter = FlopCounterMode(display=False)
    if hasattr(model, "initial_state"):
        state = model.initial_state(batch)
        if state.ndim == 3:  # SMT: (B, capacity, dim + 1), last channel = slot filled
            n = state.shape[1] if memory_filled is None else memory_filled
            if n > 0:
                state[:, -n:, -1] = 1.0
        with counter:
            model.act(obs, state, torch.zeros(batch, dtype=torch.bool))
    else:
        with counter:
            model.act(obs)
    total = counter.get_total_flops() / batch
    if not by_module:
        return total
    modules = {name: sum(c.values()) / batch for name, c in counter.get_flop_counts().items()}
    return total, modules


def matmul_gflops(n: int = 1024, seconds: float = 0.3, trials: int = 5, dtype: torch.dtype = torch.float32,
                  device: str | torch.device = "cpu") -> float:
    """Peak GFLOP/s of (n x n) @ (n x n) matmuls on ``device`` (the CPU: with torch's current
    threads): the best of ``trials`` runs of about ``seconds`` each, after one warm-up. (A
    single run varies by up to 2x on a shared machine; the best run is the machine's peak.)"""
    a, b = torch.randn(n, n, dtype=dtype, device=device), torch.randn(n, n, dtype=dtype, device=device)
    out = torch.empty(n, n, dtype=dtype, device=device)
    sync = torch.cuda.synchronize if torch.device(device).type == "cuda" else (lambda: None)
    torch.mm(a, b, out=out)
    sync()
    best = 0.0
    for _ in range(trials):
        reps, t0 = 0, time.perf_counter()
        while True:
            torch.mm(a, b, out=out)
            reps += 1
            sync()
            dt = time.perf_counter() - t0
            if dt >= seconds:
                break
        best = max(best, 2 * n ** 3 * reps / dt / 1e9)
    return best


def bench_train(preset: str = "cpu", method: str = "plex-gru", steps: int = 8192, num_envs: int | None = None,
                resolution: int | None = None, seed: int = 0, overrides: dict[str, str] | None = None,
                device: str = "auto") -> dict:
    """End-to-end training throughput of a short run (``python -m plex_ma.bench train``).

    Reports steps/s, the shares of wall time in simulation, inference and the update, the
    models' FLOPs per step, this machine's matmul GFLOP/s with the same torch threads, and
    the update's efficiency: the update's FLOPs (3x forward per sample per epoch) over its
    wall time, divided by the matmul figure. ``overrides`` sets further TrainConfig fields
    from strings (``{"num_minibatches": "4"}``); an unknown field raises ValueError.
    """
    import dataclasses
    import tempfile

    from plex_ma.config import preset_defaults, validate
    from plex_ma.trainers.device import describe
    from plex_ma.trainers.plex import make_trainer

    cfg = preset_defaults(preset, method)
    over = {"total_steps": steps, "progress": False, "seed": seed, "checkpoint_interval": 10**9, "device": device}
    if num_envs:
        over["num_envs"] = num_envs
    if resolution:
        over["resolution"] = resolution
    fields = {f.name: f for f in dataclasses.fields(cfg)}
    for key, text in (overrides or {}).items():
        if key not in fields:
            raise ValueError(f"--set: TrainConfig has no field {key!r}")
        current = getattr(cfg, key)
        if isinstance(current, bool):
            if text.lower() not in ("true", "false", "1", "0"):
                raise ValueError(f"--set {key}: expected true or false, got {text!r}")
            over[key] = text.lower() in ("true", "1")
        elif isinstance(current, (int, float)):
            try:
                over[key] = type(current)(text)
            except ValueError:
                raise ValueError(f"--set {key}: expected a {type(current).__name__}, got {text!r}") from None
        else:
            over[key] = text
    with tempfile.TemporaryDirectory() as d:
        cfg = validate(dataclasses.replace(cfg, run_dir=d, **over))
        trainer = make_trainer(cfg, log=True)
        result = trainer.train()
        trainer.close()
    flops = {k: model_flops_per_step(m.cpu()) for k, m in trainer.nets.items()}
    worker = "executor" if "executor" in flops else "policy"
    if cfg.torch_threads:
        torch.set_num_threads(cfg.torch_threads)
    peak = matmul_gflops(device=trainer.device)
    update_s = result["perf/share_update"] * steps / result["perf/fps"]
    # forward + backward ~ 3x the forward FLOPs, per stored transition and epoch
    n_worker = trainer.updates[worker] * cfg.num_envs * cfg.rollout_steps
    n_planner = trainer.updates.get("planner", 0) * cfg.n_pl * cfg.num_envs
    update_flops = 3 * cfg.ppo_epochs * (n_worker * flops[worker] + n_planner * flops.get("planner", 0.0))
    achieved = update_flops / max(update_s, 1e-9) / 1e9
    return {"benchmark": "train", "method": method, "preset": preset, "num_envs": cfg.num_envs,
            "resolution": cfg.resolution, "steps": steps, "steps_per_second": result["perf/fps"],
            "share_sim": result["perf/share_sim"], "share_inference": result["perf/share_inference"],
            "share_update": result["perf/share_update"], "share_other": result["perf/share_other"],
            "model_flops_per_step": flops,
            "matmul_gflops": peak, "update_gflops": achieved, "update_efficiency": achieved / peak,
            "torch_threads": torch.get_num_threads(), **describe(trainer.device), "overrides": dict(overrides or {})}
