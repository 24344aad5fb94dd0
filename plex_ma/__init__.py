"""plex-ma: PLEX (Planner and Executor for embodied learning in navigation) for PointGoal
navigation, as a two-agent PettingZoo environment with its own fast indoor simulator."""

__version__ = "0.1.0"


def _register() -> None:
    import gymnasium

    if "plex_ma/PointNav-v0" not in gymnasium.registry:
        gymnasium.register(id="plex_ma/PointNav-v0", entry_point="plex_ma.envs.pointnav:PointNavEnv")


_register()
