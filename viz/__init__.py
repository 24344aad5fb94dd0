"""Rerun recordings of PLEX episodes (``plex_ma.viz``), in four modules:

- :mod:`plex_ma.viz.layout`: the entity paths every recording uses
  (:data:`~plex_ma.viz.layout.ENTITY_TABLE`), colours, the default blueprint and pure helpers.
- :mod:`plex_ma.viz.rerun_io`: the rerun stream helpers and the rerun-file plumbing
  (:func:`merge_rrd`, :func:`send_training_scalars`, ...).
- :mod:`plex_ma.viz.recorder`: :class:`EpisodeRecorder`, which follows one world of a
  vector env into an ``.rrd`` file.
- :mod:`plex_ma.viz.training`: :func:`record_training_episode`, the trainers' recording hook.

``docs/viz.md`` describes the recordings, the commands that make them and the viewer layout.
"""

from __future__ import annotations

from .layout import (APPLICATION_ID, ENTITY_PATHS, TIMELINE, TRAIN_TIMELINE, default_blueprint, ego_map_rgb,
                     ego_pixel, eli_projection_matrix, pca_2d)
from .recorder import EpisodeRecorder
from .rerun_io import merge_rrd, rerun_executable, send_training_scalars
from .training import record_training_episode

__all__ = ["APPLICATION_ID", "ENTITY_PATHS", "EpisodeRecorder", "TIMELINE", "TRAIN_TIMELINE", "default_blueprint",
           "ego_map_rgb", "ego_pixel", "eli_projection_matrix", "merge_rrd", "pca_2d", "record_training_episode",
           "rerun_executable", "send_training_scalars"]
