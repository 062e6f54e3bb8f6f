"""Gamepad / joystick through pygame (SDL), no force output.

Left stick: up = forward (q_x), left/right = yaw (q_y); right stick vertical: climb (q_z, NED down).
Stick deflection is scaled to the device workspace so the same mapping and dead-band apply.
Buttons: A(0) arm, B(1) land, X(2) take-off, Y(3) pan-scan toggle, Start(7) disarm.
"""

from __future__ import annotations

import logging
import os
from typing import Any

import numpy as np
from numpy.typing import NDArray

from quadlink.errors import LinkError
from teleop.devices.base import DeviceState, HapticDevice

log = logging.getLogger(__name__)

BUTTON_ACTIONS = {0: "arm", 1: "land", 2: "takeoff", 3: "pan_scan_toggle", 7: "disarm"}


def _import_pygame() -> Any:
    os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")
    try:
        import pygame
    except ImportError as exc:
        raise LinkError("--device gamepad needs the Python package 'pygame' (pip install 'quadlink[gamepad]')") \
            from exc
    return pygame


class GamepadDevice(HapticDevice):
    name = "gamepad"
    has_force_output = False

    def __init__(self, workspace_m: tuple[float, float, float], index: int = 0) -> None:
        pg = self._pg = _import_pygame()
        pg.display.init()
        pg.joystick.init()
        if pg.joystick.get_count() <= index:
            raise LinkError(f"--device gamepad: no joystick found (SDL sees {pg.joystick.get_count()})")
        self._js = pg.joystick.Joystick(index)
        self._js.init()
        self.workspace = np.asarray(workspace_m, dtype=float)
        self._q_prev = np.zeros(3)
        self._t_prev: float | None = None
        log.info("gamepad %s open (%d axes, %d buttons)", self._js.get_name(), self._js.get_numaxes(),
                 self._js.get_numbuttons())

    def poll(self, t_s: float) -> DeviceState:
        presses: list[str] = []
        for event in self._pg.event.get():
            if event.type == self._pg.JOYBUTTONDOWN and event.button in BUTTON_ACTIONS:
                presses.append(BUTTON_ACTIONS[event.button])
        axis = [self._js.get_axis(i) if i < self._js.get_numaxes() else 0.0 for i in range(4)]
        # SDL: axis 1 is left stick vertical (up = -1), axis 0 horizontal, axis 3 right stick vertical.
        q = np.array([-axis[1], axis[0], axis[3]]) * self.workspace
        dt = 0.0 if self._t_prev is None else t_s - self._t_prev
        qdot = (q - self._q_prev) / dt if dt > 0 else np.zeros(3)
        self._q_prev, self._t_prev = q, t_s
        return DeviceState(t_s, q, qdot, tuple(presses))

    def set_force(self, force_d_n: NDArray[np.float64]) -> None:
        pass  # no force output

    def close(self) -> None:
        self._pg.joystick.quit()
        self._pg.display.quit()
