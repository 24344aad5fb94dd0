"""The recipes of docs/trainers.md for Stable-Baselines3, skrl (with and without the ELI),
RLlib and the generic Parallel-API IPPO loop: each example runs
a few hundred steps where its library is installed, and is skipped otherwise. The test
extras install Stable-Baselines3 and skrl (they keep the pinned torch); RLlib is not in
them (ray pins its own gymnasium), so its test runs only where a user installed it."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

pytestmark = [pytest.mark.slow, pytest.mark.filterwarnings("ignore")]

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def load_example(name: str):
    spec = importlib.util.spec_from_file_location(name, EXAMPLES / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.parametrize("depth_as_image", [False, True])
def test_sb3_multi_input_policy(capsys, depth_as_image):
    pytest.importorskip("stable_baselines3")
    example = load_example("train_sb3")
    argv = ["--total-timesteps", "256", "--n-steps", "128", "--num-envs", "2", "--num-scenes", "2",
            "--max-steps", "50"]
    out = example.main(argv + (["--depth-as-image"] if depth_as_image else []))
    # rgb is an image (NatureCNN); the float depth is flattened unless encoded as uint8
    assert out["extractors"] == {"rgb": "NatureCNN", "pointgoal": "Flatten",
                                 "depth": "NatureCNN" if depth_as_image else "Flatten"}
    assert out["model"].num_timesteps >= 256 and len(out["lines"]) == 1
    assert "episodes, mean return" in capsys.readouterr().out


def test_skrl_ippo_through_the_turn_based_conversion(capsys):
    pytest.importorskip("skrl", minversion="2.0")
    example = load_example("train_skrl")
    out = example.main(["--timesteps", "300", "--rollouts", "64", "--num-scenes", "2", "--max-steps", "30"])
    assert out["updates"] == 4 and out["episodes"] >= 2  # masked actions only: an unmasked one would raise
    assert "IPPO updates per agent" in capsys.readouterr().out


def test_skrl_ippo_trains_the_executor_with_the_eli(capsys):
    pytest.importorskip("skrl", minversion="2.0")
    import torch

    example = load_example("train_skrl")
    out = example.main(["--timesteps", "300", "--rollouts", "64", "--num-scenes", "2", "--max-steps", "30", "--eli"])
    executor = out["agent"].policies["executor"]
    assert type(executor).__name__ == "EliPolicy" and out["updates"] == 4
    # the ELI's own parameters were trained (they start at log std -1), and the planner saw the messages
    assert not torch.allclose(executor.eli_log_std, torch.full((128,), -1.0))
    assert len(out["eli"]) > 100 and sum(out["eli"]) / len(out["eli"]) > 0.1
    assert "mean |ELI| seen by the planner" in capsys.readouterr().out


@pytest.mark.parametrize("view", ["env", "compat_env"])
def test_rllib_multi_agent_ppo(capsys, view):
    pytest.importorskip("ray.rllib")
    example = load_example("train_rllib")
    out = example.main(["--view", view, "--iterations", "2", "--batch", "200", "--num-scenes", "2",
                        "--max-steps", "30"])
    assert out["iterations"] == 2 and out["env_steps"] >= 400
    assert "iteration 2" in capsys.readouterr().out


def test_parallel_ippo_trains_compat_env_for_4096_steps(capsys):
    """The generic Parallel-API loop (masks from infos, each agent's own Discrete space)
    trains compat_parallel_env for 4,096 steps with constructor options as its only glue."""
    import torch

    example = load_example("train_ippo_parallel")
    torch.manual_seed(0)
    before = {a: [p.clone() for p in m.parameters()] for a, m in
              {"planner": example.Agent(6148, 33), "executor": example.Agent(4 * 16 * 16 + 4, 4)}.items()}
    out = example.main(["--total-steps", "4096", "--resolution", "32", "--image-size", "16", "--num-scenes", "2",
                        "--max-steps", "60"])
    assert out["steps"] == 4096 and len(out["lines"]) == 8 and out["episodes"] >= 20
    for a, model in out["agents"].items():
        # each agent has its own space: the planner's 33 sub-goal/stop choices, the executor's 4 moves
        assert model.actor[-1].out_features == {"planner": 33, "executor": 4}[a]
        assert any(not torch.equal(p, q) for p, q in zip(model.parameters(), before[a]))  # it was updated
        # keeping only the acting agent's transitions drops no reward: every one was credited
        assert abs(out["kept_total"][a] - out["raw_total"][a]) < 1e-6 * max(1.0, abs(out["raw_total"][a]))
    assert out["raw_total"]["planner"] != 0
    assert "transitions kept planner" in capsys.readouterr().out
