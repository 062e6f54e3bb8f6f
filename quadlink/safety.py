"""The safety promise's two distances, defined once for the companion's law and for the judge (issue 28).

``SAFE_DISTANCE_M``: the companion's reference keeps no velocity component toward an obstacle inside it (paper 000,
Fig. 8: 0.45 m, centre of mass to surface). ``CLEARANCE_BOUND_M``: what the judge holds every flight to (the
minimum true clearance to every non-floor surface); the 5 cm between them is the tracking error's room. A clearance
bound is never widened.
"""

from __future__ import annotations

SAFE_DISTANCE_M = 0.45
CLEARANCE_BOUND_M = 0.40
