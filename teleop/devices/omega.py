"""Force Dimension omega.x / delta.x / sigma.x through the ``forcedimension-core`` bindings.

The SDK frame (x toward the operator, y right, z up) is turned into D (NED: x forward, y right,
z down) by ``R_D_FD = diag(-1, 1, -1)``, applied to positions, velocities and forces alike.
Button 0 toggles pan-scan, button 1 (if any) is take-off/land alternately.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
from numpy.typing import NDArray

from quadlink.errors import LinkError
from teleop.devices.base import DeviceState, HapticDevice

log = logging.getLogger(__name__)

R_D_FD = np.array([-1.0, 1.0, -1.0])  # diagonal


def _import_dhd() -> Any:
    try:
        from forcedimension_core import dhd
    except ImportError as exc:
        raise LinkError("--device omega needs the Python package 'forcedimension-core' and the Force Dimension "
                        f"SDK (pip install 'quadlink[haptic]'): {exc}") from exc
    except OSError as exc:  # bindings present, SDK shared library missing
        raise LinkError(f"--device omega: the Force Dimension SDK library (libdhd) is missing: {exc}") from exc
    return dhd


class OmegaDevice(HapticDevice):
    name = "omega"
    has_force_output = True

    def __init__(self, force_limit_n: float) -> None:
        self._dhd = _import_dhd()
        if self._dhd.open() < 0:
            raise LinkError(f"--device omega: no Force Dimension device found ({self._dhd.errorGetLastStr()})")
        self.force_limit_n = force_limit_n
        self._dhd.enableForce(True)
        self._pos = [0.0, 0.0, 0.0]
        self._vel = [0.0, 0.0, 0.0]
        self._buttons_prev = [False, False]
        self._takeoff_next = True
        log.info("haptic device %s open", self._dhd.getSystemName())

    def poll(self, t_s: float) -> DeviceState:
        self._dhd.getPosition(out=self._pos)
        self._dhd.getLinearVelocity(out=self._vel)
        presses: list[str] = []
        for i in range(2):
            pressed = bool(self._dhd.getButton(index=i))
            if pressed and not self._buttons_prev[i]:
                if i == 0:
                    presses.append("pan_scan_toggle")
                else:
                    presses.append("takeoff" if self._takeoff_next else "land")
                    self._takeoff_next = not self._takeoff_next
            self._buttons_prev[i] = pressed
        return DeviceState(t_s, R_D_FD * np.array(self._pos), R_D_FD * np.array(self._vel), tuple(presses))

    def set_force(self, force_d_n: NDArray[np.float64]) -> None:
        f = np.clip(R_D_FD * force_d_n, -self.force_limit_n, self.force_limit_n)
        self._dhd.setForce([float(v) for v in f])

    def close(self) -> None:
        try:
            self._dhd.setForce([0.0, 0.0, 0.0])
        finally:
            self._dhd.close()
