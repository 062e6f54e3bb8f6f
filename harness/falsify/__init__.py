"""Falsification (issue 31): search the flight space for the lowest clearance (``quadlink falsify``).

``space`` the typed, bounded flight space and its deterministic mapping to flight files; ``objective`` the one
function that judges a flown flight; ``search`` the Optuna ask/tell loop over the campaign runner's Ray pool;
``report`` the report of a study; ``export`` a finding as a regression flight; ``cli`` the command.
"""
