"""The planner on the agent's own ego map: geometry on synthetic maps, and navigation."""

from __future__ import annotations

import math

import numpy as np

from plex_ma.envs.map_planner import _NEIGHBOURS, MapPlanner, _distances
from plex_ma.envs.vector import PlexVectorEnv
from plex_ma.trainers.driver import MapPlannerPolicy, OracleExecutorPolicy, PlexDriver


def _decide(ego0, goal):
    ego = np.zeros((1, 2, 32, 32), np.float32)
    ego[0, 0] = ego0
    return MapPlanner().decide({"ego_map": ego, "goal": np.array([goal], np.float32)})


def test_open_map_goes_straight_for_the_lookahead():
    stop, sub = _decide(np.zeros((32, 32)), (10.0, 0.3))
    assert stop[0] == 0
    assert abs(sub[0, 0] - 2.0) < 0.5 and abs(sub[0, 1] - 0.3) < 0.5, sub  # 45-degree grid steps


def test_near_goal_is_the_sub_goal_and_a_very_near_one_stops():
    stop, sub = _decide(np.zeros((32, 32)), (1.2, -0.7))
    assert stop[0] == 0 and np.allclose(sub[0], (1.2, -0.7), atol=1e-6)
    stop, _ = _decide(np.zeros((32, 32)), (0.1, 0.0))
    assert stop[0] == 1


def test_wall_ahead_with_a_gap_on_the_right_leads_to_the_gap():
    """A wall 2 m ahead across the whole map but for a gap 3 m to the right: the sub-goal
    turns right (negative direction: column 0 is on the agent's left), and the mirror image
    turns left."""
    wall = np.zeros((32, 32))
    wall[12, :] = 1.0
    wall[12, 22:24] = 0.0  # columns 22-23: 3-4 m to the right of the agent (column 16)
    _, sub = _decide(wall, (10.0, 0.0))
    assert sub[0, 1] < -0.4, sub
    _, sub = _decide(wall[:, ::-1].copy(), (10.0, 0.0))
    assert sub[0, 1] > 0.4, sub


def test_closed_map_falls_back_towards_the_goal():
    walls = np.zeros((32, 32))
    walls[14, 13:20] = walls[18, 13:20] = walls[14:19, 13] = walls[14:19, 19] = 1.0  # a closed box around the agent
    _, sub = _decide(walls, (8.0, 1.0))
    assert math.isclose(sub[0, 0], 1.5, abs_tol=1e-6) and math.isclose(sub[0, 1], 1.0, abs_tol=1e-6)


def test_map_planner_over_the_oracle_executor_navigates():
    """On 40 procgen test episodes, with the oracle executor following its sub-goals, the
    map planner (no ground truth) reaches the goal in most of them (0.87 on 100 val
    episodes at 64 px)."""
    env = PlexVectorEnv(8, seed=0, resolution=64, split="test")
    env.worlds.fixed_episodes = list(env.worlds.fixed_episodes[:40])
    drv = PlexDriver(env, MapPlannerPolicy(), OracleExecutorPolicy(env))
    drv.reset(seed=0)
    infos = {}
    while len(infos) < 40:
        drv.decide(lambda d: infos.update({i["episode_id"]: i for i in d.result.episode_infos}))
        s = drv.step()
        infos.update({i["episode_id"]: i for i in s.result.episode_infos})
    success = np.mean([infos[e.episode_id]["success"] for e in env.worlds.fixed_episodes])
    assert success >= 0.6, success


def _cell(sub):
    """The ego-map cell (row, column) of a sub-goal (rho, theta)."""
    f, l = sub[0] * math.cos(sub[1]), sub[0] * math.sin(sub[1])
    return int(math.floor(16 - f / 0.5)), int(math.floor(16 - l / 0.5))


def test_line_of_sight_sub_goals_stay_on_seen_floor():
    """Seen floor 2 m ahead and 1-1.5 m to each side, unseen space beyond: the plain
    planner's sub-goal, 2 m along its path towards a goal ahead and to the right, lies in
    unseen space; map-los cuts it to the seen floor, nearer. With everything seen and free
    the two agree."""
    ego = np.zeros((1, 2, 32, 32), np.float32)
    ego[0, 1, 12:16, 13:19] = 1.0  # seen floor: 0-2 m ahead, 1.5 m left to 1 m right
    goal = np.array([[10.0, -0.6]], np.float32)
    _, plain = MapPlanner().decide({"ego_map": ego, "goal": goal})
    _, los = MapPlanner(line_of_sight=True).decide({"ego_map": ego, "goal": goal})
    assert ego[0, 1][_cell(plain[0])] == 0.0, plain  # unseen
    assert ego[0, 1][_cell(los[0])] == 1.0, los  # seen floor
    assert los[0, 0] < plain[0, 0] - 0.2 and los[0, 1] < 0, (los, plain)
    ego[0, 1] = 1.0
    _, los = MapPlanner(line_of_sight=True).decide({"ego_map": ego, "goal": goal})
    _, plain = MapPlanner().decide({"ego_map": ego, "goal": goal})
    assert np.allclose(los, plain), (los, plain)


def test_no_path_cuts_a_wall_corner():
    """Two blocked cells that touch the agent's cell (16, 16) and the goal's cell (15, 17): a
    diagonal step between those would pass through the corner where the blocked cells meet,
    so the distance is the way round them (6 orthogonal steps, not sqrt 2: a diagonal step
    past one blocked cell is refused too)."""
    blocked = np.zeros((32, 32), np.bool_)
    blocked[15, 16] = blocked[16, 17] = True  # ahead of the agent, and to its right
    dist = _distances(blocked, 15, 17, _NEIGHBOURS)
    assert math.isclose(dist[16, 16], 6.0), dist[16, 16]
    assert math.isclose(dist[14, 17], 1.0) and math.isclose(dist[14, 16], 2.0)


def test_line_of_sight_planner_plans_round_a_wall_to_a_near_goal():
    """A goal 1.5 m ahead behind a wall, all of it seen: the plain planner sets the goal
    itself as the sub-goal; map-los plans round the wall and sets a sub-goal it can walk to
    in a straight line."""
    ego = np.zeros((1, 2, 32, 32), np.float32)
    ego[0, 1] = 1.0
    ego[0, 0, 14, 12:21] = 1.0  # a wall 1 m ahead, 4.5 m wide
    goal = np.array([[1.5, 0.0]], np.float32)
    _, plain = MapPlanner().decide({"ego_map": ego, "goal": goal})
    _, los = MapPlanner(line_of_sight=True).decide({"ego_map": ego, "goal": goal})
    assert np.allclose(plain[0], (1.5, 0.0), atol=1e-6)
    assert abs(los[0, 1]) > 0.5, los  # off to one side, towards the wall's end
    assert ego[0, 0][_cell(los[0])] == 0.0


def test_value_iteration_planner_over_the_oracle_executor_navigates():
    """``evaluate --planner vin``: the untrained value-iteration module's sub-goal (what the
    learned planner offsets), over the oracle executor, reaches most goals."""
    from plex_ma.evaluate import main

    out = main(["--planner", "vin", "--executor", "oracle", "--split", "test", "--episodes", "32", "--num-envs", "8"])
    assert out["success"] >= 0.8, out["success"]  # 1.0 at the time of writing


def test_value_iteration_planner_without_a_network_plans_as_the_preset_does():
    """``--planner vin`` takes a planner network's own module; without one, the cells the
    config sets (the cpu preset's quarter cells, the paper's 0.5 m cells)."""
    from plex_ma.config import preset_defaults
    from plex_ma.trainers.base import build_policies
    from plex_ma.trainers.driver import make_planner

    assert make_planner("vin", None, fine_map=True).vin.fine
    assert not make_planner("vin", None, fine_map=False).vin.fine
    assert preset_defaults("cpu", "plex-gru").planner_fine_map  # what evaluation passes without a checkpoint
    paper = build_policies(preset_defaults("paper", "plex-gru"))["planner"]
    assert make_planner("vin", None, paper, fine_map=True).vin.fine  # no module of its own: the config's cells
    cpu = build_policies(preset_defaults("cpu", "plex-gru"))["planner"]
    assert make_planner("vin", None, cpu, fine_map=False).vin.fine  # the network's own module wins
