"""Policy networks: the PLEX planner and executor (paper 4.2, SPEC 5) and the flat baselines.

One module per part:

- ``planner``: :class:`Planner` and its reading of the ego map, :class:`MapEncoder`;
- ``value_iteration``: :class:`ValueIteration` over the ego map and its Bellman updates
  (:func:`bellman`, compiled numba loops on the CPU; :func:`bellman_reference`);
- ``executor``: :class:`Executor` and its RGB-D CNN, :class:`RGBDEncoder`;
- ``memory``: the recurrent memories, :class:`GRUMemory` and :class:`SMTMemory`;
- ``flat``: the flat baselines' :class:`FlatPolicy` and :class:`FlatMapPolicy`;
- ``common``: what they share (``layer_init``, ``encode_polar``, ``as_tensor``).

Observations are dicts of tensors (numpy arrays are accepted and converted) with a
leading batch dimension:

- planner:  ``ego_map`` (B, C, 32, 32) float in [0, 1]; ``goal`` (B, 2) = (distance m,
  direction rad); ``eli`` (B, 128) float.
- executor: ``rgb`` (B, H, W, 3) uint8; ``depth`` (B, H, W, 1) float in [0, 1];
  ``subgoal`` (B, 2) = (distance m, direction rad).
- flat:     ``rgb``, ``depth`` as the executor, ``pointgoal`` (B, 2); and ``ego_map`` as the
  planner for the flat policy with the map (``FlatMapPolicy``).

Every (distance, direction) vector is fed to the networks as (distance, cos, sin) so that
directions just either side of +-pi look alike (see ``encode_polar``).

Recurrent policies (executor, flat) keep a *state*: their memory's, flattened, and the
previous action, in one tensor whose first dimension is the batch
(``initial_state(batch)``), so a rollout buffer can store and index it without knowing
which memory it is. A ``starts`` mask (B,) says where a new sequence
begins (new sub-goal or new episode); the memory is cleared *before* that step is
processed. Initialisation follows CleanRL: orthogonal weights, zero biases, gain sqrt(2)
for hidden layers, 0.01 for policy heads, 1 for value heads.
"""

from plex_ma.envs.rules import ELI_DIM
from plex_ma.networks.common import encode_polar, layer_init
from plex_ma.networks.executor import Executor, ExecutorAct, RGBDEncoder
from plex_ma.networks.flat import FlatMapPolicy, FlatPolicy
from plex_ma.networks.memory import GRUMemory, MultiHeadAttention, SMTMemory
from plex_ma.networks.planner import (GOAL_FEATURES, MAP_PLAN, PI32, PLAN_FEATURES, STOP_INIT_LOGIT, SUBGOAL_MARGIN,
                                      Head, MapEncoder, Planner, PlannerAct, goal_feature_count, plan_features,
                                      planner_goal_features)
from plex_ma.networks.value_iteration import (BELLMAN_UNREACHED, DIAGONALS, EGO_CELL, SUBGOAL_REACH, ValueIteration,
                                              bellman, bellman_reference)

__all__ = [
    "ELI_DIM", "encode_polar", "layer_init",
    "Executor", "ExecutorAct", "RGBDEncoder",
    "FlatMapPolicy", "FlatPolicy",
    "GRUMemory", "MultiHeadAttention", "SMTMemory",
    "GOAL_FEATURES", "MAP_PLAN", "PI32", "PLAN_FEATURES", "STOP_INIT_LOGIT", "SUBGOAL_MARGIN", "Head", "MapEncoder",
    "Planner", "PlannerAct", "goal_feature_count", "plan_features", "planner_goal_features",
    "BELLMAN_UNREACHED", "DIAGONALS", "EGO_CELL", "SUBGOAL_REACH", "ValueIteration", "bellman",
    "bellman_reference",
]
