"""The flat baselines' policies: PPO-GRU and PPO-SMT (:class:`FlatPolicy`, the executor's
network on the end goal) and PPO-GRU+map (:class:`FlatMapPolicy`, whose heads also read the
planner's ego map as the planner's heads do)."""

from __future__ import annotations

import torch
from torch import nn

from plex_ma.envs.sim.core import NUM_ACTIONS
from plex_ma.envs.spaces import EGO_CHANNELS, EGO_SIZE
from plex_ma.networks.common import as_tensor, layer_init
from plex_ma.networks.executor import Executor
from plex_ma.networks.planner import (MAP_PLAN, PLAN_FEATURES, Head, MapEncoder, goal_feature_count, plan_features,
                                      planner_goal_features)


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
    planner's ego map, in the planner's form, the control arm that tells the hierarchy's gain
    from the map's.

    Observations: the flat ones and ``ego_map`` (B, C, 32, 32), the planner's (the flat worlds
    keep it when built with ``egomap=True``). The memory reads what PPO-GRU's reads (RGB-D and
    the point goal). The heads read what the planner's heads read (:class:`Planner`), with the
    policy's own 128-d memory output (``tanh``, as the executor's ELI) in the ELI's place:
    ``map_fc`` (FC 512 over the planner's map trunk, that output, the goal features and the
    value-iteration features), the goal features and the plan features, through heads of the
    planner's form (:class:`Head`). The map encoder is the planner's :class:`MapEncoder`; its
    value-iteration module has no parameters, so the trainer stores its read-out with each
    step (:meth:`with_map_plan`) and the PPO epochs reuse it. The map stays out of the
    recurrence, so the epochs run the map's layers over all steps at once.
    """

    reads_ego_map = True

    def __init__(self, memory: str = "gru", resolution: int = 128, ego_channels: int = 2,
                 value_iteration: bool = False, fine_map: bool = False, trunk_stride: int = 1, hidden: int = 512,
                 head_hidden: int = 256, goal_rbf: bool = False, **kw):
        super().__init__(memory=memory, resolution=resolution, **kw)
        self.map = MapEncoder(ego_channels, value_iteration=value_iteration, fine_map=fine_map, trunk_stride=trunk_stride)
        self.goal_rbf, self.goal_dim = goal_rbf, goal_feature_count(goal_rbf)
        self.map_fc = nn.Sequential(
            layer_init(nn.Linear(self.map.map_dim + self.eli_dim + self.goal_dim + self.map.vin_dim, hidden)), nn.ReLU())
        feat = hidden + self.goal_dim + PLAN_FEATURES
        self.actor = Head(feat, head_hidden, NUM_ACTIONS, 0.01)
        self.critic = Head(feat, head_hidden, 1, 1.0)

    @property
    def device(self) -> torch.device:
        return self.eli_head.weight.device

    def with_map_plan(self, obs: dict) -> dict:
        """``obs`` and, with the value-iteration module, its read-out (:meth:`MapEncoder.with_map_plan`)."""
        return self.map.with_map_plan(obs, self.goal_key)

    def _inputs(self, obs: dict) -> tuple[torch.Tensor, torch.Tensor]:
        """The memory's input (PPO-GRU's) and, for the heads, (..., 3 + map reading): the
        encoded goal, then the trunk's features, the goal features, the value-iteration
        features and the plan features."""
        x, goal = super()._inputs(obs)
        lead = x.shape[:-1]
        ego = as_tensor(obs["ego_map"], self.device, torch.float32)
        pointgoal = as_tensor(obs[self.goal_key], self.device, torch.float32).reshape(-1, 2)
        plan = obs.get(MAP_PLAN)
        plan = None if plan is None else as_tensor(plan, self.device, torch.float32).reshape(-1, self.map.vin_dim + 2)
        trunk, vin, vin_subgoal = self.map.read_map(ego.reshape(-1, *ego.shape[-3:]), pointgoal, plan)
        parts = [trunk, planner_goal_features(pointgoal, self.goal_rbf)] + ([vin] if vin is not None else [])
        parts.append(plan_features(pointgoal, vin_subgoal))
        reading = torch.cat(parts, dim=-1)
        return x, torch.cat([goal, reading.view(*lead, -1)], dim=-1)

    def _heads(self, out: torch.Tensor, goal: torch.Tensor):
        eli = torch.tanh(self.eli_head(out))
        m, g = self.map.map_dim, self.goal_dim
        trunk, goal_feats = goal[..., 3:3 + m], goal[..., 3 + m:3 + m + g]
        vin_feats, plan = goal[..., 3 + m + g:-PLAN_FEATURES], goal[..., -PLAN_FEATURES:]
        h = self.map_fc(torch.cat([trunk, eli, goal_feats, vin_feats], dim=-1))
        h = torch.cat([h, goal_feats, plan], dim=-1)
        return self.actor(h), self.critic(h).squeeze(-1), eli

    def example_obs(self, batch: int = 1, generator: torch.Generator | None = None) -> dict:
        # mostly unseen cells, some free and some obstacles, as an ego map reads
        return {**super().example_obs(batch, generator),
                "ego_map": (torch.rand(batch, EGO_CHANNELS, EGO_SIZE, EGO_SIZE, generator=generator) < 0.2).float()}
