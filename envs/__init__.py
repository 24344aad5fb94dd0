"""Environments of plex-ma (installed as ``plex_ma.envs``).

* :mod:`plex_ma.envs.plex_nav_v0`: the two-agent PettingZoo AEC environment (planner, executor).
* :mod:`plex_ma.envs.pointnav`: ``gymnasium.make("plex_ma/PointNav-v0")``, the flat task.
* :mod:`plex_ma.envs.vector`: batched versions of both for trainers.
* :mod:`plex_ma.envs.gym_vector`: ``gymnasium.make_vec("plex_ma/PointNav-v0", num_envs=N)``, the batched
  flat task as a gymnasium ``VectorEnv``.
* :mod:`plex_ma.envs.rules`: the one implementation of turn order, rewards and metrics.
* :mod:`plex_ma.envs.sim`: the batched indoor simulator; it knows nothing of agents.
"""

import gymnasium

if "plex_ma/PointNav-v0" not in gymnasium.registry:
    gymnasium.register(id="plex_ma/PointNav-v0", entry_point="plex_ma.envs.pointnav:PointNavEnv",
                       vector_entry_point="plex_ma.envs.gym_vector:PointNavGymVectorEnv")
