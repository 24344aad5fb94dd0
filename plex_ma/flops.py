"""FLOP counts of the policies and this machine's matmul speed (used by ``python -m plex_ma.bench train``).

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
        memory = model.split_state(state)[0]  # a view of the memory's part
        if memory.ndim == 3:  # SMT: (B, capacity, dim + 1), last channel = slot filled
            n = memory.shape[1] if memory_filled is None else memory_filled
            if n > 0:
                memory[:, -n:, -1] = 1.0
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
