"""What the networks share: CleanRL's layer initialisation, the polar encoding of
(distance, direction) vectors, the conversion of observations to tensors and a
convolution trunk's output size."""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn


def layer_init(layer: nn.Module, std: float = math.sqrt(2), bias: float = 0.0) -> nn.Module:
    """Orthogonal weight with gain ``std`` and constant bias (CleanRL's init)."""
    nn.init.orthogonal_(layer.weight, std)
    nn.init.constant_(layer.bias, bias)
    return layer


def encode_polar(vec: torch.Tensor) -> torch.Tensor:
    """(..., 2) = (distance, direction rad) -> (..., 3) = (distance, cos, sin)."""
    return torch.stack([vec[..., 0], torch.cos(vec[..., 1]), torch.sin(vec[..., 1])], dim=-1)


def as_tensor(x, device: torch.device | None = None, dtype: torch.dtype | None = None) -> torch.Tensor:
    """``x`` (array, tensor or number) as a tensor on ``device``, sharing a numpy array's memory where it can."""
    if isinstance(x, np.ndarray):
        x = torch.from_numpy(x)
    return torch.as_tensor(x, device=device, dtype=dtype)


def _conv_out_dim(convs: nn.Module, shape: tuple[int, ...]) -> int:
    with torch.no_grad():
        return convs(torch.zeros(1, *shape)).flatten(1).shape[1]
