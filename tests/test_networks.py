"""Networks: recurrent training pass == rollout steps, stop-gradient, shapes, init, FLOPs."""

import math

import pytest
import torch

from plex_ma.envs.sim.core import STOP
from plex_ma.networks import ELI_DIM, MAP_PLAN, STOP_INIT_LOGIT, SUBGOAL_MARGIN, Executor, FlatMapPolicy, FlatPolicy, Planner
from plex_ma.trainers.base import build_policies
from plex_ma.trainers.ppo import RolloutBuffer




@pytest.fixture(scope="module")
def planner():
    torch.manual_seed(0)
    return Planner()


def _stack(obs_list):
    return {k: torch.stack([o[k] for o in obs_list]) for k in obs_list[0]}


def _rollout(policy, buf, state, starts, gen):
    """Fill ``buf`` by stepping ``policy.act`` with the given starts (T, B); return the new state."""
    buf.initial_state = state.clone()
    for t in range(buf.num_steps):
        obs = policy.example_obs(buf.num_envs, gen)
        out, state = policy.act(obs, state, starts[t])
        buf.add(t, obs=obs, actions=out["action"], log_probs=out["log_prob"], values=out["value"],
                rewards=torch.zeros(buf.num_envs), dones=torch.zeros(buf.num_envs), starts=starts[t])
    buf.compute_returns(0.9, 0.95, last_values=torch.zeros(buf.num_envs))
    return state


@pytest.mark.parametrize("make", [
    lambda: Executor("gru", 64),
    lambda: Executor("smt", 64, smt_memory=4),  # tiny memory: the sliding window and the stored memory matter
    lambda: FlatPolicy("smt", 64, smt_memory=5),
    lambda: FlatMapPolicy("gru", 64, gru_hidden=32, value_iteration=True),  # ppo-gru-map: ego map + VIN
    lambda: Executor("gru", 64, gru_hidden=32, no_reversal=True),  # the barred turns, from the stored actions
    lambda: FlatPolicy("smt", 64, smt_memory=5, no_reversal=True),
], ids=["executor-gru", "executor-smt", "flat-smt", "flat-gru-map", "executor-gru-no-reversal", "flat-smt-no-reversal"])
def test_evaluate_sequences_matches_step_by_step(make):
    torch.manual_seed(0)
    gen = torch.Generator().manual_seed(1)
    policy = make()
    T, B = 12, 4
    starts = torch.rand(2 * T, B, generator=gen) < 0.2
    starts[0] = True
    starts[:, 0] = False  # env 0: one sequence across both rollouts, longer than the SMT memory
    starts[0, 0] = True
    starts[T, 1] = True  # env 1: starts right at the second rollout's first step
    state = policy.initial_state(B)
    for k in range(2):  # the second rollout begins with memory carried over from the first
        buf = RolloutBuffer(T, B)
        state = _rollout(policy, buf, state, starts[k * T:(k + 1) * T], gen)
        for mb_idx, mb in enumerate(buf.minibatches(2, torch.Generator().manual_seed(k))):
            with torch.no_grad():
                log_probs, entropy, values = policy.evaluate_sequences(mb.obs, mb.actions, mb.starts, mb.initial_state)
            assert log_probs.shape == values.shape == entropy.shape == (T, mb.starts.shape[1])
            torch.testing.assert_close(log_probs, mb.log_probs, atol=1e-5, rtol=0)
            torch.testing.assert_close(values, mb.values, atol=1e-5, rtol=0)


@pytest.mark.parametrize("memory", ["gru", "smt"])
def test_memory_is_used_and_reset(memory):
    torch.manual_seed(0)
    ex = Executor(memory, 64, gru_hidden=64)
    gen = torch.Generator().manual_seed(0)
    seq = _stack([ex.example_obs(2, gen) for _ in range(3)])
    actions = torch.zeros(3, 2, dtype=torch.long)
    state = ex.initial_state(2)
    with torch.no_grad():
        for _ in range(3):
            _, state = ex.act(ex.example_obs(2, gen), state, torch.zeros(2, dtype=torch.bool))
        no_start = torch.zeros(3, 2, dtype=torch.bool)
        _, _, v_mem = ex.evaluate_sequences(seq, actions, no_start, state)
        _, _, v_fresh = ex.evaluate_sequences(seq, actions, no_start, ex.initial_state(2))
        _, _, v_reset = ex.evaluate_sequences(seq, actions, no_start.index_fill(0, torch.tensor([0]), True), state)
    assert not torch.allclose(v_mem, v_fresh)  # the stored memory changes the outputs
    torch.testing.assert_close(v_reset, v_fresh, atol=1e-6, rtol=0)  # a start forgets it


@pytest.mark.parametrize("memory", ["gru", "smt"])
def test_no_reversal_bars_undoing_the_last_turn(memory):
    """With ``no_reversal`` no sequence holds LEFT then RIGHT or RIGHT then LEFT (an untrained
    policy, near uniform, does without it); a start lifts the bar."""
    def reversals(no_reversal):
        torch.manual_seed(0)
        ex = Executor(memory, 64, gru_hidden=32, smt_memory=8, no_reversal=no_reversal)
        gen = torch.Generator().manual_seed(0)
        state, prev, count, after_start = ex.initial_state(16), None, 0, 0
        for t in range(40):
            starts = torch.full((16,), t % 10 == 0)
            out, state = ex.act(ex.example_obs(16, gen), state, starts)
            a = out["action"]
            if prev is not None:
                undo = ((prev == 2) & (a == 3)) | ((prev == 3) & (a == 2))
                count += int((undo & ~starts).sum())
                after_start += int((undo & starts).sum())
            assert torch.equal(ex.split_state(state)[1], a)  # the state keeps the action taken
            prev = a
        return count, after_start
    assert reversals(False)[0] > 20
    barred, after_start = reversals(True)
    assert barred == 0 and after_start > 0


def test_planner_eli_is_detached_from_executor():
    torch.manual_seed(0)
    ex, pl = Executor("gru", 64, gru_hidden=64), Planner(channels=(8, 8), hidden=64)
    _, _, eli, _ = ex(ex.example_obs(3), ex.initial_state(3), torch.ones(3, dtype=torch.bool))
    assert eli.requires_grad and eli.shape == (3, ELI_DIM)
    eli.retain_grad()
    obs = pl.example_obs(3)
    obs["eli"] = eli
    out = pl.act(obs)
    before = {k: v.clone() for k, v in ex.state_dict().items()}
    opt = torch.optim.Adam(pl.parameters(), lr=1e-2)
    log_prob, entropy, value = pl.evaluate_actions(obs, out["stop"], out["raw_subgoal"])
    (-log_prob.mean() - entropy.mean() + (value - 1).pow(2).mean()).backward()
    assert all(p.grad is None for p in ex.parameters())
    assert eli.grad is None  # the planner used a detached copy
    eli_cols = pl.fc[0].weight.grad[:, -ELI_DIM:]
    assert eli_cols.abs().sum() > 0  # ... and did use it
    opt.step()
    for k, v in ex.state_dict().items():
        assert torch.equal(v, before[k]), k


def test_planner_without_eli_ignores_it():
    pl = Planner(use_eli=False, channels=(8, 8), hidden=64)
    obs = pl.example_obs(2)
    v1 = pl.evaluate_actions(obs, torch.zeros(2), torch.zeros(2, 2))[2]
    obs["eli"] = obs["eli"] + 5
    assert torch.equal(v1, pl.evaluate_actions(obs, torch.zeros(2), torch.zeros(2, 2))[2])


def _check_log_probs(pl, obs, out):
    """A planner's act() output: its shapes; the log-prob is computed on the raw sample and
    evaluate_actions reproduces it; a stop decision's log-prob ignores the (unused) sub-goal."""
    raw, n = out["raw_subgoal"], len(out["stop"])
    assert out["raw_subgoal"].shape == out["subgoal"].shape == (n, 2)
    assert out["log_prob"].shape == out["value"].shape == (n,)
    log_prob, _, value = pl.evaluate_actions(obs, out["stop"], raw)
    torch.testing.assert_close(log_prob, out["log_prob"])
    torch.testing.assert_close(value, out["value"])
    ones = torch.ones(n, dtype=torch.long)
    torch.testing.assert_close(pl.evaluate_actions(obs, ones, raw)[0], pl.evaluate_actions(obs, ones, raw + 3)[0])


@pytest.mark.parametrize("resolution", [64, 128])
@pytest.mark.parametrize("cls,memory", [(Executor, "gru"), (Executor, "smt"), (FlatPolicy, "gru"), (FlatPolicy, "smt")])
def test_recurrent_shapes(cls, memory, resolution):
    policy = cls(memory, resolution)
    B, T = 2, 3
    obs = policy.example_obs(B)
    assert obs["rgb"].shape == (B, resolution, resolution, 3) and obs["rgb"].dtype == torch.uint8
    assert ("subgoal" if cls is Executor else "pointgoal") in obs
    state = policy.initial_state(B)
    out, new_state = policy.act({k: v.numpy() for k, v in obs.items()}, state, [True, False])  # numpy works too
    assert out["action"].shape == out["log_prob"].shape == out["value"].shape == (B,)
    assert out["eli"].shape == (B, ELI_DIM) and out["eli"].abs().max() <= 1
    assert new_state.shape == state.shape
    # the memory's state flattened, and the previous action
    assert state.shape == ((B, 513) if memory == "gru" else (B, 128 * 129 + 1))
    seq = _stack([policy.example_obs(B) for _ in range(T)])
    lp, ent, v = policy.evaluate_sequences(seq, torch.zeros(T, B), torch.zeros(T, B, dtype=torch.bool), state)
    assert lp.shape == ent.shape == v.shape == (T, B)


def test_planner_shapes():
    pl = Planner(ego_channels=3, channels=(8, 8), hidden=64)
    obs = pl.example_obs(5)
    assert obs["ego_map"].shape == (5, 6, 32, 32) and pl.convs[0].in_channels == 3  # the trunk reads the first 3
    lp, ent, v = pl.evaluate_actions(obs, torch.zeros(5), torch.zeros(5, 2))
    assert lp.shape == ent.shape == v.shape == (5,)


def _assert_orthogonal(w, gain):
    w = w.detach().flatten(1)
    gram = w @ w.T if w.shape[0] <= w.shape[1] else w.T @ w
    torch.testing.assert_close(gram, gain ** 2 * torch.eye(gram.shape[0]), atol=1e-4 * max(gain ** 2, 1), rtol=0)


def test_orthogonal_init(planner):
    ex, pl = Executor("gru", 64), planner
    _assert_orthogonal(ex.encoder.convs[0].weight, math.sqrt(2))
    _assert_orthogonal(ex.encoder.fc[0].weight, math.sqrt(2))
    _assert_orthogonal(ex.actor.weight, 0.01)
    _assert_orthogonal(ex.critic.weight, 1.0)
    _assert_orthogonal(pl.convs[0].weight, math.sqrt(2))  # the heads: test_planner_init
    assert torch.all(ex.actor.bias == 0) and torch.all(ex.encoder.convs[0].bias == 0)


def test_flops_and_matmul_speed(planner):
    from plex_ma.flops import matmul_gflops, model_flops_per_step

    ex = Executor("gru", 64)
    flops = model_flops_per_step(ex)
    conv1 = 2 * 15 * 15 * 32 * 4 * 8 * 8  # the first conv alone: 2 * out positions * out ch * in ch * k * k
    gru = 2 * 3 * (515 * 512 + 512 * 512)
    assert flops > conv1 + gru
    assert model_flops_per_step(Executor("smt", 64)) > 0 and model_flops_per_step(planner) > 0
    assert matmul_gflops(n=256, seconds=0.05) > 0


def test_planner_actions():
    torch.manual_seed(0)
    pl = Planner(rho_max=4.0, init_std=math.exp(1.5), channels=(8, 8), hidden=64)  # wide std: samples leave the box
    obs = pl.example_obs(256)
    out = pl.act(obs)
    raw, env = out["raw_subgoal"], out["subgoal"]  # raw: (forward, left) m; env: (distance, direction)
    assert (torch.hypot(raw[:, 0], raw[:, 1]) > 4).any()
    assert env[:, 0].min() >= 0 and env[:, 0].max() <= 4 and env[:, 1].double().abs().max() <= math.pi
    torch.testing.assert_close(env[:, 1], torch.atan2(raw[:, 1], raw[:, 0]), atol=1e-6, rtol=0)
    _check_log_probs(pl, obs, out)
    edge = pl.subgoal_to_env(torch.tensor([[5.0, 0.0], [-1.0, 0.0], [0.0, -1.0]], dtype=torch.float32))
    assert edge[:, 0].tolist() == [4.0, 1.0, 1.0]
    assert edge[:, 1].tolist() == pytest.approx([0.0, math.pi, -math.pi / 2], abs=1e-6)




def test_planner_sets_no_subgoal_within_the_executors_radius():
    """Given the executor's sub-goal radius, the sub-goals sent to the env lie at least
    SUBGOAL_MARGIN beyond it (a nearer one pays the executor nothing), whatever the sample;
    the raw sample, on which the log-prob is computed, is left as it was."""
    raw = torch.tensor([[-0.1, 0.0], [0.0, 0.0], [0.1, 0.0], [0.0, 0.3], [5.0, 0.0]])
    pl = Planner(rho_max=4.0, channels=(8, 8), hidden=64, subgoal_radius=0.2)
    assert pl.subgoal_to_env(raw)[:, 0].tolist() == pytest.approx([0.25, 0.25, 0.25, 0.3, 4.0])
    assert Planner(rho_max=4.0, channels=(8, 8), hidden=64).subgoal_to_env(raw)[:, 0].tolist() == pytest.approx(
        [0.1, 0.0, 0.1, 0.3, 4.0])
    from plex_ma.config import preset_defaults
    assert build_policies(preset_defaults("cpu"))["planner"].min_subgoal_distance == pytest.approx(0.2 + SUBGOAL_MARGIN)


def test_untrained_policies_know_nothing_of_the_goal():
    """docs/spec.md section 6: no hand-set state-dependent term in any policy output. The
    cpu preset's untrained planner sets its mean sub-goal at its constant start, 1 m ahead,
    wherever the goal is, and its p(stop) is the stop head's constant start everywhere; the
    untrained executor's action probabilities are the same wherever its sub-goal is."""
    torch.manual_seed(0)
    from plex_ma.config import preset_defaults

    cfg = preset_defaults("cpu")
    nets = build_policies(cfg)
    pl = nets["planner"]
    obs = pl.example_obs(64)
    obs["goal"] = torch.stack([torch.linspace(0.0, 8.0, 64), torch.linspace(-3.0, 3.0, 64)], 1)
    stop_d, sub_d, _ = pl(obs)
    torch.testing.assert_close(sub_d.mean, torch.tensor([cfg.planner_subgoal_forward, 0.0]).expand(64, 2),
                               atol=0.2, rtol=0)
    p_stop = torch.sigmoid(torch.tensor(STOP_INIT_LOGIT))  # a constant bias, the same in every state
    torch.testing.assert_close(stop_d.probs[:, 1], p_stop.expand(64), atol=0.01, rtol=0)
    ex = nets["executor"]
    ex_obs = ex.example_obs(5)
    ex_obs["subgoal"] = torch.tensor([[2.0, 0.0], [2.0, 1.5], [2.0, -1.5], [2.0, 3.0], [0.05, 0.0]])
    p = torch.softmax(ex(ex_obs, ex.initial_state(5), torch.ones(5, dtype=torch.bool))[0], -1)
    torch.testing.assert_close(p, p[:1].expand(5, -1), atol=0.02, rtol=0)


def test_plan_features_are_positions_in_the_agents_frame():
    """plan_features: the goal clipped to the read-out's reach and the value-iteration
    sub-goal, each as (forward, left) metres; zeros without the module."""
    from plex_ma.networks import SUBGOAL_REACH, plan_features

    goal = torch.tensor([[1.0, 0.0], [8.0, math.pi / 2]])
    vin = torch.tensor([[0.5, math.pi], [2.0, -math.pi / 2]])
    expect = torch.tensor([[1.0, 0.0, -0.5, 0.0], [0.0, SUBGOAL_REACH, 0.0, -2.0]])
    torch.testing.assert_close(plan_features(goal, vin), expect, atol=1e-6, rtol=0)
    torch.testing.assert_close(plan_features(goal, None)[:, 2:], torch.zeros(2, 2))


def test_planner_init():
    """Every layer of the planner under CleanRL's initialisation: no hand-set weight."""
    pl = Planner(channels=(8, 8), hidden=64)
    for head, gain in ((pl.stop_logits, 0.01), (pl.subgoal_mean, 0.01), (pl.critic, 1.0)):
        _assert_orthogonal(head.mlp[0].weight, math.sqrt(2))
        _assert_orthogonal(head.mlp[-1].weight, gain)
        _assert_orthogonal(head.linear.weight, gain)
        assert torch.all(head.mlp[-1].bias == 0)
    assert pl.stop_logits.linear.bias.tolist() == [0.0, STOP_INIT_LOGIT] and torch.all(pl.subgoal_mean.linear.bias == 0)
    assert not hasattr(pl, "stop_skip")


def test_cnn_min_resolution_is_the_smallest_image_the_executor_takes():
    """config.CNN_MIN_RESOLUTION, the bound that train and bench check, is exactly the
    executor encoder's smallest input."""
    from plex_ma.config import CNN_MIN_RESOLUTION
    from plex_ma.networks.executor import RGBDEncoder

    RGBDEncoder(CNN_MIN_RESOLUTION, 8)
    with pytest.raises(RuntimeError):
        RGBDEncoder(CNN_MIN_RESOLUTION - 1, 8)


def test_stored_map_plan_gives_the_same_planner_pass():
    """The trainer stores the value-iteration read-out with each decision (``with_map_plan``):
    the PPO epochs' pass over it equals the pass that recomputes it, and it is really read."""
    torch.manual_seed(0)
    net = Planner(value_iteration=True, fine_map=True, subgoal_radius=0.2)
    gen = torch.Generator().manual_seed(1)
    obs = net.example_obs(4, gen)
    obs["ego_map"] = (obs["ego_map"] < 0.2).float()
    stored = net.with_map_plan(obs)
    assert stored[MAP_PLAN].shape == (4, net.vin_dim + 2) and net.with_map_plan(stored) is stored
    act = net.act(stored)
    args = (act["stop"], act["raw_subgoal"])
    for a, b in zip(net.evaluate_actions(stored, *args), net.evaluate_actions(obs, *args)):
        torch.testing.assert_close(a, b)
    wrong = {**stored, MAP_PLAN: torch.as_tensor(stored[MAP_PLAN]).flip(0)}
    assert not torch.allclose(net.evaluate_actions(wrong, *args)[0], net.evaluate_actions(obs, *args)[0])
    assert Planner().with_map_plan(obs) is obs  # no module, nothing to store


def test_constant_starts_are_the_same_in_every_state():
    """The two constant starts docs/spec.md section 6 allows: ``planner_subgoal_forward`` puts
    the untrained planner's mean sub-goal that far ahead and ``executor_stop_bias`` lowers the
    untrained executor's STOP logit, both whatever the goal or sub-goal."""
    torch.manual_seed(0)
    pl = Planner(subgoal_forward=1.0)
    obs = pl.example_obs(32)
    mean = pl(obs)[1].mean
    torch.testing.assert_close(mean, torch.tensor([1.0, 0.0]).expand(32, 2), atol=0.2, rtol=0)
    ex = Executor(resolution=40, gru_hidden=16, stop_bias=-3.0)
    ex_obs = ex.example_obs(5)
    ex_obs["subgoal"] = torch.tensor([[2.0, 0.0], [2.0, 1.5], [2.0, -1.5], [2.0, 3.0], [0.05, 0.0]])
    p = torch.softmax(ex(ex_obs, ex.initial_state(5), torch.ones(5, dtype=torch.bool))[0], -1)
    p_stop = 1 / (1 + 3 * math.exp(3.0))
    torch.testing.assert_close(p[:, STOP], torch.full((5,), p_stop), atol=0.01, rtol=0)
    torch.testing.assert_close(p[:, 1:], torch.full((5, 3), (1 - p_stop) / 3), atol=0.02, rtol=0)  # the moves




def test_goal_rbf_features_read_the_distance_finely_near_the_goal():
    """planner_goal_features(rbf=True): the five goal features, then one Gaussian bump per
    centre that peaks (1.0) at its centre, so that 0.18 m and 0.28 m differ by about half
    an input's range in several inputs (the plain features by at most 0.13). Planners and
    the map arm built with ``goal_rbf`` take the wider input."""
    from plex_ma.networks import goal_feature_count, planner_goal_features
    from plex_ma.networks.planner import GOAL_RBF_CENTRES

    goal = torch.tensor([[c, 0.3] for c in GOAL_RBF_CENTRES] + [[0.18, 0.0], [0.28, 0.0]])
    plain, fine = planner_goal_features(goal), planner_goal_features(goal, rbf=True)
    assert fine.shape == (len(goal), goal_feature_count(True)) and plain.shape == (len(goal), goal_feature_count())
    torch.testing.assert_close(fine[:, :plain.shape[1]], plain)
    bumps = fine[:len(GOAL_RBF_CENTRES), plain.shape[1]:]
    torch.testing.assert_close(bumps.diagonal(), torch.ones(len(GOAL_RBF_CENTRES)))
    assert (plain[-2] - plain[-1]).abs().max() < 0.14
    assert ((fine[-2] - fine[-1]).abs() > 0.4).sum() >= 3
    pl = Planner(channels=(8, 8), hidden=64, goal_rbf=True)
    stop_d, sub_d, value = pl(pl.example_obs(3))
    assert stop_d.probs.shape == (3, 2) and sub_d.mean.shape == (3, 2) and value.shape == (3,)
    fm = FlatMapPolicy("gru", 64, gru_hidden=32, goal_rbf=True)
    logits, value, _, _ = fm(fm.example_obs(2), fm.initial_state(2), torch.ones(2, dtype=torch.bool))
    assert logits.shape == (2, 4) and value.shape == (2,)
