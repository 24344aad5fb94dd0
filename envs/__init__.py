"""Environments of plex-ma (installed as ``plex_ma.envs``).

* :mod:`plex_ma.envs.sim`: the batched indoor simulator (scenes, physics, RGB-D, geodesics,
  ego map). It knows nothing of agents.
"""
