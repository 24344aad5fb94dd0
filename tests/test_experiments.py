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
