"""Roll and pitch for levelling a depth image: the odometry's attitude, its world held to gravity slowly (pure).

The attitude filter (:mod:`quadlink.attitude`) corrects the gyro toward the accelerometer with a 1 s time
constant (``kp_rad_s`` 1), so a manoeuvre's horizontal acceleration leaks into its roll and pitch: on paper 003's
oval (up to ~1 m/s² for a second at a time) it is off by 1-4 deg, and a floor seen 2 m ahead then reads 3-10 cm
higher or lower (``perception.floor``). The odometry's attitude has no such error: its rotation between frames
is the camera's, good to ~0.01 deg a frame. It has another: its world is levelled once, by the filter at its first
frame, and carries whatever tilt that and the frames since left (0.1-0.7 deg after a take-off in the SITL).

So the odometry's attitude is used, with its world turned toward the filter's gravity by a second complementary
filter with a long time constant (``time_constant_s``): the filter's manoeuvre errors, which change sign as the
vehicle speeds up and slows down, average out over it, while a constant tilt of the odometry's world is removed.
Only the tilt is corrected (a rotation of the world about its horizontal axes); yaw is the odometry's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from quadlink.frames import R_hq, euler_from_R
from quadlink.lie import so3_exp

__all__ = ["LevelConfig", "OdometryLevel"]

_E_Z = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class LevelConfig:
    time_constant_s: float = 20.0   # the odometry's world is turned toward the filter's gravity this slowly (0: the
                                    # filter's roll and pitch are used directly, as before)
    max_dt_s: float = 0.5           # longer gaps between tracked frames count as this


class OdometryLevel:
    """The world-tilt correction ``R_corr`` (world -> levelled world) of the odometry's attitude."""

    def __init__(self, config: LevelConfig | None = None) -> None:
        self.config = config or LevelConfig()
        self.R_corr = np.eye(3)
        self._last_s: float | None = None

    def reset(self) -> None:
        self.R_corr = np.eye(3)
        self._last_s = None

    def update(self, stamp_s: float, R_wq_odometry: NDArray[np.float64], roll_rad: float,
               pitch_rad: float) -> tuple[float, float]:
        """Roll and pitch (rad) of the body from the odometry's attitude ``R_wq_odometry`` (body -> its world),
        levelled; ``roll_rad``, ``pitch_rad``: the attitude filter's (gravity) at ``stamp_s``."""
        cfg = self.config
        R = self.R_corr @ np.asarray(R_wq_odometry, dtype=float)
        if self._last_s is not None and cfg.time_constant_s > 0.0:
            dt = min(max(stamp_s - self._last_s, 0.0), cfg.max_dt_s)
            down_odometry_q = R.T @ _E_Z                       # "down" in the body, as each attitude has it
            down_filter_q = R_hq(roll_rad, pitch_rad).T @ _E_Z
            # the small rotation (world frame) that turns the odometry's down toward the filter's; its z part is
            # yaw, which gravity does not observe
            e_w = R @ np.cross(down_filter_q, down_odometry_q)
            e_w[2] = 0.0
            self.R_corr = so3_exp(e_w * (dt / cfg.time_constant_s)) @ self.R_corr
            R = self.R_corr @ np.asarray(R_wq_odometry, dtype=float)
        self._last_s = stamp_s
        roll, pitch, _ = euler_from_R(R)
        return roll, pitch
