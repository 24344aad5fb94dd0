"""DD-PPO on torch.distributed (gloo, CPU): torchrun runs, gradient all-reduce, dead workers.

Every subprocess has a timeout, so a hang fails the test instead of blocking CI."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time

import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp
from torch import nn

from plex_ma.trainers import distributed
from plex_ma.trainers.checkpoint import load_checkpoint
from plex_ma.trainers.ppo import PPOConfig, RolloutBuffer, ppo_update

pytestmark = pytest.mark.skipif(not dist.is_available() or not dist.is_gloo_available(), reason="needs gloo")

TINY = ["--preset", "smoke", "--num-envs", "2", "--num-scenes", "2", "--executor-hidden", "32", "--rollout-steps", "16",
        "--n-pl", "2", "--ppo-epochs", "1", "--num-minibatches", "1", "--torch-threads", "1", "--no-progress"]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def child_env(**extra) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in distributed.ENV_VARS}
    env.update(OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1", **{k: str(v) for k, v in extra.items()})
    return env


def test_single_process_needs_no_group():
    assert distributed.context().world_size == 1 and not distributed.context().active
    saved = {k: os.environ.pop(k) for k in distributed.ENV_VARS if k in os.environ}
    try:
        ctx = distributed.init_from_env()
        assert not ctx.active and ctx.is_main and ctx.seed_offset == 0 and not dist.is_initialized()
    finally:
        os.environ.update(saved)
    assert distributed.all_true(True) and not distributed.any_true(False)
    assert list(distributed.common_length([1, 2])) == [1, 2]


def test_torchrun_two_workers(tmp_path):
    """2 gloo workers x 2 worlds x 16 steps = 64 steps per update; 128 steps = 2 updates."""
    run = tmp_path / "run"
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node=2", "--standalone", "-m", "plex_ma.train",
           *TINY, "--total-steps", "128", "--checkpoint-interval", "100", "--run-dir", str(run)]
    p = subprocess.run(cmd, cwd=tmp_path, env=child_env(), capture_output=True, text=True, timeout=150)
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    assert p.stdout.count("training plex-gru") == 1 and "x 2 workers (gloo)" in p.stdout  # rank 0 alone prints
    state = load_checkpoint(run / "latest.pt")
    assert state["step"] == 128 and state["updates"]["executor"] == 2
    n = sum(state["updates"].values())  # one save (the final one), by rank 0
    assert sorted(x.name for x in run.glob("*.pt")) == [f"ckpt_{n:06d}.pt", "latest.pt"]
    assert not list(run.glob(".*.tmp"))
    steps = [json.loads(x)["step"] for x in (run / "metrics.jsonl").read_text().splitlines()]
    assert steps == [64, 128]  # one metrics line per update: rank 0 alone logs, steps are totals


# ---------------------------------------------------------------- gradient all-reduce
class TinyPolicy(nn.Module):
    """A categorical policy over 3 actions from a 4-vector, with a value head."""

    def __init__(self):
        super().__init__()
        self.pi, self.v = nn.Linear(4, 3), nn.Linear(4, 1)

    def evaluate_actions(self, obs, action):
        d = torch.distributions.Categorical(logits=self.pi(obs["x"]))
        return d.log_prob(action), d.entropy(), self.v(obs["x"])[..., 0]


def _worker(rank: int, port: int, out_dir: str) -> None:
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank), WORLD_SIZE="2",
                      LOCAL_RANK=str(rank))
    torch.set_num_threads(1)
    distributed.init_from_env(timeout_s=30)
    try:
        torch.manual_seed(0)
        policy = TinyPolicy()  # same init on both ranks
        g = torch.Generator().manual_seed(100 + rank)  # different data on each rank
        x = torch.randn(8, 4, generator=g)
        loss = policy.v(x).pow(2).mean() + policy.pi(x).logsumexp(-1).mean()
        loss.backward()
        local = [p.grad.clone() for p in policy.parameters()]
        distributed.average_gradients(policy)
        averaged = [p.grad.clone() for p in policy.parameters()]
        # PPO on planner-like batches of different sizes: 5 vs 6 transitions in 4 minibatches
        # are 3 vs 4 minibatches (torch.chunk), so the common count must pad the short rank.
        m = 5 + rank
        buf = RolloutBuffer(1, m)
        buf.add(0, obs={"x": torch.randn(m, 4, generator=g)}, actions=torch.randint(0, 3, (m,), generator=g),
                log_probs=torch.full((m,), -1.1), values=torch.zeros(m), rewards=torch.zeros(m),
                dones=torch.zeros(m, dtype=torch.bool))
        buf.data["advantages"] = torch.randn(1, m, generator=g)
        buf.data["returns"] = torch.randn(1, m, generator=g)
        opt = torch.optim.Adam(policy.parameters(), lr=1e-2)
        stats = ppo_update(policy, buf, opt, PPOConfig(update_epochs=2, num_minibatches=4), g)
        torch.save({"local": local, "averaged": averaged, "params": [p.detach().clone() for p in policy.parameters()],
                    "stats": stats}, os.path.join(out_dir, f"rank{rank}.pt"))
    finally:
        distributed.shutdown()


def test_gradients_identical_across_ranks_after_allreduce(tmp_path):
    ctx = mp.spawn(_worker, args=(free_port(), str(tmp_path)), nprocs=2, join=False)
    deadline = time.monotonic() + 60
    while not ctx.join(timeout=1):
        if time.monotonic() > deadline:
            for p in ctx.processes:
                p.kill()
            pytest.fail("the 2-process gloo workers hung")
    r0, r1 = (torch.load(tmp_path / f"rank{r}.pt", weights_only=False) for r in (0, 1))
    assert any(not torch.equal(a, b) for a, b in zip(r0["local"], r1["local"]))  # the data did differ
    for a, b, l0, l1 in zip(r0["averaged"], r1["averaged"], r0["local"], r1["local"]):
        assert torch.equal(a, b)
        torch.testing.assert_close(a, (l0 + l1) / 2)
    for a, b in zip(r0["params"], r1["params"]):  # same updates everywhere: no drift
        assert torch.equal(a, b)
    assert r0["stats"]["grad_norm"] > 0


def test_gradients_are_averaged_before_clipping(monkeypatch):
    """ppo_update hands the gradients to the workers' average after backward and before
    clipping: a stand-in for the all-reduce that scales them shows in the reported norm."""
    import plex_ma.trainers.ppo as ppo_module

    policy = TinyPolicy()
    buf = RolloutBuffer(1, 4)
    buf.add(0, obs={"x": torch.randn(4, 4)}, actions=torch.tensor([0, 1, 2, 0]), log_probs=torch.full((4,), -1.1),
            values=torch.zeros(4), rewards=torch.zeros(4), dones=torch.zeros(4, dtype=torch.bool))
    buf.data["advantages"], buf.data["returns"] = torch.randn(1, 4), torch.randn(1, 4)
    seen = []

    def hook(m):  # scale every gradient up 1000x: the reported norm (before clipping) shows it
        seen.append(1)
        for p in m.parameters():
            p.grad.mul_(1000.0)

    monkeypatch.setattr(ppo_module._dist, "average_gradients", hook)
    out = ppo_update(policy, buf, torch.optim.SGD(policy.parameters(), lr=0.0), PPOConfig(update_epochs=1,
                     num_minibatches=2))
    assert len(seen) == 2 and out["grad_norm"] > 1.0


# ---------------------------------------------------------------- dead or hung workers
def _launch_pair(tmp_path, timeout_s: int):
    port = free_port()
    procs = []
    for rank in (0, 1):
        env = child_env(MASTER_ADDR="127.0.0.1", MASTER_PORT=port, RANK=rank, WORLD_SIZE=2, LOCAL_RANK=rank)
        procs.append(subprocess.Popen(
            [sys.executable, "-m", "plex_ma.train", *TINY, "--total-steps", "100000", "--checkpoint-interval", "1000",
             "--dist-timeout", str(timeout_s), "--run-dir", str(tmp_path / "run")],
            cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True))
    return procs


def _wait_for_training(run, procs, limit=90.0):
    deadline = time.monotonic() + limit
    while not (run / "metrics.jsonl").exists() or not (run / "metrics.jsonl").read_text().strip():
        if time.monotonic() > deadline or any(p.poll() is not None for p in procs):
            for p in procs:
                p.kill()
            pytest.fail("the workers did not start training: " + "".join(p.communicate()[0][-2000:] for p in procs))
        time.sleep(0.2)


@pytest.mark.parametrize("how", ["kill", "hang"])
def test_a_dead_or_hung_worker_stops_the_other_with_a_clear_error(tmp_path, how):
    """kill -9 rank 1 (its sockets close) or SIGSTOP it (only the timeout can tell): rank 0
    must exit with an error naming the cause, within the --dist-timeout, not hang."""
    timeout_s = 10
    procs = _launch_pair(tmp_path, timeout_s)
    try:
        _wait_for_training(tmp_path / "run", procs)
        os.kill(procs[1].pid, signal.SIGKILL if how == "kill" else signal.SIGSTOP)
        t0 = time.monotonic()
        out, _ = procs[0].communicate(timeout=timeout_s + 50)
        waited = time.monotonic() - t0
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
            p.communicate()
    assert procs[0].returncode not in (0, None), out[-3000:]
    assert "WorkerLost" in out and "another worker died, hung for more than 10 s" in out, out[-3000:]
    assert waited < timeout_s + 45
