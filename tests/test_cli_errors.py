"""Every user error of the command lines (train, evaluate, record, bench, episodes, scenes,
experiments, pretrained) is one
line on stderr naming the problem, with exit status 2 and no traceback, and a run that
fails before its first update leaves no run dir behind (or the given one as it was)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from plex_ma import bench, episodes, evaluate, pretrained, record, scenes, train
from plex_ma.cli import unwritable
from plex_ma.experiments.__main__ import main as experiments_main

MISSING = "/nonexistent-plex-ma-scenes"


def run(*argv: str, cwd=None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", *argv], capture_output=True, text=True, timeout=300, cwd=cwd)


def assert_one_line_error(err: str, *names: str) -> None:
    assert "Traceback" not in err, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    for name in names:
        assert name in lines[0], err


def exit_status(main, argv: list[str]) -> int:
    """What a CLI's ``main`` exits with: its return value, or the code of its SystemExit."""
    try:
        return main(argv)
    except SystemExit as e:
        return e.code


@pytest.fixture
def empty_dir(tmp_path):
    d = tmp_path / "no-plans"
    d.mkdir()
    return d


# both presets refuse bad scenes before any work
@pytest.mark.parametrize("preset", ["smoke", "cpu"])
@pytest.mark.parametrize("scenes", ["missing", "empty"])
def test_train_bad_scenes_leave_no_run_dir(tmp_path, empty_dir, scenes, preset):
    arg, says = (MISSING, "does not exist") if scenes == "missing" else (str(empty_dir), "no plan files")
    out = run("plex_ma.train", "--preset", preset, "--total-steps", "64", "--scenes", arg,
              "--run-dir", str(tmp_path / "run"))
    assert out.returncode == 2
    assert_one_line_error(out.stderr, arg, says)
    assert not (tmp_path / "run").exists()


def test_train_episodes_of_other_scenes_is_one_line(tmp_path):
    """The val split's episode file for training on the train split, with the cpu preset."""
    from plex_ma.envs.sim.episodes import default_episode_file
    path = str(default_episode_file("procgen", "val"))
    out = run("plex_ma.train", "--preset", "cpu", "--total-steps", "64", "--episodes-file", path,
              "--run-dir", str(tmp_path / "run"))
    assert out.returncode == 2
    assert_one_line_error(out.stderr, path, "none of its scenes belong to procgen/train")
    assert not (tmp_path / "run").exists()


def test_train_leaves_a_given_run_dir_as_it_was(tmp_path):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "metrics.jsonl").write_text('{"step": 64}\n{"step": 128}\n')
    before = {p.name: p.read_bytes() for p in run_dir.iterdir()}
    out = run("plex_ma.train", "--preset", "smoke", "--episodes-file", str(tmp_path / "none.json.gz"),
              "--run-dir", str(run_dir))
    assert out.returncode == 2
    assert_one_line_error(out.stderr, "none.json.gz", "does not exist")
    assert {p.name: p.read_bytes() for p in run_dir.iterdir()} == before


@pytest.mark.parametrize("argv, names", [
    (["plex_ma.evaluate", "--planner", "oracle", "--executor", "oracle", "--episodes", "2", "--scenes", MISSING],
     [MISSING, "does not exist"]),
    (["plex_ma.record", "--policy", "random", "--scenes", "EMPTY", "--out", "OUT"], ["EMPTY", "no plan files"]),
    (["plex_ma.bench", "sim", "--steps", "2", "--num-envs", "2", "--scenes", MISSING], [MISSING, "does not exist"]),
    (["plex_ma.episodes", "make", "--split", "val", "--num-episodes", "2", "--seed", "0", "--scenes", "EMPTY",
      "--out", "OUT"], ["EMPTY", "no plan files"]),
])
def test_bad_scenes_in_every_cli(tmp_path, empty_dir, argv, names):
    subs = {"EMPTY": str(empty_dir), "OUT": str(tmp_path / "out" / "file")}
    out = run(*[subs.get(a, a) for a in argv])
    assert out.returncode == 2
    assert_one_line_error(out.stderr, *[subs.get(n, n) for n in names])
    assert not (tmp_path / "out").exists()  # nothing written


@pytest.mark.parametrize("main, argv, names", [
    (train.main, ["--preset", "smoke", "--num-envs", "0"], ["--num-envs", "0"]),
    (train.main, ["--total-steps", "many"], ["--total-steps", "many"]),  # tyro's parse errors, one line too
    (train.main, ["--preset", "fast"], ["--preset", "fast", "smoke"]),
    (train.main, ["--method", "ppo"], ["--method", "ppo", "plex-gru"]),
    (train.main, ["--no-such-flag", "1"], ["unrecognized", "--no-such-flag"]),
    (train.main, ["--planner", "teacher"], ["--planner", "teacher"]),
    (train.main, ["--total-steps"], ["--total-steps", "expected a value"]),
    (evaluate.main, ["--planner", "oracle", "--executor", "oracle", "--num-envs", "0"], ["--num-envs", "0"]),
    (evaluate.main, ["--planner", "oracle", "--executor", "oracle", "--episodes", "many"], ["--episodes", "many"]),
    (evaluate.main, ["--episodes", "2"], ["--checkpoint"]),
    (record.main, ["--policy", "random", "--resolution", "0", "--out", "OUT"], ["--resolution=0"]),
    (record.main, ["--policy", "random", "--max-steps", "0", "--out", "OUT"], ["--max-steps=0"]),
    (record.main, ["--policy", "random", "--episodes", "0", "--out", "OUT"], ["--episodes", "0"]),
    (bench.main, ["sim", "--num-envs", "0"], ["--num-envs", "0"]),
    (bench.main, ["gymvec", "--steps", "0"], ["--steps", "0"]),
    (bench.main, ["sim", "--resolution", "4"], ["--resolution", "4"]),
    (bench.main, ["env", "--planner-stop-prob", "2"], ["--planner-stop-prob", "2"]),
    (bench.main, ["order", "--resolution", "32"], ["--resolution", "32"]),
    (bench.main, ["train", "--set", "no_such_field=1"], ["no_such_field"]),
    (episodes.main, ["make", "--split", "val", "--num-episodes", "0", "--seed", "0", "--out", "OUT"],
     ["--num-episodes", "0"]),
])
def test_bad_values_are_one_line(tmp_path, capsys, main, argv, names):
    argv = [str(tmp_path / "out.rrd") if a == "OUT" else a for a in argv]
    assert exit_status(main, argv) == 2
    assert_one_line_error(capsys.readouterr().err, *names)
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("main, argv, names", [
    (train.main, ["--preset", "smoke", "--run-dir", "FILE/run"], ["--run-dir", "FILE", "is not a directory"]),
    (train.main, ["--preset", "smoke", "--run-dir", "FILE"], ["--run-dir", "FILE", "is not a directory"]),
    (evaluate.main, ["--planner", "oracle", "--executor", "oracle", "--json", "FILE/e.json"], ["--json", "FILE"]),
    (evaluate.main, ["--planner", "oracle", "--executor", "oracle", "--json", "DIR"], ["--json", "is a directory"]),
    (record.main, ["--policy", "random", "--out", "FILE/r.rrd"], ["--out", "is not a directory"]),
    (record.main, ["--policy", "random", "--out", "DIR/r.rrd", "--topdown-png", "FILE/t.png"], ["--topdown-png"]),
    (episodes.main, ["make", "--split", "val", "--num-episodes", "2", "--seed", "0", "--out", "FILE/e.json.gz"],
     ["--out", "is not a directory"]),
    (scenes.main, ["render", "procgen", "--count", "1", "--out", "FILE"], ["--out", "is not a directory"]),
])
def test_unwritable_outputs_are_one_line(tmp_path, capsys, main, argv, names):
    """An output path through a file, or a directory where a file goes: refused before any work."""
    (tmp_path / "file").write_text("a file, not a directory")
    subs = {"FILE": str(tmp_path / "file"), "DIR": str(tmp_path)}
    argv = [a.replace("FILE", subs["FILE"]).replace("DIR", subs["DIR"]) for a in argv]
    assert exit_status(main, argv) == 2
    assert_one_line_error(capsys.readouterr().err, *[subs.get(n, n) for n in names])
    assert [p.name for p in tmp_path.iterdir()] == ["file"]


def test_train_help_names_the_module(capsys):
    out = run("plex_ma.train", "--help", cwd="/")
    assert out.returncode == 0
    assert out.stdout.startswith("usage: python -m plex_ma.train ")


@pytest.mark.parametrize("argv, names", [
    (["table1", "--arms", "ppo-lstm"], ["--arms", "ppo-lstm"]),
    (["table1", "--budget", "0"], ["--budget", ">= 1"]),
    (["table1", "--r2v-episodes", "-1"], ["--r2v-episodes", ">= 0"]),
    (["table1", "--success-levels", "1.5"], ["--success-levels"]),
    (["table1", "--runs-dir", "FILE/runs"], ["--runs-dir", "is not a directory"]),
    (["fig3", "--starts", "1"], ["starts", ">= 2"]),
    (["fig3", "--n-min", "9", "--n-max", "3"], ["n_min"]),
    (["fig3", "--batch", "0"], ["batch", ">= 1"]),
    (["prop1", "--walks", "1"], ["walks", ">= 2"]),
    (["prop1", "--alphas", "2"], ["alphas"]),
    (["no-such-experiment"], ["unknown experiment", "no-such-experiment"]),
])
def test_experiment_errors_are_one_line_and_write_nothing(tmp_path, capsys, argv, names):
    (tmp_path / "file").write_text("a file, not a directory")
    argv = [a.replace("FILE", str(tmp_path / "file")) for a in argv] + ["--out", str(tmp_path / "out")]
    assert exit_status(experiments_main, argv) == 2
    assert_one_line_error(capsys.readouterr().err, *names)
    assert [p.name for p in tmp_path.iterdir()] == ["file"]


@pytest.mark.parametrize("argv, names", [
    (["--bogus"], ["unrecognized arguments", "--bogus"]),
    (["export", "x.pt", "--name", "a", "--command", "c", "--notes", "{x"], ["--notes", "not JSON"]),
    (["export", "x.pt", "--name", "a", "--command", "c", "--notes", "[1]"], ["--notes", "JSON object"]),
])
def test_pretrained_errors_are_one_line(capsys, argv, names):
    assert exit_status(pretrained.main, argv) == 2
    assert_one_line_error(capsys.readouterr().err, *names)


@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs Linux's /proc")
def test_output_in_an_unwritable_filesystem_is_one_line(capsys):
    """/proc refuses new files even to root, whom os.access lets through: the probe must catch it."""
    assert "cannot write in '/proc'" in unwritable("/proc/plex-ma-run", directory=True)
    assert exit_status(train.main, ["--preset", "smoke", "--run-dir", "/proc/plex-ma-run"]) == 2
    assert_one_line_error(capsys.readouterr().err, "--run-dir", "/proc/plex-ma-run", "cannot write")
