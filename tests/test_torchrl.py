"""TorchRL: its PettingZooWrapper rolls out plex_nav_v0.env() and compat_env() unchanged,
and examples/train_torchrl.py credits each agent with all its rewards and trains.
Skipped unless TorchRL is installed; it is not a dependency of plex-ma."""

from __future__ import annotations

import importlib.util
import math
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("torchrl")

from torchrl.envs.libs.pettingzoo import PettingZooWrapper  # noqa: E402
from torchrl.envs.utils import check_env_specs  # noqa: E402

from plex_ma.envs import plex_nav_v0  # noqa: E402
from plex_ma.envs.rules import INFO_KEYS  # noqa: E402

pytestmark = [pytest.mark.filterwarnings("ignore::UserWarning"), pytest.mark.filterwarnings("ignore::FutureWarning"),
              pytest.mark.filterwarnings("ignore::DeprecationWarning")]

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "train_torchrl.py"
SMALL = dict(resolution=64, num_scenes=4, max_steps=30)


@pytest.fixture(scope="module")
def example():
    spec = importlib.util.spec_from_file_location("train_torchrl", EXAMPLE)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def wrap(env) -> PettingZooWrapper:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return PettingZooWrapper(env=env, use_mask=True, seed=0)


# ---------------------------------------------------------------- the wrapper, unchanged
@pytest.mark.parametrize("factory", [plex_nav_v0.env, plex_nav_v0.compat_env], ids=["env", "compat_env"])
def test_pettingzoo_wrapper_rolls_out(factory):
    env = wrap(factory(**SMALL))
    check_env_specs(env)
    for g in ("planner", "executor"):
        assert set(env.observation_spec[g, "info"].keys()) == set(INFO_KEYS)
    td = env.rollout(300, break_when_any_done=False)  # random actions, reset after each episode
    assert td.batch_size == (300,)
    acting = torch.stack([td[g, "mask"][:, 0] for g in ("planner", "executor")], 1)
    assert torch.all(acting.sum(1) == 1)  # one agent acts per step
    assert acting[:, 1].sum() > 0 and acting[:, 0].sum() > 0
    done = td["next", "done"].reshape(-1)
    assert int(done.sum()) >= 2
    info = td["next", "planner", "info"]
    steps = info["steps"].reshape(-1)
    # the executor-step counter of the infos follows the rollout: +1 per executor action,
    # back to 0 after each reset
    starts = torch.cat([torch.zeros(1, dtype=torch.bool), done[:-1]])
    prev = torch.cat([torch.zeros(1), steps[:-1]])
    expect = torch.where(starts, 0.0, prev) + acting[:, 1].float()
    assert torch.equal(steps, expect)
    success = info["success"].reshape(-1)
    assert torch.all(success[~done] == 0) and torch.all((success == 0) | (success == 1))
    assert torch.all(info["spl"].reshape(-1) <= success)
    # the default rollout stops at the first episode end
    first = env.rollout(300)
    assert first["next", "done"][-1].item() and not first["next", "done"][:-1].any()


# ---------------------------------------------------------------- the example
def _collect(example, frames: int, record_last: bool = False):
    """A batch from the example's policy in a single env; with ``record_last``, also what
    ``last()`` gave each agent before each of its actions (PettingZoo's cumulative reward)."""
    from torchrl.collectors import Collector

    compat = plex_nav_v0.compat_env(**SMALL)
    seen = []
    if record_last:
        step = compat.step

        def recording_step(action):
            a = compat.agent_selection
            seen.append((a, float(compat._cumulative_rewards[a])))
            step(action)

        compat.step = recording_step
    env = wrap(compat)
    torch.set_num_threads(1)  # one thread: pytest runs two workers on the two cores
    parts = example.build(env)
    collector = Collector(env, parts["policy"], frames_per_batch=frames, total_frames=frames,
                          auto_register_policy_transforms=False)
    seen.clear()
    batch = next(iter(collector))
    collector.shutdown()
    return batch, parts, seen


def test_credit(example):
    torch.manual_seed(0)
    batch, parts, last_rewards = _collect(example, 400, record_last=True)
    assert len(last_rewards) == 400
    done = batch["next", "done"].reshape(-1).numpy()
    assert done.sum() >= 3
    planner_spans = 0
    for g in ("planner", "executor"):
        tr = example.agent_transitions(batch, g, parts[g]["critic"])
        raw = batch["next", g, "reward"].reshape(-1).double().numpy()
        steps = tr["step"].numpy()
        assert np.array_equal(steps, np.flatnonzero(batch[g, "mask"].reshape(-1).numpy()))
        credited = tr["reward"].reshape(-1).double().numpy()
        ends = tr["done"].reshape(-1).numpy()
        # Each credited reward is what last() handed the agent at its next action.
        for k in range(len(steps) - 1):
            if not ends[k]:
                who, got = last_rewards[steps[k + 1]]
                assert who == g and math.isclose(credited[k], got, abs_tol=1e-5)
                planner_spans += g == "planner" and steps[k + 1] > steps[k] + 1 and got != 0
        # Over each episode that starts and ends inside the batch, the agent's credited
        # rewards add up to everything it earned.
        ep_ends = np.flatnonzero(done)
        for s, e in zip(ep_ends[:-1] + 1, ep_ends[1:]):
            mine = (steps >= s) & (steps <= e)
            if mine.any():
                assert math.isclose(credited[mine].sum(), raw[s:e + 1].sum(), abs_tol=1e-4)
                assert ends[np.flatnonzero(mine)[-1]]  # its last transition ends with the episode
        # A terminated chain's value target is its reward (no bootstrap after it).
        term = tr["terminated"].reshape(-1).numpy()
        vt = tr[g, "value_target"].reshape(-1).numpy()
        np.testing.assert_allclose(vt[term], credited[term], atol=1e-5)
    assert planner_spans >= 3  # planner transitions that earned rewards during executor turns


def test_encoders_read_the_goal_vector_after_their_image(example):
    """Each agent's encoder splits its compat observation where the env puts the goal vector:
    after the one-hot id and the planner's whole ego map (every channel) or the executor's RGB-D."""
    native, compat = plex_nav_v0.env(**SMALL), plex_nav_v0.compat_env(**SMALL)
    at = example.Encoder("planner").vec_at
    assert at == 2 + int(np.prod(native.observation_space("planner")["ego_map"].shape))
    assert example.Encoder("executor", image_size=32).vec_at == 2 + 4 * 32 * 32
    native.reset(seed=0)
    compat.reset(seed=0)
    x = torch.as_tensor(compat.observe("planner")["observation"])
    assert torch.allclose(x[at:at + 2], torch.as_tensor(native.observe("planner")["goal"], dtype=x.dtype))


def test_update_changes_both_agents(example):
    torch.manual_seed(1)
    batch, parts, _ = _collect(example, 300)
    before = {g: [p.detach().clone() for p in parts[g]["loss"].parameters()] for g in ("planner", "executor")}
    logs = example.update(parts, batch, epochs=1)
    for g in ("planner", "executor"):
        assert logs[g]["transitions"] == int(batch[g, "mask"].sum())
        assert math.isfinite(logs[g]["loss"])
        after = list(parts[g]["loss"].parameters())
        assert any(not torch.equal(a, b) for a, b in zip(before[g], after))


@pytest.mark.slow
def test_example_runs(example):
    out = example.main(["--iterations", "2", "--frames-per-batch", "150", "--num-envs", "2", "--max-steps", "30",
                        "--num-scenes", "4"])
    assert out["env_steps"] == 300
    assert len(out["history"]) == 2
    assert sum(len(h["episodes"]) for h in out["history"]) >= 2
    for h in out["history"]:
        for g in ("planner", "executor"):
            assert math.isfinite(h["losses"][g]["loss"])
