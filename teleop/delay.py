"""The operator view tells the truth about delay (issue 18, item 4): the measured round trip and where the
vehicle is now. Pure: the estimator's figures and the image's state in, numbers out.

* :class:`LinkDelay` — the TIMESYNC round trip to the companion (filtered, p50, p99) and the clock offset, a
  frozen snapshot the link thread publishes for the page, ``status.json`` and the CSV.
* The prediction — the image (and TELEOP_FEEDBACK) describes the vehicle when the frame was captured; it
  reaches the station one way later, so the vehicle is now about ``latency = rtt / 2`` further along. With
  its velocity ``v_h`` (H frame, the last state) held constant over that time the vehicle has moved
  ``d_h = v_h * latency`` (:func:`predicted_displacement_h_m`), and a point seen at ``p_c`` in the camera
  frame is now at ``p_c - R_qc^T R_hq^T d_h`` (:func:`predicted_points_c_m`: the attitude is held too;
  ``R_hq`` is the roll/pitch rotation Q -> H of :func:`quadlink.frames.R_hq`, ``R_qc`` the camera mount).
  The view draws those points hollow beside the measured ones, and a ghost marker of ``d_h`` in its
  top-down velocity inset.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from quadlink.frames import R_hq
from quadlink.mavlink.timesync import NS, TimesyncEstimator

Vec3 = tuple[float, float, float]
MAX_PREDICTION_S = 2.0      # beyond this a constant-velocity guess is no longer "where the vehicle is"


@dataclass(frozen=True)
class LinkDelay:
    """Round trip to the companion (s; NaN before the first TIMESYNC answer) and its clock offset."""

    rtt_s: float = math.nan          # exponential average (display)
    rtt_p50_s: float = math.nan
    rtt_p99_s: float = math.nan
    offset_s: float = math.nan       # companion clock minus ours
    samples: int = 0

    @property
    def one_way_s(self) -> float:
        """The one-way latency assumed for the prediction: half the filtered round trip (symmetric path)."""
        return 0.5 * self.rtt_s

    def status(self) -> dict[str, float | int | None]:
        """The figures for ``status.json`` (ms, None before the first answer)."""
        def ms(v: float) -> float | None:
            return round(v * 1e3, 1) if math.isfinite(v) else None

        return {"rtt_ms": ms(self.rtt_s), "rtt_p50_ms": ms(self.rtt_p50_s), "rtt_p99_ms": ms(self.rtt_p99_s),
                "clock_offset_ms": ms(self.offset_s), "timesync_samples": self.samples}


def link_delay(est: TimesyncEstimator) -> LinkDelay:
    """Snapshot of the estimator (call from the thread that feeds it)."""
    return LinkDelay(est.rtt_filtered_s if est.rtt_filtered_s is not None else math.nan,
                     est.rtt_percentile_s(50.0), est.rtt_percentile_s(99.0),
                     est.offset_ns / NS if est.offset_ns is not None else math.nan, est.accepted)


def predicted_displacement_h_m(v_h_m_s: ArrayLike, latency_s: float) -> Vec3 | None:
    """How far the vehicle has moved in H since its last state (constant velocity); None if unknown."""
    v = np.asarray(v_h_m_s, dtype=float).reshape(3)
    if not (math.isfinite(latency_s) and 0.0 <= latency_s <= MAX_PREDICTION_S and np.all(np.isfinite(v))):
        return None
    d = v * latency_s
    return float(d[0]), float(d[1]), float(d[2])


def predicted_points_c_m(points_c_m: ArrayLike, displacement_h_m: ArrayLike, roll_rad: float, pitch_rad: float,
                         R_qc: ArrayLike) -> NDArray[np.float64]:
    """Camera-frame points as seen from the vehicle after it moved ``displacement_h_m`` (attitude held)."""
    p = np.asarray(points_c_m, dtype=float).reshape(-1, 3)
    d_c = np.asarray(R_qc, dtype=float).T @ R_hq(roll_rad, pitch_rad).T @ np.asarray(displacement_h_m, float)
    return p - d_c
