"""Pan-scan yaw-rate carrier and the centre of the resulting yaw oscillation (paper 000, eqs. 4-5).

Pure: time comes in as an argument. The carrier ``psi_dot_s(t) = A sin(omega t)`` (eq. 4) is added to
the operator's yaw rate; if the closed-loop yaw dynamics were a perfect integrator the yaw would swing
as ``-(A/omega) cos(omega t)``. The real loop scales the swing by ``A'_omega`` and shifts it by
``phi_omega`` (see :mod:`quadlink.analysis.yaw_identification`), giving eq. (5)::

    psi_bar_s(t) = A'_omega (A / omega) cos(omega t + phi_omega)

which the reference velocity adds to the motion direction alpha (eq. 6) so the vehicle moves along the
centre of the oscillation while the camera sweeps left and right.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class PanScanParams:
    """Carrier amplitude A [rad/s], pulsation omega [rad/s] and the identified closed-loop response.

    ``gain`` is A'_omega (dimensionless, 1 for a perfect integrator) and ``phase_rad`` is phi_omega
    (-pi for a perfect integrator: the yaw lags the rate by a quarter period).
    """

    enabled: bool = True
    amplitude_rad_s: float = 0.6
    omega_rad_s: float = 1.5
    gain: float = 1.0
    phase_rad: float = -math.pi


@dataclass(frozen=True)
class PanScanState:
    """Pan-scan output at one instant."""

    yaw_rate_rad_s: float  # psi_dot_s, eq. (4)
    yaw_offset_rad: float  # psi_bar_s, eq. (5)
    enabled: bool


def pan_scan(params: PanScanParams, t_s: float) -> PanScanState:
    """Carrier yaw rate (eq. 4) and expected yaw offset (eq. 5) at time ``t_s`` since the scan started."""
    if not params.enabled or params.omega_rad_s <= 0.0 or params.amplitude_rad_s == 0.0:
        return PanScanState(0.0, 0.0, False)
    w = params.omega_rad_s
    rate = params.amplitude_rad_s * math.sin(w * t_s)  # eq. (4)
    offset = params.gain * (params.amplitude_rad_s / w) * math.cos(w * t_s + params.phase_rad)  # eq. (5)
    return PanScanState(rate, offset, True)


def swing_amplitude_rad(params: PanScanParams) -> float:
    """Half the peak-to-peak yaw swing, A'_omega A / omega [rad]."""
    if not params.enabled or params.omega_rad_s <= 0.0:
        return 0.0
    return abs(params.gain * params.amplitude_rad_s / params.omega_rad_s)
