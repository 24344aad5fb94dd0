"""Scene sources: mixes and the open-room source."""

import pytest

from plex_ma.envs.sim import load_scenes, scene_bank


def test_mix_concatenates_sources_of_the_split():
    mix = load_scenes("procgen+open-room", "val", 2)
    assert [s.scene_id for s in mix] == ["procgen-val-00000", "procgen-val-00001", "open-room-val-00000",
                                         "open-room-val-00001"]
    with pytest.raises(ValueError, match="two sources"):
        load_scenes("procgen+", "val")
    with pytest.raises(ValueError, match="unknown scene source"):
        load_scenes("procgen+nonsense", "val")


def test_open_room_is_one_empty_room():
    bank = scene_bank("open-room", "test", 1)
    g = bank.grids[0]
    assert g.num_rooms == 1 and 60 <= g.navigable_area() <= 100
    assert int(g.component.max()) == 0  # one connected navigable region
