"""The experiment runner, Fig. 3's random-policy analysis and Proposition 1's check, on tiny settings."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from plex_ma.experiments import REGISTRY, default_out_dir, register
from plex_ma.experiments.__main__ import main as cli_main
from plex_ma.experiments.fig3 import Fig3Config, free_space_walks, run_fig3
from plex_ma.experiments.prop1 import Prop1Config, beta_01, beta_paper, beta_pm1, exact_tail, run_prop1

TINY = dict(starts=20, n_min=2, n_max=6, num_scenes=3, free_walks=2000, seed=3)


def strip(res: dict) -> dict:
    return {k: v for k, v in res.items() if k not in ("timing_seconds", "machine", "provenance")}


@pytest.fixture(scope="module")
def tiny_fig3():
    return run_fig3(Fig3Config(**TINY))


# ---------------------------------------------------------------- registry and CLI
def test_registry_and_default_dir():
    assert {"fig3", "prop1"} <= set(REGISTRY)
    assert default_out_dir("fig3").parts[-2:] == ("results", "fig3")
    with pytest.raises(ValueError, match="already registered"):
        register("fig3", "plex_ma.experiments.fig3")
    with pytest.raises(ValueError):
        register("bad name!", "x")


def test_cli_lists_and_rejects_unknown(capsys):
    assert cli_main([]) == 0
    assert "fig3" in capsys.readouterr().out
    assert cli_main(["no-such-experiment"]) == 2


def test_cli_runs_prop1(tmp_path):
    out = tmp_path / "p1"
    assert cli_main(["prop1", "--out", str(out), "--walks", "2000", "--n-max", "12", "--alphas", "0.3"]) == 0
    res = json.loads((out / "prop1.json").read_text())
    assert res["config"]["walks"] == 2000 and res["N"] == list(range(1, 13))
    assert (out / "prop1.png").stat().st_size > 1000


# ---------------------------------------------------------------- fig3
def test_fig3_tiny_values_are_sensible(tiny_fig3):
    res = tiny_fig3
    ns = np.array(res["N"])
    assert ns.tolist() == [2, 3, 4, 5, 6]
    for key in ("geodesic", "geodesic_grid"):
        d = res[key]
        mean, norm = np.array(d["mean"]), np.array(d["normalised_mean"])
        assert np.all(mean >= 0) and np.all(np.isfinite(mean))
        assert np.all(norm <= 0.25 + 1e-9)  # at most one 0.25 m move per action
        assert np.allclose(norm, mean / ns)
        # monotone-ish: the distance grows with N overall
        assert mean[-1] > mean[0]
        assert np.all(np.diff(mean) > -0.1)
    g = res["geodesic"]
    assert g["mean"][0] <= 0.5 + 1e-9  # two actions move at most 0.5 m
    assert g["p_beyond_cell"][0] == 0.0  # ... so they never leave a 0.5 m cell
    assert np.all(np.array(g["mean"]) <= np.array(res["geodesic_grid"]["mean"]) + 1e-9)
    assert np.all(np.array(res["euclidean_mean"]) <= np.array(g["mean"]) + 1e-9)
    assert all(0 <= p <= 1 for p in g["p_beyond_cell"])
    assert res["scenes"]["count"] == 3 and res["grid_unreachable_endpoints"] == 0


def test_fig3_is_deterministic_and_independent_of_batch(tiny_fig3):
    again = run_fig3(Fig3Config(**TINY, batch=10))
    assert strip(again) | {"config": None} == strip(tiny_fig3) | {"config": None}
    small = {**TINY, "starts": 6, "n_max": 3}
    a, b = run_fig3(Fig3Config(**small)), run_fig3(Fig3Config(**{**small, "seed": 4}))
    assert a["geodesic_grid"]["mean"] != b["geodesic_grid"]["mean"]


def test_fig3_prefix_mode_runs():
    res = run_fig3(Fig3Config(**{**TINY, "mode": "prefix", "starts": 10}))
    assert res["config"]["mode"] == "prefix"
    assert res["geodesic"]["p_beyond_cell"][0] == 0.0


def test_free_space_reference_matches_theory():
    d = free_space_walks(np.array([1, 2, 3]), 20000, np.random.default_rng(0))
    # one action: forward with probability 1/3, 0.25 m
    assert d["mean"][0] == pytest.approx(0.25 / 3, abs=0.005)
    assert d["p_beyond_cell"][:2] == [0.0, 0.0]


def test_fig3_rejects_bad_config():
    with pytest.raises(ValueError):
        run_fig3(Fig3Config(starts=1))
    with pytest.raises(ValueError):
        run_fig3(Fig3Config(mode="both"))


# ---------------------------------------------------------------- prop1
def test_beta_formulas():
    # +-1 steps at a equal {0,1} steps at (1+a)/2 (same event), and a = 1 gives 2^-N exactly
    for a in (0.1, 0.3, 0.5, 0.9):
        assert beta_pm1(a) == pytest.approx(beta_01((1 + a) / 2))
        assert beta_pm1(a) > 0
    assert beta_pm1(1.0) == pytest.approx(math.log(2))
    # the paper's formula as written is larger than the correct {0,1} exponent for alpha > 1/2
    for a in (0.55, 0.7, 0.9):
        assert beta_paper(a) > beta_01(a)


def test_exact_tail_small_cases():
    ns = np.arange(1, 5)
    # S_N >= 0.5 N: N=1 -> S=1 (1/2); N=2 -> S=2 (1/4); N=3 -> S=3 (1/8); N=4 -> S>=2: 5/16
    assert np.allclose(exact_tail(ns, 0.5), [0.5, 0.25, 0.125, 5 / 16])


def test_prop1_empirical_under_correct_chernoff_bound():
    walks = 40_000
    res = run_prop1(Prop1Config(alphas=[0.1, 0.3, 0.5, 0.7], n_max=40, walks=walks, seed=1, chunk=15_000))
    for p in res["per_alpha"]:
        emp = np.array(p["empirical"])
        exact = np.array(p["exact"])
        bound = np.array(p["bounds"]["chernoff_pm1"]["bound"])
        tol = 4 * np.sqrt(bound * (1 - bound) / walks) + 1 / walks
        assert np.all(emp <= bound + tol)
        assert np.all(exact <= bound * (1 + 1e-12))
        assert np.all(np.abs(emp - exact) <= 5 * np.sqrt(exact * (1 - exact) / walks) + 2 / walks)
        assert p["bounds"]["chernoff_pm1"]["exact_violations_N"] == []
    # the paper's formula read as {0,1} steps is violated already at N = 1
    assert 1 in res["per_alpha"][0]["bounds"]["paper_01"]["exact_violations_N"]


def test_prop1_is_deterministic_and_independent_of_chunk():
    cfg = dict(alphas=[0.3], n_max=10, walks=3000, seed=5)
    a = run_prop1(Prop1Config(**cfg))["per_alpha"][0]["empirical"]
    b = run_prop1(Prop1Config(**cfg, chunk=1000))["per_alpha"][0]["empirical"]
    c = run_prop1(Prop1Config(**{**cfg, "seed": 6}))["per_alpha"][0]["empirical"]
    assert a.shape == (10,) and np.array_equal(a, b) and not np.array_equal(a, c)


# ---------------------------------------------------------------- Table 1 / Fig. 4 / Fig. 5
def _fake_run(out, arm: str, seed: int, success: float, reward: float) -> None:
    """The files a finished table1 run leaves: evaluation JSONs and the training metrics."""
    import gzip

    d = out / "runs" / f"{arm}-s{seed}"
    d.mkdir(parents=True)
    part = {"success": success, "spl": success / 2, "reward": reward, "distance_to_goal": 5.0,
            "collisions": 3.0, "episodes": 10}
    ev = {**part, "close": {**part, "reward": reward - 1, "episodes": 4},
          "far": {**part, "reward": reward + 1, "episodes": 6}, "per_episode": []}
    (d / "eval_test_procgen.json").write_text(json.dumps(ev))
    (d / "eval_test_r2v.json").write_text(json.dumps({**ev, "reward": reward / 2}))
    with gzip.open(d / "metrics.jsonl.gz", "wt") as f:
        for step in (0, 500, 1000):
            f.write(json.dumps({"step": step, "reward": reward * step / 1000, "metrics/success": success,
                                "metrics/episodes": 0 if step == 0 else 100}) + "\n")


def test_table1_report_aggregates_every_seed(tmp_path):
    for seed, (s, r) in enumerate([(0.2, 1.0), (0.4, 3.0)]):
        _fake_run(tmp_path, "plex-gru", seed, s, r)
        _fake_run(tmp_path, "ppo-gru", seed, s / 2, r / 2)
    _fake_run(tmp_path, "ppo-smt", 0, 0.1, 0.5)  # a missing seed is reported, not invented
    _fake_run(tmp_path, "ppo-gru-map", 0, 0.3, 2.0)  # the map control arm
    assert cli_main(["table1", "--out", str(tmp_path), "--report-only", "--budget", "1000",
                     "--arms", "plex-gru", "ppo-gru", "ppo-smt", "ppo-gru-map", "--seeds", "0", "1"]) == 0
    res = json.loads((tmp_path / "table1.json").read_text())["table"]
    pg = res["plex-gru"]["test"]["procgen"]
    assert res["plex-gru"]["seeds"] == [0, 1]
    assert pg["all"]["success"]["mean"] == pytest.approx(0.3)
    assert pg["all"]["success"]["std"] == pytest.approx(np.std([0.2, 0.4], ddof=1))
    assert pg["far"]["reward"]["values"] == [2.0, 4.0]
    assert res["plex-gru"]["test"]["r2v"]["all"]["reward"]["mean"] == pytest.approx(1.0)
    assert res["ppo-smt"]["seeds"] == [0]
    assert res["ppo-smt"]["test"]["procgen"]["all"]["reward"]["values"] == [0.5]
    # steps to success 0.5 and 0.8: neither seed reaches them (0.2, 0.4)
    assert res["plex-gru"]["steps_to_success"] == {"0.5": {"0": None, "1": None}, "0.8": {"0": None, "1": None}}
    assert res["plex-gru"]["per_seed"]["1"] == {"success": 0.4, "spl": 0.2, "collisions": 3.0, "success_close": 0.4,
                                                "success_far": 0.4, "r2v_success": 0.4, "r2v_spl": 0.2}
    md = (tmp_path / "table1.md").read_text()
    assert "| PLEX GRU | 2 | 2.000 ± 1.414 | 0.300 ± 0.141 | 0.150 ± 0.071 | 3.0 ± 0.0 |" in md
    assert "| PPO SMT | 1 | 0.500 | 0.100 | 0.050 | 3.0 |" in md  # one seed: no spread
    assert "| PPO GRU+map | 1 | 2.000 | 0.300 | 0.150 |" in md
    assert "| PLEX GRU | 1 | 0.400 | 0.200 | 3.0 | 0.400 / 0.400 | 0.400 | 0.200 | - | - |" in md  # every seed
    for png in ("fig4.png", "fig5b.png"):
        assert (tmp_path / png).stat().st_size > 1000


def test_table1_steps_to_success_need_a_full_window(tmp_path):
    """Steps to success 0.5 need a full window of 100 training episodes: a rate over fewer
    (the first episodes of a run) does not count."""
    import gzip

    from plex_ma.experiments.table1 import _load_curve, steps_to_success

    rows = [(1000, 0.9, 40),  # a window of 40 episodes
            (2000, 0.6, 40),
            (3000, 0.45, 100), (4000, 0.55, 100), (5000, 0.7, 100)]
    path = tmp_path / "metrics.jsonl.gz"
    with gzip.open(path, "wt") as f:
        for step, success, n in rows:
            f.write(json.dumps({"step": step, "reward": 1.0, "metrics/success": success, "metrics/episodes": n}) + "\n")
    curve = _load_curve(path)
    assert steps_to_success(curve, 0.5) == 4000 and steps_to_success(curve, 0.8) is None
    assert np.isnan(curve["success"][:2]).all() and curve["success"][2] == 0.45


def test_table1_curves_are_drawn_across_a_resumed_runs_empty_window():
    """A run resumed from a checkpoint without the episode window restarted it empty (NaN):
    its line bridges the gap, and the band is NaN only where no seed has a full window yet."""
    from plex_ma.experiments.table1 import mean_band

    nan = np.nan
    curves = [{"step": np.array([10.0, 20, 30, 40, 50]), "success": np.array([nan, 0.2, nan, nan, 0.6])},
              {"step": np.array([10.0, 20, 30, 40, 50]), "success": np.array([nan, 0.4, 0.5, nan, 0.8])},
              {"step": np.array([10.0, 20]), "success": np.array([nan, nan])}]  # no full window: left out
    mean, lo, hi, seeds = mean_band(curves, "success", np.array([0.0, 20, 40, 50]))
    assert seeds == 2
    s0_at_40 = 0.2 + (0.6 - 0.2) * 2 / 3  # seed 0's line from step 20 to step 50
    assert np.isnan(mean[0]) and np.allclose(mean[1:], [0.3, (s0_at_40 + 0.65) / 2, 0.7])
    assert np.allclose(lo[1:], [0.2, s0_at_40, 0.6]) and np.allclose(hi[1:], [0.4, 0.65, 0.8])
    assert mean_band(curves[2:], "success", np.array([0.0, 20])) is None


def test_table1_trains_and_evaluates_one_smoke_run(tmp_path):
    """The real path: the train CLI, then the evaluate CLI, then the report."""
    out, runs = tmp_path / "out", tmp_path / "runs"
    assert cli_main(["table1", "--out", str(out), "--runs-dir", str(runs), "--preset", "smoke", "--budget", "256",
                     "--arms", "ppo-gru", "--seeds", "0", "--eval-episodes", "2", "--r2v-episodes", "0"]) == 0
    keep = out / "runs" / "ppo-gru-s0"
    ev = json.loads((keep / "eval_test_procgen.json").read_text())
    assert ev["episodes"] == 2 and ev["method"] == "ppo-gru"
    assert (keep / "metrics.jsonl.gz").is_file() and (runs / "ppo-gru-s0" / "latest.pt").is_file()
    table = json.loads((out / "table1.json").read_text())["table"]
    assert table["ppo-gru"]["seeds"] == [0]
    # Run again: the finished run is skipped (its evaluation is not redone).
    mtime = (keep / "eval_test_procgen.json").stat().st_mtime_ns
    assert cli_main(["table1", "--out", str(out), "--runs-dir", str(runs), "--preset", "smoke", "--budget", "256",
                     "--arms", "ppo-gru", "--seeds", "0", "--eval-episodes", "2", "--r2v-episodes", "0"]) == 0
    assert (keep / "eval_test_procgen.json").stat().st_mtime_ns == mtime


def test_table1_failed_run_is_one_line_naming_its_log(tmp_path):
    """A child that fails (here train refusing --num-envs 0) stops the runner with one line
    naming the child and its log (bad options of table1 itself: tests/test_cli_errors.py)."""
    with pytest.raises(SystemExit) as e:
        cli_main(["table1", "--out", str(tmp_path / "out"), "--runs-dir", str(tmp_path / "runs"), "--preset", "smoke",
                  "--budget", "256", "--arms", "ppo-gru", "--seeds", "0", "--extra", "--num-envs", "0"])
    log = tmp_path / "out" / "runs" / "ppo-gru-s0" / "train.log"
    assert str(e.value) == f"table1: plex_ma.train exited with status 2; its log: {log}"
    lines = log.read_text().splitlines()
    assert lines[0].startswith("$ -m plex_ma.train --preset smoke --method ppo-gru --seed 0")
    assert "--num-envs" in lines[-1] and ">= 1" in lines[-1]
