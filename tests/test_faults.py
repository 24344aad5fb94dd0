"""Faults through the CLI: kill -9 then resume, corrupt checkpoints, SIGTERM, a failing save.

Every subprocess has a timeout, so a hang fails the test instead of blocking CI."""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import time

import pytest
import torch

from plex_ma.config import replace
from plex_ma.trainers import distributed, make_trainer
from plex_ma.trainers.checkpoint import load_checkpoint
from tests.test_train import tiny

# 2 worlds x 16 steps = 32 steps per update
TINY = ["--preset", "smoke", "--num-envs", "2", "--num-scenes", "2", "--executor-hidden", "32", "--rollout-steps", "16",
        "--n-pl", "2", "--ppo-epochs", "1", "--num-minibatches", "1", "--torch-threads", "1", "--no-progress"]


def train_cmd(run, *flags) -> list[str]:
    return [sys.executable, "-m", "plex_ma.train", *TINY, "--run-dir", str(run), *flags]


def env() -> dict:
    e = {k: v for k, v in os.environ.items() if k not in distributed.ENV_VARS}
    return {**e, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}


def wait_for(cond, proc, limit: float, what: str) -> None:
    deadline = time.monotonic() + limit
    while not cond():
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            pytest.fail(f"{what}: " + proc.communicate()[0][-3000:])
        time.sleep(0.05)


@pytest.mark.slow  # four launches of the CLI: ~40 s idle, ~90 s on a loaded 2-core machine
def test_kill9_at_random_moments_then_resume(tmp_path):
    """kill -9 three times at random moments (checkpoint every update); each rerun of the same
    command resumes from the last checkpoint's step, and the last one finishes."""
    run, total = tmp_path / "run", 192  # 6 updates
    cmd = train_cmd(run, "--total-steps", str(total), "--checkpoint-interval", "1")
    rng = random.Random(0)
    last_step = 0
    for cycle in range(3):
        p = subprocess.Popen(cmd, cwd=tmp_path, env=env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        # kill at a random moment after this run's first new checkpoint (maybe during a save)
        wait_for(lambda: (run / "latest.pt").exists() and load_checkpoint(run / "latest.pt")["step"] > last_step,
                 p, 90, "no checkpoint")
        time.sleep(rng.uniform(0.0, 0.8))
        p.send_signal(signal.SIGKILL)
        out = p.communicate(timeout=30)[0]
        assert p.returncode == -signal.SIGKILL, out[-2000:]
        if cycle > 0:
            assert f"at step {last_step:,}" in out, out[-2000:]  # it resumed where the last run's checkpoint was
        state = load_checkpoint(run / "latest.pt")  # a kill never leaves latest.pt half-written
        assert state["step"] > last_step
        last_step = state["step"]
        if last_step >= total:
            break
    p = subprocess.run(cmd, cwd=tmp_path, env=env(), capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-2000:]
    if last_step < total:
        assert f"resuming from {run / 'latest.pt'} at step {last_step:,}" in p.stdout
    assert load_checkpoint(run / "latest.pt")["step"] == total
    assert not list(run.glob(".*.tmp"))  # temporaries of a killed save are cleared at start-up


def test_corrupt_latest_resumes_from_previous_numbered(tmp_path):
    run = tmp_path / "run"
    p = subprocess.run(train_cmd(run, "--total-steps", "64", "--checkpoint-interval", "1"), cwd=tmp_path, env=env(),
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr[-2000:]
    newest = max(run.glob("ckpt_*.pt"))
    data = (run / "latest.pt").read_bytes()
    (run / "latest.pt").write_bytes(data[: len(data) // 3])  # truncated, as by a full disk outside atomic_save
    p = subprocess.run(train_cmd(run, "--total-steps", "96", "--checkpoint-interval", "1"), cwd=tmp_path, env=env(),
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr[-2000:]
    assert "latest.pt: cannot be loaded (corrupt, truncated" in p.stderr and "trying an older checkpoint" in p.stderr
    assert f"resuming from {newest} at step 64" in p.stdout
    assert load_checkpoint(run / "latest.pt")["step"] == 96


def test_sigterm_saves_and_exits_143(tmp_path):
    run = tmp_path / "run"
    p = subprocess.Popen(train_cmd(run, "--total-steps", "1000000", "--checkpoint-interval", "1000"), cwd=tmp_path,
                         env=env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    metrics = run / "metrics.jsonl"
    wait_for(lambda: metrics.exists() and metrics.read_text().strip(), p, 90, "training did not start")
    p.send_signal(signal.SIGTERM)
    out = p.communicate(timeout=60)[0]
    assert p.returncode == 128 + signal.SIGTERM, out[-2000:]
    assert "received SIGTERM" in out and "checkpoint saved at step" in out
    state = load_checkpoint(run / "latest.pt")
    last = json.loads(metrics.read_text().splitlines()[-1])["step"]
    assert state["step"] == last > 0  # the rollout under way finished, was trained on and saved


def test_graceful_stop_in_process(tmp_path, monkeypatch):
    """A stop request ends training after the current update, with a checkpoint."""
    monkeypatch.setattr(distributed, "_stop_signal", None)  # restored (None) after the test
    cfg = tiny(tmp_path, total_steps=10_000, checkpoint_interval=1000)
    t = make_trainer(cfg, log=False)
    with distributed.graceful_stop():
        distributed.request_stop(signal.SIGTERM)
        t.train()
    assert distributed.stop_signal() == signal.SIGTERM
    assert load_checkpoint(tmp_path / "run" / "latest.pt")["step"] == cfg.num_envs * cfg.rollout_steps


def test_failing_save_during_training_keeps_the_previous_checkpoint(tmp_path, monkeypatch):
    """A save that fails (a full disk) stops training with the error; the checkpoint before it
    stays loadable and the next run resumes from it."""
    cfg = tiny(tmp_path, total_steps=160, checkpoint_interval=1)
    t = make_trainer(cfg, log=False)
    real_save, calls = torch.save, []

    def save(*a, **k):
        calls.append(1)
        if len(calls) > 2:  # the first checkpoint (numbered + latest) goes through, then the disk is full
            raise OSError(28, "No space left on device")
        return real_save(*a, **k)

    monkeypatch.setattr(torch, "save", save)
    with pytest.raises(OSError, match="No space"):
        t.train()
    monkeypatch.undo()
    assert load_checkpoint(tmp_path / "run" / "latest.pt")["step"] == 32
    assert not list((tmp_path / "run").glob(".*.tmp"))
    t2 = make_trainer(replace(cfg, total_steps=64), log=False)
    assert t2.step == 32
