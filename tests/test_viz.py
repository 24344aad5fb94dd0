"""Rerun recordings (plex_ma.viz): files the rerun CLI verifies, the documented entity
paths, recordings of a random policy, of checkpoints (PLEX and flat) and during training."""

from __future__ import annotations

import dataclasses
import json
import math
import subprocess
from pathlib import Path

import numpy as np
import pytest
import rerun as rr
import torch

from plex_ma.config import TrainConfig, preset_defaults, replace, validate
from plex_ma.envs.vector import PlexVectorEnv, PointNavVectorEnv
from plex_ma.record import main as record_main
from plex_ma.trainers.driver import PlexDriver, RandomExecutor, RandomPlanner
from plex_ma.trainers.checkpoint import atomic_save
from plex_ma.trainers import make_trainer
from plex_ma.trainers.base import CHECKPOINT_FORMAT, build_policies
from plex_ma.viz.layout import entity_table_markdown
from plex_ma.viz import (ENTITY_PATHS, EpisodeRecorder, ego_pixel, pca_2d, record_training_episode,
                                rerun_executable)

WORLD = {p for p in ENTITY_PATHS if p.startswith("world")}
PLEX = WORLD | {"planner/ego_map", "planner/ego_map/agent", "planner/ego_map/goal", "planner/ego_map/subgoal",
                "planner/subgoal_index", "executor/rgb", "executor/depth", "reward/planner", "reward/executor",
                "metrics/distance_to_goal", "metrics/collisions", "metrics/success", "metrics/spl", "events",
                "episode"}
ELI = {"eli/tensor", "eli/projection", "eli/pca", "eli/episode"}
FLAT = WORLD - {p for p in WORLD if "subgoal" in p} | {
    "executor/rgb", "executor/depth", "reward/agent", "metrics/distance_to_goal", "metrics/collisions",
    "metrics/success", "metrics/spl", "events", "episode"}


@pytest.fixture(autouse=True)
def strict_rerun_one_thread():
    """Misuse of the rerun API raises instead of warning (and silently dropping data);
    batch-1 inference runs on one torch thread (more only spin beside other processes)."""
    rr.set_strict_mode(True)
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
    rr.set_strict_mode(False)


def verify(path) -> None:
    """``rerun rrd verify``: the file loads and every chunk decodes (footers included)."""
    r = subprocess.run([rerun_executable(), "rrd", "verify", str(path)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr


def recordings(path) -> list[tuple[set[str], set[str]]]:
    """(entity paths, timelines) of each recording in an .rrd file."""
    from rerun.chunk import RrdReader

    reader = RrdReader(str(path))
    out = []
    for store in reader.recordings():
        schema = reader.store(store=store).schema()
        paths = {p.lstrip("/") for p in schema.entity_paths()}
        timelines = {str(c).split("timeline:")[1].rstrip(")") for c in schema.index_columns()}
        out.append((paths, timelines))
    return out


def tiny_config(tmp_path, **kw) -> TrainConfig:
    cfg = replace(preset_defaults("smoke"), run_dir=str(tmp_path / "run"), num_envs=2, rollout_steps=16,
                  n_pl=2, num_scenes=2, max_steps=25, progress=False, ppo_epochs=1, num_minibatches=1,
                  torch_threads=1, record_interval=0)
    return validate(replace(cfg, **kw))


def make_checkpoint(tmp_path, method: str = "plex-gru"):
    """A checkpoint with freshly initialised networks, as the trainer writes it."""
    cfg = tiny_config(tmp_path, method=method)
    torch.manual_seed(0)
    nets = build_policies(cfg)
    path = tmp_path / f"{method}.pt"
    atomic_save({"format": CHECKPOINT_FORMAT, "config": dataclasses.asdict(cfg), "step": 0,
                 "updates": {k: 0 for k in nets}, "models": {k: m.state_dict() for k, m in nets.items()}}, path)
    return path


def test_random_policy_recording(tmp_path, capsys):
    out = tmp_path / "random.rrd"
    png = tmp_path / "topdown.png"
    record_main(["--policy", "random", "--episodes", "2", "--out", str(out), "--max-steps", "30", "--resolution",
                 "32", "--topdown-png", str(png)])
    assert "wrote 2 episode(s)" in capsys.readouterr().out
    verify(out)
    recs = recordings(out)
    assert len(recs) == 2  # one recording per episode
    for paths, timelines in recs:
        assert PLEX <= paths, sorted(PLEX - paths)
        assert not paths & ELI  # the random executor sends no ELI worth showing
        assert "step" in timelines
    from PIL import Image

    assert Image.open(png).size[0] > 50
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # temporaries are gone


def test_checkpoint_recordings_plex_and_flat(tmp_path):
    ckpt = make_checkpoint(tmp_path)
    out = tmp_path / "ckpt.rrd"
    record_main(["--checkpoint", str(ckpt), "--episodes", "1", "--out", str(out), "--split", "val"])
    verify(out)
    [(paths, _)] = recordings(out)
    assert PLEX | ELI <= paths, sorted((PLEX | ELI) - paths)

    # evaluate --record: world 0 of several, its first episodes
    from plex_ma.evaluate import main as evaluate_main

    ev = tmp_path / "eval.rrd"
    evaluate_main(["--checkpoint", str(ckpt), "--split", "val", "--episodes", "3", "--num-envs", "2",
                   "--record", str(ev)])
    verify(ev)
    recs = recordings(ev)
    assert len(recs) == 2 and all(PLEX | ELI <= p for p, _ in recs)

    flat = make_checkpoint(tmp_path, "ppo-gru")
    fl = tmp_path / "flat.rrd"
    evaluate_main(["--checkpoint", str(flat), "--split", "val", "--episodes", "1", "--num-envs", "1",
                   "--record", str(fl)])
    verify(fl)
    [(paths, _)] = recordings(fl)
    assert FLAT <= paths, sorted(FLAT - paths)
    assert not any("planner" in p for p in paths)


def test_recording_follows_the_episode(tmp_path):
    """What the recorder saw matches what the env reported, step for step."""
    env = PlexVectorEnv(2, seed=1, resolution=32, max_steps=40, num_scenes=2)
    rec = EpisodeRecorder(tmp_path / "w1.rrd", world=1, max_episodes=2, images=False)
    infos = []
    orig_step = env.step

    def step(**kw):
        res = orig_step(**kw)
        ended = np.flatnonzero(res.terminated | res.truncated)
        infos.extend(res.episode_infos[k] for k, i in enumerate(ended) if i == 1)
        return res

    env.step = step
    rng = np.random.default_rng(5)
    drv = PlexDriver(env, RandomPlanner(4.0, stop_prob=0.02, rng=rng), RandomExecutor(rng=rng))
    drv.reset(seed=5)
    rec.begin(env)
    world0 = 0  # run until world 0 has finished 3 episodes; world 1 runs as many or fewer

    def on_decision(d):
        rec.step(env, d.result, rows=d.rows)

    while world0 < 3:
        drv.decide(on_decision)
        s = drv.step()
        rec.step(env, s.result)
        world0 += int(s.result.terminated[0] or s.result.truncated[0])
    rec.end()
    assert 1 <= len(rec.episodes) <= 2
    for got, want in zip(rec.episodes, infos):
        assert got["finished"] and got["steps"] == want["steps"]
        assert got["collisions"] == want["collisions"] and got["success"] == want["success"]
        assert math.isclose(got["distance_to_goal"], want["distance_to_goal"], abs_tol=1e-9)
    assert "reset_rows" not in vars(env.worlds)  # the recorder leaves the env as it is
    verify(tmp_path / "w1.rrd")
    for paths, _ in recordings(tmp_path / "w1.rrd"):
        assert not paths & {"executor/rgb", "executor/depth", "planner/ego_map"}


def test_training_records_into_run_dir_without_changing_training(tmp_path):
    cfg = tiny_config(tmp_path, total_steps=2 * 2 * 16, record_interval=1)
    trainer = make_trainer(cfg, record=record_training_episode)
    trainer.train()
    trainer.close()
    rec_dir = tmp_path / "run" / "recordings"
    files = sorted(p.name for p in rec_dir.glob("*.rrd"))
    assert files == ["update_000001.rrd", "update_000002.rrd"], files
    verify(rec_dir / "update_000002.rrd")
    [(paths, timelines)] = recordings(rec_dir / "update_000002.rrd")
    assert PLEX | ELI <= paths
    assert "train/learner/executor_policy_loss" in paths and {"step", "train_step"} <= timelines

    # the same run without recordings learns exactly the same
    plain = tiny_config(tmp_path / "plain", total_steps=cfg.total_steps, record_interval=0)
    t2 = make_trainer(plain, record=record_training_episode)
    t2.train()
    t2.close()

    def learner(run_dir):
        lines = [json.loads(x) for x in (tmp_path / run_dir / "metrics.jsonl").read_text().splitlines()]
        return [{k: v for k, v in d.items() if k.startswith("learner/")} for d in lines]

    a, b = learner("run"), learner("plain/run")
    assert len(a) == len(b) == 2
    for x, y in zip(a, b):
        assert x.keys() == y.keys()
        for k in x:
            assert math.isclose(x[k], y[k], rel_tol=1e-5, abs_tol=1e-7), k


def test_training_recording_failure_warns(tmp_path):
    cfg = tiny_config(tmp_path)
    trainer = make_trainer(cfg)
    (tmp_path / "a_file").write_text("")
    with pytest.warns(UserWarning, match="recording an episode"):  # its directory cannot be made
        assert record_training_episode(trainer, tmp_path / "a_file" / "x.rrd") is None
    with pytest.raises(OSError):
        record_training_episode(trainer, tmp_path / "a_file" / "x.rrd", raise_errors=True)
    trainer.close()


def test_training_scalars_alone(tmp_path):
    out = tmp_path / "scalars.rrd"
    rec = EpisodeRecorder(out)
    rec.log_training_scalars(100, {"metrics/success": 0.5, "learner/loss": 1.0, "nan": float("nan"), "s": "x"})
    rec.log_training_scalars(200, {"metrics/success": 0.75})
    rec.end()
    verify(out)
    [(paths, timelines)] = recordings(out)
    assert {"train/metrics/success", "train/learner/loss"} <= paths and "train/nan" not in paths
    assert "train_step" in timelines


def test_helpers():
    # straight ahead is up (row 0) on the ego map; to the left is column 0
    assert np.allclose(ego_pixel(np.array([4.0, 0.0]), 32, 0.5), [16, 8])
    assert np.allclose(ego_pixel(np.array([4.0, math.pi / 2]), 32, 0.5), [8, 16])
    assert np.allclose(ego_pixel(np.array([100.0, 0.0]), 32, 0.5), [16, 0])  # clamped to the border
    x = np.random.default_rng(0).normal(size=(50, 128)) * np.linspace(3, 0.1, 128)
    p = pca_2d(x)
    assert p.shape == (50, 2) and p[:, 0].var() >= p[:, 1].var() > 0
    assert not pca_2d(np.ones((5, 128))).any() and pca_2d(np.ones((1, 128))).shape == (1, 2)


def test_docs_entity_table_is_the_layout_table():
    """docs/viz.md holds exactly what ``python -m plex_ma.viz.layout`` prints."""
    doc = (Path(__file__).resolve().parents[1] / "docs" / "viz.md").read_text()
    start = "<!-- entity table: the output of python -m plex_ma.viz.layout -->\n"
    body = doc.split(start, 1)[1].split("<!-- end of entity table -->", 1)[0]
    assert body == entity_table_markdown()
    assert [line.split("`")[1] for line in body.splitlines()[2:]] == list(ENTITY_PATHS)


def test_vector_envs_report_the_final_pose():
    """The pose an episode ended at comes with the step that ended it, before the autoreset."""
    env = PlexVectorEnv(2, seed=1, resolution=32, max_steps=40, num_scenes=2)
    env.reset()
    before = env.worlds.pose(np.arange(2))
    res = env.step(stop=np.ones(2, np.int64), subgoal=np.zeros((2, 2)))  # both planners stop on the spot
    assert res.terminated.all()
    np.testing.assert_array_equal(res.final_pose, before)
    res = env.step(stop=np.zeros(2, np.int64), subgoal=np.zeros((2, 2)))
    assert res.final_pose is None

    flat = PointNavVectorEnv(2, seed=1, resolution=32, max_steps=40, num_scenes=2)
    flat.reset()
    before = flat.worlds.pose(np.arange(2))
    _, _, term, _, infos = flat.step(np.zeros(2, np.int64))  # STOP
    assert term.all() and len(infos) == 2
    np.testing.assert_array_equal(flat.final_pose, before)
    flat.step(np.ones(2, np.int64))
    assert flat.final_pose is None
