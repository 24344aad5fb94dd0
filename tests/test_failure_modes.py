"""``scripts/failure_modes.py``: the failure report of a planner over the oracle executor."""

import runpy
import sys
from pathlib import Path

import numpy as np

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "failure_modes.py"


def test_failure_report_counts_the_failures(monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", [str(SCRIPT), "--planner", "map", "--split", "val", "--episodes", "24",
                                      "--num-envs", "8"])
    runpy.run_path(str(SCRIPT), run_name="__main__")
    out = capsys.readouterr().out.splitlines()
    n_fail = int(out[0].split()[0])
    assert out[0].endswith("(map planner over the oracle executor, ground truth)")
    assert 0 <= n_fail < 24  # the map planner over the oracle executor succeeds in most episodes
    rows = out[2:2 + n_fail]
    assert all(int(r.split()[1]) == 500 or float(r.split()[3]) >= 0.2 for r in rows)  # a time-out or a failed stop
    assert out[-1].startswith("standing in place over the last 100 actions:")


def test_n_ex_sweep_runs_each_value(monkeypatch, capsys):
    """``scripts/n_ex_sweep.py``: one row per N_EX on the same episodes; the map planner over
    the oracle executor gains from an executor that can turn round before control returns."""
    sweep = SCRIPT.parent / "n_ex_sweep.py"
    monkeypatch.setattr(sys, "argv", [str(sweep), "--planner", "map", "--executor", "oracle", "--n-ex", "10", "18",
                                      "--episodes", "64", "--num-envs", "8"])
    runpy.run_path(str(sweep), run_name="__main__")
    rows = [r.split() for r in capsys.readouterr().out.splitlines()[2:]]
    assert [int(r[0]) for r in rows] == [10, 18]
    s10, s18 = (float(r[1]) for r in rows)
    assert s18 >= 0.9 and s18 > s10


def test_executor_turns_separate_straight_and_detour_sub_goals():
    """``scripts/executor_turns.py``: under the map planner, the oracle executor ends most
    turns at its sub-goal; map-los sets fewer sub-goals that need a detour than map."""
    sys.path.insert(0, str(SCRIPT.parent))
    import executor_turns
    from plex_ma.config import TrainConfig, replace

    cfg = replace(TrainConfig(method="plex-gru"), n_ex=18, resolution=64)
    a = executor_turns.turns(cfg, {}, "map", "oracle", steps=150, worlds=8)
    b = executor_turns.turns(cfg, {}, "map-los", "oracle", steps=150, worlds=8)
    assert len(a) > 20 and len(b) > 20
    assert np.mean(b[:, 2] < 0.5) > 0.6  # the oracle executor reaches the sub-goals of map-los
    detour = lambda t: np.mean(t[:, 1] > executor_turns.DETOUR_RATIO * t[:, 0] + executor_turns.DETOUR_SLACK)  # noqa: E731
    assert detour(b) < detour(a), (detour(a), detour(b))
    assert "detour" in executor_turns.report(a)
