"""Identification of the closed-loop yaw response to the pan-scan carrier: A'_omega and phi_omega (eq. 5).

Two ways, both pure:

* :func:`identify_from_log` — from a short logged flight with the pan-scan on: commanded yaw rate and
  gyro yaw rate sampled at known times. Both are fitted by linear least squares with
  ``a sin(omega t) + b cos(omega t) + c`` at the known carrier pulsation (the constant absorbs the
  operator's mean yaw rate and the gyro bias). The ratio of the gyro to the command amplitude is
  A'_omega and the phase difference shifted by -pi (the integration from rate to angle) is phi_omega.
* :func:`identify_first_order` — from a first-order closed-loop yaw-rate model
  ``G(s) = exp(-s T_d) / (tau s + 1)`` (the tracker's time constant and any transport delay):
  ``A'_omega = |G(j omega)|``, ``phi_omega = arg G(j omega) - pi``.

With either, eq. (5) gives the centre of the yaw oscillation; the ideal integrator is A' = 1, phi = -pi.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from quadlink.errors import QuadlinkError
from quadlink.frames import wrap_pi


class IdentificationError(QuadlinkError):
    """The data cannot identify the yaw response (too short, no excitation, bad shapes)."""


@dataclass(frozen=True)
class SinusoidFit:
    """``amplitude * sin(omega t + phase_rad) + offset`` fitted to samples; ``rms_residual`` of the fit."""

    amplitude: float
    phase_rad: float
    offset: float
    rms_residual: float


@dataclass(frozen=True)
class YawResponse:
    """Closed-loop yaw response at the carrier pulsation: A'_omega (gain) and phi_omega (phase_rad), eq. (5)."""

    gain: float
    phase_rad: float
    omega_rad_s: float


def fit_sinusoid(t_s: ArrayLike, y: ArrayLike, omega_rad_s: float) -> SinusoidFit:
    """Least-squares fit of ``a sin(wt) + b cos(wt) + c`` at the known pulsation ``omega_rad_s``."""
    t = np.asarray(t_s, dtype=float).ravel()
    v = np.asarray(y, dtype=float).ravel()
    if t.shape != v.shape:
        raise IdentificationError(f"time and signal lengths differ ({t.size} vs {v.size})")
    ok = np.isfinite(t) & np.isfinite(v)
    t, v = t[ok], v[ok]
    if omega_rad_s <= 0:
        raise IdentificationError("omega must be positive")
    if t.size < 8 or (t.max() - t.min()) * omega_rad_s < math.pi:
        raise IdentificationError("need at least half a carrier period and 8 samples to fit the sinusoid")
    A = np.column_stack([np.sin(omega_rad_s * t), np.cos(omega_rad_s * t), np.ones_like(t)])
    coef, *_ = np.linalg.lstsq(A, v, rcond=None)
    a, b, c = (float(x) for x in coef)
    residual = v - A @ coef
    # a sin + b cos = R sin(wt + phi) with R = hypot(a, b), phi = atan2(b, a)
    return SinusoidFit(math.hypot(a, b), math.atan2(b, a), c, float(np.sqrt(np.mean(residual**2))))


def identify_from_log(t_s: ArrayLike, commanded_yaw_rate_rad_s: ArrayLike, gyro_yaw_rate_rad_s: ArrayLike,
                      omega_rad_s: float) -> YawResponse:
    """A'_omega and phi_omega from commanded vs measured (gyro) yaw rate of a logged pan-scan flight."""
    cmd = fit_sinusoid(t_s, commanded_yaw_rate_rad_s, omega_rad_s)
    gyro = fit_sinusoid(t_s, gyro_yaw_rate_rad_s, omega_rad_s)
    if cmd.amplitude < 1e-6:
        raise IdentificationError("the commanded yaw rate has no component at the carrier pulsation")
    gain = gyro.amplitude / cmd.amplitude
    # Yaw angle = integral of yaw rate: the extra -pi/2 of the integral on both signals turns the
    # carrier sin into the -cos of eq. (5), i.e. phi_omega = (phase lag of the loop) - pi.
    phase = wrap_pi(gyro.phase_rad - cmd.phase_rad - math.pi)
    return YawResponse(gain, float(phase), omega_rad_s)


def identify_first_order(time_constant_s: float, omega_rad_s: float, delay_s: float = 0.0) -> YawResponse:
    """A'_omega, phi_omega of the first-order (plus delay) closed-loop yaw-rate model at ``omega_rad_s``."""
    if time_constant_s < 0 or delay_s < 0 or omega_rad_s <= 0:
        raise IdentificationError("time constant and delay must be >= 0 and omega > 0")
    wt = omega_rad_s * time_constant_s
    gain = 1.0 / math.sqrt(1.0 + wt * wt)
    phase = wrap_pi(-math.atan(wt) - omega_rad_s * delay_s - math.pi)
    return YawResponse(gain, float(phase), omega_rad_s)
