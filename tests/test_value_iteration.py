"""The planner's value-iteration module: distances against a reference search, its sub-goal
on synthetic maps, that it has no parameters (and old checkpoints' learned cost is
ignored), and the stop-gradient with it in the planner."""

from __future__ import annotations

import numpy as np
import torch

from plex_ma.envs.map_planner import _NEIGHBOURS, _distances
from plex_ma.envs.rules import ELI_DIM
from plex_ma.networks import Executor, Planner, ValueIteration, bellman, bellman_reference


def test_bellman_matches_dijkstra_on_a_random_grid():
    """Unit cost on free cells, a prohibitive one on blocked cells: the distances equal the
    map planner's Dijkstra (8 neighbours, sqrt 2 diagonals, no corner cutting) wherever it
    reaches, and exceed any path's length wherever it does not."""
    rng = np.random.default_rng(0)
    blocked = rng.random((24, 24)) < 0.3
    blocked[5, 7] = False
    ref = _distances(blocked.copy(), 5, 7, _NEIGHBOURS)
    cost = torch.tensor(np.where(blocked, 1e3, 1.0), dtype=torch.float32)[None]
    src = torch.zeros(1, 24, 24, dtype=torch.bool)
    src[0, 5, 7] = True
    got = bellman(cost, src, iterations=150)[0].numpy()
    free = np.isfinite(ref)
    assert free.sum() > 100
    np.testing.assert_allclose(got[free], ref[free], rtol=1e-5)
    assert np.all(got[~free] >= 1e3)


def test_compiled_bellman_matches_the_tensor_reference():
    """The CPU path (compiled loops) against the tensor operations, on a batch of maps with
    walls, the map's edge and unreached cells: the same distances bit for bit, for smooth
    costs and for whole-number costs (1 on free cells, 100 on walls), where ties are
    everywhere; with 300 updates, more than any map needs, the loops stop early at the fixed
    point and still match."""
    gen = torch.Generator().manual_seed(0)
    B, s = 6, 32
    walls = (torch.rand(B, s, s, generator=gen) > 0.8).float()
    smooth = 1 + torch.nn.functional.softplus(96 * walls - 4 + torch.randn(B, s, s, generator=gen))
    src = torch.zeros(B, s, s, dtype=torch.bool)
    src[torch.arange(B), torch.randint(s, (B,), generator=gen), torch.randint(s, (B,), generator=gen)] = True
    for cost, iterations in ((smooth, 40), (smooth, 12), (1 + 99 * walls, 40), (smooth, 300), (1 + 99 * walls, 300)):
        ref, got = bellman_reference(cost, src, iterations), bellman(cost, src, iterations)
        assert torch.equal(ref, got)
        assert (ref < 1e4).float().mean() > 0.3  # most cells reached, the rest not


def _subgoal(obstacles: np.ndarray, goal: tuple[float, float]) -> np.ndarray:
    ego = torch.zeros(1, 2, 32, 32)
    ego[0, 0] = torch.as_tensor(obstacles, dtype=torch.float32)
    with torch.no_grad():
        _, sub = ValueIteration()(ego, torch.tensor([goal], dtype=torch.float32))
    return sub[0].numpy()


def test_open_map_sub_goal_heads_for_the_goal_within_reach():
    rho, theta = _subgoal(np.zeros((32, 32)), (10.0, 0.3))
    assert 1.2 <= rho <= 2.2 and abs(theta - 0.3) < 0.35, (rho, theta)  # octile steps: not exactly the goal's direction


def test_near_goal_in_the_open_is_the_sub_goal():
    assert np.allclose(_subgoal(np.zeros((32, 32)), (1.2, -0.7)), (1.2, -0.7), atol=1e-5)


def test_a_near_goal_in_a_cell_marked_as_obstacle_is_still_the_sub_goal():
    """A 0.5 m cell that holds the goal beside a wall is marked as an obstacle; the sub-goal
    search still enters it, so the goal itself is the sub-goal, not a free cell next to it."""
    obstacles = np.zeros((32, 32))
    obstacles[13, 16] = 1.0  # the goal's cell, 1.2 m ahead
    assert np.allclose(_subgoal(obstacles, (1.2, 0.0)), (1.2, 0.0), atol=1e-5)


def test_wall_with_a_gap_on_the_right_leads_right_and_its_mirror_left():
    wall = np.zeros((32, 32))
    wall[12, :] = 1.0
    wall[12, 22:24] = 0.0  # a gap 3-4 m to the agent's right (column 0 is on its left)
    assert _subgoal(wall, (10.0, 0.0))[1] < -0.4
    assert _subgoal(wall[:, ::-1].copy(), (10.0, 0.0))[1] > 0.4


def test_module_has_no_parameters():
    """The cost is fixed: no parameters, no gradient."""
    pl = Planner(channels=(8, 8), hidden=64, value_iteration=True)
    assert not list(pl.vin.parameters())
    ego = (torch.rand(2, 2, 32, 32) < 0.2).float().requires_grad_()
    feats, _ = pl.vin(ego, torch.tensor([[6.0, 0.5], [1.5, 0.1]]))
    assert not feats.requires_grad


def test_stop_gradient_holds_with_the_value_iteration_planner():
    torch.manual_seed(0)
    ex = Executor("gru", 64, gru_hidden=64)
    pl = Planner(channels=(8, 8), hidden=64, value_iteration=True)
    _, _, eli, _ = ex(ex.example_obs(3), ex.initial_state(3), torch.ones(3, dtype=torch.bool))
    obs = pl.example_obs(3)
    obs["eli"] = eli
    before = {k: v.clone() for k, v in ex.state_dict().items()}
    out = pl.act(obs)
    opt = torch.optim.Adam(pl.parameters(), lr=1e-2)
    log_prob, entropy, value = pl.evaluate_actions(obs, out["stop"], out["raw_subgoal"])
    (-log_prob.mean() - entropy.mean() + (value - 1).pow(2).mean()).backward()
    assert all(p.grad is None for p in ex.parameters())
    assert pl.convs[0].weight.grad.abs().sum() > 0
    opt.step()
    for k, v in ex.state_dict().items():
        assert torch.equal(v, before[k]), k
    assert ELI_DIM == eli.shape[1]

