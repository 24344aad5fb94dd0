"""Determinism (same seed, same scenes, episodes and observations) and the procedural
splits: disjoint scenes, house sizes and episode distances over the default train split."""

from __future__ import annotations

import hashlib

import numpy as np

from plex_ma.envs.sim import DEFAULT_NUM_SCENES, BatchedSim, SceneBank, generate_episodes, rasterize
from plex_ma.envs.sim.procgen import HouseParams, generate_house
from plex_ma.envs.sim.sources import _colour_seed, procgen_scenes, procgen_seed

from .sim_helpers import bank_of, small_house

SCENE_FIELDS = ("walls", "doors", "boxes", "box_heights", "box_categories")


def geometry_hash(scene) -> str:
    h = hashlib.sha256()
    for f in SCENE_FIELDS:
        h.update(np.ascontiguousarray(getattr(scene, f)).tobytes())
    h.update(str(scene.wall_thickness).encode())
    return h.hexdigest()


def test_same_seed_same_house_and_grid():
    for seed in (0, 7, 123456789):
        a, b = generate_house(seed), generate_house(seed)
        for f in SCENE_FIELDS:
            np.testing.assert_array_equal(getattr(a, f), getattr(b, f))
        ga, gb = rasterize(a), rasterize(b)
        for f in ("kind", "nav", "room", "component", "kind_lo", "kind_hi", "kind_mat"):
            np.testing.assert_array_equal(getattr(ga, f), getattr(gb, f))
    assert len({geometry_hash(generate_house(s)) for s in range(12)}) == 12  # seeds matter


def test_same_seed_same_episodes():
    bank = bank_of(small_house(5), small_house(6))
    a, b = generate_episodes(bank, 12, seed=3), generate_episodes(bank, 12, seed=3)
    assert a == b
    assert generate_episodes(bank, 12, seed=4) != a
    # the first episodes do not depend on how many are asked for
    assert generate_episodes(bank, 5, seed=3) == a[:5]


def test_same_actions_same_observations():
    bank = bank_of(small_house(5), small_house(6))
    eps = generate_episodes(bank, 3, seed=0)
    rng = np.random.default_rng(0)
    acts = rng.integers(0, 4, size=(40, 3))
    runs = []
    for _ in range(2):
        sim = BatchedSim(bank, 3, resolution=32, pose_noise=(0.05, 0.02), seed=11)
        for i, ep in enumerate(eps):
            sim.reset_world(i, ep)
        frames = []
        for a in acts:
            sim.step(a)
            frames.append((sim.rgb.copy(), sim.depth.copy(), sim.pos.copy(), sim.est_pose.copy(), sim.egomap()))
        runs.append(frames)
    for fa, fb in zip(*runs):
        for x, y in zip(fa, fb):
            np.testing.assert_array_equal(x, y)
    assert not np.array_equal(runs[0][0][0], runs[0][-1][0])  # the agents did move


def test_splits_never_share_a_scene():
    seeds = {s: {procgen_seed(s, i) for i in range(5000)} for s in ("train", "val", "test")}
    assert all(len(v) == 5000 for v in seeds.values())
    assert not (seeds["train"] & seeds["val"] or seeds["train"] & seeds["test"] or seeds["val"] & seeds["test"])


def test_default_splits_disjoint_house_sizes_and_episode_distances():
    # One test, so that the 72 train houses are generated once per test process.
    scenes = {s: procgen_scenes(s) for s in ("train", "val", "test")}
    assert {s: len(v) for s, v in scenes.items()} == DEFAULT_NUM_SCENES
    ids = [sc.scene_id for v in scenes.values() for sc in v]
    hashes = [geometry_hash(sc) for v in scenes.values() for sc in v]
    assert len(set(ids)) == len(ids)
    assert len(set(hashes)) == len(hashes)  # no two scenes share their geometry
    for split, v in scenes.items():
        assert all(sc.scene_id.startswith(f"procgen-{split}-") for sc in v)

    # House sizes: the longer side lies in [6, 25] m and the train split covers that range.
    spans = []
    for sc in scenes["train"]:
        x0, y0, x1, y1 = sc.bounds()
        spans.append(max(x1 - x0, y1 - y0))
    spans = np.array(spans)
    assert spans.min() >= 6.0 - 1e-6 and spans.max() <= 25.0 + 1e-6
    assert spans.min() < 7.5 and spans.max() > 20.0
    assert np.sum(spans < 10) >= 10 and np.sum(spans > 15) >= 10

    # Episode geodesic distances over the train split cover about 1-30 m.
    bank = SceneBank([rasterize(sc, seed=_colour_seed(sc.scene_id)) for sc in scenes["train"]])
    d = np.array([e.geodesic_distance for e in generate_episodes(bank, 2 * len(bank), seed=0)])
    assert d.min() >= 1.0 and d.max() <= 30.0
    assert d.min() < 2.0 and d.max() > 15.0
    assert np.sum(d < 5.76) >= 0.15 * len(d) and np.sum(d >= 5.76) >= 0.3 * len(d)


def test_house_params_change_the_size_range():
    small = [generate_house(s, params=HouseParams(min_side=6.0, max_side=7.0)) for s in range(6)]
    for sc in small:
        x0, y0, x1, y1 = sc.bounds()
        assert 6.0 - 1e-6 <= max(x1 - x0, y1 - y0) <= 7.0 + 1e-6


def test_kept_images_equal_a_fresh_render():
    """A world whose agent does not move keeps its image; it must be the image a fresh
    render of that pose gives (STOP, turns and moves into walls, with pose noise)."""
    bank = bank_of(small_house(5), small_house(6))
    eps = generate_episodes(bank, 4, seed=1)
    sim = BatchedSim(bank, 4, resolution=32, pose_noise=(0.05, 0.02), seed=2)
    ref = BatchedSim(bank, 4, resolution=32, seed=2)
    for i, ep in enumerate(eps):
        sim.reset_world(i, ep)
        ref.reset_world(i, ep)
    rng = np.random.default_rng(0)
    kept = 0
    for _ in range(120):
        acts = rng.choice([0, 1, 1, 1, 2, 3], size=4)  # forward-heavy: agents bump into walls
        prev = sim.rgb.copy()
        sim.step(acts)
        kept += int(np.sum(np.all(sim.rgb == prev, axis=(1, 2, 3))))
        ref.pos[:], ref.heading[:] = sim.pos, sim.heading
        ref._sense(np.ones(4, bool))  # every world rendered afresh
        np.testing.assert_array_equal(sim.rgb, ref.rgb)
        np.testing.assert_array_equal(sim.depth, ref.depth)
    assert kept > 60  # STOPs and blocked moves did keep images
