"""The PLEX planner (:class:`Planner`, every output learned) and its reading of the ego map
(:class:`MapEncoder`, which the flat policy with the map shares)."""

from __future__ import annotations

import math
from typing import TypedDict

import numpy as np
import torch
from torch import nn
from torch.distributions import Categorical, Normal

from plex_ma.envs.rules import ELI_DIM
from plex_ma.envs.spaces import EGO_CHANNELS, EGO_SIZE
from plex_ma.networks.common import _conv_out_dim, as_tensor, layer_init
from plex_ma.networks.value_iteration import SUBGOAL_REACH, ValueIteration

# float32(pi) is slightly *above* pi, so a float32 angle clamped to it can fail a float64
# `|theta| <= pi` range check; clamp to the float32 just below pi instead.
PI32 = float(np.nextafter(np.float32(np.pi), np.float32(0)))

GOAL_FEATURES = 5  # planner_goal_features' width
GOAL_RBF_CENTRES = tuple(0.1 * k for k in range(11))  # m: the goal distance's Gaussian bumps (goal_rbf)
GOAL_RBF_WIDTH = 0.1  # m
PLAN_FEATURES = 4  # plan_features' width
SUBGOAL_MARGIN = 0.05  # m: sub-goals lie at least this far beyond the executor's sub-goal radius
MAP_PLAN = "map_plan"  # observation key of a stored value-iteration read-out (MapEncoder.map_plan)
STOP_INIT_LOGIT = -3.0  # the stop head's constant starting bias: p(stop) ~0.05 in every state


class PlannerAct(TypedDict):
    """A planner decision per env, as :meth:`Planner.act` returns it."""
    stop: torch.Tensor  # (B,) long: 1 ends the episode
    raw_subgoal: torch.Tensor  # (B, 2) the Gaussian sample (rho, theta): what PPO stores and scores
    subgoal: torch.Tensor  # (B, 2) the sample mapped into the action box: what the env gets
    log_prob: torch.Tensor  # (B,)
    value: torch.Tensor  # (B,)


def goal_feature_count(rbf: bool = False) -> int:
    """The width of :func:`planner_goal_features`."""
    return GOAL_FEATURES + (len(GOAL_RBF_CENTRES) if rbf else 0)


def planner_goal_features(goal: torch.Tensor, rbf: bool = False) -> torch.Tensor:
    """(B, 2) goal (distance m, direction rad) -> (B, 5): distance / 10, cos, sin, and
    exp(-distance / 0.5) and min(distance, 2) for a fine reading near the goal (where
    the planner decides to stop). With ``rbf``, then the distance expanded in Gaussian bumps
    (``GOAL_RBF_CENTRES``, 0.1 m apart over 0-1 m, width 0.1 m), so that 0.1 m near the goal
    moves several inputs by about half their range."""
    d, th = goal[..., 0], goal[..., 1]
    feats = [d / 10, torch.cos(th), torch.sin(th), torch.exp(-d / 0.5), d.clamp(max=2.0)]
    if rbf:
        feats += [torch.exp(-((d - c) / GOAL_RBF_WIDTH) ** 2) for c in GOAL_RBF_CENTRES]
    return torch.stack(feats, dim=-1)


def plan_features(goal: torch.Tensor, vin_subgoal: torch.Tensor | None) -> torch.Tensor:
    """(B, PLAN_FEATURES): where a sub-goal could go, as positions in the agent's frame
    (forward, left; m), the frame in which the planner's sub-goal is sampled: the goal clipped
    to the read-out's reach ``SUBGOAL_REACH``, and the value-iteration read-out's sub-goal
    (zeros without the module). Input features only: the heads learn what to make of them."""
    d, th = goal[..., 0].clamp(max=SUBGOAL_REACH), goal[..., 1]
    parts = [d * torch.cos(th), d * torch.sin(th)]
    if vin_subgoal is None:
        parts += [torch.zeros_like(d), torch.zeros_like(d)]
    else:
        rho, theta = vin_subgoal[..., 0], vin_subgoal[..., 1]
        parts += [rho * torch.cos(theta), rho * torch.sin(theta)]
    return torch.stack(parts, dim=-1)


class Head(nn.Module):
    """A policy or value head: an MLP (``hidden`` ReLU units) plus a linear path from the
    same input, each output layer started at gain ``std`` (CleanRL's init, no hand-set
    weights). The linear path lets a head follow an input feature (the planner's sub-goal
    positions) without first having to learn it through the ReLUs."""

    def __init__(self, inputs: int, hidden: int, out: int, std: float):
        super().__init__()
        self.mlp = nn.Sequential(layer_init(nn.Linear(inputs, hidden)), nn.ReLU(),
                                 layer_init(nn.Linear(hidden, out), std=std))
        self.linear = layer_init(nn.Linear(inputs, out), std=std)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.mlp(x) + self.linear(x)


class MapEncoder(nn.Module):
    """The planner's reading of the ego map, one definition for the PLEX planner (a subclass)
    and the flat PPO-GRU+map policy (:class:`FlatMapPolicy`, which holds one):

    - ``convs``: the paper's trunk, conv 4x4/2 and conv 3x3/1 (ReLU) over the map's first
      ``ego_channels`` channels (obstacles, explored floor), flattened (``map_dim`` features:
      10,816; with ``trunk_stride`` 2 the second conv is 3x3/2 and they are 3,136);
    - ``vin`` (with ``value_iteration``, else None): a :class:`ValueIteration` module over
      the map (with ``fine_map``, its 0.25 m quarter cells) and the goal (``vin_dim``
      features, which end with its sub-goal as (distance / ``SUBGOAL_REACH``, cos, sin)).
    """

    def __init__(self, ego_channels: int = 2, channels: tuple[int, int] = (32, 64), map_size: int = 32,
                 value_iteration: bool = False, fine_map: bool = False, trunk_stride: int = 1):
        super().__init__()
        self.convs = nn.Sequential(
            layer_init(nn.Conv2d(ego_channels, channels[0], 4, stride=2)), nn.ReLU(),
            layer_init(nn.Conv2d(channels[0], channels[1], 3, stride=trunk_stride)), nn.ReLU(),
            nn.Flatten(),
        )
        self.map_dim = _conv_out_dim(self.convs, (ego_channels, map_size, map_size))
        self.vin = ValueIteration(fine=fine_map) if value_iteration else None
        self.vin_dim = self.vin.out_dim if self.vin is not None else 0

    def map_plan(self, ego: torch.Tensor, goal: torch.Tensor) -> torch.Tensor:
        """The value-iteration read-out (B, vin_dim + 2): its features and its sub-goal
        (distance m, direction rad). It has no parameters, so the rollouts store it with each
        observation (under ``MAP_PLAN``) and the PPO epochs reuse it."""
        feats, subgoal = self.vin(ego, goal)
        return torch.cat([feats, subgoal], dim=1)

    @torch.no_grad()
    def with_map_plan(self, obs: dict, goal_key: str = "goal") -> dict:
        """``obs`` and, with the value-iteration module, its read-out under ``MAP_PLAN`` (a
        numpy array (B, vin_dim + 2)) for the goal under ``goal_key``: what the trainers
        store with each decision or step."""
        if self.vin is None or MAP_PLAN in obs:
            return obs
        dev = self.convs[0].weight.device
        ego = as_tensor(obs["ego_map"], dev, torch.float32)
        goal = as_tensor(obs[goal_key], dev, torch.float32)
        return {**obs, MAP_PLAN: self.map_plan(ego, goal).cpu().numpy()}

    def read_map(self, ego: torch.Tensor, goal: torch.Tensor, plan: torch.Tensor | None = None
                 ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
        """ego (B, C, S, S), goal (B, 2) = (distance m, direction rad) -> the trunk's features
        (B, map_dim), the value-iteration features (B, vin_dim) and its sub-goal (B, 2) =
        (distance m, direction rad) (both None without the module). ``plan``, where given, is
        :meth:`map_plan`'s read-out computed beforehand."""
        trunk = self.trunk(ego)
        if self.vin is None:
            return trunk, None, None
        if plan is None:
            plan = self.map_plan(ego, goal)
        return trunk, plan[:, :self.vin_dim], plan[:, self.vin_dim:]

    def trunk(self, ego: torch.Tensor) -> torch.Tensor:
        """ego (B, C, S, S) -> the trunk's features (B, map_dim), from the map's first ``ego_channels`` channels."""
        return self.convs(ego[:, :self.convs[0].in_channels])

    def forward(self, ego: torch.Tensor, goal: torch.Tensor, plan: torch.Tensor | None = None) -> torch.Tensor:
        """(B, map_dim + vin_dim): the trunk's and the value-iteration module's features
        (``plan`` as in :meth:`read_map`)."""
        trunk, vin, _ = self.read_map(ego, goal, plan)
        return trunk if vin is None else torch.cat([trunk, vin], dim=1)


class Planner(MapEncoder):
    """Planner: ego map CNN + ELI + goal -> 512 -> (+ goal and plan features) -> heads: stop
    logits, Gaussian sub-goal, value.

    The paper gives the trunk (conv 4x4/2, conv 3x3/1, flatten, concatenate the ELI, FC 512,
    concatenate the goal vector) and leaves the heads open. Here the goal features
    (:func:`planner_goal_features`) also enter the FC layer, so that map and goal interact,
    and each head (:class:`Head`) reads the FC output, the goal features and the plan
    features (:func:`plan_features`: the goal, and the value-iteration read-out's sub-goal,
    as positions in the agent's frame).

    Every output is a learned function under standard initialisation (docs/spec.md section
    6): there is no hand-set state-dependent term, so the untrained planner's sub-goals
    scatter round the agent wherever the goal is. The stop logit starts with a constant bias
    (``STOP_INIT_LOGIT``, p(stop) about 0.05 in every state): at a coin flip, episodes ended
    within a decision or two, the executor had nothing to learn from and resets took most of
    the time.

    Sub-goal action: the policy samples an *unbounded* raw sub-goal position (forward, left)
    in metres in the agent's frame from two Gaussians with state-dependent means and
    state-independent learnable log-stds (started at std ``init_std``). A position, unlike
    (distance, direction), is a linear function of the plan features, and it has no
    wrap-around. The raw sample is what the rollout buffer stores and what ``log_prob`` is
    computed on; only the copy sent to the environment is mapped into the action box by
    ``subgoal_to_env``: (distance, direction) with the distance clipped to
    [``min_subgoal_distance``, rho_max]. Given the executor's ``subgoal_radius``,
    ``min_subgoal_distance`` lies ``SUBGOAL_MARGIN`` beyond it: a nearer sub-goal pays the
    executor nothing (envs/rules.py), so it would STOP on the spot.
    """

    def __init__(self, ego_channels: int = 2, eli_dim: int = ELI_DIM, use_eli: bool = True,
                 rho_max: float = 4.0, hidden: int = 512, channels: tuple[int, int] = (32, 64),
                 map_size: int = 32, init_std: float = 0.5, head_hidden: int = 256,
                 value_iteration: bool = False, subgoal_radius: float | None = None, fine_map: bool = False,
                 subgoal_forward: float = 0.0, trunk_stride: int = 1, goal_rbf: bool = False):
        # ``convs`` and ``vin`` (the map reading) keep their names: checkpoints key on them
        super().__init__(ego_channels, channels, map_size, value_iteration, fine_map, trunk_stride)
        self.eli_dim, self.use_eli, self.rho_max = eli_dim, use_eli, rho_max
        self.goal_rbf, self.goal_dim = goal_rbf, goal_feature_count(goal_rbf)
        # no sub-goal within the executor's radius (None: any distance)
        self.min_subgoal_distance = 0.0 if subgoal_radius is None else min(subgoal_radius + SUBGOAL_MARGIN, rho_max)
        self.fc = nn.Sequential(layer_init(nn.Linear(self.map_dim + eli_dim + self.goal_dim + self.vin_dim, hidden)),
                                nn.ReLU())
        feat = hidden + self.goal_dim + PLAN_FEATURES
        self.stop_logits = Head(feat, head_hidden, 2, 0.01)
        with torch.no_grad():  # a constant, the same in every state (docs/spec.md section 6 allows it)
            self.stop_logits.linear.bias[1] = STOP_INIT_LOGIT
        self.subgoal_mean = Head(feat, head_hidden, 2, 0.01)
        self.critic = Head(feat, head_hidden, 1, 1.0)
        if subgoal_forward:  # a constant start of the sub-goal mean, this far ahead in every state
            with torch.no_grad():
                self.subgoal_mean.linear.bias[0] += subgoal_forward
        self.subgoal_log_std = nn.Parameter(torch.full((2,), math.log(init_std)))

    def encode(self, obs: dict) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """The trunk: (FC output (B, hidden), goal features (B, goal_dim), the raw goal
        (B, 2), the value-iteration sub-goal (B, 2) or None). A stored read-out under
        ``MAP_PLAN`` replaces the module's (:meth:`MapEncoder.map_plan`)."""
        dev = self.convs[0].weight.device
        ego = as_tensor(obs["ego_map"], dev, torch.float32)
        raw_goal = as_tensor(obs["goal"], dev, torch.float32)
        goal = planner_goal_features(raw_goal, self.goal_rbf)
        if self.use_eli:
            # Stop-gradient (paper 3, SPEC 5): the planner's loss must never reach the
            # executor's parameters, so the ELI always enters the planner detached.
            eli = as_tensor(obs["eli"], dev, torch.float32).detach()
        else:
            eli = torch.zeros(ego.shape[0], self.eli_dim, device=dev)
        plan = obs.get(MAP_PLAN)
        plan = None if plan is None else as_tensor(plan, dev, torch.float32)
        trunk, vin_features, vin_subgoal = self.read_map(ego, raw_goal, plan)
        parts = [trunk, eli, goal] + ([vin_features] if vin_features is not None else [])
        return self.fc(torch.cat(parts, dim=1)), goal, raw_goal, vin_subgoal

    def features(self, obs: dict) -> torch.Tensor:
        """(B, hidden + goal_dim + PLAN_FEATURES): what the heads read."""
        h, goal, raw_goal, vin_subgoal = self.encode(obs)
        return torch.cat([h, goal, plan_features(raw_goal, vin_subgoal)], dim=1)

    def forward(self, obs: dict) -> tuple[Categorical, Normal, torch.Tensor]:
        """(stop distribution, sub-goal distribution over raw (forward, left) positions,
        value (B,))."""
        h = self.features(obs)
        mean = self.subgoal_mean(h)
        subgoal = Normal(mean, self.subgoal_log_std.exp().expand_as(mean))
        return Categorical(logits=self.stop_logits(h)), subgoal, self.critic(h).squeeze(-1)

    @staticmethod
    def _log_prob_entropy(stop_d: Categorical, sub_d: Normal, stop: torch.Tensor, subgoal: torch.Tensor):
        # The sub-goal only matters when the planner continues (stop == 0), so its
        # log-prob only counts then. The entropy is H(stop) + H(subgoal), not the joint's
        # exact H(stop) + p(continue) H(subgoal): the latter would let the entropy bonus
        # push p(continue) up and bias the agent against stopping.
        cont = (stop == 0).float()
        log_prob = stop_d.log_prob(stop) + cont * sub_d.log_prob(subgoal).sum(-1)
        entropy = stop_d.entropy() + sub_d.entropy().sum(-1)
        return log_prob, entropy

    def subgoal_to_env(self, subgoal: torch.Tensor) -> torch.Tensor:
        """Map raw (forward, left) samples into the action box: (distance, direction), the
        distance clipped to [min_subgoal_distance, rho_max]."""
        rho = torch.hypot(subgoal[..., 0], subgoal[..., 1]).clamp(self.min_subgoal_distance, self.rho_max)
        theta = torch.atan2(subgoal[..., 1], subgoal[..., 0]).clamp(-PI32, PI32)
        return torch.stack([rho, theta], dim=-1)

    @torch.no_grad()
    def act(self, obs: dict, deterministic: bool = False) -> PlannerAct:
        """One decision per env (:class:`PlannerAct`)."""
        stop_d, sub_d, value = self(obs)
        if deterministic:
            stop, subgoal = stop_d.probs.argmax(-1), sub_d.mean
        else:
            stop, subgoal = stop_d.sample(), sub_d.sample()
        log_prob, _ = self._log_prob_entropy(stop_d, sub_d, stop, subgoal)
        return PlannerAct(stop=stop, raw_subgoal=subgoal, subgoal=self.subgoal_to_env(subgoal),
                          log_prob=log_prob, value=value)

    def evaluate_actions(self, obs: dict, stop: torch.Tensor, raw_subgoal: torch.Tensor):
        """(log_prob, entropy, value), each (B,), for stored actions (raw sub-goal samples)."""
        stop_d, sub_d, value = self(obs)
        log_prob, entropy = self._log_prob_entropy(stop_d, sub_d, stop.long(), raw_subgoal)
        return log_prob, entropy, value

    def example_obs(self, batch: int = 1, generator: torch.Generator | None = None) -> dict:
        return {"ego_map": torch.rand(batch, EGO_CHANNELS, EGO_SIZE, EGO_SIZE, generator=generator),
                "goal": torch.rand(batch, 2, generator=generator) * torch.tensor([10.0, 2 * math.pi]) - torch.tensor([0.0, math.pi]),
                "eli": torch.randn(batch, self.eli_dim, generator=generator)}
