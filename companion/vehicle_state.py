"""What the companion knows of the autopilot from its HEARTBEAT and EXTENDED_SYS_STATE."""

from __future__ import annotations

import logging
from dataclasses import dataclass

from companion.modes import VehicleStatus
from quadlink.mavlink import mavlink
from quadlink.px4_modes import Px4AutoSubMode, Px4MainMode, decode_custom_mode

log = logging.getLogger("companion.daemon")


@dataclass
class VehicleState:
    armed: bool = False
    landed_state: int | None = None
    custom_mode: int = 0
    heartbeat_wall_s: float | None = None

    def on_heartbeat(self, base_mode: int, custom_mode: int, now_s: float) -> None:
        """The autopilot's HEARTBEAT fields, received at ``now_s`` (monotonic)."""
        armed = bool(base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
        if armed != self.armed:
            log.info("autopilot %s", "armed" if armed else "disarmed")
        self.armed = armed
        self.custom_mode = custom_mode
        self.heartbeat_wall_s = now_s

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
