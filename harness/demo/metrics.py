"""Flight-report metrics (issue 8), pure functions of logged time series.

Every series is sampled in simulated time (seconds since the SITL started), which is the common
time base of the truth stream, the bridge (board time) and the companion (camera capture time).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from quadlink.analysis.yaw_identification import fit_sinusoid as fit_at

Array = NDArray[np.float64]


def interpolate(t_src_s: Array, values: Array, t_s: Array) -> Array:
    """Linear interpolation of ``values`` (N or N×k) at times ``t_s``; NaN outside the source span."""
    values = np.asarray(values, dtype=float)
    t_src_s = np.asarray(t_src_s, dtype=float)
    if values.ndim == 1:
        out = np.interp(t_s, t_src_s, values, left=np.nan, right=np.nan)
        return np.asarray(out, dtype=float)
    return np.stack([interpolate(t_src_s, values[:, k], t_s) for k in range(values.shape[1])], axis=1)


def velocity_ned_to_h(v_ned_m_s: Array, yaw_rad: Array) -> Array:
    """Rotate world-NED velocities into H (yaw only): ``v_h = Rz(yaw)^T v_ned``."""
    v = np.asarray(v_ned_m_s, dtype=float)
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    return np.stack([c * v[:, 0] + s * v[:, 1], -s * v[:, 0] + c * v[:, 1], v[:, 2]], axis=1)


def rmse_per_axis(t_est_s: Array, v_est: Array, t_ref_s: Array, v_ref: Array, mask: Array | None = None) -> Array:
    """RMSE per column of ``v_est`` against ``v_ref`` interpolated at the estimate's stamps."""
    ref = interpolate(t_ref_s, v_ref, t_est_s)
    err = np.asarray(v_est, dtype=float) - ref
    ok = np.all(np.isfinite(err), axis=1)
    if mask is not None:
        ok &= mask
    if not np.any(ok):
        return np.full(err.shape[1], np.nan)
    return np.sqrt(np.mean(err[ok] ** 2, axis=0))


@dataclass(frozen=True)
class GapStats:
    count_over: int
    max_gap_s: float
    threshold_s: float


def stream_gaps(t_s: Array, threshold_s: float = 0.1) -> GapStats:
    """Gaps between consecutive stamps of a stream longer than ``threshold_s``."""
    t = np.sort(np.asarray(t_s, dtype=float))
    if t.size < 2:
        return GapStats(0, math.inf if t.size == 0 else 0.0, threshold_s)
    gaps = np.diff(t)
    return GapStats(int(np.sum(gaps > threshold_s)), float(gaps.max()), threshold_s)


def fraction_at_or_below(t_est_s: Array, d_est_m: Array, t_ref_s: Array, d_ref_m: Array,
                         tolerance_m: float = 0.0) -> float:
    """Fraction of valid estimates with ``d_est <= d_ref + tolerance`` (the paper's safe side)."""
    ref = interpolate(t_ref_s, d_ref_m, t_est_s)
    est = np.asarray(d_est_m, dtype=float)
    ok = np.isfinite(ref) & np.isfinite(est) & (est >= 0)
    if not np.any(ok):
        return math.nan
    return float(np.mean(est[ok] <= ref[ok] + tolerance_m))


@dataclass(frozen=True)
class Sinusoid:
    amplitude: float
    frequency_hz: float
    phase_rad: float
    offset: float
    residual_rms: float


def fit_sinusoid(t_s: Array, y: Array, min_hz: float = 0.02, max_hz: float = 5.0) -> Sinusoid:
    """Least-squares ``offset + a sin(2 pi f t + phase)`` with the frequency unknown.

    Scans trial frequencies (coarse log grid, then a fine one around the best) and, at each, uses the
    closed-form fit at a known pulsation (:func:`quadlink.analysis.yaw_identification.fit_sinusoid`);
    works on irregular sampling.
    """
    t = np.asarray(t_s, dtype=float)
    y = np.asarray(y, dtype=float)
    ok = np.isfinite(t) & np.isfinite(y)
    t, y = t[ok], y[ok]
    if t.size < 8:
        return Sinusoid(math.nan, math.nan, math.nan, math.nan, math.nan)
    lo = max(min_hz, 1.0 / max(t[-1] - t[0], 1e-6))

    def residual(f: float) -> float:
        return fit_at(t, y, 2 * math.pi * f).rms_residual

    best = min(np.geomspace(lo, max_hz, 400), key=residual)
    f_best = float(min(np.linspace(best * 0.97, best * 1.03, 121), key=residual))
    fit = fit_at(t, y, 2 * math.pi * f_best)
    return Sinusoid(fit.amplitude, f_best, fit.phase_rad, fit.offset, fit.rms_residual)


TOUCHDOWN_REST_M = 0.02    # the centre of mass within this of its height at the start: resting on the floor
TOUCHDOWN_WINDOW_S = 0.2   # the impact's speed: the fastest descent over this long before coming to rest


def touchdown_m_s(t_s: Array, p_local_ned_m: Array, rest_m: float = TOUCHDOWN_REST_M,
                  window_s: float = TOUCHDOWN_WINDOW_S) -> float:
    """The last landing's vertical speed at impact (m/s, descending positive): the fastest descent, from consecutive
    truth positions, over the ``window_s`` before the centre of mass last came back within ``rest_m`` of where it
    rested at the start (on the floor). NaN if it never left the floor, or did not come back to it (in the air at the
    end, or landed on an object)."""
    t = np.asarray(t_s, dtype=float)
    z = np.asarray(p_local_ned_m, dtype=float).reshape(-1, 3)[:, 2]
    airborne = np.flatnonzero(z < -rest_m)
    if t.size < 2 or airborne.size == 0 or airborne[-1] + 1 >= z.size:
        return math.nan
    k = int(airborne[-1]) + 1                      # the first sample at rest after the last one in the air
    dt = np.diff(t[:k + 1])
    vz = np.diff(z[:k + 1]) / np.where(dt > 0, dt, np.inf)
    window = t[1:k + 1] >= t[k] - window_s
    return float(np.max(vz[window]))
