"""The one PLEX rollout driver: planner decisions and executor steps over a ``PlexVectorEnv``.

Training, evaluation, recording and the benchmarks all run PLEX through :class:`PlexDriver`,
with a pluggable policy for each agent:

============  =====================================  =====================================
agent         learned                                stand-ins
============  =====================================  =====================================
planner       :class:`LearnedPlanner` (a network)    :class:`RandomPlanner`, :class:`OraclePlannerPolicy`,
                                                     :class:`MapPlannerPolicy`,
                                                     :class:`ValueIterationPlannerPolicy`
executor      :class:`LearnedExecutor` (a network)   :class:`RandomExecutor`, :class:`OracleExecutorPolicy`
============  =====================================  =====================================

One driver iteration is :meth:`PlexDriver.decide` (every world whose turn is the planner's
gets a decision; a stop ends that episode, the world resets and needs another decision,
so this repeats until every world is in an executor turn) followed by one
:meth:`PlexDriver.step` (one executor action in all N worlds at once). The executor's
memory restarts at the first step of every turn (each sub-goal) and at every new episode.

The oracles read the world's ground truth (:mod:`plex_ma.envs.oracle`); their
``ground_truth`` attribute is True and every output that used one says so.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from plex_ma.envs.map_planner import STOP_DISTANCE, MapPlanner
from plex_ma.envs.oracle import OracleExecutor, OraclePlanner
from plex_ma.envs.rules import ELI_DIM, PLANNER
from plex_ma.envs.sim.core import STOP
from plex_ma.envs.vector import PlexVecStep, PlexVectorEnv
from plex_ma.networks.value_iteration import ValueIteration

# --------------------------------------------------------------------------- planners


class LearnedPlanner:
    """A :class:`~plex_ma.networks.Planner` network: sampled or (``deterministic``) greedy."""

    learns, ground_truth, name = True, False, "learned"

    def __init__(self, net, deterministic: bool = False):
        self.net, self.deterministic = net, deterministic

    def decide(self, obs: dict, rows: np.ndarray) -> dict:
        """stop (k,) int64 and subgoal (k, 2) float32 for the env; raw_subgoal, log_prob, value
        and the observations as acted on (with the stored map read-out) for PPO."""
        obs = self.net.with_map_plan(obs)  # stored with the decision: the PPO epochs reuse it
        with torch.no_grad():
            out = self.net.act(obs, deterministic=self.deterministic)
        # decisions are few: everything comes back to the CPU, where their transitions wait
        out = {k: v.cpu() for k, v in out.items()}
        return {"stop": out["stop"].numpy().astype(np.int64), "subgoal": out["subgoal"].numpy(),
                "raw_subgoal": out["raw_subgoal"], "log_prob": out["log_prob"], "value": out["value"],
                "obs": obs}


class RandomPlanner:
    """Sub-goals with distance uniform in [``min_distance``, ``max_distance``] and direction
    uniform within +-``max_angle``; stops with probability ``stop_prob``."""

    learns, ground_truth, name = False, False, "random"

    def __init__(self, max_distance: float, max_angle: float = np.pi, stop_prob: float = 0.0,
                 min_distance: float = 0.5, rng: np.random.Generator | None = None):
        self.lo, self.hi, self.max_angle, self.stop_prob = min_distance, max_distance, max_angle, stop_prob
        self.rng = rng if rng is not None else np.random.default_rng()

    def decide(self, obs: dict, rows: np.ndarray) -> dict:
        k = len(rows)
        sub = np.stack([self.rng.uniform(self.lo, self.hi, k), self.rng.uniform(-self.max_angle, self.max_angle, k)], 1)
        stop = (self.rng.random(k) < self.stop_prob).astype(np.int64)
        return {"stop": stop, "subgoal": sub.astype(np.float32)}


class OraclePlannerPolicy:
    """The shortest-path planner of :mod:`plex_ma.envs.oracle` (ground truth)."""

    learns, ground_truth, name = False, True, "oracle"

    def __init__(self, env: PlexVectorEnv, lookahead: float = 2.0):
        self.oracle = OraclePlanner(env.worlds, lookahead)

    def decide(self, obs: dict, rows: np.ndarray) -> dict:
        stop, sub = self.oracle.decide(rows)
        return {"stop": stop, "subgoal": sub}


class MapPlannerPolicy:
    """The shortest-path planner on the agent's own ego map (:mod:`plex_ma.envs.map_planner`):
    the learned planner's observations only, no ground truth."""

    learns, ground_truth = False, False

    def __init__(self, line_of_sight: bool = False):
        self.planner = MapPlanner(line_of_sight=line_of_sight)
        self.name = "map-los" if line_of_sight else "map"

    def decide(self, obs: dict, rows: np.ndarray) -> dict:
        stop, sub = self.planner.decide(obs)
        return {"stop": stop, "subgoal": sub}


class ValueIterationPlannerPolicy:
    """The value-iteration module's sub-goal alone (:class:`~plex_ma.networks.ValueIteration`,
    which has no weights): the hand-written planner that the learned one is measured
    against, whose sub-goal the learned planner reads as a feature, on the 0.5 m cells or with
    ``fine_map`` the 0.25 m quarter cells (as a given planner network's own module does).
    It reads the planner's observations only and stops as the map planner does."""

    learns, ground_truth, name = False, False, "vin"

    def __init__(self, stop_distance: float = STOP_DISTANCE, fine_map: bool = False):
        self.vin, self.stop_distance = ValueIteration(fine=fine_map), stop_distance

    def decide(self, obs: dict, rows: np.ndarray) -> dict:
        goal = torch.as_tensor(np.asarray(obs["goal"], np.float32))
        _, sub = self.vin(torch.as_tensor(np.asarray(obs["ego_map"], np.float32)), goal)  # no gradient
        return {"stop": (goal[:, 0] < self.stop_distance).numpy().astype(np.int64), "subgoal": sub.numpy()}


# --------------------------------------------------------------------------- executors


class LearnedExecutor:
    """An :class:`~plex_ma.networks.Executor` network: sampled or (``deterministic``) greedy."""

    learns, ground_truth, name = True, False, "learned"

    def __init__(self, net, deterministic: bool = False):
        self.net, self.deterministic = net, deterministic

    def initial_state(self, n: int):
        return self.net.initial_state(n)

    def act(self, obs: dict, state, starts: np.ndarray):
        out, state = self.net.act(obs, state, starts, deterministic=self.deterministic)
        return {"action": out["action"].cpu().numpy(), "eli": out["eli"].cpu().numpy(), "log_prob": out["log_prob"],
                "value": out["value"]}, state


class _StatelessExecutor:
    learns = False

    def initial_state(self, n: int):
        return None


class RandomExecutor(_StatelessExecutor):
    """Uniform random moves and turns; STOP with probability ``stop_prob``; a zero ELI."""

    ground_truth, name = False, "random"

    def __init__(self, stop_prob: float = 0.05, rng: np.random.Generator | None = None):
        self.stop_prob = stop_prob
        self.rng = rng if rng is not None else np.random.default_rng()

    def act(self, obs: dict, state, starts: np.ndarray):
        n = len(starts)
        moves = self.rng.integers(1, 4, n)
        action = np.where(self.rng.random(n) < self.stop_prob, STOP, moves).astype(np.int64)
        return {"action": action, "eli": np.zeros((n, ELI_DIM), np.float32)}, None


class OracleExecutorPolicy(_StatelessExecutor):
    """The shortest-path follower of :mod:`plex_ma.envs.oracle` (ground truth)."""

    ground_truth, name = True, "oracle"

    def __init__(self, env: PlexVectorEnv):
        self.oracle = OracleExecutor(env.worlds)

    def act(self, obs: dict, state, starts: np.ndarray):
        action, eli = self.oracle.act(np.arange(len(starts)))
        return {"action": action, "eli": eli}, None


# --------------------------------------------------------------------------- the driver


@dataclass
class Decision:
    """One round of planner decisions: the worlds ``rows`` decided on ``obs`` with ``out``."""

    rows: np.ndarray
    obs: dict  # planner observations of the rows (copies)
    out: dict  # the planner policy's output for the rows
    result: PlexVecStep  # the env step that applied them


@dataclass
class ExecutorStep:
    """One executor action in every world."""

    obs: dict  # the executor observations acted on (copies)
    starts: np.ndarray  # (N,) bool: the memory restarted before this action
    out: dict  # the executor policy's output (action, eli, and log_prob, value if learned)
    state: object  # the executor's memory after this action
    result: PlexVecStep  # the env step


class PlexDriver:
    """Steps a :class:`PlexVectorEnv` with a planner and an executor policy (module docstring).

    Finished episodes are reported in each step's ``result.episode_infos``; their returns
    (the planner's reward summed over the episode, i.e. the episode reward) are in
    :attr:`episode_returns` of the same step, in the same order.
    """

    def __init__(self, env: PlexVectorEnv, planner, executor):
        self.env, self.planner, self.executor = env, planner, executor
        self.n = env.num_envs
        self.env_seconds = 0.0  # time spent inside env.step (the rest is the policies and bookkeeping)
        self.episode_returns: list[float] = []

    def reset(self, seed: int | None = None) -> None:
        self.turn, self.planner_obs, self.executor_obs = self.env.reset(seed=seed)
        self.state = self.executor.initial_state(self.n)
        self.starts = np.ones(self.n, np.bool_)
        self.ret = np.zeros(self.n)

    def _env_step(self, **actions) -> PlexVecStep:
        t0 = time.perf_counter()
        res = self.env.step(**actions)
        self.env_seconds += time.perf_counter() - t0
        self.ret += res.rewards[:, PLANNER]
        ended = np.flatnonzero(res.terminated | res.truncated)
        self.episode_returns = self.ret[ended].tolist()
        self.ret[ended] = 0.0
        self.turn, self.planner_obs, self.executor_obs = res.turn, res.planner_obs, res.executor_obs
        return res

    def decide(self, on_decision=None, until=None) -> None:
        """Planner decisions until every world is in an executor turn (or ``until()`` is true
        after a round). ``on_decision(decision)`` sees each round."""
        while True:
            rows = np.flatnonzero(self.turn == PLANNER)
            if not len(rows):
                return
            obs = {k: v[rows] for k, v in self.planner_obs.items()}
            out = self.planner.decide(obs, rows)
            stop = np.zeros(self.n, np.int64)
            sub = np.zeros((self.n, 2), np.float32)
            stop[rows], sub[rows] = out["stop"], out["subgoal"]
            res = self._env_step(stop=stop, subgoal=sub)
            self.starts[rows] = True  # a new sub-goal (or episode) begins an executor turn
            if on_decision is not None:
                on_decision(Decision(rows, obs, out, res))
            if until is not None and until():
                return

    def step(self) -> ExecutorStep:
        """One executor action in every world (call :meth:`decide` first)."""
        if np.any(self.turn == PLANNER):
            raise RuntimeError("some worlds wait for a planner decision: call decide() before step()")
        starts = self.starts.copy()
        obs = {k: np.array(v) for k, v in self.executor_obs.items()}
        out, self.state = self.executor.act(obs, self.state, starts)
        res = self._env_step(action=out["action"], eli=out["eli"])
        ended = res.terminated | res.truncated
        self.starts = res.executor_turn_end | ended
        return ExecutorStep(obs, starts, out, self.state, res)


#: The planner policies :func:`make_planner` builds by name (the ``--planner`` choices of the CLIs).
PLANNER_KINDS = ("learned", "oracle", "random", "map", "map-los", "vin")
#: The executor policies :func:`make_executor` builds by name.
EXECUTOR_KINDS = ("learned", "oracle", "random")


def make_planner(kind: str, env: PlexVectorEnv, net=None, deterministic: bool = False, rng=None,
                 fine_map: bool = False, **random_kw):
    """A planner policy by name: 'learned' (needs ``net``), 'random', 'oracle', 'map', 'map-los'
    (the map planner with sub-goals in a straight line over seen floor) or 'vin' (the
    value-iteration module's sub-goal: on the cells of ``net``'s own module, else on the
    quarter cells with ``fine_map``)."""
    if kind in ("learn", "learned"):
        if net is None:
            raise ValueError("a learned planner needs a network (a checkpoint)")
        return LearnedPlanner(net, deterministic)
    if kind == "random":
        return RandomPlanner(rng=rng, **({"max_distance": env.config.rho_max} | random_kw))
    if kind == "oracle":
        return OraclePlannerPolicy(env)
    if kind in ("map", "map-los"):
        return MapPlannerPolicy(line_of_sight=kind == "map-los")
    if kind == "vin":
        vin = getattr(net, "vin", None)
        return ValueIterationPlannerPolicy(fine_map=vin.fine if vin is not None else fine_map)
    raise ValueError(f"unknown planner {kind!r}; choose one of {', '.join(PLANNER_KINDS)}")


def make_executor(kind: str, env: PlexVectorEnv, net=None, deterministic: bool = False, rng=None):
    """An executor policy by name: 'learned' (needs ``net``), 'random' or 'oracle'."""
    if kind in ("learn", "learned"):
        if net is None:
            raise ValueError("a learned executor needs a network (a checkpoint)")
        return LearnedExecutor(net, deterministic)
    if kind == "random":
        return RandomExecutor(rng=rng)
    if kind == "oracle":
        return OracleExecutorPolicy(env)
    raise ValueError(f"unknown executor {kind!r}; choose one of {', '.join(EXECUTOR_KINDS)}")
