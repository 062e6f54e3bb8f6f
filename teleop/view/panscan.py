"""Pan-scan component of the yaw rate and the yaw displacement it causes, paper 000 section VI-B.

The measured yaw rate (gyro: operator command + pan-scan oscillation + bias + noise) goes through

1. a band-pass filter with unit gain and zero phase at the oscillation frequency f (second-order
   resonator, bilinear transform with pre-warping: exactly 0 dB / 0 deg at f) -> psi_s' estimate;
2. a peak-to-peak frequency estimator on the band-pass output (successive extrema with hysteresis;
   f = 1 / (2 x mean half-period)) which re-tunes the band-pass, so f need not be known;
3. integration of psi_s' -> yaw displacement, whose bias (integration constant, drift from the
   residual gyro bias) is removed by a low-pass: the moving average over one estimated period
   (a boxcar has its nulls at f and its harmonics, so it keeps the bias and drops the oscillation).

The image is then shifted by p_x = k_px psi_s (view/compensation.py). Pure: samples and their
times in, estimates out; non-uniform sample times are handled by re-tuning on the mean step.

Beyond the paper: the operator's own yaw command is known to the ground station (TELEOP_FEEDBACK:
yaw_rate_cmd - pan_scan_yaw_rate). Its expected response (a first-order yaw loop, time constant
``operator_yaw_time_constant_s``) is subtracted from the gyro before the band-pass, so the transients
of the operator's turns do not leak into psi_s (benchmarks/bench_teleop.py: 15 % -> 2 % residual
with frequent turns). With no operator yaw input this is exactly the paper's scheme.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass


class BandPass:
    """Second-order band-pass, unit gain and zero phase at ``f0_hz`` (RBJ constant-peak-gain form)."""

    def __init__(self, f0_hz: float, q: float, fs_hz: float) -> None:
        self.q = q
        self._x1 = self._x2 = self._y1 = self._y2 = 0.0
        self.f0_hz = f0_hz
        self.fs_hz = fs_hz
        self.tune(f0_hz, fs_hz)

    def tune(self, f0_hz: float, fs_hz: float) -> None:
        f0_hz = min(f0_hz, 0.45 * fs_hz)
        w0 = 2.0 * math.pi * f0_hz / fs_hz
        alpha = math.sin(w0) / (2.0 * self.q)
        a0 = 1.0 + alpha
        self._b0, self._b2 = alpha / a0, -alpha / a0
        self._a1, self._a2 = -2.0 * math.cos(w0) / a0, (1.0 - alpha) / a0
        self.f0_hz, self.fs_hz = f0_hz, fs_hz

    def step(self, x: float) -> float:
        y = self._b0 * x + self._b2 * self._x2 - self._a1 * self._y1 - self._a2 * self._y2
        self._x2, self._x1 = self._x1, x
        self._y2, self._y1 = self._y1, y
        return y


class PeakToPeakFrequency:
    """Frequency of an oscillation from the times of its successive extrema (with hysteresis)."""

    def __init__(self, initial_hz: float, min_hz: float, max_hz: float, hysteresis_fraction: float = 0.3,
                 min_hysteresis: float = 1e-3, half_periods: int = 4, rms_time_s: float = 3.0) -> None:
        self.frequency_hz = initial_hz
        self.min_hz, self.max_hz = min_hz, max_hz
        self.hysteresis_fraction = hysteresis_fraction
        self.min_hysteresis = min_hysteresis
        self.amplitude = 0.0
        self.rms_time_s = rms_time_s
        self._mean_sq = 0.0              # slow mean square of the input: sets the hysteresis above the noise
        self._t_prev: float | None = None
        self.extrema = 0                 # number of confirmed extrema (lock indicator)
        self._half: deque[float] = deque(maxlen=half_periods)
        self._rising: bool | None = None
        self._ext_value = 0.0
        self._ext_t = 0.0
        self._last_ext: tuple[float, float] | None = None   # (t, value) of the last confirmed extremum

    def update(self, x: float, t_s: float) -> float:
        dt = 0.0 if self._t_prev is None else max(t_s - self._t_prev, 0.0)
        self._t_prev = t_s
        k = 1.0 if self._mean_sq == 0.0 else min(dt / self.rms_time_s, 1.0)
        self._mean_sq += k * (x * x - self._mean_sq)
        # hysteresis: a fraction of the sinusoid amplitude sqrt(2) rms (noise alone never crosses it)
        h = max(self.min_hysteresis, self.hysteresis_fraction * math.sqrt(2.0 * self._mean_sq))
        if self._rising is None:
            self._rising, self._ext_value, self._ext_t = True, x, t_s
            return self.frequency_hz
        if self._rising:
            if x > self._ext_value:
                self._ext_value, self._ext_t = x, t_s
            elif self._ext_value - x > h:
                self._confirm()
                self._rising, self._ext_value, self._ext_t = False, x, t_s
        else:
            if x < self._ext_value:
                self._ext_value, self._ext_t = x, t_s
            elif x - self._ext_value > h:
                self._confirm()
                self._rising, self._ext_value, self._ext_t = True, x, t_s
        return self.frequency_hz

    def _confirm(self) -> None:
        t, v = self._ext_t, self._ext_value
        if self._last_ext is not None:
            half_s = t - self._last_ext[0]
            p2p = abs(v - self._last_ext[1])
            self.amplitude = p2p / 2.0 if self.amplitude == 0.0 else 0.7 * self.amplitude + 0.3 * p2p / 2.0
            if half_s > 0:
                self._half.append(half_s)
                f = 1.0 / (2.0 * sum(self._half) / len(self._half))
                self.frequency_hz = min(max(f, self.min_hz), self.max_hz)
        self._last_ext = (t, v)
        self.extrema += 1


@dataclass(frozen=True)
class PanScanEstimate:
    yaw_rate_rad_s: float        # band-passed pan-scan component of the yaw rate (psi_s' hat)
    yaw_rad: float               # unbiased yaw displacement from the centre of oscillation (psi_s hat)
    frequency_hz: float          # peak-to-peak estimate
    amplitude_rad_s: float       # of the yaw-rate oscillation
    locked: bool                 # enough extrema seen for the frequency to mean something


class PanScanEstimator:
    """Band-pass + peak-to-peak tuning + integration + moving-average bias removal (section VI-B)."""

    def __init__(self, initial_hz: float = 0.5, min_hz: float = 0.05, max_hz: float = 3.0, q: float = 1.5,
                 bias_periods: float = 1.0, fade_time_s: float = 1.0,
                 operator_yaw_time_constant_s: float = 0.15) -> None:
        self.freq = PeakToPeakFrequency(initial_hz, min_hz, max_hz)
        self.operator_yaw_time_constant_s = operator_yaw_time_constant_s
        self._operator_rate = 0.0        # modelled response of the yaw loop to the operator's command
        self.q = q
        self.bias_periods = bias_periods
        self.fade_time_s = fade_time_s
        self._bp: BandPass | None = None
        self._t_prev: float | None = None
        self._dt_mean: float | None = None
        self._y_prev = 0.0
        self._psi_int = 0.0
        self._hist: deque[tuple[float, float]] = deque()   # (t, integrated yaw) over the bias window
        self._gain = 1.0
        self.last = PanScanEstimate(0.0, 0.0, initial_hz, 0.0, False)

    def reset(self) -> None:
        self.__init__(self.freq.frequency_hz, self.freq.min_hz, self.freq.max_hz, self.q,  # type: ignore[misc]
                      self.bias_periods, self.fade_time_s, self.operator_yaw_time_constant_s)

    def update(self, gyro_yaw_rate_rad_s: float, t_s: float, enabled: bool = True,
               operator_yaw_rate_cmd_rad_s: float = 0.0) -> PanScanEstimate:
        """One gyro sample at ``t_s``; ``operator_yaw_rate_cmd_rad_s``: the operator's yaw command (0 if unknown)."""
        gyro_yaw_rate_rad_s = float(gyro_yaw_rate_rad_s)
        operator = float(operator_yaw_rate_cmd_rad_s)
        if not math.isfinite(gyro_yaw_rate_rad_s):
            return self.last
        if not math.isfinite(operator):
            operator = 0.0
        if self._t_prev is None:
            self._t_prev = t_s
            return self.last
        dt = t_s - self._t_prev
        if dt <= 0.0:
            return self.last
        if dt > 1.0:   # stream gap: start over rather than integrate across it
            self.reset()
            self._t_prev = t_s
            return self.last
        self._t_prev = t_s
        self._dt_mean = dt if self._dt_mean is None else 0.95 * self._dt_mean + 0.05 * dt
        tau = self.operator_yaw_time_constant_s
        self._operator_rate += (1.0 - math.exp(-dt / tau) if tau > 0 else 1.0) * (operator - self._operator_rate)
        fs = 1.0 / self._dt_mean
        f0 = self.freq.frequency_hz
        if self._bp is None:
            self._bp = BandPass(f0, self.q, fs)
        elif abs(f0 - self._bp.f0_hz) > 0.01 * self._bp.f0_hz or abs(fs - self._bp.fs_hz) > 0.05 * self._bp.fs_hz:
            self._bp.tune(f0, fs)
        y = self._bp.step(gyro_yaw_rate_rad_s - self._operator_rate)
        self.freq.update(y, t_s)
        self._psi_int += 0.5 * (y + self._y_prev) * dt      # trapezoidal integration
        self._y_prev = y
        # bias: moving average of the integral over one estimated period (low-pass with nulls at f)
        window_s = self.bias_periods / self.freq.frequency_hz
        self._hist.append((t_s, self._psi_int))
        while self._hist and self._hist[0][0] < t_s - window_s:
            self._hist.popleft()
        bias = _time_average(self._hist)
        target = 1.0 if enabled else 0.0
        step = dt / self.fade_time_s
        self._gain = min(self._gain + step, target) if target > self._gain else max(self._gain - step, target)
        self.last = PanScanEstimate(self._gain * y, self._gain * (self._psi_int - bias), self.freq.frequency_hz,
                                    self.freq.amplitude, self.freq.extrema >= 3)
        return self.last


def _time_average(samples: deque[tuple[float, float]]) -> float:
    if len(samples) < 2:
        return samples[-1][1] if samples else 0.0
    area = 0.0
    it = iter(samples)
    t0, v0 = next(it)
    first = t0
    for t1, v1 in it:
        area += 0.5 * (v0 + v1) * (t1 - t0)
        t0, v0 = t1, v1
    span = t0 - first
    return area / span if span > 0 else v0
