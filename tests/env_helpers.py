"""Helpers shared by the environment tests: small configs, hand-made episodes, drivers."""

from __future__ import annotations

import math

import numpy as np

from plex_ma.envs.sim import Episode

# Small and fast: 64 px images, 4 procedural training scenes (numba caches its kernels on disk).
SMALL = dict(resolution=64, num_scenes=4)
ELI_ZERO = np.zeros(128, np.float32)


def planner_action(stop=0, rho=1.0, theta=0.0) -> dict:
    return {"stop": int(stop), "subgoal": np.array([rho, theta], np.float32)}


def executor_action(a: int, eli=None) -> dict:
    return {"action": int(a), "eli": ELI_ZERO if eli is None else np.asarray(eli, np.float32)}


def line_episode(raw, length: float, behind: float = 0.0, clearance: float = 0.3, episode_id: int = 900) -> Episode:
    """An episode whose goal lies ``length`` m straight ahead of the start, with free
    space ``behind`` m behind it, in the scene of ``raw``'s (AEC or gym env) first world.
    The start heading faces the goal; ``geodesic_distance`` is the simulator's own."""
    w = raw.worlds
    sim = w.sim
    for s, grid in enumerate(sim.bank.grids):
        rows, cols = np.nonzero(grid.nav)
        order = np.random.default_rng(s).permutation(len(rows))
        for k in order[:4000]:
            start = grid.cell_center(np.array([rows[k], cols[k]]))
            for heading in (0.0, math.pi / 2, math.pi, -math.pi / 2):
                d = np.array([math.cos(heading), math.sin(heading)])
                n = np.array([-d[1], d[0]])
                ts = np.arange(-behind - clearance, length + clearance + 1e-9, 0.05)
                pts = [start + t * d + o * n for t in ts for o in (-clearance, 0.0, clearance)]
                if not np.all(grid.is_navigable(np.array(pts))):
                    continue
                goal = start + length * d
                geo = w.geo.distance(s, start, goal)
                if not math.isfinite(geo):
                    continue
                return Episode(episode_id, grid.scene_id, (float(start[0]), float(start[1])), heading,
                               (float(goal[0]), float(goal[1])), float(geo))
    raise RuntimeError("no straight free corridor found in the scenes")


def drive(env, executor_actions, subgoal=(2.0, 0.0)):
    """Step an AEC env through ``executor_actions``; whenever the planner is to act it
    proposes ``subgoal`` (never stops). Returns the number of AEC steps taken."""
    steps = 0
    todo = list(executor_actions)
    while todo:
        if env.agent_selection == "planner":
            env.step(planner_action(0, *subgoal))
        else:
            env.step(executor_action(todo.pop(0)))
        steps += 1
    return steps


def state_snapshot(env) -> dict:
    """Everything a step could change, copied (AEC env, wrapped or not)."""
    raw = env.unwrapped
    w = raw.worlds
    s = w.sim
    snap = {k: getattr(w, k).copy() for k in ("turn", "turn_steps", "subgoal", "subgoal_raw", "subgoal_dist", "eli",
                                              "planner_decisions", "steps", "collisions", "done")}
    snap.update({k: getattr(s, k).copy() for k in ("pos", "heading", "path_length", "distance_to_goal", "est_pose",
                                                    "rgb", "depth", "amap")})
    snap["agent_selection"] = raw.agent_selection
    snap["agents"] = list(raw.agents)
    for k in ("rewards", "_cumulative_rewards", "terminations", "truncations"):
        snap[k] = dict(getattr(raw, k))
    return snap


def assert_same_state(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for k in a:
        if isinstance(a[k], np.ndarray):
            np.testing.assert_array_equal(a[k], b[k], err_msg=k)
        else:
            assert a[k] == b[k], k
