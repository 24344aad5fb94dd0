"""``--device``: the networks, rollouts and updates run where asked; a GPU that is not there
is a one-line error; ``auto`` is the CPU on a machine without CUDA (CI) and gives the same
first update as ``cpu``. The CUDA tests skip without a GPU."""

from __future__ import annotations

import json

import pytest
import torch

from plex_ma.config import parse
from plex_ma.trainers.device import DeviceError, describe, resolve_device
from plex_ma.trainers import make_trainer

from .test_train import tiny

needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
no_cuda = pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a CUDA GPU")


def first_update(tmp_path, method: str, device: str) -> tuple[torch.device, dict]:
    t = make_trainer(tiny(tmp_path, method=method, device=device, total_steps=32), log=False)
    t.train()
    worker = "policy" if "policy" in t.nets else "executor"
    return t.device, {k: v.detach().cpu().clone() for k, v in t.nets[worker].state_dict().items()}


def test_resolve_device_and_bad_names():
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    assert describe(torch.device("cpu")) == {"device": "cpu"}
    with pytest.raises(DeviceError, match="tpu"):
        resolve_device("tpu")
    with pytest.raises(ValueError, match="--device"):
        parse(["--preset", "smoke", "--device", "tpu"])


@no_cuda
def test_cuda_without_a_gpu_is_a_clear_error(capsys):
    with pytest.raises(DeviceError, match="no CUDA GPU"):
        resolve_device("cuda")
    from plex_ma.bench import main as bench_main
    from plex_ma.evaluate import main as evaluate_main
    from plex_ma.train import main as train_main

    for cli, argv in [(train_main, ["--preset", "smoke", "--device", "cuda"]),
                      (evaluate_main, ["--planner", "oracle", "--executor", "oracle", "--device", "cuda"]),
                      (bench_main, ["train", "--preset", "smoke", "--device", "cuda:1"])]:
        with pytest.raises(SystemExit) as e:
            cli(argv)
        err = capsys.readouterr().err
        assert e.value.code == 2 and "no CUDA GPU" in err and "Traceback" not in err


@pytest.mark.parametrize("method", ["plex-gru", "ppo-gru"])
def test_networks_and_rollouts_live_on_the_device(tmp_path, method):
    t = make_trainer(tiny(tmp_path, method=method, device="cpu", total_steps=32), log=False)
    t.train()
    assert t.device == torch.device("cpu")
    assert all(p.device == t.device for m in t.nets.values() for p in m.parameters())
    for opt in t.opts.values():
        for state in opt.state.values():
            assert all(v.device == t.device for v in state.values() if isinstance(v, torch.Tensor) and v.ndim)


@no_cuda
@pytest.mark.parametrize("method", ["plex-gru", "ppo-gru"])
def test_auto_gives_the_same_first_update_as_cpu(tmp_path, method):
    dev_cpu, cpu = first_update(tmp_path / "cpu", method, "cpu")
    dev_auto, auto = first_update(tmp_path / "auto", method, "auto")
    assert dev_cpu == dev_auto == torch.device("cpu")
    assert all(torch.equal(cpu[k], auto[k]) for k in cpu)


@needs_cuda
@pytest.mark.parametrize("method", ["plex-gru", "ppo-gru"])
def test_cuda_training_updates_on_the_gpu_and_resumes_on_the_cpu(tmp_path, method):
    dev, after = first_update(tmp_path, method, "cuda")
    assert dev.type == "cuda"
    # the CUDA run's checkpoint resumes on the CPU with the weights it saved
    t = make_trainer(tiny(tmp_path, method=method, device="cpu", total_steps=32), log=False)
    worker = "policy" if "policy" in t.nets else "executor"
    assert t.step == 32 and t.device.type == "cpu"
    assert all(torch.equal(v, after[k]) for k, v in t.nets[worker].state_dict().items())


@needs_cuda
def test_bench_train_reports_the_gpu(capsys):
    from plex_ma.bench import main as bench_main

    bench_main(["train", "--preset", "smoke", "--steps", "256", "--device", "cuda", "--json"])
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert out["device"].startswith("cuda") and out["gpu"] and out["steps_per_second"] > 0
