"""Where the networks run: ``--device {auto,cpu,cuda,cuda:N}``.

The simulator always runs on the CPU (numba threads over the worlds). The networks, the
rollout storage, GAE and the PPO updates live on the chosen device; observations cross to
it once per step, as one batch per agent, and actions come back as one array.
"""

from __future__ import annotations

import torch


class DeviceError(ValueError):
    """A device that this machine does not have."""


def resolve_device(name: str) -> torch.device:
    """``auto``: the first CUDA GPU when torch sees one, else the CPU. ``cuda`` or
    ``cuda:N`` raises :class:`DeviceError` on a machine without that GPU."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cpu":
        return torch.device("cpu")
    if name == "cuda" or name.startswith("cuda:"):
        if not torch.cuda.is_available():
            build = "a CPU-only build of torch" if torch.version.cuda is None else f"torch built for CUDA {torch.version.cuda}"
            raise DeviceError(f"--device {name}: no CUDA GPU is available here ({build}, torch {torch.__version__}); "
                              f"use --device cpu or --device auto")
        dev = torch.device(name)
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise DeviceError(f"--device {name}: this machine has {torch.cuda.device_count()} CUDA GPU(s)")
        return dev
    raise DeviceError(f"--device {name!r}: choose auto, cpu, cuda or cuda:N")


def describe(device: torch.device) -> dict:
    """The device and, for a GPU, its name (for benchmark and run reports)."""
    out = {"device": str(device)}
    if device.type == "cuda":
        out["gpu"] = torch.cuda.get_device_name(device)
    return out
