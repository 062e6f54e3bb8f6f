"""Trajectories through waypoints (pure): the minimum-snap generator of paper 003 ("Autonomous Navigation")."""

from quadlink.trajectory.minsnap import (
    MinSnapTrajectory,
    TrajectorySample,
    allocate_times_proportional,
    minimum_snap,
)

__all__ = ["MinSnapTrajectory", "TrajectorySample", "allocate_times_proportional", "minimum_snap"]
