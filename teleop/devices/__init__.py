"""Device backends behind one interface (:class:`HapticDevice`), chosen by name.

``virtual`` (eq. (1) simulated, operator from a YAML script), ``keyboard`` (the virtual device
pushed from the terminal), ``omega`` (Force Dimension SDK), ``gamepad`` (SDL joystick, no force).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from quadlink.errors import ConfigError
from teleop.config import DeviceConfig
from teleop.devices.base import BUTTONS, DeviceState, HapticDevice
from teleop.devices.script import load_script
from teleop.devices.virtual import OperatorSource, ScriptedOperator, VirtualDevice

DEVICE_NAMES = ("virtual", "keyboard", "omega", "gamepad")

__all__ = ["BUTTONS", "DEVICE_NAMES", "DeviceState", "HapticDevice", "open_device"]


def open_device(name: str, cfg: DeviceConfig, script: str | Path | None = None,
                script_clock: Callable[[], float | None] | None = None) -> HapticDevice:
    """Open a backend; QuadlinkError (one line naming what is missing) if it cannot be.

    ``script_clock``: the time the script follows (None: the device's wall time); see ScriptedOperator.
    """
    if script is not None and name != "virtual":
        raise ConfigError(f"--script drives the virtual device only (got --device {name})")
    if name == "virtual":
        operator: OperatorSource = ScriptedOperator(load_script(script), script_clock) if script else OperatorSource()
        return VirtualDevice(cfg, operator)
    if name == "keyboard":
        from teleop.devices.keyboard import KeyboardOperator

        return VirtualDevice(cfg, KeyboardOperator())
    if name == "omega":
        from teleop.devices.omega import OmegaDevice

        return OmegaDevice(cfg.force_limit_n)
    if name == "gamepad":
        from teleop.devices.gamepad import GamepadDevice

        return GamepadDevice(cfg.workspace_m)
    raise ConfigError(f"unknown device '{name}' (choose from {', '.join(DEVICE_NAMES)})")
