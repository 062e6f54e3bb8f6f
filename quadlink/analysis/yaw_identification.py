"""Identification of the closed-loop yaw response to the pan-scan carrier: A'_omega and phi_omega (eq. 5).

Three ways, all pure:

* :func:`identify_from_log` — from a short logged flight with the pan-scan on: commanded yaw rate and
  gyro yaw rate sampled at known times. Both are fitted by linear least squares with
  ``a sin(omega t) + b cos(omega t) + c`` at the known carrier pulsation (the constant absorbs the
  operator's mean yaw rate and the gyro bias). The ratio of the gyro to the command amplitude is
  A'_omega and the phase difference shifted by -pi (the integration from rate to angle) is phi_omega.
* :func:`identify_first_order` — from a first-order closed-loop yaw-rate model
  ``G(s) = exp(-s T_d) / (tau s + 1)`` (the tracker's time constant and any transport delay):
  ``A'_omega = |G(j omega)|``, ``phi_omega = arg G(j omega) - pi``.
* :func:`fit_yaw_loop` — from any teleop flight's TELEOP_FEEDBACK (``quadlink identify-yaw LOG.tlog``): a
  first-order-plus-delay loop fitted from the whole commanded yaw rate (the operator's yawing excites it too,
  where :func:`identify_from_log` would take it for noise) to the measured one, evaluated at the carrier.

With either, eq. (5) gives the centre of the yaw oscillation; the ideal integrator is A' = 1, phi = -pi.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

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


@dataclass(frozen=True)
class FeedbackSeries:
    """What TELEOP_FEEDBACK carries for the identification, per message: stamp, the pan-scan component of the
    commanded yaw rate, the whole commanded yaw rate (operator + pan-scan), the measured yaw rate."""

    t_s: np.ndarray
    pan_scan_rad_s: np.ndarray
    yaw_rate_cmd_rad_s: np.ndarray
    gyro_yaw_rate_rad_s: np.ndarray


@dataclass(frozen=True)
class YawLoopFit:
    """First-order-plus-delay yaw-rate loop fitted to a flight, ``G(s) = K exp(-s T_d) / (tau s + 1)``, and its
    response at the carrier; ``rms_residual_rad_s``: the model run from the command alone against the measured
    yaw rate; ``samples`` used."""

    time_constant_s: float
    delay_s: float
    static_gain: float
    rms_residual_rad_s: float
    samples: int
    response: YawResponse


def _simulate_arx(a: float, b: float, c: float, u: NDArray[np.float64], d: int, y0: float) -> NDArray[np.float64]:
    """``y[k+1] = a y[k] + b u[k-d] + c`` from ``y0`` (the command before the log's start taken as its first value)."""
    out = np.empty(u.size)
    out[0] = y = y0
    uu = u.tolist()
    for k in range(u.size - 1):
        y = a * y + b * uu[max(k - d, 0)] + c
        out[k + 1] = y
    return out


def fit_yaw_loop(series: FeedbackSeries, omega_rad_s: float, rate_hz: float = 50.0,
                 max_delay_s: float = 0.2) -> YawLoopFit:
    """Fit the yaw-rate loop from the whole commanded yaw rate (operator + pan-scan: the operator's yawing is
    excitation too, not noise) to the measured one, and evaluate it at the carrier.

    The series is resampled on a ``rate_hz`` grid; for each whole-sample delay ``d`` up to ``max_delay_s`` the
    ARX model ``y[k+1] = a y[k] + b u[k-d] + c`` is fitted by linear least squares (``c`` takes the gyro bias),
    and the delay whose model, run from the command alone, follows the measurement best is kept.
    ``tau = -dt / ln a``, ``K = b / (1 - a)``; the response is that of the discrete model at ``omega`` with
    eq. (5)'s -pi (rate to angle), as :func:`identify_first_order`.
    """
    t = np.asarray(series.t_s, dtype=float)
    if t.size < 8 or not np.all(np.diff(t) > 0):
        raise IdentificationError("need at least 8 feedback samples with increasing stamps")
    if omega_rad_s <= 0:
        raise IdentificationError("omega must be positive")
    dt = 1.0 / rate_hz
    grid = np.arange(t[0], t[-1], dt)
    u = np.interp(grid, t, series.yaw_rate_cmd_rad_s)
    y = np.interp(grid, t, series.gyro_yaw_rate_rad_s)
    if float(np.std(u)) < 1e-3:
        raise IdentificationError("the commanded yaw rate does not move: nothing to identify")
    best: tuple[float, int, float, float] | None = None
    for d in range(int(max_delay_s / dt) + 1):
        n = y.size - 1 - d
        if n < 8:
            break
        A = np.column_stack([y[d:d + n], u[:n], np.ones(n)])
        (a, b, c), *_ = np.linalg.lstsq(A, y[d + 1:d + 1 + n], rcond=None)
        if not (0.0 < a < 1.0 and b > 0.0):
            continue     # not a lag driven by the command: a delay that does not fit
        # the delay is chosen on the simulation error (the model run from the command alone), which one-step
        # prediction cannot judge: with y[k] as a regressor any delay predicts the next sample well
        y_sim = _simulate_arx(float(a), float(b), float(c), u, d, float(y[0]))
        rms = float(np.sqrt(np.mean((y - y_sim) ** 2)))
        if best is None or rms < best[0]:
            best = (rms, d, float(a), float(b))
    if best is None:
        raise IdentificationError("no delay up to max_delay_s gives a stable first-order lag driven by the command")
    rms, d, a, b = best
    z = np.exp(1j * omega_rad_s * dt)
    G = b * z ** (-d) / (z - a)           # y[k+1] = a y[k] + b u[k-d]  ->  G(z) = b z^-d / (z - a)
    response = YawResponse(float(abs(G)), float(wrap_pi(float(np.angle(G)) - math.pi)), omega_rad_s)
    return YawLoopFit(-dt / math.log(a), d * dt, float(b / (1.0 - a)), rms, int(y.size), response)


def identify_first_order(time_constant_s: float, omega_rad_s: float, delay_s: float = 0.0) -> YawResponse:
    """A'_omega, phi_omega of the first-order (plus delay) closed-loop yaw-rate model at ``omega_rad_s``."""
    if time_constant_s < 0 or delay_s < 0 or omega_rad_s <= 0:
        raise IdentificationError("time constant and delay must be >= 0 and omega > 0")
    wt = omega_rad_s * time_constant_s
    gain = 1.0 / math.sqrt(1.0 + wt * wt)
    phase = wrap_pi(-math.atan(wt) - omega_rad_s * delay_s - math.pi)
    return YawResponse(gain, float(phase), omega_rad_s)
