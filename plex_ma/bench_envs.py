"""The environment benchmarks of ``python -m plex_ma.bench``: ``sim``, ``env``, ``turns``, ``geodesic`` and ``gymvec``.

``sim`` steps the raw batched simulator with random movement actions (no STOP, so
episodes run to 500 steps and reset): every step renders RGB-D, updates the ego maps and
looks up the geodesic distance to the goal. Resets (episode sampling with its Dijkstra
field) are included in the timing.

``env`` measures the environments built on it, with random valid actions (the planner
stops with a small probability, so episodes are long):

* ``aec_turns_per_second``: ``plex_nav_v0.env()`` (one world) driven the PettingZoo way
  (``agent_iter``, ``last()``, ``step``), every turn of either agent counted;
* ``vector_steps_per_second``: ``PlexVectorEnv`` at ``--num-envs`` worlds, one action per
  world per call (planner or executor), i.e. ``num_envs * calls / s``;
* ``vector_executor_steps_per_second``: only the executor actions of those, i.e. the
  simulator steps the vector env delivers;
* ``sim_steps_per_second``: the raw simulator as ``sim`` drives it, at the same
  ``--num-envs`` and ``--resolution``, timed in ``--rounds`` rounds that alternate with the
  vector env's (after ``--warmup`` untimed calls of each), so that a drift in the shared
  machine's speed falls on both. Its worlds start in the vector env's first episodes
  (rendering costs depend on the house and the pose) and reset at their long-run rate, one
  per world every 500 steps, with episode clocks spread over [0, 500) at the start (the
  env's resets are timed too). Before timing, the corner graphs behind the sub-goal
  distances are built for every house, as in a long run (well under a second for the 72
  procgen training houses; otherwise a short bench times this one-off cost whenever an
  episode starts in a house not met yet). Both sides' random actions are drawn before each
  timed round, so neither time includes the random number generator;
* ``ratio``: vector executor steps / raw simulator steps, the env's overhead over the
  simulator (a planner action steps no simulator, so counting it would flatter the env;
  ``ratio_all_actions`` counts it anyway). The goal is ``ratio >= 0.7`` at 64 worlds, 128 px.
  ``ratio_cpu`` is the same ratio per second of process CPU time (both threads), which
  a virtual machine's steal time does not inflate.

``turns`` measures what an outside trainer that steps one world turn by turn gets (RLlib,
SB3 through SuperSuit, Tianshou, TorchRL's PettingZooWrapper): ``plex_nav_v0.env()`` and
``compat_env()``, each with one world at ``--resolution``, driven as ``env``'s AEC figure is
(random valid actions; the compat planner picks a random sub-goal of its grid), against
the raw one-world simulator driven as ``sim`` drives it, in one process. Each of
``--rounds`` rounds times ``--turns`` turns of each env and as many simulator steps, the
first of the three rotating from round to round; ``aec_ratio`` and ``compat_ratio`` are
the medians over the rounds of turns/s over the simulator's steps/s (``_cpu``: per second
of process CPU time). A turn of either agent counts, as a simulator step does.

``geodesic`` times the sub-goal distance queries on one thread (``--queries`` random
points and sub-goals up to 4 m away, snapped as the env snaps them): the corner graphs the
env uses against A* on the same queries, with the largest difference between the two.

``gymvec`` times ``gymnasium.make_vec("plex_ma/PointNav-v0", num_envs=N)`` (the batched
vector env, ``vectorization_mode="vector_entry_point"``) against gymnasium's
``SyncVectorEnv`` of N single ``PointNav-v0`` envs (``vectorization_mode="sync"``, each
with ``make``'s checker wrappers), both from the same seed and given the same random
actions drawn before timing: the two run the same episodes in lockstep, and the bench
checks that their observations still agree after every round (``identical``). Actions
are random moves, STOP with probability ``--stop-prob`` (0: episodes run to
``--max-steps`` and truncate). The two are timed in ``--rounds`` alternating rounds (after
``--warmup`` untimed steps of each), the first of each round alternating too;
``speedup`` is the batched env's steps/s over the sync one's, overall and
``speedup_min``/``_median``/``_max`` over the rounds; ``speedup_cpu`` the same per second
of process CPU time. Episode resets (sampling an episode with its Dijkstra field, about
3 ms) cost the same in both, so frequent episode ends lower the speedup.
"""

from __future__ import annotations

import os
import platform
import time

import gymnasium
import numba
import numpy as np

from plex_ma.envs import plex_nav_v0
from plex_ma.envs.compat import CompatEnv
from plex_ma.envs.sim import BatchedSim, Geodesics, scene_bank
from plex_ma.envs.sim.episodes import sample_episode
from plex_ma.envs.vector import EXECUTOR, PlexVectorEnv


def machine() -> dict:

    return {"cpus": os.cpu_count(), "numba_threads": numba.get_num_threads(), "platform": platform.platform(),
            "python": platform.python_version(), "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY")}


class _RawSim:
    """The raw batched simulator driven as ``bench sim`` drives it: random movement actions
    (no STOP), an episode reset (sampling with its Dijkstra field) after 500 steps.

    ``episodes`` starts the worlds in given episodes (default: sampled ones). With
    ``steady``, the worlds' episode clocks start spread over [0, 500), as in a simulator
    that has been running for a while, so that resets come at their long-run rate (one per
    world every 500 steps) from the first call instead of all at step 500."""

    def __init__(self, num_envs: int, resolution: int, seed: int, scenes: str, num_scenes: int | None,
                 episodes: list | None = None, steady: bool = False):

        self.bank = scene_bank(scenes, "train", num_scenes)
        self.sim = BatchedSim(self.bank, num_envs, resolution=resolution, seed=seed)
        self.rng = np.random.default_rng(seed)
        self.geo = Geodesics(self.bank)
        self.sample = sample_episode
        self.n = num_envs
        for i in range(num_envs):
            if episodes is None:
                self._reset(i)
            else:
                self.sim.reset_world(i, episodes[i])
        self.sim.step(self.actions(1)[0])  # compile / warm up
        self.t_steps = self.rng.integers(0, 500, num_envs) if steady else np.zeros(num_envs, np.int64)
        self.resets = 0

    def _reset(self, i: int) -> None:
        self.sim.reset_world(i, *self.sample(self.bank, int(self.rng.integers(len(self.bank))), self.rng, self.geo, i))

    def actions(self, calls: int) -> np.ndarray:
        """Random moves (no STOP) for ``calls`` steps of all worlds, drawn ahead of timing."""
        return self.rng.integers(1, 4, (calls, self.n))

    def run(self, actions: np.ndarray) -> float:
        """Step all worlds once per row of ``actions``; returns the seconds it took."""
        t0 = time.perf_counter()
        for a in actions:
            self.sim.step(a)
            self.t_steps += 1
            for i in np.flatnonzero(self.t_steps >= 500):
                self._reset(int(i))
                self.t_steps[i] = 0
                self.resets += 1
        return time.perf_counter() - t0


def bench_sim(num_envs: int, resolution: int, steps: int, seed: int, scenes: str = "procgen",
              num_scenes: int | None = None) -> dict:
    raw = _RawSim(num_envs, resolution, seed, scenes, num_scenes)
    dt = raw.run(raw.actions(steps))
    return {"benchmark": "sim", "steps_per_second": steps * num_envs / dt, "num_envs": num_envs,
            "resolution": resolution, "steps": steps * num_envs, "seconds": dt, "resets": raw.resets,
            "memory_per_world_bytes": raw.sim.memory_per_world(), "scene_bank_bytes": raw.bank.nbytes,
            "machine": machine()}


def bench_geodesic(queries: int, seed: int, scenes: str = "procgen", num_scenes: int | None = None,
                   rho_max: float = 4.0, astar_queries: int = 500) -> dict:
    """Sub-goal distance queries on one thread: the corner graphs (``BatchedSim.distance_to``,
    what the env asks after every executor move, with its straight-line shortcut) against A*
    (``Geodesics.distance``, with the same shortcut) on the same queries. Each query goes from a random navigable point of a random scene to a
    point up to ``rho_max`` away in a random direction, snapped as the env snaps sub-goals."""


    bank = scene_bank(scenes, "train", num_scenes)
    sim = BatchedSim(bank, queries, resolution=8, egomap=False)
    geo = Geodesics(bank)
    rng = np.random.default_rng(seed)
    sim.scene_idx[:] = rng.integers(len(bank), size=queries)
    for i, s in enumerate(sim.scene_idx):
        cells, centres = geo.navigable_cells(int(s))
        sim.pos[i] = centres[rng.integers(len(cells))] + rng.uniform(-0.02, 0.02, 2)
    ang = rng.uniform(-np.pi, np.pi, queries)
    raw = sim.pos + rng.uniform(0, rho_max, (queries, 1)) * np.stack([np.cos(ang), np.sin(ang)], 1)
    rows = np.arange(queries)
    targets = sim.snap_to_navigable(raw, rows)
    t0 = time.perf_counter()
    sim.prepare_geodesics(np.unique(sim.scene_idx))
    build = time.perf_counter() - t0
    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        best = np.inf
        for _ in range(3):
            t0 = time.perf_counter()
            d = sim.distance_to(targets, rows)
            best = min(best, time.perf_counter() - t0)
    finally:
        numba.set_num_threads(threads)
    k = min(astar_queries, queries)
    t0 = time.perf_counter()
    ref = np.full(queries, np.inf)
    ref[:k] = [geo.distance(int(sim.scene_idx[i]), sim.pos[i], targets[i]) for i in range(k)]
    t_astar = time.perf_counter() - t0
    sim.shorten_to_straight_line(targets, rows[:k], ref)  # as distance_to does
    ref = ref[:k]
    euclid = np.hypot(*(sim.pos - targets).T)
    return {"benchmark": "geodesic", "queries": queries, "corner_graph_us_per_query": best / queries * 1e6,
            "astar_us_per_query": t_astar / k * 1e6, "astar_queries": k,
            "max_abs_difference_m": float(np.max(np.abs(d[:k] - ref))),
            "detour_fraction": float(np.mean(d > 1.3 * euclid + 0.1)), "scenes": len(np.unique(sim.scene_idx)),
            "graph_build_seconds": build, "machine": machine()}


def _turns(env, rng: np.random.Generator, planner_stop_prob: float, executor_stop_prob: float):
    """``run(n)``: ``n`` turns of ``env`` (``plex_nav_v0.env()`` or ``compat_env()``) driven
    the PettingZoo way (``agent_iter``, ``last()``, ``step``) with random valid actions, from a
    reset with a fresh seed and again after each episode; it returns the episodes begun. The
    planner stops with ``planner_stop_prob`` (compat: else a random sub-goal of its grid),
    the executor chooses STOP with ``executor_stop_prob``, else a random move."""
    compat = isinstance(env.unwrapped, CompatEnv)
    rho_max = env.unwrapped.config.rho_max
    planner_actions = env.action_space("planner").n if compat else 0
    zero_eli = np.zeros(128, np.float32)

    def action(agent: str):
        if agent == "planner":
            stop = rng.random() < planner_stop_prob
            if compat:
                return 0 if stop else int(rng.integers(1, planner_actions))
            return {"stop": int(stop),
                    "subgoal": np.array([rng.uniform(0, rho_max), rng.uniform(-np.pi, np.pi)], np.float32)}
        a = 0 if rng.random() < executor_stop_prob else int(rng.integers(1, 4))
        return a if compat else {"action": a, "eli": zero_eli}

    def run(n: int) -> int:
        episodes = 0
        done = 0
        while done < n:
            env.reset(seed=int(rng.integers(2**31)))
            episodes += 1
            for agent in env.agent_iter(n - done):
                _, _, term, trunc, _ = env.last()
                env.step(None if term or trunc else action(agent))
                done += 1
        return episodes

    return run


def bench_turns(resolution: int = 128, turns: int = 1000, seed: int = 0, scenes: str = "procgen",
                num_scenes: int | None = None, rounds: int = 5, warmup: int = 100, planner_stop_prob: float = 0.01,
                executor_stop_prob: float = 0.1) -> dict:
    """One world, one process: ``plex_nav_v0.env()`` and ``compat_env()`` turns/s against the
    raw one-world simulator's steps/s, in alternating rounds (see the module docstring)."""
    rng = np.random.default_rng(seed)
    cfg = dict(resolution=resolution, scenes=scenes, num_scenes=num_scenes)
    runs = {}
    for name, env in (("aec", plex_nav_v0.env(**cfg)), ("compat", plex_nav_v0.compat_env(**cfg))):
        env.reset(seed=seed)
        env.unwrapped.worlds.sim.prepare_geodesics()  # as in a long run (see bench env)
        runs[name] = _turns(env, rng, planner_stop_prob, executor_stop_prob)
    raw = _RawSim(1, resolution, seed, scenes, num_scenes, steady=True)
    for run in runs.values():
        run(warmup)
    raw.run(raw.actions(warmup))
    names = ("sim", "aec", "compat")
    rate = {name: [] for name in names}
    rate_cpu = {name: [] for name in names}
    for k in range(rounds):
        for name in names[k % 3:] + names[:k % 3]:  # who goes first rotates
            acts = raw.actions(turns) if name == "sim" else None  # drawn before timing
            t, c = time.perf_counter(), time.process_time()
            if name == "sim":
                raw.run(acts)
            else:
                runs[name](turns)
            rate[name].append(turns / (time.perf_counter() - t))
            rate_cpu[name].append(turns / max(time.process_time() - c, 1e-9))
    out = {"benchmark": "turns", "resolution": resolution, "turns": turns, "rounds": rounds,
           "planner_stop_prob": planner_stop_prob, "executor_stop_prob": executor_stop_prob}
    for name, what in zip(names, ("sim_steps", "aec_turns", "compat_turns")):
        out[f"{what}_per_second"] = float(np.median(rate[name]))
    for name in ("aec", "compat"):
        out[f"{name}_ratio"] = float(np.median(np.array(rate[name]) / rate["sim"]))
        out[f"{name}_ratio_cpu"] = float(np.median(np.array(rate_cpu[name]) / rate_cpu["sim"]))
    out["machine"] = machine()
    return out


def bench_env(num_envs: int, resolution: int, steps: int, seed: int, scenes: str = "procgen",
              aec_turns: int = 2000, planner_stop_prob: float = 0.01, executor_stop_prob: float = 0.1,
              num_scenes: int | None = None, rounds: int = 10, warmup: int = 20) -> dict:
    """AEC turns/s of one ``plex_nav_v0.env``, ``PlexVectorEnv`` steps/s at ``num_envs``
    worlds and the raw simulator's steps/s under the same settings (see the module docstring)."""

    rng = np.random.default_rng(seed)
    cfg = dict(resolution=resolution, scenes=scenes, num_scenes=num_scenes)

    # One AEC env, driven as a PettingZoo user would.
    env = plex_nav_v0.env(**cfg)
    rho_max = env.unwrapped.config.rho_max
    run_aec = _turns(env, rng, planner_stop_prob, executor_stop_prob)

    run_aec(50)  # load the compiled kernels
    t0 = time.perf_counter()
    aec_episodes = run_aec(aec_turns)
    aec_dt = time.perf_counter() - t0

    # The vector env: every world gets an action each call; each reads its agent's part.
    venv = PlexVectorEnv(num_envs, seed=seed, **cfg)
    venv.reset()
    n = num_envs

    zero_elis = np.zeros((n, 128), np.float32)

    def vec_actions(calls: int) -> list[dict]:
        """Both agents' actions for ``calls`` steps, drawn ahead of timing (as the raw
        simulator's are): the bench times the env, not the random number generator."""
        return [dict(stop=(rng.random(n) < planner_stop_prob).astype(np.int64),
                     subgoal=np.stack([rng.uniform(0, rho_max, n), rng.uniform(-np.pi, np.pi, n)], 1),
                     action=np.where(rng.random(n) < executor_stop_prob, 0, rng.integers(1, 4, n)), eli=zero_elis)
                for _ in range(calls)]

    counts = {"executor_steps": 0, "ended": 0}

    def run_vec(actions: list[dict]) -> float:
        t0 = time.perf_counter()
        for a in actions:
            out = venv.step(**a)
            counts["executor_steps"] += int(np.sum(out.acted == EXECUTOR))
            counts["ended"] += len(out.episode_infos)
        return time.perf_counter() - t0

    # The raw simulator starts in the vector env's first episodes (the same houses and
    # poses: the cost of rendering depends on them) and resets at its long-run rate.
    raw = _RawSim(num_envs, resolution, seed, scenes, num_scenes, episodes=list(venv.worlds.sim.episodes), steady=True)
    # A long run has built every house's corner graph; without this a short bench would time
    # that one-off cost whenever an episode starts in a house not seen yet.
    venv.worlds.sim.prepare_geodesics()
    run_vec(vec_actions(warmup))
    raw.run(raw.actions(warmup))
    # Interleave the two in rounds: on a shared machine the speed drifts over seconds, and
    # timing one after the other would fold that drift into the ratio.
    counts["executor_steps"] = counts["ended"] = 0
    vec_dt = sim_dt = vec_cpu = sim_cpu = 0.0
    rounds = max(1, min(rounds, steps))
    for k in range(rounds):
        calls = steps // rounds + (k < steps % rounds)
        vec_acts, raw_acts = vec_actions(calls), raw.actions(calls)
        c0 = time.process_time()
        vec_dt += run_vec(vec_acts)
        c1 = time.process_time()
        sim_dt += raw.run(raw_acts)
        vec_cpu += c1 - c0
        sim_cpu += time.process_time() - c1
    executor_steps = counts["executor_steps"]
    vec_sps = steps * n / vec_dt
    vec_ex_sps = executor_steps / vec_dt
    sim_sps = steps * n / sim_dt
    return {"benchmark": "env", "num_envs": num_envs, "resolution": resolution,
            "aec_turns_per_second": aec_turns / aec_dt, "aec_turns": aec_turns, "aec_episodes": aec_episodes,
            "vector_steps_per_second": vec_sps, "vector_executor_steps_per_second": vec_ex_sps,
            "vector_calls": steps, "vector_executor_fraction": executor_steps / (steps * n),
            "vector_episodes_ended": counts["ended"], "sim_steps_per_second": sim_sps, "sim_resets": raw.resets,
            "ratio": vec_ex_sps / sim_sps, "ratio_all_actions": vec_sps / sim_sps,
            "ratio_cpu": (executor_steps / vec_cpu) / (steps * n / sim_cpu), "rounds": rounds,
            "planner_stop_prob": planner_stop_prob, "executor_stop_prob": executor_stop_prob,
            "machine": machine()}


def bench_gymvec(num_envs: int = 16, resolution: int = 64, steps: int = 300, seed: int = 0, scenes: str = "procgen",
                 num_scenes: int | None = None, rounds: int = 10, warmup: int = 20, stop_prob: float = 0.0,
                 max_steps: int = 500) -> dict:
    """The batched gymnasium vector env against ``SyncVectorEnv`` of single envs, in
    alternating rounds on the same actions (see the module docstring)."""


    cfg = dict(resolution=resolution, scenes=scenes, num_scenes=num_scenes, max_steps=max_steps)
    envs = {"vector": gymnasium.make_vec("plex_ma/PointNav-v0", num_envs=num_envs,
                                         vectorization_mode="vector_entry_point", **cfg),
            "sync": gymnasium.make_vec("plex_ma/PointNav-v0", num_envs=num_envs, vectorization_mode="sync", **cfg)}
    last = {name: e.reset(seed=seed)[0] for name, e in envs.items()}
    rng = np.random.default_rng(seed)
    n = num_envs

    def actions(calls: int) -> np.ndarray:
        return np.where(rng.random((calls, n)) < stop_prob, 0, rng.integers(1, 4, (calls, n)))

    ended = {"count": 0}

    def run(name: str, acts: np.ndarray) -> tuple[float, float]:
        env = envs[name]
        t, c = time.perf_counter(), time.process_time()
        for a in acts:
            obs, _, term, trunc, _ = env.step(a)
            if name == "vector":
                ended["count"] += int(np.sum(term | trunc))
        last[name] = obs
        return time.perf_counter() - t, time.process_time() - c

    def same() -> bool:
        return all(np.array_equal(last["vector"][k], last["sync"][k]) for k in last["sync"])

    warm = actions(warmup)
    for name in envs:
        run(name, warm)
    identical = same()
    ended["count"] = 0
    rounds = max(1, min(rounds, steps))
    wall = {"vector": [], "sync": []}
    cpu = {"vector": [], "sync": []}
    for k in range(rounds):
        acts = actions(steps // rounds + (k < steps % rounds))
        for name in (("vector", "sync") if k % 2 == 0 else ("sync", "vector")):
            dt, dc = run(name, acts)
            wall[name].append(dt / len(acts))
            cpu[name].append(dc / len(acts))
        identical &= same()
    for e in envs.values():
        e.close()
    per_round = np.array(wall["sync"]) / np.array(wall["vector"])
    vec_s, sync_s = sum(wall["vector"]) / rounds, sum(wall["sync"]) / rounds
    return {"benchmark": "gymvec", "num_envs": num_envs, "resolution": resolution, "steps": steps * n,
            "stop_prob": stop_prob, "max_steps": max_steps,
            "vector_steps_per_second": n / vec_s, "sync_steps_per_second": n / sync_s, "speedup": sync_s / vec_s,
            "speedup_min": float(per_round.min()), "speedup_median": float(np.median(per_round)),
            "speedup_max": float(per_round.max()), "speedup_cpu": sum(cpu["sync"]) / sum(cpu["vector"]),
            "episodes_ended": ended["count"], "rounds": rounds, "identical": bool(identical), "machine": machine()}
