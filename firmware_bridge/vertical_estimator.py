"""Vertical speed and height from the accelerometer alone, for flight without odometry (pure, step-based).

On the ground the RGB-D camera (30 deg down, 0.5 m minimum range) sees the floor too close, so the
companion's visual odometry starts only after the vehicle has climbed ~0.3-0.5 m. The first phase of the
take-off (and a landing when odometry never came) therefore flies on this estimate:

    a_z = (R_hq f_q)_z + g - b_z                 (vertical acceleration in H, NED: + down)
    v_z += a_z dt,   h -= v_z dt                  (bounded: |v_z| <= the climb/descent limits, h >= 0)

* ``f_q`` is the specific force (accelerometer, body FRD) rotated into the horizontal frame H with the
  attitude estimate's roll and pitch; at rest it reads ``-g e3`` so ``a_z`` = 0.
* ``b_z``, the vertical accelerometer bias, is the low-passed ``(R_hq f_q)_z + g`` while the vehicle is
  *pinned* on the ground (time constant ``bias_tau_s``).
* The hover thrust of the vehicle config is the prior that says when the vehicle can be airborne at all:
  while the commanded collective thrust is below ``liftoff_fraction_of_hover`` x hover thrust the ground
  holds the vehicle, so ``v_z`` and ``h`` stay 0 (a zero-velocity update) and the bias keeps being learnt.
  Once the thrust crosses it the estimator integrates until :meth:`reset_ground`.

Ground contact without a velocity reference: with the collective thrust below the hover thrust the vehicle
must accelerate downwards unless the ground carries it, so "thrust < hover and no vertical acceleration"
(``accel_z_m_s2``) is touchdown even when the integrated velocity has drifted.

Integration of a 10-bit accelerometer drifts (a residual bias of 0.02 m/s^2 is 0.12 m/s after 6 s), so the
autopilot only flies on this for a bounded time and height (``BRG_TKO_OL_T``, ``BRG_TKO_OL_ALT``).

**With the board's barometer** (the ``Z`` frame: MPX4115A altitude, 50 Hz; issue 30) the estimate no longer
drifts: a third-order complementary filter pulls the height toward the baro height (relative to the baro's
reading averaged over ``BARO_GROUND_TAU_S`` while the estimator was pinned on the ground), the vertical
speed with it, and learns the accelerometer's bias in the air::

    e = z_baro - AB(h);   h += (w + k1 e) dt;   w += (u + k2 e) dt;   b += k3 e dt     (w = -v_z up, u = -a_z up)

with the triple pole at ``baro_bandwidth_rad_s`` (k1 = 3 w0, k2 = 3 w0^2, k3 = w0^3): the accelerometer carries
the fast motion, the baro's noise (a few cm after the board's oversampling) and its slow drift are filtered.
``z_baro`` is not the pressure's height: it is the board's alpha-beta filter of it (``firmware/src/baro.c``,
alpha 2^-7 and beta 2^-15 per 2 ms tick: a second-order low-pass at 2.8 rad/s, damping 0.7), which lags a climb
as it starts: 0.08 m at most, 0.2 m up, for the take-off's 0.5 m/s reached at 2 m/s^2. So the innovation
compares it with ``AB(h)``, the same filter run on this estimate (what the frame would read if the estimate were
the truth), not with ``h``: compared with ``h``, the blind climb's height ran 0.06-0.10 m behind the truth at the
odometry's hand-over 0.4 m up and the take-off ended at 1.27-1.31 m for 1.2 m (SITL, 3 runs). The filter inside
the loop costs phase margin (71 deg at w0 = 1 rad/s without it, 27 deg with it), so the pole moves to 0.7 rad/s
(42 deg).
A baro frame older than ``BARO_STALE_S`` (or marked invalid or saturated) is not used: the accelerometer-only
estimate goes on from where the fused one was.

The baro's ground reference drifts (weather, the sensor warming up: after 2.7 min of hover the SITL's had moved
0.06-0.51 m), so in the air a better height (the odometry's, :meth:`VerticalEstimator.reference_height`) moves the
reference slowly toward what it implies, as PX4's EKF2 learns its baro's bias against its height reference. The
frame's climb rate, which the drift does not move, is kept beside the estimate (``baro_climb_m_s``): a landing
uses it to tell that its descent has stopped below the floor a drifted height reads.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from quadlink.mk.messages import BaroAltitude

DEFAULT_BIAS_TAU_S = 1.0
DEFAULT_LIFTOFF_FRACTION_OF_HOVER = 0.7  # no vehicle within 30 % of its configured mass lifts off below this
ACCEL_LOWPASS_TAU_S = 0.1  # the vertical acceleration the ground-contact test looks at
DEFAULT_BARO_BANDWIDTH_RAD_S = 0.7  # the fused filter's triple pole: the baro's noise is cut above ~0.1 Hz
BARO_STALE_S = 0.2                  # a baro reading older than this (10 frames at 50 Hz) is not fused
BARO_GROUND_TAU_S = 1.0             # the ground's baro reference is averaged over this while pinned (one 'Z'
                                    # frame is 0.04 m RMS off at rest, 0.18 m peak to peak: the SITL's sensor)
DEFAULT_BARO_REREF_TAU_S = 20.0     # ... and follows a better height over this in the air (reference_height): the
                                    # SITL's baro had drifted 0.06-0.51 m after 2.7 min of hover, its odometry's
                                    # height 0-5 mm; a baro's drift (weather, warm-up) is minutes, not seconds


@dataclass(frozen=True)
class VerticalEstimate:
    vz_m_s: float  # vertical velocity in H, NED (+ down)
    height_m: float  # above the point where the estimator was last pinned (+ up)
    accel_bias_m_s2: float  # vertical specific-force bias learnt on the ground
    pinned: bool  # on the ground: the thrust is below lift-off
    accel_z_m_s2: float  # bias-corrected vertical acceleration (NED), low-passed (ACCEL_LOWPASS_TAU_S)
    baro_fused: bool = False  # the last update was corrected by a fresh baro reading
    baro_climb_m_s: float = math.nan  # the board's barometric climb rate (+ up), NaN when not fresh: its 'Z' frame's,
                                      # the derivative of the pressure's height, which its drift does not move


class VerticalEstimator:
    def __init__(self, hover_thrust_fraction: float, max_climb_m_s: float = 1.5, max_descent_m_s: float = 1.0,
                 bias_tau_s: float = DEFAULT_BIAS_TAU_S,
                 liftoff_fraction_of_hover: float = DEFAULT_LIFTOFF_FRACTION_OF_HOVER,
                 baro_bandwidth_rad_s: float = DEFAULT_BARO_BANDWIDTH_RAD_S) -> None:
        if not 0.0 < hover_thrust_fraction < 1.0:
            raise ValueError("hover thrust fraction must be in (0, 1)")
        self.hover_thrust_fraction = hover_thrust_fraction
        self.max_climb_m_s = max_climb_m_s
        self.max_descent_m_s = max_descent_m_s
        self.bias_tau_s = bias_tau_s
        self.liftoff_fraction_of_hover = liftoff_fraction_of_hover
        self._vz = 0.0
        self._h = 0.0
        self._bias: float | None = None
        self._pinned = True
        self._a_lp = 0.0
        w0 = float(baro_bandwidth_rad_s)
        if not w0 > 0.0:
            raise ValueError("baro bandwidth must be > 0 rad/s")
        self._k = (3.0 * w0, 3.0 * w0 * w0, w0 ** 3)
        self._baro_alt_m: float | None = None   # the last usable baro altitude (board's reference, + up)
        self._baro_t_s = -math.inf
        self._baro_climb_m_s = math.nan
        self._baro_ground_m: float | None = None  # the baro altitude where the estimator was last pinned
        self._t_s = 0.0                          # the estimator's own time (sum of the IMU's dt)
        self._fused = False
        self._h_board_m = 0.0       # AB(h): the board's alpha-beta filter run on this estimate (height, + up)
        self._climb_board_m_s = 0.0  # and its climb rate (+ up)

    def on_baro(self, altitude_m: float, valid: bool = True, climb_m_s: float = math.nan) -> None:
        """A ``Z`` frame's barometric altitude (m, + up, the board's reference) and climb rate (m/s, + up; NaN if
        not given), received now (the estimator's time): used until they are ``BARO_STALE_S`` old. Invalid or
        non-finite altitudes are ignored."""
        if not valid or not math.isfinite(altitude_m):
            return
        self._baro_alt_m = float(altitude_m)
        self._baro_climb_m_s = float(climb_m_s) if math.isfinite(climb_m_s) else math.nan
        self._baro_t_s = self._t_s
        if self._pinned and self._baro_ground_m is None:
            self._baro_ground_m = self._baro_alt_m   # the first reading; averaged from here while pinned

    def _baro_height_m(self) -> float | None:
        """The baro's height above where the estimator was last pinned, if fresh."""
        if self._baro_alt_m is None or self._baro_ground_m is None or self._t_s - self._baro_t_s > BARO_STALE_S:
            return None
        return self._baro_alt_m - self._baro_ground_m

    def reference_height(self, height_m: float, dt_s: float, tau_s: float = DEFAULT_BARO_REREF_TAU_S) -> None:
        """In the air, a better height above the take-off point (the odometry's, while it is good): the baro's
        ground reference follows it over ``tau_s`` (<= 0: it does not), so the baro's drift since the take-off
        leaves the floor the fused height reads (PX4's EKF2 learns its baro's bias against its height reference
        so). The frame is the board's filter of the pressure's height: it is compared with that height filtered
        the same way (``AB(h)``'s lag added to ``height_m``). Not on the ground (pinned), without a fresh frame,
        or with a non-finite height."""
        if tau_s <= 0.0 or self._pinned or self._baro_alt_m is None or self._baro_ground_m is None \
                or not math.isfinite(height_m) or self._t_s - self._baro_t_s > BARO_STALE_S:
            return
        ground_m = self._baro_alt_m - (float(height_m) + self._h_board_m - self._h)
        self._baro_ground_m += (ground_m - self._baro_ground_m) * min(1.0, max(dt_s, 0.0) / tau_s)

    def reset_ground(self) -> None:
        """On the ground (landed, disarmed, or at the start of a take-off): pin; the learnt bias is kept."""
        self._vz = 0.0
        self._h = 0.0
        self._h_board_m = self._climb_board_m_s = 0.0
        self._pinned = True

    def align(self, height_m: float, vz_m_s: float) -> None:
        """In the air, from a better source (the odometry's last height and vertical speed, NED): the
        accelerometer-only estimate continues from there (the learnt bias is kept)."""
        if math.isfinite(height_m) and math.isfinite(vz_m_s):
            h_old, w_old = self._h, -self._vz
            self._h = max(float(height_m), 0.0)
            self._vz = min(max(float(vz_m_s), -self.max_climb_m_s), self.max_descent_m_s)
            # the filter's output moves with the estimate: it models the board's filter of the true height, and
            # the correction says that height was this much off
            self._h_board_m += self._h - h_old
            self._climb_board_m_s += -self._vz - w_old
            self._pinned = False

    def update(self, dt_s: float, a_h_z_m_s2: float, thrust_fraction: float, on_ground: bool = False) -> None:
        """One IMU sample: ``a_h_z_m_s2`` = (R_hq f_q)_z + g (NED), the commanded collective thrust (0..1)."""
        dt_s = min(max(float(dt_s), 0.0), 0.1)
        self._t_s += dt_s
        if self._bias is None:
            self._bias = float(a_h_z_m_s2)  # converge at once from the first sample (at rest at start-up)
        self._a_lp += (float(a_h_z_m_s2) - self._bias - self._a_lp) * dt_s / max(ACCEL_LOWPASS_TAU_S, dt_s)
        if on_ground:
            self._pinned = True
        liftoff_thrust = self.liftoff_fraction_of_hover * self.hover_thrust_fraction
        if self._pinned and (on_ground or thrust_fraction < liftoff_thrust):
            self._bias += (float(a_h_z_m_s2) - self._bias) * dt_s / max(self.bias_tau_s, dt_s)
            self._vz = 0.0
            self._h = 0.0
            self._h_board_m = self._climb_board_m_s = 0.0
            if self._baro_alt_m is not None and self._t_s - self._baro_t_s <= BARO_STALE_S:
                # the ground's baro reading, averaged (a single frame's noise became the take-off's height
                # error: 0.11-0.15 m at the odometry's hand-over 0.2 m up), follows the weather
                if self._baro_ground_m is None:
                    self._baro_ground_m = self._baro_alt_m
                self._baro_ground_m += (self._baro_alt_m - self._baro_ground_m) * min(
                    1.0, dt_s / BARO_GROUND_TAU_S)
            self._fused = False
            return
        self._pinned = False
        a_z = float(a_h_z_m_s2) - self._bias
        h_baro = self._baro_height_m()
        self._fused = h_baro is not None
        if h_baro is not None:
            k1, k2, k3 = self._k
            e = h_baro - self._h_board_m
            self._h += k1 * e * dt_s
            self._vz -= k2 * e * dt_s        # w = -vz gains k2 e
            self._bias += k3 * e * dt_s      # the estimate lags low: the downward acceleration read too large
        self._vz = min(max(self._vz + a_z * dt_s, -self.max_climb_m_s), self.max_descent_m_s)
        h = self._h - self._vz * dt_s
        if h < 0.0 and self._fused and self._vz > 0.0:
            # at the ground on the barometer: the floor has stopped the descent. With the height held at 0 the
            # baro's innovation is 0 too, and a descent rate the accelerometer did not see end (a soft touchdown)
            # would stay in the estimate for good, and the touchdown test (|vz| small) never pass
            self._vz = 0.0
        self._h = max(h, 0.0)
        r = self._h - self._h_board_m
        self._h_board_m += (self._climb_board_m_s + BaroAltitude.FILTER_ALPHA_1_S * r) * dt_s
        self._climb_board_m_s += BaroAltitude.FILTER_BETA_1_S2 * r * dt_s

    @property
    def estimate(self) -> VerticalEstimate:
        climb = self._baro_climb_m_s if self._t_s - self._baro_t_s <= BARO_STALE_S else math.nan
        return VerticalEstimate(self._vz, self._h, self._bias or 0.0, self._pinned, self._a_lp, self._fused, climb)

    @property
    def vz_m_s(self) -> float:
        return self._vz

    @property
    def baro_altitude_m(self) -> float | None:
        """The board's own barometric altitude (m, + up, from its reference at its power-up; never re-referenced:
        :meth:`reference_height` moves the ground this estimator reads it from, not it), if fresh."""
        if self._baro_alt_m is None or self._t_s - self._baro_t_s > BARO_STALE_S:
            return None
        return self._baro_alt_m

    @property
    def height_m(self) -> float:
        return self._h
