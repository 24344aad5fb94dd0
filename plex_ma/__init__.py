"""plex-ma: PLEX (Planner and Executor for embodied learning in navigation) for PointGoal
navigation, as a two-agent PettingZoo environment with its own fast indoor simulator."""

import os as _os
import sys as _sys

__version__ = "0.1.0"

# plex_ma's own commands (``python -m plex_ma.train`` and the rest) make torch's OpenMP
# threads wait passively: spinning threads slow torch many times over as soon as anything
# else runs on a small machine (docs/performance.md). The runtime reads this once, when torch
# loads it, so only the program can choose it; a plain ``import plex_ma`` leaves torch as it
# is, and the order of imports does not matter (the simulator does not use OpenMP).
def _run_as_command() -> bool:
    """True while ``python [options] -m plex_ma.<module>`` imports this package
    (``sys.argv[0]`` is ``-m`` while the module is located; ``sys.orig_argv`` names it)."""
    if _sys.argv[:1] != ["-m"]:
        return False
    args = iter(getattr(_sys, "orig_argv", [])[1:])
    for arg in args:
        if arg == "--check-hash-based-pycs":  # the one long option with a value
            next(args, None)
        elif arg.startswith("-") and not arg.startswith("--"):
            for i, flag in enumerate(arg[1:], 2):  # short flags, combined as in -um
                if flag in "mcWX":  # the flags with a value: in the rest of arg, or next
                    value = arg[i:] or next(args, "")
                    if flag in "mc":
                        return flag == "m" and value.split(".")[0] == "plex_ma"
                    break
    return False


_set_wait_policy = _run_as_command() and "OMP_WAIT_POLICY" not in _os.environ  # kept for `bench order`
if _set_wait_policy:
    _os.environ["OMP_WAIT_POLICY"] = "PASSIVE"

import gymnasium as _gymnasium  # noqa: E402

# gymnasium.make("plex_ma/PointNav-v0") and gymnasium.make_vec(...) after `import plex_ma`
if "plex_ma/PointNav-v0" not in _gymnasium.registry:
    _gymnasium.register(id="plex_ma/PointNav-v0", entry_point="plex_ma.envs.pointnav:PointNavEnv",
                        vector_entry_point="plex_ma.envs.gym_vector:PointNavGymVectorEnv")
