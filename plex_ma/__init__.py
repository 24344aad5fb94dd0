"""plex-ma: PLEX (Planner and Executor for embodied learning in navigation) for PointGoal
navigation, as a two-agent PettingZoo environment with its own fast indoor simulator."""

__version__ = "0.1.0"
