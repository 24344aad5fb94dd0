"""plex-ma: PLEX (Planner and Executor for embodied learning in navigation) for PointGoal
navigation, as a two-agent PettingZoo environment with its own fast indoor simulator."""

import os as _os

__version__ = "0.1.0"

# OpenMP threads that spin while waiting (the default) collapse torch's CPU speed by 10-40x
# as soon as anything else runs on a small machine (measured here: a 16-world executor
# forward pass took 220 ms instead of 7 ms with other jobs on the 2 cores). Passive waiting
# costs little when the machine is quiet. Must be set before torch or numba start OpenMP.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import gymnasium as _gymnasium  # noqa: E402  (after the OpenMP setting above)

# gymnasium.make("plex_ma/PointNav-v0") and gymnasium.make_vec(...) after `import plex_ma`
if "plex_ma/PointNav-v0" not in _gymnasium.registry:
    _gymnasium.register(id="plex_ma/PointNav-v0", entry_point="plex_ma.envs.pointnav:PointNavEnv",
                        vector_entry_point="plex_ma.envs.gym_vector:PointNavGymVectorEnv")
