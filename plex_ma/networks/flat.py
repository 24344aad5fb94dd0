"""The flat baselines' policies: PPO-GRU and PPO-SMT (:class:`FlatPolicy`, the executor's
network on the end goal) and PPO-GRU+map (:class:`FlatMapPolicy`, which also reads the
planner's ego map through its :class:`~plex_ma.networks.planner.MapEncoder`)."""

from __future__ import annotations

import torch

from plex_ma.envs.spaces import EGO_CHANNELS, EGO_SIZE
from plex_ma.networks.common import as_tensor
from plex_ma.networks.executor import Executor
from plex_ma.networks.planner import MAP_PLAN, MapEncoder


class FlatPolicy(Executor):
    """Flat PointNav baselines: PPO-GRU (Savva et al. 2019) and PPO-SMT (Fang et al. 2019).

    The executor's network with the end goal (``pointgoal``) in place of the sub-goal; the
    trainer passes ``starts`` only at episode starts, so the memory spans the episode. The
    SMT memory keeps the episode's last ``smt_memory`` steps (the trainer passes
    ``--smt-memory``, 128; episodes run up to 500 steps). Unlike Savva et al., the heads
    sit on the same 128-d output layer as the executor's, so the baselines and PLEX differ
    only in the hierarchy.
    """

    goal_key = "pointgoal"
    reads_ego_map = False  # the flat worlds need not keep ego maps (FlatMapPolicy's do)

    def __init__(self, memory: str = "gru", resolution: int = 128, smt_memory: int = 128, **kw):
        super().__init__(memory=memory, resolution=resolution, smt_memory=smt_memory, **kw)

    def with_map_plan(self, obs: dict) -> dict:
        """The observations the rollout stores (:meth:`FlatMapPolicy.with_map_plan` adds to them)."""
        return obs


class FlatMapPolicy(FlatPolicy):
    """PPO-GRU+map (``ppo-gru-map``): the flat PPO-GRU baseline that also reads the PLEX
    planner's ego map, the control arm that tells the hierarchy's gain from the map's.

    Observations: the flat ones and ``ego_map`` (B, C, 32, 32), the planner's (the flat worlds
    keep it when built with ``egomap=True``). The map goes through the planner's
    :class:`MapEncoder` (its trunk and, with ``value_iteration``, its value-iteration module,
    which reads the point goal as the planner reads its goal), and those features enter the
    memory beside the image features and the encoded goal; everything after the memory is
    :class:`FlatPolicy`'s. The value-iteration module has no parameters, so the trainer
    stores its read-out with each step (:meth:`with_map_plan`) and the PPO epochs reuse it.
    """

    reads_ego_map = True

    def __init__(self, memory: str = "gru", resolution: int = 128, ego_channels: int = 2,
                 value_iteration: bool = False, fine_map: bool = False, **kw):
        encoder = MapEncoder(ego_channels, value_iteration=value_iteration, fine_map=fine_map)
        super().__init__(memory=memory, resolution=resolution, extra_inputs=encoder.map_dim + encoder.vin_dim, **kw)
        self.map = encoder

    def with_map_plan(self, obs: dict) -> dict:
        """``obs`` and, with the value-iteration module, its read-out (:meth:`MapEncoder.with_map_plan`)."""
        return self.map.with_map_plan(obs, self.goal_key)

    def _map_inputs(self, obs: dict) -> tuple[torch.Tensor, torch.Tensor]:
        """The ego maps (B, C, S, S) and point goals (B, 2) of observations with any leading dims."""
        ego = as_tensor(obs["ego_map"], self.device, torch.float32)
        pointgoal = as_tensor(obs[self.goal_key], self.device, torch.float32)
        return ego.reshape(-1, *ego.shape[-3:]), pointgoal.reshape(-1, 2)

    def _inputs(self, obs: dict) -> tuple[torch.Tensor, torch.Tensor]:
        x, goal = super()._inputs(obs)
        plan = obs.get(MAP_PLAN)
        plan = None if plan is None else as_tensor(plan, self.device, torch.float32).reshape(-1, self.map.vin_dim + 2)
        feat = self.map(*self._map_inputs(obs), plan)
        return torch.cat([x, feat.view(*x.shape[:-1], -1)], dim=-1), goal

    def example_obs(self, batch: int = 1, generator: torch.Generator | None = None) -> dict:
        # mostly unseen cells, some free and some obstacles, as an ego map reads
        return {**super().example_obs(batch, generator),
                "ego_map": (torch.rand(batch, EGO_CHANNELS, EGO_SIZE, EGO_SIZE, generator=generator) < 0.2).float()}
