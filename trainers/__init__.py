"""PPO trainers for PLEX and the flat baselines; :func:`make_trainer` picks one by method."""

from __future__ import annotations

from collections.abc import Callable

from plex_ma.config import TrainConfig

from .base import Trainer
from .flat import FlatTrainer
from .plex import PlexTrainer


def make_trainer(cfg: TrainConfig, log: bool = True, record: Callable[[Trainer], object] | None = None) -> Trainer:
    """The trainer of ``cfg.method``; ``log`` and ``record`` as in :class:`~plex_ma.trainers.base.Trainer`."""
    return (PlexTrainer if cfg.method.startswith("plex") else FlatTrainer)(cfg, log, record)
