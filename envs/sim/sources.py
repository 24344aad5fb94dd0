"""Scene sources and splits: which scenes a ``scenes=`` / ``split=`` pair means.

``scenes="procgen"`` (the default) gives procedural houses; ``"r2v"`` the real floor plans;
a directory, the plans in it; ``"procgen+r2v"`` a mix (``num_scenes`` applies to each part). Each split draws from its own
seed stream, so the train, val and test splits never share a house; by default they
hold 72, 16 and 16 scenes (the paper's 72 train / 16 test shape), and any number can be
asked for. :data:`SOURCES` is the registry of named sources.
"""

from __future__ import annotations

import os
import zlib
from functools import lru_cache
from pathlib import Path
from typing import Callable

import numpy as np

from . import r2v
from .bank import SceneBank
from .procgen import generate_house
from .scene import Scene, SceneError, SceneGrid, rasterize

SPLITS = ("train", "val", "test")
DEFAULT_NUM_SCENES = {"train": 72, "val": 16, "test": 16}
_SPLIT_CODE = {"train": 1, "val": 2, "test": 3}


def procgen_seed(split: str, index: int) -> int:
    """The house seed of scene ``index`` of a procedural split (disjoint across splits)."""
    return int(np.random.SeedSequence([_SPLIT_CODE[split], int(index)]).generate_state(1, np.uint32)[0])


def procgen_scenes(split: str, num_scenes: int | None = None) -> list[Scene]:
    n = DEFAULT_NUM_SCENES[split] if num_scenes is None else num_scenes
    return [generate_house(procgen_seed(split, i), scene_id=f"procgen-{split}-{i:05d}") for i in range(n)]


def open_room_scenes(split: str, num_scenes: int | None = None) -> list[Scene]:
    """Empty rectangular rooms (8-10 m), for debugging and for training the executor alone."""
    out = []
    for i in range(1 if num_scenes is None else num_scenes):
        rng = np.random.default_rng(procgen_seed(split, i))
        w, h = (round(float(rng.uniform(8.0, 10.0)), 1) for _ in range(2))
        walls = [(0, 0, w, 0), (w, 0, w, h), (w, h, 0, h), (0, h, 0, 0)]
        out.append(Scene(scene_id=f"open-room-{split}-{i:05d}", walls=np.array(walls), source="open-room"))
    return out


#: The named scene sources: each maps (split, num_scenes) to scenes. A name that is not
#: here is read as a directory of floor plans (:func:`.r2v.directory_scenes`).
SOURCES: dict[str, Callable[[str, int | None], list[Scene]]] = {"procgen": procgen_scenes,
                                                                "open-room": open_room_scenes,
                                                                "r2v": r2v.r2v_scenes}


def check_split(split: str) -> None:
    if split not in SPLITS:
        raise ValueError(f"split must be one of {SPLITS}, got {split!r}")


def load_scenes(scenes: str = "procgen", split: str = "train", num_scenes: int | None = None) -> list[Scene]:
    """The scenes of ``split`` from source ``scenes`` (a source name or a directory)."""
    check_split(split)
    if num_scenes is not None and (not isinstance(num_scenes, (int, np.integer)) or num_scenes < 1):
        raise ValueError(f"num_scenes must be a positive integer or None, got {num_scenes!r}")
    if "+" in scenes:  # a mix, e.g. "procgen+r2v": each part's scenes of this split
        parts = [p for p in scenes.split("+") if p]
        if len(parts) < 2:
            raise ValueError(f"scene mix {scenes!r} needs at least two sources joined by '+'")
        return [sc for p in parts for sc in load_scenes(p, split, num_scenes)]
    if scenes in SOURCES:
        return SOURCES[scenes](split, num_scenes)
    found = r2v.directory_scenes(scenes, split, num_scenes)
    if found is not None:
        return found
    known = f"a scene source is one of {sorted(SOURCES)}, a directory of plan files, or sources joined by '+'"
    path = Path(scenes).expanduser()
    if path.exists():
        raise SceneError(f"scene directory {scenes!r} is not a directory ({known})")
    if os.sep in scenes or scenes.startswith((".", "~")):
        raise SceneError(f"scene directory {scenes!r} does not exist ({known})")
    raise SceneError(f"unknown scene source {scenes!r}; {known}")


@lru_cache(maxsize=16)
def _bank(scenes: str, split: str, num_scenes: int | None) -> SceneBank:
    grids: list[SceneGrid] = []
    for sc in load_scenes(scenes, split, num_scenes):
        grids.append(rasterize(sc, seed=_colour_seed(sc.scene_id)))
    if not grids:
        raise SceneError(f"scene source {scenes!r} split {split!r} has no usable scenes")
    return SceneBank(grids)


def _colour_seed(scene_id: str) -> int:
    return zlib.crc32(scene_id.encode())


def scene_bank(scenes: str = "procgen", split: str = "train", num_scenes: int | None = None) -> SceneBank:
    """The rasterised scene bank of a source and split (cached per process)."""
    check_split(split)
    return _bank(str(scenes), split, num_scenes)
