"""plex-ma: PLEX (Planner and Executor for embodied learning in navigation) for PointGoal
navigation, as a two-agent PettingZoo environment with its own fast indoor simulator."""

import os as _os
import sys as _sys
import warnings as _warnings

__version__ = "0.1.0"

# torch's OpenMP threads spin while they wait (the default) and collapse torch's CPU speed
# by 10-40x as soon as anything else runs on a small machine (measured here: a 16-world
# executor forward pass took 220 ms instead of 7 ms with other jobs on the 2 cores).
# Passive waiting costs little when the machine is quiet. The OpenMP runtime reads this
# once, when torch loads it, so it must be set before torch is imported. (The simulator's
# numba kernels do not use OpenMP: envs/sim/kernels.py.)
_wait_policy_given = "OMP_WAIT_POLICY" in _os.environ
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


class OpenMPWarning(RuntimeWarning):
    """torch was imported before plex_ma, too late for plex_ma's ``OMP_WAIT_POLICY``."""


def _check_torch_came_first() -> None:
    torch = _sys.modules.get("torch")
    if _wait_policy_given or torch is None:
        return
    try:
        spinning = torch.backends.openmp.is_available() and torch.get_num_threads() > 1
    except Exception:  # a partly imported or stubbed torch: nothing to say
        return
    if spinning:
        _warnings.warn(
            "torch was imported before plex_ma, so its OpenMP threads spin while they wait; beside other busy "
            "processes that makes torch many times slower. Export OMP_WAIT_POLICY=PASSIVE (or import plex_ma "
            "before torch). The environments run at the same speed either way.", OpenMPWarning, stacklevel=3)


_check_torch_came_first()

import gymnasium as _gymnasium  # noqa: E402  (after the OpenMP setting above)

# gymnasium.make("plex_ma/PointNav-v0") and gymnasium.make_vec(...) after `import plex_ma`
if "plex_ma/PointNav-v0" not in _gymnasium.registry:
    _gymnasium.register(id="plex_ma/PointNav-v0", entry_point="plex_ma.envs.pointnav:PointNavEnv",
                        vector_entry_point="plex_ma.envs.gym_vector:PointNavGymVectorEnv")
