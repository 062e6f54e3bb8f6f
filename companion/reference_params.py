"""The reference velocity's gains and safety limits (:class:`ReferenceParams`, the ``reference:`` section of
configs/companion.yaml), shared by the stages of eqs. (2)-(8): :mod:`companion.operator_input`,
:mod:`companion.obstacle_points`, :mod:`companion.avoidance`, :mod:`companion.vertical_limits`, and their
composition, :func:`companion.reference.reference_velocity`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from companion.vertical_limits import VerticalParams
from quadlink.safety import SAFE_DISTANCE_M


@dataclass(frozen=True)
class ReferenceParams:
    """Gains and safety limits of the reference velocity.

    k_v_m_s: horizontal speed at full handle deflection (eq. 2); k_climb_m_s: climb speed at full
    deflection; k_psi_rad_s: yaw rate at full deflection (eq. 3). Repulsion (eq. 7): eta gain
    [m^3/s], influence distance d_0, limit on |v_o|, how the points' contributions combine (``weighted``:
    the paper's weighted sum, see :func:`companion.avoidance.repulsion_velocity`; ``sum``: plain
    superposition); safe distance (paper Fig. 8: 0.45 m) inside which the reference has no component
    toward the obstacle. The default eta = 0.13 m^3/s makes one obstacle cancel the full-deflection push
    (k_v = 0.6 m/s) at 0.47 m, so a vehicle pushed at an obstacle comes to rest just outside the safe
    distance; ``approach_gain_per_s`` bounds the closing speed toward points within d_0 to gain x (d - safe
    distance) so it gets there without coasting through (see
    :func:`companion.avoidance.limit_speed_toward_obstacles`). ``horizontal_only``:
    repulsion and the safe distance act in the horizontal plane, on the points within
    ``vertical_band_m`` of the vehicle's height (the camera looks down, so it samples tall obstacles
    mostly below the vehicle: in 3D their sum would push the vehicle up, and the floor is not an
    obstacle to horizontal motion); False is the paper's 3D form. The band is as tall as the safe distance:
    near a wall the camera, blind within its minimum range, sees only the wall's lower part (0.45 m from a
    wall, nothing higher than ~0.39 m below the vehicle), and a point just below a narrower band, taken in
    3D, let the vehicle close to 0.30 m of the wall it samples (CI, corner push: sqrt(0.45^2 - 0.32^2)); a
    point within the safe distance of the vehicle's height is nearer than the safe distance in 3D whenever
    the vehicle is over it, so projecting it costs no passage the safe distance allows. When the height above
    the take-off floor is known, points within ``floor_margin_m`` of the floor are the floor, not obstacles (a low
    vehicle sees the floor ahead at its own height: repelled by it, it would back away blindly).

    Safety constraints (issue 14): ``stopping_time_s`` is the distance the vehicle travels, per m/s of its
    speed, after its reference drops to zero — the bridge's velocity loop (PI, time constant ~0.5 s, with
    its integral's overshoot: ~0.7 s in a closed-loop simulation of the real tracker) plus the
    camera-to-setpoint latency; the closing-speed bound toward a point counts the measured closing speed
    times this time as distance already used up (see :func:`companion.avoidance.limit_speed_toward_obstacles`).
    ``surface_gap_m``: neighbouring map points closer than this are taken as one surface and the segment
    between them constrains the motion (the camera samples a wall with one point per image sector:
    between two samples 0.5 m apart a vehicle kept 0.45 m from both is only 0.37 m from the wall;
    bridging gaps narrower than twice the safe distance forbids no passage the vehicle could take).
    ``out_of_band_3d``: points outside the height band (a box top below the vehicle, a ceiling point
    above it) constrain the motion by their 3D distance instead of being ignored. Vertical limits
    (:mod:`companion.vertical_limits`): ``max_height_m`` above the take-off floor (an altitude fence),
    ``room_height_m`` (the ceiling as the operator entered it, kept ``safe_distance_m`` away and
    ``room_height_error_m`` more, the entry's possible error; with no entry, ``assumed_room_height_m``, the lowest
    ceiling the stack assumes: the camera looks down and never sees the ceiling, and a 2.0 m altitude fence in a
    2.0-2.1 m room left the falsifier's vehicles 0.10 m from it; None relies on the fence alone),
    ``floor_min_height_m`` (the lowest
    height the reference descends to; take-off and landing are the autopilot's). ``takeoff_height_m``:
    height of the vehicle's origin above the floor when it stands on it (its landing gear):
    :func:`companion.reference.reference_velocity`'s ``height_m`` is the odometry's, counted from the
    take-off pose, held to the floor the camera sees with ``floor_height_time_constant_s``
    (:mod:`companion.height`; 0: the odometry's alone); without a floor seen for ``height_fix_max_age_s`` the
    height is not verified and the vehicle does not climb toward a configured ceiling. ``map_drift_m_s``: the
    velocity error the odometry may keep up; every map point counts as this much nearer per second since the
    camera last saw it (:func:`companion.obstacle_points.drifted_toward`; 0: off).
    """

    k_v_m_s: float = 0.6
    k_climb_m_s: float = 0.4
    k_psi_rad_s: float = 0.8
    deadband: float = 0.03
    combine: Literal["weighted", "sum"] = "weighted"
    repulsion_gain_m3_s: float = 0.13
    influence_distance_m: float = 0.9
    max_repulsion_m_s: float = 1.0
    safe_distance_m: float = SAFE_DISTANCE_M
    approach_gain_per_s: float = 1.2
    max_speed_m_s: float = 1.5
    unknown_sector_guard_rad: float = math.radians(15.0)
    horizontal_only: bool = True
    vertical_band_m: float = 0.45
    floor_margin_m: float = 0.15
    stopping_time_s: float = 0.8
    surface_gap_m: float = 0.9
    out_of_band_3d: bool = True
    max_height_m: float | None = None
    room_height_m: float | None = None
    room_height_error_m: float = 0.10
    assumed_room_height_m: float | None = None   # configs/companion.yaml ships 2.0
    floor_min_height_m: float = 0.3
    takeoff_height_m: float = 0.0
    floor_height_time_constant_s: float = 0.5
    height_fix_max_age_s: float = 4.0
    map_drift_m_s: float = 0.01

    def vertical(self) -> VerticalParams:
        """The vertical limits' parameters (:mod:`companion.vertical_limits`), sharing the safe distance and
        the closing-speed law."""
        # no entry: the lowest ceiling assumed (a lower bound, so no entry error on it)
        entered = self.room_height_m is not None
        room = self.room_height_m if entered else self.assumed_room_height_m
        return VerticalParams(self.max_height_m, room, self.safe_distance_m, self.floor_min_height_m,
                              self.approach_gain_per_s if math.isfinite(self.approach_gain_per_s) else 1.2,
                              self.stopping_time_s, self.room_height_error_m if entered else 0.0)
