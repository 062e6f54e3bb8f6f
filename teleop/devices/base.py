"""The one interface every device backend implements (position q in D, buttons, force output)."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

#: Button actions a device (or a script) can emit; the station maps them to vehicle commands.
BUTTONS = ("arm", "disarm", "takeoff", "land", "pan_scan_on", "pan_scan_off", "pan_scan_toggle", "quit")


@dataclass(frozen=True)
class DeviceState:
    """One reading of the device: handle position/velocity in D (NED, m, m/s), new button presses."""

    t_s: float
    q_m: NDArray[np.float64]
    qdot_m_s: NDArray[np.float64]
    buttons: tuple[str, ...] = ()
    operator_force_n: NDArray[np.float64] | None = None   # known only for the virtual device


class HapticDevice(ABC):
    """A device backend. ``poll`` is called by the force loop at 1 kHz, then ``set_force``."""

    name: str = "device"
    has_force_output: bool = True

    @abstractmethod
    def poll(self, t_s: float) -> DeviceState:
        """Read the device at time ``t_s`` (the loop's clock)."""

    @abstractmethod
    def set_force(self, force_d_n: NDArray[np.float64]) -> None:
        """Command the force on the handle (D frame, N); ignored by devices without force output."""

    @property
    def finished(self) -> bool:
        """True when a scripted operator has played its whole script."""
        return False

    def close(self) -> None:  # noqa: B027 - optional hook
        """Release the device (force off)."""
