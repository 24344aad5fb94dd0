"""Generic PPO machinery: GAE conventions, the rollout buffer's minibatches, ppo_update."""

import json

import torch

from plex_ma.bench import main as bench_main
from plex_ma.config import preset_defaults, replace
from plex_ma.networks import Executor, Planner
from plex_ma.trainers.plex import PlexTrainer
from plex_ma.trainers.ppo import PPOConfig, RolloutBuffer, compute_gae, ppo_loss, ppo_update




def test_gae_hand_computed():
    gamma, lam = 0.9, 0.5
    # env 0: terminates at t=1; the rollout ends mid-episode, bootstrapping from V(o_T) = 3.
    # env 1: truncated at t=1 (bootstrap V(final obs) = 2), terminates at t=3.
    # 99 marks bootstrap values that must be ignored.
    rewards = torch.tensor([[1.0, 0.0], [2.0, 1.0], [3.0, 0.0], [4.0, 1.0]])
    values = torch.tensor([[0.5, 1.0], [1.0, 1.0], [1.5, 1.0], [2.0, 1.0]])
    dones = torch.tensor([[0, 0], [1, 1], [0, 0], [0, 1]], dtype=torch.bool)
    truncated = torch.tensor([[0, 0], [0, 1], [0, 0], [0, 0]], dtype=torch.bool)
    boot = torch.tensor([[99.0, 99.0], [99.0, 2.0], [99.0, 99.0], [3.0, 99.0]])
    adv, ret = compute_gae(rewards, values, dones, truncated, boot, gamma, lam)
    # env 0, backwards: d3 = 4 + .9*3 - 2 = 4.7; d2 = 3 + .9*2 - 1.5 = 3.3 -> 3.3 + .45*4.7 = 5.415
    #   d1 = 2 + 0 - 1 = 1 (terminal, chain cut); d0 = 1 + .9*1 - .5 = 1.4 -> 1.4 + .45*1 = 1.85
    # env 1: d3 = 1 - 1 = 0; d2 = 0 + .9 - 1 = -.1; d1 = 1 + .9*2 - 1 = 1.8 (truncated, chain cut)
    #   d0 = 0 + .9 - 1 = -.1 -> -.1 + .45*1.8 = .71
    expected = torch.tensor([[1.85, 0.71], [1.0, 1.8], [5.415, -0.1], [4.7, 0.0]])
    torch.testing.assert_close(adv, expected)
    torch.testing.assert_close(ret, expected + values)
    # numpy input and "truncated implies done" give the same answer
    adv2, _ = compute_gae(rewards.numpy(), values.numpy(), (dones & ~truncated).numpy(), truncated.numpy(),
                          boot.numpy(), gamma, lam)
    torch.testing.assert_close(adv2, expected)


def test_buffer_compute_returns_uses_last_values():
    buf = RolloutBuffer(2, 2)
    for t in range(2):
        buf.add(t, obs={"x": torch.zeros(2, 1)}, actions=torch.zeros(2), log_probs=torch.zeros(2),
                values=torch.ones(2), rewards=torch.ones(2), dones=torch.tensor([False, t == 1]),
                bootstrap_values=torch.full((2,), 99.0))
    buf.compute_returns(gamma=0.5, lam=1.0, last_values=torch.tensor([4.0, 4.0]))
    # env 0 bootstraps from last_values (4); env 1 terminated at the last step (0).
    torch.testing.assert_close(buf.data["returns"], torch.tensor([[1 + 0.5 * (1 + 0.5 * 4), 1.5], [1 + 0.5 * 4, 1.0]]))


def _fill(buf, T, B, seed=0, recurrent=False):
    g = torch.Generator().manual_seed(seed)
    if recurrent:
        buf.initial_state = torch.arange(B, dtype=torch.float32)[:, None].repeat(1, 3)
    for t in range(T):
        buf.add(t, obs={"x": torch.full((B, 2), float(t)), "env": torch.arange(B)},
                actions={"stop": torch.zeros(B, dtype=torch.long), "subgoal": torch.randn(B, 2, generator=g)},
                log_probs=torch.randn(B, generator=g), values=torch.randn(B, generator=g),
                rewards=torch.randn(B, generator=g), dones=torch.rand(B, generator=g) < 0.2,
                starts=torch.rand(B, generator=g) < 0.3)
    buf.compute_returns(0.95, 0.95, last_values=torch.zeros(B))


def test_minibatches_cover_rollout():
    T, B = 5, 6
    flat = RolloutBuffer(T, B)
    _fill(flat, T, B)
    seen = []
    for mb in flat.minibatches(4, torch.Generator().manual_seed(0)):
        assert mb.initial_state is None and mb.obs["x"].ndim == 2 and mb.actions["subgoal"].shape[1:] == (2,)
        seen += list(zip(mb.obs["x"][:, 0].long().tolist(), mb.obs["env"].tolist()))
    assert sorted(seen) == [(t, b) for t in range(T) for b in range(B)]

    rec = RolloutBuffer(T, B)
    _fill(rec, T, B, recurrent=True)
    envs = []
    for mb in rec.minibatches(3, torch.Generator().manual_seed(0)):
        idx = mb.obs["env"][0]
        assert torch.equal(mb.obs["env"], idx.expand(T, -1))  # whole env columns ...
        assert torch.equal(mb.obs["x"][:, :, 0], torch.arange(T, dtype=torch.float32)[:, None].expand(-1, len(idx)))  # ... in time order
        assert torch.equal(mb.starts, rec.data["starts"][:, idx])
        assert torch.equal(mb.initial_state[:, 0], idx.float())  # with their own initial memory
        assert torch.equal(mb.advantages, rec.data["advantages"][:, idx])
        envs += idx.tolist()
    assert sorted(envs) == list(range(B))


def _loss(policy, buf, cfg):
    with torch.no_grad():
        return ppo_loss(policy, next(buf.minibatches(1)), cfg)[0].item()


def _planner_batch():
    """A small planner and one 8-step rollout of 4 worlds under it, returns computed."""
    torch.manual_seed(0)
    pl = Planner(channels=(8, 8), hidden=64)
    buf = RolloutBuffer(8, 4)
    g = torch.Generator().manual_seed(0)
    for t in range(8):
        obs = pl.example_obs(4, g)
        out = pl.act(obs)
        buf.add(t, obs=obs, actions={"stop": out["stop"], "raw_subgoal": out["raw_subgoal"]}, log_probs=out["log_prob"],
                values=out["value"], rewards=torch.randn(4, generator=g), dones=torch.zeros(4))
    buf.compute_returns(0.95, 0.95, last_values=torch.zeros(4))
    return pl, buf


def test_ppo_update_reduces_loss_planner():
    pl, buf = _planner_batch()
    cfg = PPOConfig(num_minibatches=2)
    before = _loss(pl, buf, cfg)
    opt = torch.optim.Adam(pl.parameters(), lr=1e-3)
    for _ in range(3):
        stats = ppo_update(pl, buf, opt, cfg, generator=torch.Generator().manual_seed(1))
    assert set(stats) == {"policy_loss", "value_loss", "entropy", "approx_kl", "clip_fraction",
                          "explained_variance", "grad_norm", "epochs"}
    assert stats["approx_kl"] > 0 and stats["grad_norm"] > 0 and stats["epochs"] == cfg.update_epochs
    assert _loss(pl, buf, cfg) < before - 0.05


def test_target_kl_ends_the_epochs_once_the_policy_has_moved():
    """With target_kl the update stops after the first epoch whose mean approximate KL
    exceeds it; the policy then moves less than over all epochs."""
    moved = {}
    for target in (None, 1e-6, 1e3):
        pl, buf = _planner_batch()
        before = [p.detach().clone() for p in pl.parameters()]
        stats = ppo_update(pl, buf, torch.optim.Adam(pl.parameters(), lr=1e-2), PPOConfig(target_kl=target),
                           generator=torch.Generator().manual_seed(1))
        moved[target] = sum((p.detach() - b).norm().item() for p, b in zip(pl.parameters(), before))
        # the first epoch's second minibatch is read after the first one's step: its KL is > 0
        assert stats["epochs"] == (1 if target == 1e-6 else 4), (target, stats)
    assert moved[1e-6] < 0.8 * moved[None] and moved[1e3] == moved[None]


def test_ppo_update_reduces_loss_recurrent():
    torch.manual_seed(0)
    ex = Executor("gru", 64, gru_hidden=32)
    T, B = 6, 4
    buf = RolloutBuffer(T, B)
    g = torch.Generator().manual_seed(0)
    state = ex.initial_state(B)
    buf.initial_state = state.clone()
    for t in range(T):
        obs = ex.example_obs(B, g)
        starts = torch.rand(B, generator=g) < 0.3
        out, state = ex.act(obs, state, starts)
        buf.add(t, obs=obs, actions=out["action"], log_probs=out["log_prob"], values=out["value"],
                rewards=out["action"].float() - 1.5, dones=torch.zeros(B), starts=starts)
    buf.compute_returns(0.9, 0.95, last_values=torch.zeros(B))
    cfg = PPOConfig(num_minibatches=2)
    before = _loss(ex, buf, cfg)
    stats = ppo_update(ex, buf, torch.optim.Adam(ex.parameters(), lr=1e-3), cfg)
    assert stats["approx_kl"] > 0 and -1 <= stats["clip_fraction"] <= 1
    assert _loss(ex, buf, cfg) < before - 0.05


def test_bench_adam_times_each_implementation(capsys):
    """``python -m plex_ma.bench adam`` times the loop, foreach and fused Adam steps over
    both PLEX networks."""
    bench_main(["adam", "--preset", "smoke", "--steps", "2", "--rounds", "1", "--json"])
    out = json.loads(capsys.readouterr().out)
    for net in ("planner", "executor"):
        assert out[f"{net}_params"] > 0
        assert all(out[f"{net}_{impl}_ms"] > 0 for impl in ("loop", "foreach", "fused"))


def test_trainer_uses_fused_adam(tmp_path):
    cfg = replace(preset_defaults("smoke"), run_dir=str(tmp_path), progress=False, record_interval=0)
    tr = PlexTrainer(cfg, log=False)
    assert all(o.defaults["fused"] for o in tr.opts.values())
    tr.env.close()
