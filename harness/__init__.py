"""The tools floor: what starts processes and judges them (demo, campaign, paper 003's experiments, netem,
the trajectory streamer, reports). It may import every floor below (``sim_sitl``, ``firmware_bridge``,
``companion``, ``teleop``, ``perception``, ``quadlink``); nothing below imports it."""
