"""Episodes: Habitat's generator rules over many samples, and episode files (round trip,
and a clear EpisodeFileError for every kind of broken file)."""

from __future__ import annotations

import gzip
import json
import math
from functools import lru_cache

import numpy as np
import pytest

from plex_ma.envs.sim import Episode, EpisodeFileError, Geodesics, generate_episodes, load_episodes, save_episodes
from plex_ma.envs.sim.episodes import ratio_keep_probability
from plex_ma.envs.sim.sources import scene_bank

N_EPISODES = 200


@lru_cache(maxsize=1)
def bank_and_episodes():
    bank = scene_bank("procgen", "val", 4)
    return bank, generate_episodes(bank, N_EPISODES, seed=123)


def ratio(ep: Episode) -> float:
    return ep.geodesic_distance / math.dist(ep.start_position, ep.goal_position)


def test_episodes_follow_the_rules():
    bank, eps = bank_and_episodes()
    geo = Geodesics(bank)
    assert [e.episode_id for e in eps] == list(range(N_EPISODES))
    assert [e.scene_id for e in eps] == [bank.scene_ids[i % len(bank)] for i in range(N_EPISODES)]
    for e in eps:
        s = bank.scene_ids.index(e.scene_id)
        grid = bank.grids[s]
        start, goal = np.array(e.start_position), np.array(e.goal_position)
        assert grid.is_navigable(start) and grid.is_navigable(goal)
        (rs, cs), (rg, cg) = grid.world_to_cell(start), grid.world_to_cell(goal)
        assert grid.component[rs, cs] == grid.component[rg, cg] >= 0  # connected
        assert 1.0 <= e.geodesic_distance <= 30.0
        assert -math.pi <= e.start_heading <= math.pi
        # the stored distance is the geodesic distance (recomputed by A*, float32 field)
        assert geo.distance(s, start, goal) == pytest.approx(e.geodesic_distance, abs=1e-4)
        assert e.geodesic_distance >= math.dist(e.start_position, e.goal_position) - 1e-6


def test_start_headings_are_uniform():
    from scipy.stats import kstest

    _, eps = bank_and_episodes()
    h = np.array([e.start_heading for e in eps])
    assert kstest((h + math.pi) / (2 * math.pi), "uniform").pvalue > 1e-3


def unfiltered_ratios(bank, n_goals: int, starts_per_goal: int, seed: int) -> np.ndarray:
    """geodesic/euclidean ratios of start-goal pairs drawn uniformly over the navigable
    cells with a geodesic distance in [1, 30] m, without the ratio rule."""
    rng = np.random.default_rng(seed)
    geo = Geodesics(bank)
    out = []
    for k in range(n_goals):
        s = k % len(bank)
        grid = bank.grids[s]
        nav = np.flatnonzero(grid.nav.ravel())
        goal = grid.cell_center(np.array(divmod(int(nav[rng.integers(len(nav))]), grid.shape[1])))
        field = geo.field(s, goal)
        ok = nav[(field[nav] >= 1.0) & (field[nav] <= 30.0)]
        for c in ok[rng.integers(len(ok), size=starts_per_goal)]:
            start = grid.cell_center(np.array(divmod(int(c), grid.shape[1])))
            out.append(geo.lookup(s, field, start) / math.dist(start, goal))
    return np.array(out)


def test_ratio_rule_thins_out_straight_episodes():
    bank, eps = bank_and_episodes()
    kept = np.array([ratio(e) for e in eps])
    raw = unfiltered_ratios(bank, 40, 10, seed=0)
    f_kept, f_raw = np.mean(kept < 1.1), np.mean(raw < 1.1)
    assert f_raw > 0.25  # without the rule, straight-line episodes are common
    assert f_kept < 0.5 * f_raw  # the rule removes most of them
    assert f_kept > 0.0  # ... but keeps some (probability up to 20 * 0.12^2 = 0.29)
    # Kept ratios below 1.1 lean towards 1.1, where the keep probability is highest.
    low_kept, low_raw = kept[kept < 1.1], raw[raw < 1.1]
    assert np.mean(low_kept) > np.mean(low_raw)
    assert np.mean(low_kept < 1.02) < 0.5 * np.mean(low_raw < 1.02) + 0.05


def test_ratio_keep_probability_is_habitats():
    assert ratio_keep_probability(1.1) == 1.0 and ratio_keep_probability(3.0) == 1.0
    for r in (0.98, 1.0, 1.05, 1.0999):
        assert ratio_keep_probability(r) == pytest.approx(20 * (r - 0.98) ** 2)


# ---------------------------------------------------------------------- episode files
def test_save_load_round_trip_is_exact_and_deterministic(tmp_path):
    _, eps = bank_and_episodes()
    a, b = tmp_path / "a.json.gz", tmp_path / "sub" / "b.json.gz"
    save_episodes(eps[:50], a)
    save_episodes(eps[:50], b)
    assert load_episodes(a) == eps[:50]  # floats survive bit for bit
    assert a.read_bytes() == b.read_bytes()  # no timestamp or name in the gzip header
    data = json.loads(gzip.decompress(a.read_bytes()))
    assert data["version"] == 1 and len(data["episodes"]) == 50
    assert set(data["episodes"][0]) == {"episode_id", "scene_id", "start_position", "start_heading",
                                        "goal_position", "geodesic_distance"}


def _record() -> dict:
    return {"episode_id": 0, "scene_id": "procgen-val-00000", "start_position": [1.0, 2.0], "start_heading": 0.5,
            "goal_position": [3.0, 4.0], "geodesic_distance": 3.5}


def _gz(obj) -> bytes:
    return gzip.compress(json.dumps(obj).encode(), mtime=0)


def _broken_files() -> dict[str, tuple[bytes | None, str]]:
    good = _gz({"version": 1, "episodes": [_record()]})
    corrupt = bytearray(good)
    corrupt[len(corrupt) // 2] ^= 0xFF  # flip bits in the deflate stream / CRC
    no_field = _record()
    del no_field["goal_position"]
    bad_type = _record()
    bad_type["start_position"] = "here"
    short_pos = _record()
    short_pos["goal_position"] = [1.0]
    nan = _record()
    nan["geodesic_distance"] = float("nan")
    return {
        "missing": (None, "does not exist"),
        "not_gzip": (json.dumps({"version": 1, "episodes": [_record()]}).encode(), "gzip"),
        "truncated": (good[: len(good) - 12], "gzip"),
        "corrupt": (bytes(corrupt), "gzip"),
        "empty": (b"", "JSON"),
        "not_json": (gzip.compress(b"{not json", mtime=0), "JSON"),
        "not_an_object": (_gz([_record()]), "'episodes'"),
        "wrong_version": (_gz({"version": 99, "episodes": [_record()]}), "version"),
        "no_version": (_gz({"episodes": [_record()]}), "version"),
        "missing_field": (_gz({"version": 1, "episodes": [no_field]}), "goal_position"),
        "bad_type": (_gz({"version": 1, "episodes": [bad_type]}), "start_position"),
        "short_position": (_gz({"version": 1, "episodes": [short_pos]}), "goal_position"),
        "nan": (_gz({"version": 1, "episodes": [nan]}), "geodesic_distance"),
        "record_not_object": (_gz({"version": 1, "episodes": [[1, 2]]}), "record 0"),
        "no_episodes": (_gz({"version": 1, "episodes": []}), "no episodes"),
    }


@pytest.mark.parametrize("case", sorted(_broken_files()))
def test_broken_episode_files_raise_episode_file_error(tmp_path, case):
    content, expect = _broken_files()[case]
    path = tmp_path / f"{case}.json.gz"
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(EpisodeFileError) as err:
        load_episodes(path)
    msg = str(err.value)
    assert str(path) in msg, msg  # names the file
    assert expect.lower() in msg.lower(), msg  # and the problem
    assert isinstance(err.value, ValueError)


def test_a_good_file_loads(tmp_path):
    path = tmp_path / "good.json.gz"
    path.write_bytes(_gz({"version": 1, "episodes": [_record(), dict(_record(), episode_id=1)]}))
    eps = load_episodes(path)
    assert len(eps) == 2 and eps[0].goal_position == (3.0, 4.0) and eps[1].episode_id == 1


def test_max_geodesic_bounds_sampled_episodes():
    """A curriculum's bound (``max_geodesic``) holds every sampled episode within it."""
    from plex_ma.envs.sim.episodes import sample_episode
    bank, _ = bank_and_episodes()
    geo, rng = Geodesics(bank), np.random.default_rng(0)
    short = [sample_episode(bank, s % len(bank), rng, geo, max_geodesic=2.5)[0].geodesic_distance for s in range(40)]
    assert all(1.0 <= d <= 2.5 for d in short)
    full = [sample_episode(bank, s % len(bank), rng, geo)[0].geodesic_distance for s in range(40)]
    assert max(full) > 5.0
