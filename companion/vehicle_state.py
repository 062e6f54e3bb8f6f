"""What the companion knows of the autopilot from its HEARTBEAT, EXTENDED_SYS_STATE and ALTITUDE."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

from companion.modes import VehicleStatus
from quadlink.mavlink import mavlink
from quadlink.px4_modes import Px4AutoSubMode, Px4MainMode, decode_custom_mode

log = logging.getLogger("companion.daemon")

BARO_HEIGHT_MAX_AGE_S = 0.5   # an ALTITUDE older than this is not the vehicle's height any more
BARO_GROUND_MEAN_SAMPLES = 20  # the baro's ground reference: the mean of up to this many ALTITUDEs (1 s at 20 Hz)


@dataclass
class VehicleState:
    armed: bool = False
    landed_state: int | None = None
    custom_mode: int = 0
    heartbeat_wall_s: float | None = None
    baro_height_m: float | None = None      # ALTITUDE.altitude_relative: the autopilot's barometer-fused height
    baro_height_s: float | None = None      # when it came (monotonic)
    # ALTITUDE.altitude_monotonic: the board's own barometric altitude (never re-referenced), and its value when the
    # vehicle was last on the ground (None: not seen on the ground since the companion started)
    baro_monotonic_m: float | None = None
    baro_monotonic_ground_m: float | None = None
    baro_ground_samples: int = 0            # of this stay on the ground (0 in the air): the reference's mean

    def on_heartbeat(self, base_mode: int, custom_mode: int, now_s: float) -> None:
        """The autopilot's HEARTBEAT fields, received at ``now_s`` (monotonic)."""
        armed = bool(base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
        if armed != self.armed:
            log.info("autopilot %s", "armed" if armed else "disarmed")
        self.armed = armed
        self.custom_mode = custom_mode
        self.heartbeat_wall_s = now_s

    def on_altitude(self, altitude_relative_m: float, now_s: float, altitude_monotonic_m: float = math.nan) -> None:
        """The autopilot's ALTITUDE at ``now_s``: its barometer-fused height above the take-off spot and its
        board's own barometric altitude (NaN: none). On the ground the latter is the take-off's reference."""
        h = float(altitude_relative_m)
        self.baro_height_m = h if math.isfinite(h) else None
        m = float(altitude_monotonic_m)
        self.baro_monotonic_m = m if math.isfinite(m) else None
        if self.status().in_air:
            self.baro_ground_samples = 0
        elif self.baro_monotonic_m is not None:
            # the mean of the last BARO_GROUND_MEAN_SAMPLES on the ground (the board's altitude jitters by centimetres;
            # one sample would be the reference's error), restarted at each landing (the baro drifted in the flight)
            n = self.baro_ground_samples = min(self.baro_ground_samples + 1, BARO_GROUND_MEAN_SAMPLES)
            prev = self.baro_monotonic_ground_m if n > 1 and self.baro_monotonic_ground_m is not None \
                else self.baro_monotonic_m
            self.baro_monotonic_ground_m = prev + (self.baro_monotonic_m - prev) / n
        self.baro_height_s = now_s

    def baro_height(self, now_s: float) -> float | None:
        """The height above the take-off spot the autopilot's barometer gives, for the ceiling: the higher of its
        fused height (whose reference follows the odometry's height in the air, BRG_BARO_REF_T) and the board's own
        altitude since the vehicle was last on the ground (which follows nothing), if they came within
        BARO_HEIGHT_MAX_AGE_S of ``now_s``; None without either."""
        if self.baro_height_s is None or now_s - self.baro_height_s > BARO_HEIGHT_MAX_AGE_S:
            return None
        heights = [self.baro_height_m] if self.baro_height_m is not None else []
        if self.baro_monotonic_m is not None and self.baro_monotonic_ground_m is not None and self.status().in_air:
            heights.append(self.baro_monotonic_m - self.baro_monotonic_ground_m)
        return max(heights) if heights else None

    def status(self) -> VehicleStatus:
        px4 = decode_custom_mode(self.custom_mode)
        auto = px4.main == Px4MainMode.AUTO
        if self.landed_state is not None and self.landed_state != mavlink.MAV_LANDED_STATE_UNDEFINED:
            in_air = self.landed_state in (mavlink.MAV_LANDED_STATE_IN_AIR, mavlink.MAV_LANDED_STATE_TAKEOFF,
                                           mavlink.MAV_LANDED_STATE_LANDING)
        else:
            in_air = self.armed
        taking_off = (self.landed_state == mavlink.MAV_LANDED_STATE_TAKEOFF
                      or (auto and px4.sub == Px4AutoSubMode.TAKEOFF))
        landing = self.landed_state == mavlink.MAV_LANDED_STATE_LANDING or (auto and px4.sub == Px4AutoSubMode.LAND)
        return VehicleStatus(self.armed, in_air, taking_off, landing, self.landed_state is not None)
