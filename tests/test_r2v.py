"""Real floor plans (Raster-to-Vector): the loader on hand-made plans of known geometry,
its errors, the bundled plans and their splits, the sources, episodes on real plans and
the ``python -m plex_ma.scenes`` CLI."""

from __future__ import annotations

import json
import math
import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from plex_ma.envs.sim import SceneError, load_scenes, rasterize
from plex_ma.envs.sim import r2v
from plex_ma.envs.sim import sources
from plex_ma.envs.sim.bank import SceneBank
from plex_ma.envs.sim.episodes import MAX_GEODESIC, MIN_GEODESIC, Geodesics, generate_episodes
from plex_ma.envs.sim.scene import MAT_FURNITURE, MAT_VOID, MAT_WALL

S = r2v.DEFAULT_SCALE  # 0.02 m per pixel


def plan_text(walls=(), doors=(), icons=(), labels=()) -> str:
    """A plan file: walls/doors are (x0, y0, x1, y1) px, icons/labels (x0, y0, x1, y1, name)."""
    rows = [(*w, "wall") for w in walls] + [(*d, "door") for d in doors] + list(icons) + list(labels)
    return "".join("\t".join(str(v) for v in r) + "\t1\t1\t\n" for r in rows)


# Two 4 x 4 m rooms side by side (400 x 200 px), split by a wall at x = 200 px.
OUTLINE = [(0, 0, 400, 0), (400, 0, 400, 200), (400, 200, 0, 200), (0, 200, 0, 0)]
MIDDLE = (200, 0, 200, 200)
LABELS = [(40, 70, 80, 85, "bedroom"), (290, 70, 330, 85, "living_room")]


def world(x_px: float, y_px: float, y_max_px: float = 200) -> np.ndarray:
    """Pixel -> world metres for the plans above (x from 0, y flipped about y_max)."""
    return np.array([x_px * S, (y_max_px - y_px) * S])


def load(tmp_path, text: str, name: str = "plan", **kw):
    f = tmp_path / f"{name}.txt"
    f.write_text(text)
    scene = r2v.load_plan(f, **kw)
    grid = rasterize(scene)
    return scene, grid


def geodesic(grid, a, b) -> float:
    bank = SceneBank([grid])
    return Geodesics(bank).distance(0, np.asarray(a, float), np.asarray(b, float))


LEFT, RIGHT = world(100, 100), world(300, 100)


# ----------------------------------------------------------------------------- known geometry


def test_door_is_open_and_scene_fields(tmp_path):
    scene, grid = load(tmp_path, plan_text(OUTLINE + [MIDDLE], doors=[(200, 75, 200, 125)], labels=LABELS),
                       name="two_rooms")
    assert scene.scene_id == "two_rooms" and scene.source == "r2v"
    assert scene.wall_thickness == r2v.WALL_THICKNESS
    assert np.allclose(scene.bounds(), (0, 0, 8.0, 4.0))  # translated, metres
    assert len(scene.boxes) == 0  # room labels are not geometry
    d = geodesic(grid, LEFT, RIGHT)
    assert 4.0 <= d <= 4.3  # straight through the door


def test_wall_without_door_is_closed(tmp_path):
    _, grid = load(tmp_path, plan_text(OUTLINE + [MIDDLE]))
    assert math.isinf(geodesic(grid, LEFT, RIGHT))
    assert grid.component[tuple(grid.world_to_cell(LEFT))] != grid.component[tuple(grid.world_to_cell(RIGHT))]


def test_geodesic_goes_around_a_wall(tmp_path):
    # A wall from the bottom (y = 200 px) up to y = 40 px leaves a 0.8 m gap at the top.
    _, grid = load(tmp_path, plan_text(OUTLINE + [(200, 200, 200, 40)]))
    a, b = world(100, 150), world(300, 150)  # 1 m above the bottom wall, 4 m apart
    tip = world(200, 40)
    lower = 2 * math.hypot(2.0, tip[1] + r2v.WALL_THICKNESS / 2 + 0.1 - a[1])
    d = geodesic(grid, a, b)
    assert np.hypot(*(a - b)) == pytest.approx(4.0)
    assert lower - 0.05 <= d <= lower + 0.6


def test_exterior_door_stays_closed(tmp_path):
    _, grid = load(tmp_path, plan_text(OUTLINE + [MIDDLE], doors=[(0, 75, 0, 125)]))
    mat = grid.kind_mat[grid.kind]
    r, c = grid.world_to_cell(world(0, 100))
    assert mat[r, c] == MAT_WALL
    r, c = grid.world_to_cell(world(-10, 100))
    assert mat[r, c] == MAT_VOID  # outside the apartment is void


def test_furniture_blocks(tmp_path):
    icons = [(20, 20, 70, 60, "bathtub"), (300, 150, 360, 180, "closet")]
    scene, grid = load(tmp_path, plan_text(OUTLINE + [MIDDLE], icons=icons))
    assert scene.box_categories.tolist() == [r2v.ICONS["bathtub"][0], r2v.ICONS["closet"][0]]
    assert np.allclose(scene.box_heights, [r2v.ICONS["bathtub"][1], r2v.ICONS["closet"][1]])
    # The bathtub is at the top-left in the image: high y in the world.
    assert np.allclose(scene.boxes[0], [0.4, 2.8, 1.4, 3.6])
    mat = grid.kind_mat[grid.kind]
    centres = grid.cell_center(np.stack(np.indices(grid.shape), -1))
    inside = ((centres[..., 0] > 0.4) & (centres[..., 0] < 1.4) & (centres[..., 1] > 2.8) & (centres[..., 1] < 3.6))
    assert inside.sum() > 100
    assert not grid.nav[inside].any()
    assert (mat[inside] == MAT_FURNITURE + 2).all()
    assert np.allclose(grid.kind_hi[grid.kind[inside]], 0.55)
    assert grid.is_navigable(world(100, 150)) and not grid.is_navigable(world(45, 40))


def test_small_gap_in_outline_is_snapped(tmp_path, monkeypatch):
    walls = [(0, 0, 391, 0), (400, 0, 400, 200), (400, 200, 0, 200), (0, 200, 0, 0)]  # 9 px gap, top right
    _, closed = load(tmp_path, plan_text(OUTLINE))
    _, snapped = load(tmp_path, plan_text(walls))
    assert snapped.navigable_area() == pytest.approx(closed.navigable_area(), rel=0.01)
    monkeypatch.setattr(r2v, "SNAP_TOLERANCE_PX", 0.0)
    with pytest.raises(SceneError, match="nothing navigable"):  # the outside leaks in
        load(tmp_path, plan_text(walls), name="leaky")


def test_snap_walls_meets_at_corner():
    w = np.array([[0, 50, 100, 50], [103, 53, 103, 200], [0, 0, 0, 46]], float)
    out = r2v.snap_walls(w, tol=10)
    assert np.allclose(out, [[0, 50, 103, 50], [103, 50, 103, 200], [0, 0, 0, 50]])
    far = np.array([[0, 50, 100, 50], [130, 53, 130, 200]], float)
    assert np.allclose(r2v.snap_walls(far, tol=10), far)  # beyond tolerance: left alone


def test_door_off_its_wall_is_projected(tmp_path, monkeypatch):
    text = plan_text(OUTLINE + [MIDDLE], doors=[(195, 75, 195, 125)])  # 5 px beside the wall
    _, grid = load(tmp_path, text)
    assert 4.0 <= geodesic(grid, LEFT, RIGHT) <= 4.3
    monkeypatch.setattr(r2v, "DOOR_TOLERANCE_PX", 0.0)
    _, grid = load(tmp_path, text, name="dropped")
    assert math.isinf(geodesic(grid, LEFT, RIGHT))


def test_door_next_to_a_corner_does_not_open_the_outer_wall(tmp_path, monkeypatch):
    # The door runs right up to the outer wall; its cut must not punch through it.
    text = plan_text(OUTLINE + [MIDDLE], doors=[(200, 0, 200, 50)])
    _, grid = load(tmp_path, text)
    assert math.isfinite(geodesic(grid, LEFT, RIGHT))
    mat = grid.kind_mat[grid.kind]
    centres = grid.cell_center(np.stack(np.indices(grid.shape), -1))
    # The cut may reach the outer wall's centre line, never its outer half.
    outer = (centres[..., 1] > 4.0) & (centres[..., 1] < 4.06) & (np.abs(centres[..., 0] - 4.0) < 0.5)
    assert outer.sum() >= 20 and (mat[outer] == MAT_WALL).all()
    # Without the inset the cut would reach the outside, and the door would stay closed.
    monkeypatch.setattr(r2v, "DOOR_INSET", 0.0)
    _, grid = load(tmp_path, text, name="no_inset")
    assert math.isinf(geodesic(grid, LEFT, RIGHT))


def test_auto_scale_uses_door_widths(tmp_path):
    text = plan_text(OUTLINE + [MIDDLE], doors=[(200, 40, 200, 100), (200, 110, 200, 140)])  # median 45 px
    scene = r2v.load_plan_grid(text.encode(), "auto", scale="auto")[0]
    assert np.allclose(scene.bounds()[2], 400 * r2v.AUTO_DOOR_WIDTH / 45)


# ----------------------------------------------------------------------------- errors


@pytest.mark.parametrize("content, match", [
    (b"1\t2\t3\t4\twall\t1\t1\n5\t6\t7", r"line 2: .*got 3 field.*truncated"),
    (b"0\t0\t100\t0\twall\t1\t1\n0\t0\t0\t100\tdo", r"line 2: unknown category 'do'.*truncated"),
    (b"\x00\x1f\x8b\x08garbage", r"not a text file"),
    (b"\xff\xfe\xfa", r"not a text file"),
    (b"", r"has no walls"),
    (b"1 2 3 4 bedroom\n", r"has no walls"),
    (b"0 0 100 0 wall\nx 1 2 3 wall\n", r"line 2: coordinates are not numbers"),
    (b"0 0 nan 0 wall\n", r"line 1: coordinates must be finite"),
    (b"0 0 100 0 wall\n0 0 1 1 sofa\n", r"line 2: unknown category 'sofa'"),
    (b"0 0 100 0 wall\n", r"nothing navigable"),
    (b"0 0 19000 0 wall\n", r"larger than 100 m"),
])
def test_malformed_plans_raise_scene_error(tmp_path, content, match):
    f = tmp_path / "bad_plan_7.txt"
    f.write_bytes(content)
    with pytest.raises(SceneError, match=match) as e:
        r2v.load_plan(f)
    assert str(e.value).startswith("plan 'bad_plan_7': ")


def test_truncated_real_plan(tmp_path):
    pid = r2v.bundled_ids("train")[0]
    data = r2v.bundled_plans()[pid]
    f = tmp_path / f"{pid}.txt"
    f.write_bytes(data[: len(data) // 2 - 3])
    with pytest.raises(SceneError, match=rf"plan '{pid}': .*(truncated|has no walls|navigable)"):
        r2v.load_plan(f)


def test_small_plan_is_rejected_for_area(tmp_path):
    box = [(0, 0, 100, 0), (100, 0, 100, 100), (100, 100, 0, 100), (0, 100, 0, 0)]  # 2 x 2 m
    with pytest.raises(SceneError, match=r"plan .tiny.: navigable area too small: 2\.\d m\^2 < 8 m\^2"):
        load(tmp_path, plan_text(box), name="tiny")


def test_plan_split_into_small_parts_is_rejected(tmp_path):
    # Two closed 3 x 3 m rooms: about 14 m^2 navigable in all, but no part reaches 8 m^2.
    walls = [(0, 0, 300, 0), (300, 0, 300, 150), (300, 150, 0, 150), (0, 150, 0, 0), (150, 0, 150, 150)]
    with pytest.raises(SceneError, match=r"plan 'split': largest navigable component too small: "
                       r"\d\.\d m\^2 < 8 m\^2 \(1\d\.\d m\^2 in 2 parts"):
        load(tmp_path, plan_text(walls), name="split")


def test_missing_file_and_bad_scale(tmp_path):
    with pytest.raises(SceneError, match="plan 'nope': cannot read"):
        r2v.load_plan(tmp_path / "nope.txt")
    with pytest.raises(SceneError, match="scale"):
        r2v.load_plan(plan_text(OUTLINE).encode(), "p", scale=-1.0)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(st.one_of(
    st.tuples(st.integers(-5, 400), st.integers(-5, 400), st.integers(-5, 400), st.integers(-5, 400),
              st.sampled_from(["wall", "door", "toilet", "closet", "PS", "bedroom", "point"])).map(
        lambda t: "\t".join(map(str, t)) + "\t1\t1"),
    st.text(max_size=30)), max_size=25), st.binary(max_size=20))
def test_loader_never_crashes(lines, tail):
    data = "\n".join(lines).encode() + tail
    try:
        r2v.load_plan(data, "fuzz")
    except SceneError as e:
        assert str(e).startswith("plan 'fuzz': ")


# ----------------------------------------------------------------------------- bundled plans


def test_bundle_and_splits():
    ids = r2v.bundled_ids()
    assert len(ids) == 1040
    parts = {sp: set(r2v.bundled_ids(sp)) for sp in ("train", "val", "test")}
    assert sum(map(len, parts.values())) == 1040
    assert not (parts["train"] & parts["val"] or parts["train"] & parts["test"] or parts["val"] & parts["test"])
    assert 0.75 < len(parts["train"]) / 1040 < 0.85 and 0.07 < len(parts["val"]) / 1040 < 0.13
    idx = r2v.bundled_index()
    assert idx["fingerprint"] == r2v.loader_fingerprint(), "index.json is stale: python -m plex_ma.scenes index"
    assert idx["split_sizes"] == {sp: len(v) for sp, v in parts.items()}
    assert r2v.split_of("000209a30b61b563f93faf6a6466ffab_0001") == "train"  # pinned: splits never move
    assert (r2v.DATA_DIR / "LICENSE").read_text().startswith("MIT License")
    assert "Raster-to-Vector" in (r2v.DATA_DIR / "README.md").read_text()


def test_sample_of_bundled_plans_load_or_reject_by_name():
    """A deterministic sample of 100 plans (the full check: python -m plex_ma.scenes check r2v)."""
    ids = r2v.bundled_ids()
    rejects = r2v.bundled_index()["rejects"]
    sample = ids[:: len(ids) // 100][:100]
    for pid in sample:
        try:
            scene = r2v.load_plan(r2v.bundled_plans()[pid], pid)
        except SceneError as e:
            assert str(e).startswith(f"plan {pid!r}: ")
            assert pid in rejects, str(e)
        else:
            assert scene.scene_id == pid and pid not in rejects


def test_r2v_source_is_registered():
    assert sources.SOURCES["r2v"] is r2v.r2v_scenes
    scenes = load_scenes("r2v", "val", 3)
    assert len(scenes) == 3
    rejects = r2v.bundled_index()["rejects"]
    for sc in scenes:
        assert sc.source == "r2v" and r2v.split_of(sc.scene_id) == "val" and sc.scene_id not in rejects
    assert [s.scene_id for s in scenes] == [i for i in r2v.bundled_ids("val") if i not in rejects][:3]


def test_episodes_on_real_plans_obey_spec():
    grids = [rasterize(sc) for sc in load_scenes("r2v", "test", 4)]
    bank = SceneBank(grids)
    geo = Geodesics(bank)
    eps = generate_episodes(bank, 24, seed=3)
    for ep in eps:
        s = bank.scene_ids.index(ep.scene_id)
        g = bank.grids[s]
        a, b = np.array(ep.start_position), np.array(ep.goal_position)
        assert MIN_GEODESIC <= ep.geodesic_distance <= MAX_GEODESIC
        assert g.is_navigable(a) and g.is_navigable(b)
        assert g.component[tuple(g.world_to_cell(a))] == g.component[tuple(g.world_to_cell(b))]
        d = geo.distance(s, a, b)
        assert math.isfinite(d) and abs(d - ep.geodesic_distance) < 0.05 * ep.geodesic_distance + 0.1


# ----------------------------------------------------------------------------- directory source and CLI


@pytest.fixture
def plan_dir(tmp_path):
    d = tmp_path / "plans"
    d.mkdir()
    (d / "a_good.txt").write_text(plan_text(OUTLINE + [MIDDLE], doors=[(200, 75, 200, 125)]))
    (d / "b_good.txt").write_text(plan_text(OUTLINE, icons=[(20, 20, 70, 60, "toilet")]))
    (d / "c_bad.txt").write_bytes(b"0\t0\t300\t0\twall\t1\t1\n0\t0\t30")
    (d / "notes.md").write_text("not a plan")
    return d


def test_directory_source_warns_and_skips(plan_dir):
    with pytest.warns(UserWarning, match=r"skipped 1 of 3 plans(.|\n)*plan 'c_bad': parse error at line 2"):
        scenes = load_scenes(str(plan_dir), "test")
    assert [s.scene_id for s in scenes] == ["a_good", "b_good"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert [s.scene_id for s in load_scenes(str(plan_dir), "train", 1)] == ["a_good"]


def test_missing_or_empty_directory(tmp_path):
    with pytest.raises(SceneError, match=r"scene directory '.*missing' does not exist"):
        load_scenes(str(tmp_path / "missing"), "train")
    (tmp_path / "plan.txt").write_text("")
    with pytest.raises(SceneError, match="is not a directory"):
        load_scenes(str(tmp_path / "plan.txt"), "train")
    (tmp_path / "plan.txt").unlink()
    with pytest.raises(SceneError, match="no plan files"):
        load_scenes(str(tmp_path), "train")


def test_cli_check_and_render(plan_dir, tmp_path, capsys):
    from plex_ma import scenes

    out = tmp_path / "check.json"
    rc = scenes.main(["check", str(plan_dir), "--episodes", "2", "--jobs", "1", "--json", str(out),
                      "--compare", "procgen", "--split", "val"])
    assert rc == 0
    data = json.loads(out.read_text())
    s, p = data["summaries"]
    assert (s["scenes"], s["loaded"], s["rejected"], s["crashed"]) == (3, 2, 1, 0)
    assert list(s["reasons"]) == ["parse error at line N"]
    assert set(s["repairs"]) == {"wall_ends_snapped", "doors_projected", "doors_dropped"}
    assert s["episodes"] == 4 and not s["spec_violations"]
    assert p["source"].startswith("procgen") and p["loaded"] == p["scenes"] == 16
    assert "navigable area" in capsys.readouterr().out
    rc = scenes.main(["render", str(plan_dir), "--out", str(tmp_path / "img"), "--count", "5"])
    pngs = sorted(p.name for p in (tmp_path / "img").glob("*.png"))
    assert rc == 0 and pngs == ["a_good.png", "b_good.png"]


def test_components_are_what_the_geodesic_search_connects():
    """Every cell of a navigable component is reachable from every other under the
    geodesic graph (no corner cutting), on the real test plans, whose slanted walls make
    cells that touch only at a corner. Sub-goals are snapped into the agent's component,
    so a component that joined such cells gave sub-goals the agent could not reach (a
    training run on procgen+r2v stopped with 'sub-goal unreachable after snapping')."""
    scenes = load_scenes("r2v", "test")
    bank = SceneBank([rasterize(s) for s in scenes])
    geo = Geodesics(bank)
    checked = 0
    for s, grid in enumerate(bank.grids):
        for c in np.unique(grid.component[grid.component >= 0]):
            cells = np.argwhere(grid.component == c)
            field = geo.field(s, grid.cell_center(cells[0])).reshape(grid.shape)
            assert np.all(field[tuple(cells.T)] < 1e29), f"{grid.scene_id}: component {c} is not connected"
            checked += 1
    assert checked >= len(scenes)
