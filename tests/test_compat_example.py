"""examples/train_compat_tianshou.py: runs, and credits each agent with all its rewards.
Skipped unless Tianshou (2.x) is installed; it is not a dependency of plex-ma."""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("tianshou", minversion="2.0")

pytestmark = [pytest.mark.slow, pytest.mark.filterwarnings("ignore")]

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "train_compat_tianshou.py"
SMALL = dict(resolution=64, num_scenes=4, max_steps=30)


@pytest.fixture(scope="module")
def example():
    spec = importlib.util.spec_from_file_location("train_compat_tianshou", EXAMPLE)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_credit(example):
    from tianshou.data import Collector, VectorReplayBuffer

    algorithm, train_envs, _ = example.build(SMALL, num_envs=2, seed=0)
    buffer = VectorReplayBuffer(2000, 2)
    collector = Collector(algorithm, train_envs, buffer)
    collector.reset()
    collector.collect(n_step=400)
    batch, indices = buffer.sample(0)
    raw_rew = np.asarray(batch.rew, np.float64).copy()
    agents = np.asarray(batch.obs.agent_id).copy()
    ended = np.asarray(batch.terminated | batch.truncated).copy()
    example.credit_turns(batch, buffer, indices, algorithm._dispatcher.agent_idx)
    new_rew = np.asarray(batch.rew, np.float64)
    col = {"planner": 0, "executor": 1}

    # Split the data into episodes (each sub-buffer is in time order).
    episodes, start = [], 0
    sub = np.searchsorted(buffer.subbuffer_edges, indices, side="right")
    for p in range(len(indices)):
        last_of_sub = p + 1 == len(indices) or sub[p + 1] != sub[p]
        if ended[p] or last_of_sub:
            episodes.append((start, p + 1, bool(ended[p])))
            start = p + 1
    complete = [(s, e) for s, e, done in episodes if done]
    assert len(complete) >= 3
    planner_checked = 0
    for s, e in complete:
        for a, c in col.items():
            mine = [p for p in range(s, e) if agents[p] == a]
            if not mine:  # the planner stopped at once: the executor never acted, nor earned
                assert raw_rew[s:e, c].sum() == 0
                continue
            # All that agent earned in the episode, on its own transitions only.
            assert math.isclose(new_rew[mine, c].sum(), raw_rew[s:e, c].sum(), abs_tol=1e-4)
            for k, p in enumerate(mine[:-1]):
                q = mine[k + 1]
                # The reward of p is what the agent earned until its next turn (its last() there),
                assert math.isclose(new_rew[p, c], raw_rew[p:q, c].sum(), abs_tol=1e-5)
                # its next observation is its own, and the episode goes on.
                assert batch.obs_next.agent_id[p] == a
                np.testing.assert_array_equal(batch.obs_next.obs[p], batch.obs.obs[q])
                assert not batch.terminated[p] and not batch.truncated[p]
                planner_checked += a == "planner" and q > p + 1
            # Its last transition ends with the episode.
            assert batch.terminated[mine[-1]] or batch.truncated[mine[-1]]
    assert planner_checked >= 3  # planner transitions that spanned an executor turn


def test_example_runs(example):
    out = example.main(["--epochs", "1", "--steps-per-epoch", "300", "--steps-per-collect", "150",
                        "--num-envs", "2", "--eval-episodes", "2", "--max-steps", "30", "--num-scenes", "4"])
    assert out["env_steps"] >= 300
    for phase in ("before", "after"):
        assert math.isfinite(out[phase]["planner_return"]) and math.isfinite(out[phase]["executor_return"])
        assert out[phase]["episodes"] >= 2
