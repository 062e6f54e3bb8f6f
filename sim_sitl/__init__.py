"""sim_sitl package."""
