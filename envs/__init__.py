"""Environments of plex-ma (installed as ``plex_ma.envs``).

* :mod:`plex_ma.envs.plex_nav_v0`: the two-agent PettingZoo AEC environment (planner, executor);
  :mod:`plex_ma.envs.plex_nav` holds its ``raw_env``, :mod:`plex_ma.envs.compat` its Box/Discrete view.
* :mod:`plex_ma.envs.pointnav`: ``gymnasium.make("plex_ma/PointNav-v0")``, the flat task (registered by
  ``import plex_ma``).
* :mod:`plex_ma.envs.vector`: batched versions of both for trainers.
* :mod:`plex_ma.envs.gym_vector`: ``gymnasium.make_vec("plex_ma/PointNav-v0", num_envs=N)``, the batched
  flat task as a gymnasium ``VectorEnv``.
* :mod:`plex_ma.envs.rules`: the one implementation of turn order, rewards and metrics.
* :mod:`plex_ma.envs.sim`: the batched indoor simulator; it knows nothing of agents.
"""

