"""Flight campaigns (issue 15): randomized flights of the whole stack on Ray, and their statistics.

``draws`` (every random choice of a flight, from its seed), ``sessions`` (operator sessions),
``offboard_client`` (a MAVSDK-style scripted operator), ``safety`` (the minimum true distance to walls,
obstacles and the ceiling), ``runner`` (Ray), ``report`` (campaign.json, campaign.png), ``cli``; paper 003's
experiments as campaigns (issue 19): ``experiments`` (their draws), ``experiment_flight``, ``experiment_report``.
The arenas come from :mod:`sim_sitl.scenario_gen`.
"""

from harness.campaign.cli import command

__all__ = ["command"]
