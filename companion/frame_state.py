"""What the camera-rate step leaves for the rest of the loop (pure: stamps, modes and parameters are arguments).

The frame step (:func:`companion.frame_step.frame_step`) runs once per camera frame; between frames the daemon
still answers from what the last one left: TELEOP_FEEDBACK (on the IMU's stamps), the operator image, the pose
the motion arbiter resolves scripts against, the fallback setpoints while the camera is silent; and the messages
that describe the vehicle (ODOMETRY, ATTITUDE, LOCAL_POSITION_NED, OBSTACLE_DISTANCE) are built from it.
:class:`FrameState` holds it: perception's last output and the odometry's health (with the reset counter that
ODOMETRY carries), the last reference, the nearest obstacle and the avoidance's points, the camera mount, the
last gyro sample, the height held to the floor (:mod:`companion.height`), and the pan-scan's time origin (the
entry into TELEOP).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator
from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion import messages as msgs
from companion.arbiter import Pose
from companion.frame_step import NO_SCAN, FrameStep, fallback_step, feedback_message, operator_image_meta
from companion.height import HeightEstimator, HeightParams
from companion.modes import Mode
from companion.obstacle_points import sector_distances_m
from companion.operator_input import OperatorInput
from companion.pan_scan import PanScanParams, PanScanState, pan_scan
from companion.reference import ReferenceOutput
from companion.reference_params import ReferenceParams
from perception.obstacle_map import ObstacleSectors
from perception.pipeline import PerceptionOutput
from quadlink.camera import RgbdFrame
from quadlink.operator_image import OperatorImageMeta


class FrameState:
    """The state between camera frames; ``height``: the height estimator's parameters."""

    def __init__(self, height: HeightParams) -> None:
        self.last_output: PerceptionOutput | None = None          # perception's last output (perception.pipeline)
        self.last_ref: ReferenceOutput | None = None
        self.odometry_ok = False
        self.reset_counter = 0                       # ODOMETRY's reset_counter: the estimate restarted
        self.height = HeightEstimator(height)
        self.R_qc = np.eye(3)                        # the camera mount of the last frame
        self.gyro_q_rad_s = np.zeros(3)              # the last IMU sample's gyro (Q)
        self.nearest: tuple[NDArray[np.float64], float] | None = None   # nearest obstacle (vector in H, m)
        self.avoidance_points_h_m: NDArray[np.float64] | None = None   # the avoidance's points at the last frame
        self._scan_t0_s: float | None = None

    def on_odometry(self, out: PerceptionOutput | None, first_frame: bool) -> None:
        """Perception's output for a frame (None: it failed on it): the odometry's health; good again after a
        failure (not on the first frame), the estimate has restarted: the reset counter tells the autopilot."""
        ok = out is not None and bool(out.odometry_ok)
        if ok and not self.odometry_ok and not first_frame:
            self.reset_counter += 1
        self.odometry_ok = ok

    def on_step(self, step: FrameStep) -> None:
        """A frame's decision: its reference, and the nearest obstacle and points for the feedback and the image."""
        self.nearest = step.nearest
        self.avoidance_points_h_m = step.obstacle_points_h_m
        self.last_ref = step.ref

    # ------------------------------------------------------------------ the pan-scan's time
    def on_mode(self, mode: Mode, frame_stamp_s: float | None) -> None:
        """The mode now: entering TELEOP starts the pan-scan's time at the latest frame's stamp (0 before any)."""
        if mode == Mode.TELEOP and self._scan_t0_s is None:
            self._scan_t0_s = frame_stamp_s if frame_stamp_s is not None else 0.0
        elif mode != Mode.TELEOP:
            self._scan_t0_s = None

    def scan(self, mode: Mode, stamp_s: float, params: PanScanParams) -> PanScanState:
        """The pan-scan at ``stamp_s`` (eqs. 4-5): none outside TELEOP."""
        if mode != Mode.TELEOP or self._scan_t0_s is None:
            return NO_SCAN
        return pan_scan(params, stamp_s - self._scan_t0_s)

    # ------------------------------------------------------------------ what is read between frames
    def position_m(self, out: PerceptionOutput) -> NDArray[np.float64]:
        """The odometry's position (local NED from the take-off pose) with the height held to the floor
        (:mod:`companion.height`): what the arbiter, the autopilot's ODOMETRY and the ground station get."""
        p = np.array(out.position_m, dtype=float)
        if self.height.height_m is not None and out.odometry_ok:
            p[2] = -self.height.height_m
        return p

    def pose(self, mode: Mode, frame_stamp_s: float | None, scan_params: PanScanParams) -> Pose:
        """What the arbiter needs of the state: the odometry's position and yaw, the pan-scan's offset; the height
        is the one held to the floor, so a trajectory's altitude is the floor's, not the drift's."""
        out = self.last_output
        scan = self.scan(mode, frame_stamp_s, scan_params) if frame_stamp_s is not None else NO_SCAN
        if out is None or not out.odometry_ok or out.position_m is None:
            return Pose(None, None, scan.yaw_offset_rad)
        p = self.position_m(out)
        return Pose((float(p[0]), float(p[1]), float(p[2])), float(out.yaw_rad), scan.yaw_offset_rad)

    def fallback(self, op: OperatorInput, params: ReferenceParams, operator_enabled: bool,
                 stamp_s: float, baro_height_m: float | None = None) -> ReferenceOutput:
        """No camera frame: the reference from the last map (:func:`companion.frame_step.fallback_step`), kept as
        the last reference; ``baro_height_m``: the autopilot's barometer-fused height (None: none fresh)."""
        self.last_ref = fallback_step(self.last_output, op, self.R_qc, params, operator_enabled,
                                      height_above_takeoff_m=self.height.height_m,
                                      height_verified=self.height.verified(stamp_s), baro_height_m=baro_height_m)
        return self.last_ref

    def odometry_message(self, stamp_s: float, out: PerceptionOutput) -> Any:
        """ODOMETRY at ``stamp_s`` for perception's output ``out`` (:func:`companion.messages.odometry_message`)."""
        return msgs.odometry_message(stamp_s, self.position_m(out), out.roll_rad, out.pitch_rad, out.yaw_rad,
                                     out.v_h_m_s, out.omega_q_rad_s, out.v_h_cov, bool(out.odometry_ok),
                                     float(out.odometry_fitness), self.reset_counter)

    def telemetry(self, stamp_s: float, out: PerceptionOutput, min_distance_cm: int,
                  max_distance_cm: int, params: ReferenceParams) -> Iterator[Any]:
        """ATTITUDE, LOCAL_POSITION_NED and OBSTACLE_DISTANCE at ``stamp_s`` for the ground stations, one by one.
        OBSTACLE_DISTANCE holds the avoidance's points of the last frame step (the floor out, within the height
        band with ``params.horizontal_only``), sector by sector
        (:func:`companion.obstacle_points.sector_distances_m`)."""
        yield msgs.attitude_message(stamp_s, out.roll_rad, out.pitch_rad, out.yaw_rad, out.omega_q_rad_s)
        yield msgs.local_position_message(stamp_s, self.position_m(out), out.yaw_rad, out.v_h_m_s)
        yield msgs.obstacle_distance_message(stamp_s, self.obstacle_sectors(out, params), min_distance_cm,
                                             max_distance_cm)

    def obstacle_sectors(self, out: PerceptionOutput, params: ReferenceParams) -> ObstacleSectors:
        """Perception's sector summary with its distances replaced by the avoidance's (its unknown sectors kept)."""
        s = out.sectors
        band_m = params.vertical_band_m if params.horizontal_only else math.inf
        distances = sector_distances_m(self.avoidance_points_h_m, s.distances_m, s.increment_deg,
                                       s.angle_offset_deg, s.min_distance_m, band_m)
        return dataclasses.replace(s, distances_m=distances)

    def feedback(self, stamp_s: float, scan: PanScanState, mode: Mode, gcs_ok: bool, obstacles_fresh: bool) -> Any:
        """TELEOP_FEEDBACK at ``stamp_s`` (:func:`companion.frame_step.feedback_message`)."""
        return feedback_message(stamp_s, self.last_output, self.last_ref, scan, self.R_qc, self.nearest,
                                self.gyro_q_rad_s, mode, self.odometry_ok, gcs_ok, obstacles_fresh)

    def image_meta(self, frame: RgbdFrame, out: PerceptionOutput, ref: ReferenceOutput, mode: Mode,
                   scan_params: PanScanParams) -> OperatorImageMeta:
        """The operator image's metadata for ``frame`` (:func:`companion.frame_step.operator_image_meta`)."""
        return operator_image_meta(frame.stamp_s, out, ref, self.scan(mode, frame.stamp_s, scan_params), scan_params,
                                   self.gyro_q_rad_s, mode, self.avoidance_points_h_m, frame.R_qc, frame.p_qc_m)
