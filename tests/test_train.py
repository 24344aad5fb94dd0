"""The trainer, the CLIs, checkpoints and learning (each test can fail)."""

from __future__ import annotations

import dataclasses
import json
import os

import numpy as np
import pytest
import torch

from plex_ma.config import PRESETS, TrainConfig, from_dict, parse, preset_defaults, replace, setting, validate
from plex_ma.envs.sim.episodes import default_episode_file
from plex_ma.evaluate import main as evaluate_main
from plex_ma.trainers.checkpoint import CheckpointError, atomic_save, find_resumable, load_checkpoint, save_checkpoint
from plex_ma.trainers import make_trainer
from plex_ma.trainers.base import saved_config
from plex_ma.trainers.plex import PlexTrainer


def tiny(tmp_path, **kw) -> TrainConfig:
    """A configuration small enough for a few seconds of training (N_EX 18: turns short enough
    that a hundred-odd steps hold planner updates)."""
    cfg = replace(preset_defaults("smoke"), run_dir=str(tmp_path / "run"), total_steps=96, num_envs=2,
                  rollout_steps=16, n_pl=2, n_ex=18, num_scenes=2, executor_hidden=32, smt_memory=16,
                  progress=False, ppo_epochs=1, num_minibatches=1, torch_threads=1)
    return validate(replace(cfg, **kw))


@pytest.mark.parametrize("method,eli", [("plex-gru", True), ("plex-gru", False), ("plex-smt", True),
                                        ("ppo-gru", True), ("ppo-smt", True), ("ppo-gru-map", True)])
def test_smoke_training_every_method(tmp_path, method, eli):
    cfg = tiny(tmp_path, method=method, eli=eli)
    trainer = make_trainer(cfg)
    trainer.train()
    trainer.close()
    state = load_checkpoint(tmp_path / "run" / "latest.pt")
    assert state["config"]["method"] == method and state["config"]["env"]["eli"] == eli
    assert state["step"] >= cfg.total_steps
    lines = [json.loads(x) for x in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    keys = set().union(*lines)
    assert "perf/fps" in keys
    if method.startswith("plex"):  # each agent's learning, inside the update's share of the wall time
        for x in lines:
            for agent in ("executor", "planner"):
                assert 0.0 <= x[f"perf/share_learn_{agent}"] <= x["perf/share_update"] + 1e-9
        assert lines[-1]["perf/share_learn_executor"] > 0.0
    if os.path.exists("/proc/self/statm"):  # resident memory, for soak checks (Linux)
        assert all(50 < x["perf/rss_mib"] < 64_000 for x in lines if "perf/fps" in x)
    prefix = "learner/executor_" if method.startswith("plex") else "learner/"
    for k in ("policy_loss", "value_loss", "entropy", "approx_kl", "clip_fraction", "explained_variance",
              "grad_norm"):
        assert prefix + k in keys


@pytest.mark.parametrize("method", ["plex-gru", "ppo-gru-map"])
def test_zero_steps_writes_the_untrained_agent(tmp_path, method):
    """``--total-steps 0`` writes the fresh networks (the untrained agent of every results
    table) without a step of training, and ``evaluate`` reads them."""
    from plex_ma.train import main as train_main

    run = tmp_path / "run"
    train_main(["--preset", "smoke", "--method", method, "--total-steps", "0", "--run-dir", str(run),
                "--no-progress", "--seed", "3"])
    state = load_checkpoint(run / "latest.pt")
    assert state["step"] == 0 and all(v == 0 for v in state["updates"].values())
    fresh = make_trainer(replace(preset_defaults("smoke", method), run_dir=str(tmp_path / "other"), seed=3,
                                 progress=False))
    for name, net in fresh.nets.items():  # the same seed builds the same networks
        for k, v in net.state_dict().items():
            assert torch.equal(v, state["models"][name][k]), (name, k)
    fresh.close()
    res = evaluate_main(["--checkpoint", str(run / "latest.pt"), "--split", "val", "--episodes", "2",
                         "--num-envs", "2"])
    assert res["episodes"] == 2


def test_resume_restores_optimizer_and_step(tmp_path, capsys):
    """A resume restores the weights, the optimisers, the step and the window of finished
    episodes, so the logged training success goes on where it stopped."""
    cfg = tiny(tmp_path, max_steps=20)
    t1 = make_trainer(cfg)
    t1.train()
    t1.close()
    saved = load_checkpoint(tmp_path / "run" / "latest.pt")
    window = saved["episodes"]["success"]
    assert len(window) > 0 and window == [float(x) for x in t1.stats.success]
    t2 = make_trainer(replace(cfg, total_steps=cfg.total_steps * 2))
    assert "resuming" in capsys.readouterr().out
    assert t2.step == saved["step"] and t2.updates == saved["updates"]
    assert list(t2.stats.success) == window and list(t2.stats.reward) == saved["episodes"]["reward"]
    for k, opt in t2.opts.items():
        a, b = opt.state_dict()["state"], saved["optimizers"][k]["state"]
        assert a.keys() == b.keys() and len(a) > 0
        for i in a:
            assert torch.equal(a[i]["exp_avg"], b[i]["exp_avg"])
    for k, m in t2.nets.items():
        for name, p in m.state_dict().items():
            assert torch.equal(p, saved["models"][k][name])
    t2.train()
    t2.close()
    assert load_checkpoint(tmp_path / "run" / "latest.pt")["step"] >= 2 * cfg.total_steps
    rows = [json.loads(x) for x in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    resumed = [r for r in rows if r["step"] > saved["step"]]
    assert resumed and resumed[0].get("metrics/episodes", 0) >= len(window)


def test_anneal_lr_falls_linearly_to_zero_at_the_last_step(tmp_path):
    """--anneal-lr: each agent's learning rate is its base value x (1 - step / total_steps)
    before every update, the planner's from --planner-lr; a resumed run with a longer
    budget follows the new schedule."""
    cfg = tiny(tmp_path, anneal_lr=True, lr=1e-3, planner_lr=5e-4)
    t = make_trainer(cfg)
    t.train()
    t.close()
    lines = [json.loads(x) for x in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert len(lines) >= 3
    for d in lines:
        frac = max(1 - d["step"] / cfg.total_steps, 0.0)
        assert d["learner/executor_lr"] == pytest.approx(1e-3 * frac)
        assert d["learner/planner_lr"] == pytest.approx(5e-4 * frac)
    assert lines[-1]["learner/executor_lr"] == 0.0
    t2 = make_trainer(replace(cfg, total_steps=2 * cfg.total_steps))
    t2._loop_start()
    assert t2.opts["executor"].param_groups[0]["lr"] == pytest.approx(1e-3 * (1 - t2.step / (2 * cfg.total_steps)))
    t2.close()


def test_only_latest_holds_the_optimisers_and_resume_from_it_is_exact(tmp_path):
    """Numbered checkpoints leave out the optimiser state (a third of the size); a resume
    from latest.pt restores every bit the trainer had: weights, Adam's moments and step
    counts, the step, the updates and the random generators."""
    cfg = tiny(tmp_path, checkpoint_interval=1, keep_checkpoints=2)
    t1 = make_trainer(cfg)
    t1.train()
    t1.close()
    run = tmp_path / "run"
    numbered = sorted(run.glob("ckpt_*.pt"))
    assert len(numbered) == 2
    full = load_checkpoint(run / "latest.pt")
    for p in numbered:
        state = load_checkpoint(p)
        assert "optimizers" not in state and state.keys() == full.keys() - {"optimizers"}
    assert numbered[-1].stat().st_size < 0.5 * (run / "latest.pt").stat().st_size
    t2 = make_trainer(cfg)
    assert t2.step == t1.step and t2.updates == t1.updates
    assert torch.equal(torch.get_rng_state(), full["torch_rng"])
    assert torch.equal(t2.gen.get_state(), t1.gen.get_state())
    assert torch.equal(t2.planner_gen.get_state(), t1.planner_gen.get_state())
    for k in t1.nets:
        for (n, a), b in zip(t1.nets[k].state_dict().items(), t2.nets[k].state_dict().values()):
            assert torch.equal(a, b), n
        s1, s2 = t1.opts[k].state_dict(), t2.opts[k].state_dict()
        assert s1["param_groups"] == s2["param_groups"] and s1["state"].keys() == s2["state"].keys()
        for i in s1["state"]:
            for name, v in s1["state"][i].items():
                assert torch.equal(v, s2["state"][i][name]), (k, i, name)
    t2.close()


def test_resume_logs_each_step_once(tmp_path):
    """Resumed from an older checkpoint (latest.pt corrupt, the newest numbered one gone), the
    run drops the rows logged after that checkpoint (and a line cut by a crash), then logs
    the same steps again: metrics.jsonl holds each step once."""
    cfg = tiny(tmp_path, checkpoint_interval=1, keep_checkpoints=3)
    t = make_trainer(cfg)
    t.train()
    t.close()
    run = tmp_path / "run"
    metrics = run / "metrics.jsonl"
    first = [json.loads(x)["step"] for x in metrics.read_text().splitlines()]
    assert first == sorted(set(first)) and len(first) >= 3
    numbered = sorted(run.glob("ckpt_*.pt"))
    (run / "latest.pt").write_bytes(b"corrupt")
    numbered[-1].unlink()
    resume_step = load_checkpoint(numbered[-2])["step"]
    assert resume_step < first[-1]
    with open(metrics, "a") as f:
        f.write('{"step": 9')  # cut short by a crash
    with pytest.warns(UserWarning):
        t2 = make_trainer(cfg)
    assert t2.step == resume_step
    assert metrics.read_text().endswith('{"step": 9')  # nothing is rewritten before the first update
    t2.train()
    t2.close()
    again = [json.loads(x)["step"] for x in metrics.read_text().splitlines()]
    assert again == first


def test_resume_refuses_another_method(tmp_path):
    cfg = tiny(tmp_path)
    t = make_trainer(cfg)
    t.train()
    t.close()
    with pytest.raises(CheckpointError, match="method"):
        make_trainer(replace(cfg, method="ppo-gru"))


def test_same_seed_same_first_update(tmp_path):
    params = []
    for run in ("a", "b"):
        cfg = tiny(tmp_path / run, total_steps=32)
        t = make_trainer(cfg, log=False)
        t.train()
        params.append({k: v.clone() for k, v in t.nets["executor"].state_dict().items()})
    assert all(torch.equal(params[0][k], params[1][k]) for k in params[0])


def test_parallel_planner_learning_matches_sequential(tmp_path):
    """The planner's update on its own thread beside the executor's gives the same networks,
    bit for bit, as the two updates one after the other: they share no parameters and draw
    from separate generators."""
    nets = {}
    for parallel in (True, False):
        cfg = tiny(tmp_path / str(parallel), total_steps=128, n_pl=1, parallel_updates=parallel)
        t = make_trainer(cfg, log=False)
        assert (t.pool is not None) == parallel
        t.train()
        t.close()
        assert t.updates["planner"] >= 2
        nets[parallel] = {k: {n: v.clone() for n, v in m.state_dict().items()} for k, m in t.nets.items()}
    for k in nets[True]:
        assert all(torch.equal(nets[True][k][n], nets[False][k][n]) for n in nets[True][k]), k


def test_resume_restores_the_planner_sampler(tmp_path):
    """The planner's generator (its minibatch order) is checkpointed."""
    cfg = tiny(tmp_path, n_pl=1)
    t = make_trainer(cfg)
    t.train()
    t.close()
    saved = load_checkpoint(tmp_path / "run" / "latest.pt")
    resumed = make_trainer(replace(cfg, total_steps=2 * cfg.total_steps))
    assert torch.equal(resumed.planner_gen.get_state(), saved["planner_sampler_rng"])
    assert torch.equal(resumed.planner_gen.get_state(), t.planner_gen.get_state())
    resumed.close()


def test_corrupt_latest_falls_back_to_previous(tmp_path):
    run = tmp_path / "run"
    save_checkpoint(run, {"format": 1, "config": {}, "step": 1}, 1)
    save_checkpoint(run, {"format": 1, "config": {}, "step": 2}, 2)
    data = (run / "latest.pt").read_bytes()
    (run / "latest.pt").write_bytes(data[: len(data) // 2])  # truncated
    with pytest.warns(UserWarning, match="latest.pt"):
        state, path = find_resumable(run)
    assert state["step"] == 2 and path.name == "ckpt_000002.pt"
    for p in run.glob("*.pt"):
        p.write_bytes(b"garbage")
    with pytest.raises(CheckpointError, match="corrupt"), pytest.warns(UserWarning):
        find_resumable(run)
    with pytest.raises(CheckpointError, match="cannot be loaded"):
        load_checkpoint(run / "latest.pt")


def test_failed_save_keeps_previous_checkpoint(tmp_path, monkeypatch):
    path = tmp_path / "latest.pt"
    atomic_save({"format": 1, "config": {}, "step": 7}, path)
    (tmp_path / "plain").write_bytes(b"")  # a checkpoint gets a new file's usual permissions, not mkstemp's 0o600
    assert path.stat().st_mode & 0o777 == (tmp_path / "plain").stat().st_mode & 0o777
    (tmp_path / "plain").unlink()

    def boom(*a, **k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(torch, "save", boom)
    with pytest.raises(OSError):
        atomic_save({"format": 1, "config": {}, "step": 8}, path)
    monkeypatch.undo()
    assert load_checkpoint(path)["step"] == 7
    assert [p.name for p in tmp_path.iterdir()] == ["latest.pt"]  # no temporary left behind


def test_checkpoint_is_loaded_with_weights_only(tmp_path):
    class Evil:
        def __reduce__(self):
            return (os.system, ("echo pwned",))

    torch.save({"format": 1, "config": {}, "x": Evil()}, tmp_path / "evil.pt")
    with pytest.raises(CheckpointError):
        load_checkpoint(tmp_path / "evil.pt")


def test_planner_update_leaves_executor_untouched(tmp_path):
    # the two updates one after the other, so that nothing but the planner's update runs
    # inside the spy (the parallel path gives the same networks: see the test above)
    cfg = tiny(tmp_path, total_steps=160, n_pl=1, parallel_updates=False)
    t = PlexTrainer(cfg, log=False)
    before = {k: v.clone() for k, v in t.executor.state_dict().items()}
    calls = []
    real = t._update_planner

    def spy():
        snap = {k: v.clone() for k, v in t.executor.state_dict().items()}
        for p in t.executor.parameters():
            p.grad = None
        out = real()
        calls.append(all(torch.equal(snap[k], v) for k, v in t.executor.state_dict().items()))
        assert all(p.grad is None or not p.grad.any() for p in t.executor.parameters())
        return out

    t._update_planner = spy
    t.train()
    assert calls and all(calls), "a planner update changed the executor"
    assert any(not torch.equal(before[k], v) for k, v in t.executor.state_dict().items())  # executor did learn


def test_cli_help_and_bad_config(capsys):
    with pytest.raises(SystemExit) as e:
        parse(["--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    assert "--method" in out and "--no-eli" in out and "--preset" in out and "--total-steps" in out
    with pytest.raises(ValueError, match="num-envs"):
        parse(["--preset", "smoke", "--num-envs", "0"])
    cfg = parse(["--preset", "smoke", "--num-envs", "3"])
    assert cfg.num_envs == 3 and cfg.total_steps == preset_defaults("smoke").total_steps
    from plex_ma.train import main as train_main

    with pytest.raises(SystemExit) as e:  # the CLI: exit status 2 and one line naming the flag
        train_main(["--preset", "smoke", "--clip", "0"])
    assert e.value.code == 2 and "--clip" in capsys.readouterr().err
    with pytest.raises(ValueError, match="--planner-lr"):
        parse(["--preset", "smoke", "--planner-lr", "0"])
    assert parse(["--preset", "smoke", "--planner-lr", "1e-4"]).planner_lr == 1e-4
    with pytest.raises(ValueError, match="--planner-target-kl"):
        parse(["--preset", "smoke", "--planner-target-kl", "0"])
    assert parse(["--preset", "smoke", "--planner-target-kl", "0.03"]).planner_target_kl == 0.03


def test_defaults_are_the_cpu_recipe_and_flat_methods_get_theirs():
    """TrainConfig() is the recommended recipe: the cpu preset for PLEX adds nothing to it; the
    flat baselines get the cpu preset's flat departures; the paper preset restores the env's
    own (the paper's) settings; a flag on the command line still wins."""
    # the flat methods' update on every core (torch's default threads)
    assert PRESETS["cpu"]("plex-gru") == {} and PRESETS["cpu"]("ppo-gru") == {"torch_threads": 0}
    assert PRESETS["cpu"]("ppo-smt") == {"torch_threads": 0, "lr": 3e-4}  # its own sweep's best
    for method in ("plex-gru", "plex-smt"):
        cfg = preset_defaults("cpu", method)
        assert replace(cfg, preset="cpu", method="plex-gru", run_dir=TrainConfig().run_dir) == TrainConfig(), method
    for method in ("ppo-gru", "ppo-smt", "ppo-gru-map"):
        cfg, flat = preset_defaults("cpu", method), PRESETS["cpu"](method)
        assert all(setting(cfg, k) == v and v != setting(TrainConfig(), k) for k, v in flat.items()), method
    paper = preset_defaults("paper")
    assert (paper.env.n_ex, paper.env.subgoal_radius, paper.env.executor_stop_penalty) == (10, 0.5, 0.0)
    assert (paper.env.resolution, paper.n_pl, paper.executor_hidden, paper.planner_value_iteration) == (256, 128, 512, False)
    assert (paper.gamma_ex, paper.planner_trunk_stride, paper.curriculum_steps) == (0.9, 1, 0)
    cfg = parse(["--preset", "cpu", "--resolution", "64", "--ppo-epochs", "4"])
    assert cfg.env.resolution == 64 and cfg.ppo_epochs == 4 and cfg.num_envs == TrainConfig().num_envs
    assert parse(["--preset", "cpu", "--method", "ppo-gru"]).ppo_epochs == 4
    assert parse(["--preset", "cpu", "--method", "ppo-smt"]).lr == 3e-4
    assert parse(["--preset", "cpu", "--method", "ppo-smt", "--lr", "1e-3"]).lr == 1e-3


def test_env_settings_are_train_flags_that_reach_the_env(tmp_path):
    """Every env setting is a train flag of its own name, validated by the env, passed to the
    training worlds (PLEX's whole config, PointNav's shared part) and saved in checkpoints
    nested as ``env``; a flat saved config (env fields at the top level) reads the same."""
    argv = ["--preset", "smoke", "--run-dir", str(tmp_path / "run"), "--slack-reward", "-0.02",
            "--pose-noise", "0.05", "0.01", "--no-eli", "--n-ex", "7", "--success-distance", "0.3"]
    cfg = parse(argv)
    assert (cfg.env.slack_reward, cfg.env.pose_noise, cfg.env.eli, cfg.env.n_ex) == (-0.02, (0.05, 0.01), False, 7)
    with pytest.raises(ValueError, match="success_distance=9"):
        parse(["--preset", "smoke", "--success-distance", "9"])
    with pytest.raises(ValueError, match="resolution.*36"):  # the env allows 8 px, the executor's CNN needs 36
        parse(["--preset", "smoke", "--resolution", "32"])
    for method, env_cls in (("plex-gru", "PlexConfig"), ("ppo-gru", "NavConfig")):
        t = make_trainer(replace(cfg, method=method, progress=False), log=False)
        got = t.env.config
        assert type(got).__name__ == env_cls and got.slack_reward == -0.02 and got.pose_noise == (0.05, 0.01)
        assert got.success_distance == 0.3 and got.split == "train"
        if method == "plex-gru":
            assert got.n_ex == 7 and not got.eli
        t.close()
    saved = dataclasses.asdict(cfg)
    assert from_dict(saved) == cfg
    flat = {k: v for k, v in saved.items() if k != "env"} | saved["env"]
    assert from_dict(flat) == cfg


def test_saved_config_refuses_other_formats_and_ignores_retired_settings():
    """A checkpoint of this format whose config holds retired settings (the teacher and the
    planner's imitation, the planner's own PPO settings, the executor's warm-up, the priors
    format 1 could hold; a flat method's stop radius) loads without them; their flags no
    longer exist. A PLEX checkpoint whose planner used the stop radius is refused by name. A
    checkpoint of another format (format 1's networks could hold hand-set priors) is refused with one
    error that names the format."""
    from plex_ma.trainers.base import CHECKPOINT_FORMAT

    cfg = preset_defaults("cpu")
    retired = {"teacher": "map-los", "teacher_subgoal_steps": 260_000, "planner_imitation_steps": 724_000,
               "imitation_minibatches": 8, "planner_entropy_coef": None,
               "planner_minibatches": 2, "executor_goal_skip": True, "planner_warmup_steps": 40_000,
               "warmup_scenes": "open-room", "warmup_max_steps": 40, "planner_prior": False,
               "executor_stop_prior": None, "executor_heading_prior": None}
    assert from_dict(dataclasses.asdict(cfg) | retired) == cfg
    assert saved_config({"format": CHECKPOINT_FORMAT, "config": dataclasses.asdict(cfg) | retired}) == cfg
    with pytest.raises(CheckpointError, match="checkpoint format 1 is not 2"):
        saved_config({"format": 1, "config": dataclasses.asdict(cfg)})
    # a PLEX planner that stopped by its sub-goal's distance has no stop head: refused by name;
    # a flat method's config held the same key without using it
    with pytest.raises(CheckpointError, match="--planner-stop-radius"):
        saved_config({"format": CHECKPOINT_FORMAT, "config": dataclasses.asdict(cfg) | {"planner_stop_radius": 0.2}})
    flat = preset_defaults("cpu", "ppo-gru")
    assert saved_config({"format": CHECKPOINT_FORMAT,
                         "config": dataclasses.asdict(flat) | {"planner_stop_radius": 0.2}}) == flat
    assert not preset_defaults("paper").executor_no_reversal
    for flag in ("--teacher-subgoal-steps", "--planner-imitation-steps", "--planner-minibatches",
                 "--planner-entropy-coef", "--executor-goal-skip",
                 "--planner-warmup-steps", "--warmup-max-steps", "--warmup-scenes", "--executor-stop-prior",
                 "--executor-heading-prior", "--planner-stop-radius"):
        with pytest.raises(ValueError, match=f"unrecognized arguments: {flag}"):
            parse(["--preset", "smoke", flag, "100"])


def test_evaluate_cli_writes_json(tmp_path):
    cfg = tiny(tmp_path)
    t = make_trainer(cfg)
    t.train()
    t.close()
    out = tmp_path / "eval.json"
    evaluate_main(["--checkpoint", str(tmp_path / "run" / "latest.pt"), "--split", "val", "--episodes", "3",
                   "--num-envs", "2", "--json", str(out)])
    res = json.loads(out.read_text())
    for part in (res, res["close"], res["far"]):
        for k in ("success", "spl", "reward", "distance_to_goal", "collisions", "episodes"):
            assert k in part
    assert res["episodes"] == 3 == res["close"]["episodes"] + res["far"]["episodes"]
    assert len({r["episode_id"] for r in res["per_episode"]}) == 3
    # the per-episode records name the scene by its string id (infos carry only its index)
    assert all(r["scene_id"].startswith("procgen-val-") for r in res["per_episode"])


@pytest.mark.parametrize("content, says", [(b"\x00" * 100, "cannot be loaded"),
                                            (b"garbage", "cannot be loaded"),
                                            (None, "is a directory")], ids=["zeros", "garbage", "directory"])
def test_evaluate_rejects_a_bad_checkpoint(tmp_path, capsys, content, says):
    """Zeros, garbage (torch's errors for both run to many lines) or a directory: one line."""
    bad = tmp_path / "bad.pt"
    bad.mkdir() if content is None else bad.write_bytes(content)
    with pytest.raises(SystemExit) as e:
        evaluate_main(["--checkpoint", str(bad), "--episodes", "1"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and says in err and len(err.strip().splitlines()) == 1, err


@pytest.mark.slow
def test_executor_alone_learns_to_reach_subgoals(tmp_path):
    """In an open room, under random sub-goals 0.5-1.5 m away within +-0.5 rad, the executor's
    success (STOP within 0.5 m, over turns not already within reach) rises from about 0.1
    (a random executor) to at least 0.6."""
    cfg = replace(
        preset_defaults("smoke"), run_dir=str(tmp_path / "run"), scenes="open-room", num_scenes=1,
        planner="random", random_subgoal_angle=0.5, resolution=64, gamma_ex=0.9, executor_stop_bias=0.0,
        anneal_lr=False, n_ex=10, subgoal_radius=0.5, executor_stop_penalty=0.0,
        executor_collision_reward=0.0,
        max_steps=40, total_steps=16_000, num_envs=8, rollout_steps=32, ppo_epochs=4, num_minibatches=2,
        progress=False, torch_threads=1, checkpoint_interval=1000)
    t = make_trainer(validate(cfg))
    t.train()
    t.close()
    lines = [json.loads(x) for x in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    curve = [d["metrics/executor_success"] for d in lines if "metrics/executor_success" in d]
    assert curve[0] < 0.3, curve[:5]
    assert np.mean(curve[-3:]) >= 0.6, curve[-10:]


@pytest.mark.slow
def test_plex_learns_from_the_reward_alone(tmp_path):
    """PLEX end to end with the cpu preset's recipe (no prior, no teacher: both agents learn
    by PPO on the reward alone), in one open room with 100-step episodes, 16 worlds and
    64,000 steps (about two and a half minutes of two cores). The untrained executor reaches
    its sub-goal in about 5% of its first turns and the episodes' reward turns negative (the
    planner's constant sub-goal, 1 m ahead, leads nowhere in particular; its lowest, -1.48);
    after training the executor reaches 0.89 of its sub-goals over the last three updates
    and the episodes end nearer the goal than they began (reward +3.02 to +3.16 there),
    measured with ``train --scenes open-room --num-scenes 1 --num-envs 16 --max-steps 100
    --total-steps 64000``. The planner rarely stops in the right place yet (training success
    at most 0.09)."""
    cfg = replace(preset_defaults("cpu"), run_dir=str(tmp_path / "run"), scenes="open-room", num_scenes=1,
                  num_envs=16, max_steps=100, total_steps=64_000, progress=False, record_interval=0)
    t = make_trainer(validate(cfg))
    t.train()
    t.close()
    assert t.updates["planner"] >= 10
    lines = [json.loads(x) for x in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    ex = [d["metrics/executor_success"] for d in lines if "metrics/executor_success" in d]
    reward = [d["reward"] for d in lines if "reward" in d]
    assert ex[0] < 0.2 and np.mean(ex[-3:]) >= 0.7, (ex[:3], ex[-3:])
    assert min(reward) < -1.0 and np.mean(reward[-3:]) > 2.0, (min(reward), reward[-3:])


def test_training_counts_episodes_ended_by_planner_stop(tmp_path):
    """Episodes that a planner stop ends (inside the planner's decisions) count in the
    training statistics as well as those cut by max_steps."""
    from plex_ma.trainers.driver import RandomPlanner

    cfg = tiny(tmp_path, planner="random", max_steps=10_000, total_steps=64, n_ex=2)
    t = make_trainer(cfg)
    t.driver.planner = RandomPlanner(2.0, stop_prob=0.5, rng=np.random.default_rng(0))
    t.train()
    t.close()
    assert len(t.stats.success) >= 5  # no episode reaches max_steps: all of them ended by a stop


def test_torch_threads_hold_after_the_simulator_starts(tmp_path):
    """--torch-threads survives the simulator's first numba kernels (on numba's OpenMP
    layer they share torch's OpenMP runtime and set its thread count to numba's); checked
    in a fresh process."""
    import subprocess
    import sys

    code = ("import torch\n"
            "from plex_ma.config import preset_defaults, replace\n"
            "from plex_ma.trainers import make_trainer\n"
            f"cfg = replace(preset_defaults('smoke'), run_dir={str(tmp_path / 'run')!r}, total_steps=32,\n"
            "    num_envs=2, rollout_steps=16, num_scenes=2, torch_threads=1, progress=False)\n"
            "t = make_trainer(cfg)\n"
            "t.train()\n"
            "print('threads', torch.get_num_threads())\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                         env={**os.environ, "NUMBA_NUM_THREADS": "2", "OMP_NUM_THREADS": "2"})
    assert out.returncode == 0, out.stderr[-2000:]
    assert "threads 1" in out.stdout, out.stdout


@pytest.mark.parametrize("method", ["plex-gru", "ppo-gru"])
def test_curriculum_grows_the_episodes_distance(tmp_path, method):
    """--curriculum-steps: before each update the training worlds' largest episode distance
    is curriculum_distance(step), 2.5 m at step 0 rising linearly to 30 m; the episodes
    sampled then respect it."""
    from plex_ma.trainers.base import curriculum_distance
    assert curriculum_distance(0, 100) == 2.5 and curriculum_distance(50, 100) == 16.25
    assert curriculum_distance(100, 100) == curriculum_distance(500, 100) == 30.0
    cfg = tiny(tmp_path, method=method, curriculum_steps=10_000)
    t = make_trainer(cfg)
    t._loop_start()
    assert t.env.worlds.max_geodesic == 2.5
    t.env.worlds.reset_rows(np.arange(cfg.num_envs))
    assert all(t.env.worlds.info(i)["geodesic_distance"] <= 2.5 for i in range(cfg.num_envs))
    t.train()
    assert t.env.worlds.max_geodesic == pytest.approx(curriculum_distance(t.step, 10_000))
    t.close()
