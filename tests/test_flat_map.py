"""PPO-GRU+map (``ppo-gru-map``): the flat worlds' ego map, the policy's map encoder, and a
training run through the CLIs (each test can fail)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from plex_ma.config import parse, preset_defaults, replace, validate
from plex_ma.envs.rules import NavConfig, PlexConfig, PlexWorlds, PointNavWorlds
from plex_ma.envs.sim.core import MOVE_FORWARD, TURN_LEFT, TURN_RIGHT
from plex_ma.envs.vector import PointNavVectorEnv
from plex_ma.evaluate import main as evaluate_main
from plex_ma.networks.planner import MAP_PLAN
from plex_ma.networks import FlatMapPolicy, FlatPolicy, MapEncoder, Planner, ValueIteration
from plex_ma.train import main as train_main
from plex_ma.trainers import make_trainer
from plex_ma.trainers.base import build_policies
from plex_ma.trainers.checkpoint import CheckpointError, load_checkpoint

SMALL = dict(resolution=32, num_scenes=2, max_steps=200)


@pytest.mark.parametrize("pose_noise", [(0.0, 0.0), (0.05, 0.02)])
def test_flat_worlds_give_the_planners_ego_map(pose_noise):
    """For the same episode and the same moves, the flat worlds built with egomap=True observe
    the ego map and goal vector PLEX's planner observes (PlexWorlds.planner_obs), pose noise
    included; built without it (ppo-gru, ppo-smt) they keep no map."""
    plex = PlexWorlds(PlexConfig(**SMALL, pose_noise=pose_noise, n_ex=100), 1, seed=3)
    flat = PointNavWorlds(NavConfig(**SMALL, pose_noise=pose_noise), 1, seed=3, egomap=True)
    plex.reset_rows([0])
    flat.reset_rows([0], episodes=[plex.sim.episodes[0]])

    def same():
        p, f = plex.planner_obs([0]), flat.obs([0])
        np.testing.assert_array_equal(f["ego_map"], p["ego_map"])
        np.testing.assert_array_equal(f["pointgoal"], p["goal"])
        np.testing.assert_array_equal(flat.pose([0]), plex.pose([0]))
        return f["ego_map"]

    same()
    plex.step(stop=np.zeros(1, np.int64), subgoal=np.array([[1.0, 0.0]], np.float32))  # the executor's turn
    moves = [TURN_LEFT] * 9 + [MOVE_FORWARD, TURN_RIGHT] * 6 + [MOVE_FORWARD] * 8
    for a in moves:
        plex.step(action=np.array([a]), eli=np.zeros((1, 128), np.float32))
        flat.step(np.array([a]))
        ego = same()
    assert not flat.done[0] and not plex.done[0]
    assert ego[0, 0].sum() > 0 and ego[0, 1].sum() > 0  # it has seen obstacles and free floor
    assert "ego_map" not in PointNavWorlds(NavConfig(**SMALL), 1, seed=3).obs([0])


def test_vector_env_ego_map_is_opt_in():
    on = PointNavVectorEnv(2, seed=1, egomap=True, **SMALL)
    off = PointNavVectorEnv(2, seed=1, **SMALL)
    obs_on, obs_off = on.reset(), off.reset()
    assert "ego_map" in on.observation_space.spaces and "ego_map" not in off.observation_space.spaces
    assert set(obs_on) == set(obs_off) | {"ego_map"} and not off.worlds.sim.use_egomap
    for _ in range(3):
        obs_on, *_ = on.step(np.full(2, MOVE_FORWARD))
        obs_off, *_ = off.step(np.full(2, MOVE_FORWARD))
    np.testing.assert_array_equal(obs_on["ego_map"], on.worlds.sim.egomap())
    assert on.observation_space.contains({k: np.asarray(v[0]) for k, v in obs_on.items()})
    for k in obs_off:  # the same worlds either way: the map only adds an observation
        np.testing.assert_array_equal(obs_on[k], obs_off[k])


def test_map_policy_reads_the_map_through_the_planners_encoder():
    """The policy's map encoder is the planner's (same modules, same parameter names under
    ``map.``, the value-iteration module in both), its heads read the planner's heads'
    features and its memory PPO-GRU's inputs; the map changes the policy's output and
    its gradient reaches the encoder's convolutions."""
    torch.manual_seed(0)
    policy = FlatMapPolicy("gru", 64, gru_hidden=32, value_iteration=True)
    planner = Planner(value_iteration=True)
    assert isinstance(planner, MapEncoder) and type(policy.map) is MapEncoder
    planner_map = {k: v.shape for k, v in planner.state_dict().items() if k.startswith(("convs.", "vin."))}
    policy_map = {k.removeprefix("map."): v.shape for k, v in policy.state_dict().items() if k.startswith("map.")}
    assert policy_map == planner_map and len(policy_map) == 4
    assert type(policy.map.vin) is type(planner.vin) is ValueIteration
    assert policy.reads_ego_map and not FlatPolicy.reads_ego_map
    # the heads read what the planner's read, in the same form; the memory reads what PPO-GRU's reads
    assert policy.map_fc[0].in_features == planner.fc[0].in_features
    assert policy.actor.mlp[0].in_features == policy.critic.mlp[0].in_features == planner.subgoal_mean.mlp[0].in_features
    flat = FlatPolicy("gru", 64, gru_hidden=32)
    assert policy.memory.gru.input_size == flat.memory.gru.input_size
    gen = torch.Generator().manual_seed(2)
    obs = policy.example_obs(3, gen)
    starts = torch.ones(3, dtype=torch.bool)
    with torch.no_grad():
        a = policy(obs, policy.initial_state(3), starts)[0]
        b = policy({**obs, "ego_map": 1 - obs["ego_map"]}, policy.initial_state(3), starts)[0]
    assert (a - b).abs().max() > 1e-4
    seq = {k: v.unsqueeze(0) for k, v in obs.items()}
    lp, ent, v = policy.evaluate_sequences(seq, torch.zeros(1, 3), starts[None], policy.initial_state(3))
    (v.sum() + lp.sum()).backward()
    assert policy.map.convs[0].weight.grad.abs().sum() > 0


def test_stored_map_plan_gives_the_same_training_pass():
    """The rollout stores the value-iteration read-out (``with_map_plan``) and the PPO epochs
    reuse it: on real ego maps, the sequences' log-probs, entropies, values and gradients
    equal those of a pass that recomputes it (up to float rounding: torch's vectorised sin,
    cos and atan2 round differently across batch sizes); without the module nothing is added."""
    torch.manual_seed(0)
    policy = FlatMapPolicy("gru", 64, gru_hidden=32, value_iteration=True, fine_map=True)
    env = PointNavVectorEnv(3, seed=5, egomap=True, **SMALL | dict(resolution=64))
    obs, steps = env.reset(), []
    for t in range(6):
        steps.append(policy.with_map_plan(obs))
        obs, *_ = env.step(np.array([MOVE_FORWARD, TURN_LEFT, MOVE_FORWARD if t % 2 else TURN_RIGHT]))
    assert steps[0][MAP_PLAN].shape == (3, policy.map.vin_dim + 2)
    stored = {k: torch.as_tensor(np.stack([s[k] for s in steps])) for k in steps[0]}
    recomputed = {k: v for k, v in stored.items() if k != MAP_PLAN}
    actions, starts = torch.zeros(6, 3), torch.zeros(6, 3, dtype=torch.bool)
    passes = []
    for seq in (stored, recomputed):
        policy.zero_grad()
        out = policy.evaluate_sequences(seq, actions, starts, policy.initial_state(3))
        sum(x.sum() for x in out).backward()
        passes.append([*out, *(p.grad.clone() for p in policy.parameters() if p.grad is not None)])
    assert len(passes[0]) == len(passes[1]) > 10
    for a, b in zip(*passes):
        torch.testing.assert_close(a, b)
    # a wrong read-out would change the pass
    policy.zero_grad()
    wrong = policy.evaluate_sequences({**stored, MAP_PLAN: stored[MAP_PLAN].flip(0)}, actions, starts,
                                      policy.initial_state(3))[2]
    assert (wrong - passes[0][2]).abs().max() > 1e-4
    plain = FlatMapPolicy("gru", 64, gru_hidden=32)
    assert plain.with_map_plan(obs) is obs and FlatPolicy("gru", 64).with_map_plan(obs) is obs


def test_method_builds_the_map_policy_with_the_presets_value_iteration():
    cfg = preset_defaults("cpu", "ppo-gru-map")
    assert cfg.planner_value_iteration and validate(cfg).method == "ppo-gru-map"
    net = build_policies(cfg)["policy"]
    assert type(net) is FlatMapPolicy and net.map.vin is not None
    assert build_policies(replace(cfg, planner_value_iteration=False))["policy"].map.vin is None
    # --planner-trunk-stride 2: the planner's and the map arm's trunk both give 3,136 features (10,816 at 1)
    strided = replace(cfg, planner_trunk_stride=2)
    assert build_policies(strided)["policy"].map.map_dim == 7 * 7 * 64 and net.map.map_dim == 13 * 13 * 64
    assert build_policies(replace(strided, method="plex-gru"))["planner"].map_dim == 7 * 7 * 64
    assert type(build_policies(replace(cfg, method="ppo-gru"))["policy"]) is FlatPolicy
    assert parse(["--preset", "smoke", "--method", "ppo-gru-map"]).method == "ppo-gru-map"
    with pytest.raises(ValueError, match="method.*unknown method"):
        validate(replace(cfg, method="ppo-smt-map"))


def test_smoke_training_and_evaluation_through_the_clis(tmp_path, capsys):
    """``train --preset smoke --method ppo-gru-map`` (here with the value-iteration module and
    fewer steps) trains, writes a checkpoint that ``evaluate`` loads and runs, and the
    checkpoint refuses a run whose map encoder differs."""
    run = tmp_path / "run"
    train_main(["--preset", "smoke", "--method", "ppo-gru-map", "--planner-value-iteration", "--total-steps", "256",
                "--num-envs", "2", "--rollout-steps", "32", "--num-minibatches", "1", "--checkpoint-interval", "2",
                "--executor-hidden", "32", "--num-scenes", "2", "--run-dir", str(run), "--no-progress",
                "--torch-threads", "1", "--record-interval", "0"])
    state = load_checkpoint(run / "latest.pt")
    assert state["config"]["method"] == "ppo-gru-map" and state["step"] >= 256
    assert state["config"]["planner_value_iteration"] is True
    lines = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    assert any("learner/policy_loss" in x for x in lines)
    out = tmp_path / "eval.json"
    evaluate_main(["--checkpoint", str(run / "latest.pt"), "--split", "val", "--episodes", "2", "--num-envs", "2",
                   "--json", str(out)])
    res = json.loads(out.read_text())
    assert res["method"] == "ppo-gru-map" and res["episodes"] == 2
    capsys.readouterr()
    cfg = replace(preset_defaults("smoke", "ppo-gru-map"), run_dir=str(tmp_path / "ft"), checkpoint=str(run / "latest.pt"),
                  executor_hidden=32, planner_value_iteration=False, progress=False)
    with pytest.raises(CheckpointError, match="planner_value_iteration"):
        make_trainer(validate(cfg), log=False)
