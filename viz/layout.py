"""What a PLEX recording holds and how it is shown: entity paths, colours, the blueprint.

:data:`ENTITY_TABLE` is the one list of the entity paths every recording uses (stable;
positions are world metres, ``x`` east, ``y`` north); :data:`ENTITY_PATHS` maps each path
to what it shows. The "Entity paths" table of ``docs/viz.md`` is its rendering:

    python -m plex_ma.viz.layout        # prints the table as markdown

The helpers here are pure: they turn ego maps, polar vectors and ELIs into what is logged.
"""

from __future__ import annotations

import math

import numpy as np
import rerun.blueprint as rrb

APPLICATION_ID = "plex_ma"
TIMELINE = "step"  # executor actions since the episode began
TRAIN_TIMELINE = "train_step"  # training environment steps
ELI_PROJECTION_SEED = 20240601

# (entity path, rerun type, what it shows), in the order of the docs' table.
ENTITY_TABLE: tuple[tuple[str, str, str], ...] = (
    ("world", "Transform3D, static", "flips `y` so that north is up in 2-D views"),
    ("world/map", "Image + Transform3D, static",
     "the scene's top-down map (`topdown_view` without the path), placed in metres"),
    ("world/start", "Points2D, static", "start position"),
    ("world/goal", "Points2D, static", "end goal"),
    ("world/agent", "Points2D", "the agent's position"),
    ("world/agent/heading", "Arrows2D", "its heading (0.5 m long)"),
    ("world/path", "LineStrips2D", "the path so far"),
    ("world/collisions", "Points2D", "every place a move was blocked so far"),
    ("world/subgoal", "Points2D",
     "the active sub-goal, snapped to the nearest reachable point (labelled `#k`)"),
    ("world/subgoal_raw", "Points2D", "the active sub-goal as the planner proposed it"),
    ("world/subgoals", "Points2D", "every snapped sub-goal proposed so far, coloured by `k`"),
    ("world/subgoals_raw", "Points2D", "every raw sub-goal proposed so far, coloured by `k`"),
    ("world/subgoal_line", "LineStrips2D", "the agent to the active sub-goal"),
    ("planner/ego_map", "Image",
     ("the planner's ego map, the observation it decides on, logged whenever the planner is to act "
      "(32 x 32: obstacles red, explored floor light, unknown dark; row 0 straight ahead)")),
    ("planner/ego_map/agent", "Points2D", "the agent on the ego map (pixel coordinates)"),
    ("planner/ego_map/goal", "Points2D", "the end goal on the ego map, clamped to its border"),
    ("planner/ego_map/subgoal", "Points2D", "the sub-goal the planner proposed from this map"),
    ("planner/subgoal_index", "Scalars", "index `k` of the sub-goal each executor step served (-1: none)"),
    ("executor/rgb", "Image (EncodedImage if JPEG)", "the executor's RGB image"),
    ("executor/depth", "DepthImage", "its depth image (millimetres as uint16)"),
    ("eli/tensor", "Tensor (128)", "the ELI the executor sent at this step"),
    ("eli/projection", "Points2D",
     ("every ELI of the episode so far through one fixed random orthonormal projection to 2-D (the same "
      "in every recording), coloured by sub-goal index, the latest one larger")),
    ("eli/pca", "Points2D, static",
     ("the episode's ELIs on their first two principal components (in units of the first one's standard "
      "deviation), dark (first step) to yellow (last); logged at the end")),
    ("eli/episode", "Tensor (steps, 128), static",
     "all of the episode's ELIs, one row per executor step; logged at the end"),
    ("reward/planner", "Scalars", "the planner's reward of each step"),
    ("reward/executor", "Scalars", "the executor's reward of each step"),
    ("reward/agent", "Scalars", "the flat baselines' reward of each step (instead of the two above)"),
    ("metrics/distance_to_goal", "Scalars", "geodesic distance to the end goal (m)"),
    ("metrics/collisions", "Scalars", "collisions so far"),
    ("metrics/success", "Scalars", "success at the episode's end (0/1)"),
    ("metrics/spl", "Scalars", "SPL at the episode's end"),
    ("events", "TextLog", "sub-goals, executor STOPs (reached or not) and the episode's end"),
    ("episode", "TextDocument, static", "scene, episode id, geodesic distance and the result"),
    ("train/<key>", "Scalars",
     ("training metrics (`train/metrics/success`, `train/learner/executor_policy_loss`, `train/perf/fps`, "
      "...) on the `train_step` timeline (environment steps)")),
)
ENTITY_PATHS: dict[str, str] = {path: what for path, _, what in ENTITY_TABLE}

# Colours (RGB).
GOAL = (220, 30, 30)
START = (30, 30, 200)
AGENT = (20, 160, 60)
PATH = (30, 110, 230)
SUBGOAL = (250, 160, 0)
SUBGOAL_RAW = (230, 120, 0)
COLLISION = (160, 0, 160)
PALETTE = np.array([(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189),
                    (140, 86, 75), (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207)], np.uint8)


def entity_table_markdown() -> str:
    """:data:`ENTITY_TABLE` as the markdown table of ``docs/viz.md``."""
    lines = ["| entity path | what | type |", "|---|---|---|"]
    lines += [f"| `{path}` | {what} | {kind} |" for path, kind, what in ENTITY_TABLE]
    return "\n".join(lines) + "\n"


def default_blueprint(map_extent: tuple[float, float, float, float] | None = None) -> rrb.Blueprint:
    """The layout sent with every recording: the top-down map with path and sub-goals on the
    left above the plots; the ego map, RGB and depth, the ELI and the event log on the right.

    ``map_extent`` (x_min, x_max, y_min, y_max in world metres) zooms the map view onto the
    scene (sub-goals proposed outside it are then off screen until one zooms out)."""
    bounds = None
    if map_extent is not None:
        x0, x1, y0, y1 = map_extent
        bounds = rrb.VisualBounds2D(x_range=[x0, x1], y_range=[-y1, -y0])  # the view shows y flipped
    top_down = rrb.Spatial2DView(name="Top-down map (world)", origin="/", contents=["world/**"],
                                 visual_bounds=bounds)
    plots = rrb.Tabs(
        rrb.TimeSeriesView(name="Rewards", origin="reward"),
        rrb.TimeSeriesView(name="Distance to goal", origin="metrics/distance_to_goal"),
        rrb.TimeSeriesView(name="Collisions", origin="metrics/collisions"),
        rrb.TimeSeriesView(name="Sub-goal index", origin="planner/subgoal_index"),
        rrb.TimeSeriesView(name="Training (timeline train_step)", origin="train"),
    )
    images = rrb.Horizontal(
        rrb.Spatial2DView(name="Planner ego map", origin="planner/ego_map"),
        rrb.Spatial2DView(name="Executor RGB", origin="executor/rgb"),
        rrb.Spatial2DView(name="Executor depth", origin="executor/depth"),
    )
    eli = rrb.Tabs(
        rrb.Spatial2DView(name="ELI projection", origin="eli/projection",  # fixed axes: comparable across runs
                          visual_bounds=rrb.VisualBounds2D(x_range=[-4.0, 4.0], y_range=[-4.0, 4.0])),
        rrb.Spatial2DView(name="ELI PCA (episode)", origin="eli/pca",
                          visual_bounds=rrb.VisualBounds2D(x_range=[-4.0, 4.0], y_range=[-4.0, 4.0])),
        rrb.TensorView(name="ELI tensor", origin="eli/tensor"),
    )
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(top_down, plots, row_shares=[3, 2]),
            rrb.Vertical(images, eli, rrb.TextLogView(name="Events", origin="events"), row_shares=[2, 2, 1]),
            column_shares=[3, 2],
        ),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="expanded", timeline=TIMELINE),
    )


def ego_map_rgb(ego: np.ndarray) -> np.ndarray:
    """(..., 2, S, S) ego maps (obstacles, explored floor in [0, 1]) -> (..., S, S, 3) uint8
    pictures: obstacles red, explored floor light, the rest dark."""
    obs = np.clip(ego[..., 0, :, :], 0, 1)[..., None]
    free = np.clip(ego[..., 1, :, :], 0, 1)[..., None]
    img = np.array([60, 60, 66], np.float32) * (1 - free) + np.array([225, 225, 220], np.float32) * free
    img = img * (1 - obs) + np.array([205, 55, 40], np.float32) * obs
    return img.astype(np.uint8)


def ego_pixel(polar: np.ndarray, size: int, cell: float, clamp: bool = True) -> np.ndarray:
    """(distance m, direction rad) from the agent -> (u, v) on the ego map (column, row): the
    agent sits at the centre, row 0 is straight ahead and column 0 to the agent's left."""
    rho, th = float(polar[0]), float(polar[1])
    fwd, left = rho * math.cos(th), rho * math.sin(th)
    u, v = size / 2 - left / cell, size / 2 - fwd / cell
    if clamp:
        u, v = min(max(u, 0.0), float(size)), min(max(v, 0.0), float(size))
    return np.array([u, v], np.float32)


def eli_projection_matrix(dim: int = 128, seed: int = ELI_PROJECTION_SEED) -> np.ndarray:
    """A fixed (dim, 2) orthonormal projection, the same in every recording."""
    q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(dim, 2)))
    return q.astype(np.float32)


def pca_2d(x: np.ndarray) -> np.ndarray:
    """(T, D) -> (T, 2) coordinates on the first two principal components, in units of the
    first one's standard deviation (zeros if the points hardly vary)."""
    x = np.asarray(x, np.float64)
    out = np.zeros((len(x), 2), np.float32)
    if len(x) < 2:
        return out
    xc = x - x.mean(0)
    if not np.any(xc):
        return out
    _, _, vt = np.linalg.svd(xc, full_matrices=False)
    k = min(2, vt.shape[0])
    y = xc @ vt[:k].T
    sd = y[:, 0].std()
    if sd < 1e-6:
        return out
    out[:, :k] = (y / sd).astype(np.float32)
    return out


def time_colours(n: int) -> np.ndarray:
    """(n, 3) uint8 colours from dark blue through green to yellow, one per point in time."""
    t = np.linspace(0, 1, max(n, 1))[:, None]
    a, b, c = np.array([68, 1, 84]), np.array([33, 145, 140]), np.array([253, 231, 37])
    col = np.where(t < 0.5, a + (b - a) * (t / 0.5), b + (c - b) * ((t - 0.5) / 0.5))
    return col[:n].astype(np.uint8)


__all__ = ["APPLICATION_ID", "ENTITY_PATHS", "ENTITY_TABLE", "TIMELINE", "TRAIN_TIMELINE", "default_blueprint",
           "ego_map_rgb", "ego_pixel", "eli_projection_matrix", "entity_table_markdown", "pca_2d", "time_colours"]


if __name__ == "__main__":
    print(entity_table_markdown(), end="")
