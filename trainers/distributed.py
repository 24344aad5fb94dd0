"""Decentralized distributed PPO (the DD-PPO scheme) on ``torch.distributed``, and graceful stops.

Launch with torchrun; every worker is one process that simulates its own ``num_envs`` worlds
(seeded apart by rank), collects its own rollouts and runs the same PPO updates, with the
gradients averaged over all workers after ``backward`` and before clipping (``ppo_update``
calls :func:`average_gradients`). Every worker therefore applies the same update to the same
parameters and the models never drift apart; no parameter server, no central learner::

    torchrun --nproc_per_node=2 --standalone -m plex_ma.train --preset cpu --num-envs 8

- The process group starts only when torchrun's variables (``RANK``, ``WORLD_SIZE``,
  ``LOCAL_RANK``, ``MASTER_ADDR``, ``MASTER_PORT``) say ``WORLD_SIZE > 1``; otherwise nothing
  here does anything and training is the single-process trainer, same code path.
- Backend: nccl when the networks run on CUDA (``--device``), each rank on its
  ``LOCAL_RANK`` GPU; gloo when they run on the CPU. ``PLEX_DIST_BACKEND`` overrides it for
  CUDA runs (with nccl, CPU tensors go through the worker's GPU for the all-reduce).
- Every collective has a finite timeout (``--dist-timeout`` seconds, also used for the
  start-up rendezvous). A worker that dies or hangs makes the others fail with
  :class:`WorkerLost`, whose message says so, instead of waiting forever.
- Rank 0 alone logs, records and writes checkpoints; rank 0 reads the checkpoint to resume
  and sends it to the others, so other nodes need no shared file system.
- Step counts are totals over all workers (each environment step adds
  ``num_envs * world_size``).

Graceful stop: :func:`graceful_stop` turns the first SIGTERM or SIGINT into a request that the
trainer checks after each update (all workers agree on it, see :func:`should_stop`): the
current rollout and its update finish, a checkpoint is written, and ``python -m
plex_ma.train`` exits with 128 + the signal number (143 for SIGTERM, 130 for SIGINT). A second
signal stops at once with the default action (losing the work since the last checkpoint).
"""

from __future__ import annotations

import contextlib
import os
import signal
from dataclasses import dataclass, field
from datetime import timedelta
from typing import Callable, Iterable, Iterator, TypeVar

import torch
import torch.distributed as dist
from torch import nn

from . import checkpoint
from .checkpoint import CheckpointError, remove_stale_temporaries

T = TypeVar("T")

ENV_VARS = ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT")
SEED_STRIDE = 1_000_003  # seeds of rank r's worlds and samplers are offset by r * SEED_STRIDE


class WorkerLost(RuntimeError):
    """A collective with the other workers failed: one died, hung past the timeout, or the
    network failed."""


@dataclass
class DistContext:
    rank: int = 0
    world_size: int = 1
    local_rank: int = 0
    backend: str | None = None
    device: torch.device = field(default_factory=lambda: torch.device("cpu"))
    timeout_s: float = 0.0

    @property
    def active(self) -> bool:
        return self.world_size > 1 and dist.is_available() and dist.is_initialized()

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    @property
    def seed_offset(self) -> int:
        return self.rank * SEED_STRIDE


_ctx = DistContext()


def context() -> DistContext:
    """This process's place in the run (a single-process context when not distributed)."""
    return _ctx


def init_from_env(timeout_s: float = 300.0, backend: str | None = None) -> DistContext:
    """Start the process group if torchrun's variables ask for more than one worker."""
    global _ctx
    world = int(os.environ.get("WORLD_SIZE", "1") or 1)
    if world <= 1 or "RANK" not in os.environ:
        _ctx = DistContext()
        return _ctx
    missing = [v for v in ("MASTER_ADDR", "MASTER_PORT") if v not in os.environ]
    if missing:
        raise RuntimeError(f"WORLD_SIZE={world} but {', '.join(missing)} not set: launch with torchrun "
                           f"(see docs/distributed.md)")
    rank, local = int(os.environ["RANK"]), int(os.environ.get("LOCAL_RANK", "0"))
    backend = backend or os.environ.get("PLEX_DIST_BACKEND") or ("nccl" if torch.cuda.is_available() else "gloo")
    device = torch.device("cpu")
    if backend == "nccl":
        torch.cuda.set_device(local)
        device = torch.device("cuda", local)
    if not dist.is_initialized():
        try:
            dist.init_process_group(backend, timeout=timedelta(seconds=timeout_s))
        except Exception as e:
            raise WorkerLost(f"rank {rank}/{world}: could not join the process group at "
                             f"{os.environ['MASTER_ADDR']}:{os.environ['MASTER_PORT']} within {timeout_s:g} s "
                             f"(--dist-timeout): {type(e).__name__}: {e}") from e
    _ctx = DistContext(rank, world, local, backend, device, timeout_s)
    return _ctx


def shutdown() -> None:
    """Leave the process group (after a normal end; a failed run just exits)."""
    global _ctx
    if dist.is_available() and dist.is_initialized():
        # all ranks leave together, so none tears the group down while rank 0 still saves
        # the last checkpoint
        _collective("the barrier before leaving the process group", dist.barrier)
        dist.destroy_process_group()
    _ctx = DistContext()


def _collective(what: str, fn: Callable[[], T]) -> T:
    try:
        return fn()
    except Exception as e:
        raise WorkerLost(
            f"rank {_ctx.rank} of {_ctx.world_size}: {what} failed; another worker died, hung for more than "
            f"{_ctx.timeout_s:g} s (--dist-timeout) or the network failed. Stopping this worker; rerun the "
            f"same command to resume from the last checkpoint. ({type(e).__name__}: {e})") from e


def _all_reduce(x: torch.Tensor, op, what: str) -> torch.Tensor:
    y = x.to(_ctx.device)
    _collective(what, lambda: dist.all_reduce(y, op=op))
    return y.to(x.device)


# ---------------------------------------------------------------- gradients and agreement
def average_gradients(params: nn.Module | Iterable[nn.Parameter]) -> None:
    """Replace every gradient by its mean over the workers (one all-reduce of a flat buffer).

    A parameter that has a gradient on some workers but not on others gets the sum of the
    gradients present divided by the number of workers. No-op when not distributed."""
    if not _ctx.active:
        return
    params = [p for p in (params.parameters() if isinstance(params, nn.Module) else params) if p.requires_grad]
    if not params:
        return
    has = torch.tensor([p.grad is not None for p in params], dtype=torch.float32, device=params[0].device)
    flat = torch.cat([(p.grad.detach() if p.grad is not None else torch.zeros_like(p)).reshape(-1).float()
                      for p in params] + [has])
    flat = _all_reduce(flat, dist.ReduceOp.SUM, "the gradient all-reduce")
    present = flat[-len(params):] > 0
    flat = flat[:-len(params)] / _ctx.world_size
    offset = 0
    for p, ok in zip(params, present.tolist()):
        n = p.numel()
        if ok:
            g = flat[offset:offset + n].view_as(p).to(p.dtype)
            if p.grad is None:
                p.grad = g.clone()
            else:
                p.grad.copy_(g)
        offset += n


def all_true(flag: bool) -> bool:
    """True when ``flag`` is true on every worker (``flag`` itself when not distributed)."""
    if not _ctx.active:
        return bool(flag)
    return bool(_all_reduce(torch.tensor([int(bool(flag))]), dist.ReduceOp.MIN, "an agreement all-reduce").item())


def any_true(flag: bool) -> bool:
    """True when ``flag`` is true on some worker (``flag`` itself when not distributed)."""
    if not _ctx.active:
        return bool(flag)
    return bool(_all_reduce(torch.tensor([int(bool(flag))]), dist.ReduceOp.MAX, "an agreement all-reduce").item())


def common_length(items: Iterable[T]) -> Iterator[T | None]:
    """The items, padded with None up to the longest count on any worker, so every worker
    takes part in as many gradient all-reduces (a worker with a smaller planner batch may
    cut it into fewer minibatches). The items themselves when not distributed."""
    if not _ctx.active:
        yield from items
        return
    items = list(items)
    n = int(_all_reduce(torch.tensor([len(items)]), dist.ReduceOp.MAX, "a minibatch-count all-reduce").item())
    yield from items
    for _ in range(n - len(items)):
        yield None


def broadcast_object(obj):
    """Rank 0's ``obj`` on every worker."""
    if not _ctx.active:
        return obj
    box = [obj if _ctx.is_main else None]
    _collective("a broadcast from rank 0", lambda: dist.broadcast_object_list(box, src=0, device=_ctx.device))
    return box[0]


# ---------------------------------------------------------------- trainer hooks
def find_resumable(run_dir):
    """``checkpoint.find_resumable`` on rank 0, its answer (or its error) sent to every worker."""
    if _ctx.is_main:
        remove_stale_temporaries(run_dir)  # left by a kill during a save; nothing is saving now
    if not _ctx.active:
        return checkpoint.find_resumable(run_dir)
    answer = None
    if _ctx.is_main:
        try:
            answer = ("ok", checkpoint.find_resumable(run_dir))
        except CheckpointError as e:
            answer = ("error", str(e))
    answer = broadcast_object(answer)
    if answer[0] == "error":
        raise CheckpointError(answer[1] if _ctx.is_main else f"rank 0: {answer[1]}")
    return answer[1]


def sync_start(trainer) -> None:
    """After building (and maybe resuming) a trainer: every worker takes rank 0's parameters,
    and workers other than rank 0 reseed their samplers apart. No-op when not distributed."""
    if not _ctx.active:
        return
    for m in trainer.nets.values():
        for t in list(m.parameters()) + list(m.buffers()):
            y = t.data.to(_ctx.device)
            _collective("the start-up parameter broadcast", lambda y=y: dist.broadcast(y, src=0))
            t.data.copy_(y.to(t.device))
    if not _ctx.is_main:
        seed = trainer.cfg.seed + _ctx.seed_offset + trainer.step
        torch.manual_seed(seed)
        trainer.gen.manual_seed(seed)


# ---------------------------------------------------------------- graceful stop
_stop_signal: int | None = None


def request_stop(signum: int = signal.SIGTERM) -> None:
    """Ask the trainer to stop after its current update (what the signal handler does)."""
    global _stop_signal
    _stop_signal = signum


def stop_signal() -> int | None:
    """The signal that asked for a stop, or None."""
    return _stop_signal


def should_stop() -> bool:
    """Checked by the trainers after every update: has any worker been asked to stop?"""
    return any_true(_stop_signal is not None)


@contextlib.contextmanager
def graceful_stop(signals=(signal.SIGTERM, signal.SIGINT)):
    """Within the block, the first of ``signals`` requests a stop (see the module docstring);
    a second one gets the default action at once. Restores the previous handlers on exit."""
    global _stop_signal
    _stop_signal = None

    def handler(signum, frame):
        if _stop_signal is not None:  # second signal: stop now
            signal.signal(signum, signal.SIG_DFL)
            if signum == signal.SIGINT:
                raise KeyboardInterrupt
            os.kill(os.getpid(), signum)
            return
        request_stop(signum)
        if _ctx.is_main:
            print(f"\nreceived {signal.Signals(signum).name}: finishing the current rollout and update, then saving "
                  f"a checkpoint (send it again to stop at once)", flush=True)

    previous = {}
    try:
        for s in signals:
            previous[s] = signal.signal(s, handler)
    except ValueError:  # not the main thread: no handlers, nothing to restore
        pass
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
