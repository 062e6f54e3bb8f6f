"""Offboard service: setpoint and odometry ingestion, and the velocity estimate in H (pure; time as argument).

Velocity setpoints (SET_POSITION_TARGET_LOCAL_NED, type_mask 1479 velocity + yaw rate, 3527 velocity only,
2503 velocity + yaw): in MAV_FRAME_BODY_NED, BODY_OFFSET_NED and BODY_FRD the velocity is taken in the
yaw-aligned body frame H (rotated by yaw only), which is what PX4's mavlink receiver and ArduCopter's GUIDED
mode do with these frames; in MAV_FRAME_LOCAL_NED / LOCAL_OFFSET_NED it is in the odometry's local NED frame
and rotated into H with the yaw estimate. A setpoint with any used field non-finite is refused and counted
(issue 16), so no NaN reaches the control step. ODOMETRY gives the velocity in H; the IMU propagates it
between odometry messages (``a_h = R_hq f_q + g e3``, at most :data:`IMU_PREDICTION_HORIZON_S`).
"""

from __future__ import annotations

import logging
import math
from typing import Any

import numpy as np

from firmware_bridge.attitude_filter import AttitudeEstimate
from firmware_bridge.drag_velocity import low_pass
from firmware_bridge.geometric_tracker import SetpointRejected, decode_trajectory_setpoint
from firmware_bridge.modes import FlightMode, TakeoffPhase
from firmware_bridge.state import AttitudeSetpoint, BridgeState, Outbound, VelocitySetpoint
from quadlink.frames import GRAVITY_M_S2, R_from_quat_wxyz, R_hq, Rz, euler_from_R, wrap_pi
from quadlink.mavlink import mavlink
from quadlink.mavlink.setpoint_masks import (
    ATM_ATTITUDE,
    ATM_THRUST,
    ATM_YAW_RATE,
    BODY_FRAMES,
    TM_ACCEL,
    TM_YAW,
    TM_YAW_RATE,
)

log = logging.getLogger("firmware_bridge.autopilot")

# SET_POSITION_TARGET_LOCAL_NED type_mask bits (POSITION_TARGET_TYPEMASK)
ODOM_WORLD_FRAMES = (mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_FRAME_LOCAL_FRD)
ODOM_BODY_FRAMES = (mavlink.MAV_FRAME_BODY_FRD, mavlink.MAV_FRAME_BODY_NED)

# SET_ATTITUDE_TARGET type_mask bits (ATTITUDE_TARGET_TYPEMASK)

IMU_PREDICTION_HORIZON_S = 0.3
TKO_REANCHOR_M = 0.3   # odometry back in an open-loop take-off: its height this far from the climb -> re-anchored
VZ_GATE_MIN_HEIGHT_M = 0.3   # outside a take-off the vertical gate acts only this high on the barometer: lower,
                             # in a landing, the baro-fused height read 0 (and its vertical speed 0) with the
                             # vehicle still 0.1-0.2 m up and descending (eight campaign flights, seed 777); there a
                             # landing flies level on the baro anyway (BRG_LAND_LVL_ALT, 0.3 m). Higher (0.5 m), a
                             # phantom descent refused above and accepted below held a landing hovering at the line
POSITION_CORRECTION_MAX_M_S = 1.0  # a trajectory setpoint's position term, per axis (a far x_d is not a sprint)
DEAD_RECKONING_LEAK_TAU_S = 3.0
IMU_DT_MAX_S = 0.1  # a longer gap (or a step back) restarts the integration at the nominal sample period
QUAT_NORM_TOLERANCE = 0.1
YAW_TRACK_GAIN_1_S = 2.0  # an absolute yaw target is tracked through the yaw-rate command


class OffboardService:
    """Setpoint, odometry and IMU ingestion into the shared :class:`~firmware_bridge.state.BridgeState`: owns the
    setpoints (``vel_sp``, ``att_sp``), the odometry and IMU fields and the velocity estimate in H; depends on no
    other service."""

    def __init__(self, state: BridgeState) -> None:
        self.state = state

    def on_imu(self, now_s: float, time_usec: int, accel_q_m_s2: np.ndarray,
               gyro_q_rad_s: np.ndarray) -> AttitudeEstimate:
        """One IMU sample (SI, body FRD) at board time ``time_usec``; returns the attitude estimate it gave."""
        s = self.state
        dt = 0.0 if s.imu_time_s is None else now_s - s.imu_time_s
        if s.imu_time_s is None or dt < 0 or dt > IMU_DT_MAX_S:
            dt = 1.0 / s.vehicle.imu.rate_hz
        s.imu_time_s = now_s
        s.last_imu_time_usec = int(time_usec)
        s.imu_samples += 1
        s.last_accel_q = np.asarray(accel_q_m_s2, dtype=float)
        s.last_gyro_q = np.asarray(gyro_q_rad_s, dtype=float)
        est = s.filter.update(now_s, s.last_gyro_q, s.last_accel_q)
        # acceleration in H from the specific force: a_h = R_hq f_q + g e3
        a_h = R_hq(est.roll_rad, est.pitch_rad) @ s.last_accel_q + np.array([0.0, 0.0, GRAVITY_M_S2])
        if s.in_air:
            s.dv_h_imu += a_h * dt
            s.v_h_gate_ref += a_h * dt
            s.v_h_dead_reckoned += a_h * dt - s.v_h_dead_reckoned * (dt / DEAD_RECKONING_LEAK_TAU_S)
        board = s.last_board_command
        s.vertical.update(dt, float(a_h[2]), board.thrust if board.armed else 0.0, on_ground=not s.in_air)
        # the drag's velocity is learnt from the odometry while it is good and fresh (in the air only)
        learn = s.in_air and s.odom_ok and s.odom_time_s is not None and \
            now_s - s.odom_time_s <= IMU_PREDICTION_HORIZON_S
        v_q = R_hq(est.roll_rad, est.pitch_rad).T @ (s.v_h_odom + s.dv_h_imu) if learn else None
        s.drag.update(dt, s.last_accel_q[:2], None if v_q is None else v_q[:2])
        if s.in_air and not learn and s.odom_time_s is not None:
            # past the IMU's prediction horizon the horizontal dead reckoning is the drag's velocity where it is
            # known: the integral of a_h carries the tilt error (the board's level is 0.5-1 deg off, 0.1-0.2 m/s^2),
            # and it starts from the last accepted odometry, which may have been slow already. In front of the
            # black partition the odometry read 0.0-0.1 m/s for a second with the vehicle at 0.1-0.3 m/s, then
            # failed; HOLD on the integral flew on 0.45 m in the 2.7 s before the loss was declared, to 0.25 m of
            # the partition (tests/sitl/test_invisible_sitl.py, CI on 92bef0e and afc0755)
            drag_h = self.drag_velocity_h(est)
            if drag_h is not None:
                s.v_h_dead_reckoned[:2] = drag_h[:2]
        if learn and not s.drag_told:
            c = s.drag.coefficients()
            if c is not None:
                s.drag_told = True
                s.event(mavlink.MAV_SEVERITY_INFO, f"Drag learnt: k {c[0][0]:.2f}/{c[1][0]:.2f} 1/s")
        return est

    def drag_velocity_h(self, est: AttitudeEstimate, nominal: bool = True) -> np.ndarray | None:
        """The horizontal velocity in H from the drag (:mod:`firmware_bridge.drag_velocity`), if BRG_DRAG_HOLD and
        learnt in this flight, or (``nominal``) on BRG_DRAG_K_NOM where the flight has not moved enough to learn it."""
        s = self.state
        if s.params["BRG_DRAG_HOLD"] <= 0.0:
            return None
        v_q = s.drag.velocity_q_xy(s.params["BRG_DRAG_K_NOM"] if nominal else 0.0)
        if v_q is None:
            return None
        return R_hq(est.roll_rad, est.pitch_rad) @ np.array([v_q[0], v_q[1], 0.0])

    def v_est_h(self, now_s: float) -> np.ndarray:
        """Velocity in H: last odometry plus the IMU-integrated change since (short horizon); past it, in the air, the
        IMU's dead reckoning from the last accepted odometry on (a frozen odometry velocity is flown on as if it were
        still true: with the odometry failed in front of a dark partition, HOLD crept 0.25 m toward it before the
        loss was declared)."""
        s = self.state
        if s.odom_time_s is not None and now_s - s.odom_time_s <= IMU_PREDICTION_HORIZON_S:
            v = s.v_h_odom + s.dv_h_imu
        elif s.in_air and s.odom_time_s is not None:
            v = s.v_h_dead_reckoned.copy()
        else:
            v = s.v_h_odom.copy()
        return self._vz_within_baro(v)

    def _vz_within_baro(self, v_h: np.ndarray) -> np.ndarray:
        """In the air, the vertical velocity held within BRG_ODOM_VZBAND of the barometer-fused estimate's (where the
        vertical gate has a reference, :meth:`_vz_reference`): the odometry's is flown while the two agree, never
        more than the band away from the barometer's. An odometry degrading before it fails can read level flight, or a
        descent, while the vehicle climbs: the search's trial 31 (seed 15, on ``392dd2d``) read 0.0-0.1 m/s of
        descent for a second as the vehicle climbed at 0.2-0.3 m/s under a ceiling limit (the baro-fused estimate
        said so, within 0.05 m/s), 0.25-0.35 m/s off -- under the gate's 0.5 -- and the tracker climbed on to
        0.27 m from the ceiling before the odometry was declared lost."""
        band = self.state.params["BRG_ODOM_VZBAND"]
        if band <= 0.0 or not self.state.in_air:
            return v_h
        ref = self._vz_reference()
        if ref is None:
            return v_h
        out = np.array(v_h, dtype=float)
        out[2] = min(max(float(out[2]), ref - band), ref + band)
        return out

    def velocity_reference(self, sp: VelocitySetpoint, yaw_rad: float) -> tuple[np.ndarray, float]:
        if sp.v_h is not None:
            v_ref = np.array(sp.v_h)
        else:
            assert sp.v_ned is not None
            v_ref = Rz(-yaw_rad) @ np.array(sp.v_ned)  # local NED -> H: rotate by -yaw about z
        if sp.yaw_rate_rad_s is not None:
            yaw_rate = sp.yaw_rate_rad_s
        elif sp.yaw_rad is not None:
            yaw_rate = YAW_TRACK_GAIN_1_S * wrap_pi(sp.yaw_rad - yaw_rad)  # yaw tracked through the yaw-rate command
        else:
            yaw_rate = 0.0
        return v_ref, yaw_rate

    def trajectory_terms(self, sp: VelocitySetpoint, yaw_rad: float,
                         now_s: float) -> tuple[np.ndarray, np.ndarray | None]:
        """A trajectory setpoint's extra terms in H: the velocity correction of its position x_d and its a_d.

        With a position (LOCAL_NED, the odometry's frame) and fresh odometry, v_ref gains -(k_x / k_v) e_x,
        e_x = p_odom - x_d, clamped to ``POSITION_CORRECTION_MAX_M_S`` per axis: through the velocity-only eq. (4)
        (-k_v (v - v_ref)) that is paper 003's -k_x e_x - k_v e_v exactly (BRG_GEO_KX, BRG_GEO_KV).
        """
        s = self.state
        dv = np.zeros(3)
        if sp.p_ned is not None and s.odom_p_ned_m is not None and s.odom_ok \
                and s.fresh(s.odom_time_s, now_s, s.params["BRG_ODOM_LOSS_T"]):
            k_v = s.params["BRG_GEO_KV"]
            k_p = s.params["BRG_GEO_KX"] / k_v if k_v > 0 else 0.0
            e_x = s.odom_p_ned_m - np.array(sp.p_ned)
            dv = Rz(-yaw_rad) @ np.clip(-k_p * e_x, -POSITION_CORRECTION_MAX_M_S, POSITION_CORRECTION_MAX_M_S)
        if sp.a_h is not None:
            return dv, np.array(sp.a_h)
        if sp.a_ned is not None:
            return dv, Rz(-yaw_rad) @ np.array(sp.a_ned)
        return dv, None

    def on_set_position_target_local_ned(self, now_s: float, msg: Any, link: int) -> list[Outbound]:
        s = self.state
        if not s.for_us(msg):
            return []
        tm = int(msg.type_mask)
        frame = msg.coordinate_frame
        yaw_rate = None if tm & TM_YAW_RATE else float(msg.yaw_rate)
        yaw = None if tm & TM_YAW or yaw_rate is not None else float(msg.yaw)
        if not all(math.isfinite(x) for x in (yaw_rate, yaw) if x is not None):
            self._reject_setpoint("Setpoint rejected: non-finite field")  # issue 16: never a NaN to the board
            return []
        try:
            # PX4's masks: velocity (+ acceleration a_d, + position x_d in LOCAL_NED); body frames stay in H
            # (decoded at yaw 0, i.e. unrotated; the control step rotates local NED into H with the current yaw)
            target = decode_trajectory_setpoint(msg, yaw_rad=0.0)
        except SetpointRejected as exc:
            self._reject_setpoint(f"Setpoint rejected: {exc}"[:50])
            return []
        v = (float(target.v_ned_m_s[0]), float(target.v_ned_m_s[1]), float(target.v_ned_m_s[2]))
        has_accel = (tm & TM_ACCEL) == 0
        a = (float(target.a_ned_m_s2[0]), float(target.a_ned_m_s2[1]), float(target.a_ned_m_s2[2])) \
            if has_accel else None
        p = None if target.p_ned_m is None else \
            (float(target.p_ned_m[0]), float(target.p_ned_m[1]), float(target.p_ned_m[2]))
        body = frame in BODY_FRAMES
        s.vel_sp = VelocitySetpoint(v if body else None, None if body else v, yaw_rate, yaw,
                                    a_h=a if body else None, a_ned=None if body else a, p_ned=p)
        s.att_sp = None
        s.setpoint_time_s = now_s
        if s.mode == FlightMode.OFFBOARD and s.armed_cmd and not s.in_air and v[2] < -0.1:
            s.in_air = True  # a climb command from the ground takes off
            s.z_ground_m = s.odom_z_m
        return []

    def on_set_attitude_target(self, now_s: float, msg: Any, link: int) -> list[Outbound]:
        s = self.state
        if not s.for_us(msg):
            return []
        tm = msg.type_mask
        q = np.asarray(msg.q, dtype=float)
        if tm & ATM_ATTITUDE:
            roll = pitch = 0.0
            yaw = None
        else:
            if not np.all(np.isfinite(q)) or abs(np.linalg.norm(q) - 1.0) > QUAT_NORM_TOLERANCE:
                self._reject_setpoint("Attitude setpoint rejected: quaternion")
                return []
            roll, pitch, yaw_q = euler_from_R(R_from_quat_wxyz(q / np.linalg.norm(q)))
            yaw = yaw_q
        yaw_rate = None if tm & ATM_YAW_RATE else float(msg.body_yaw_rate)
        if yaw_rate is not None:
            yaw = None
        thrust = None if tm & ATM_THRUST else float(msg.thrust)
        if not all(math.isfinite(x) for x in (yaw_rate, thrust) if x is not None):
            self._reject_setpoint("Attitude setpoint rejected: non-finite field")  # min(max(NaN)) passes NaN
            return []
        s.att_sp = AttitudeSetpoint(float(roll), float(pitch), yaw_rate, yaw, thrust)
        s.vel_sp = None
        s.setpoint_time_s = now_s
        if s.mode == FlightMode.OFFBOARD and s.armed_cmd and not s.in_air and thrust is not None \
                and thrust > 0.5 * s.tracker.hover_thrust_fraction:
            s.in_air = True
        return []

    def on_odometry(self, now_s: float, msg: Any, link: int) -> list[Outbound]:
        s = self.state
        q = np.asarray(msg.q, dtype=float)
        v = np.array([msg.vx, msg.vy, msg.vz], dtype=float)
        if not np.all(np.isfinite(v)) or msg.frame_id not in ODOM_WORLD_FRAMES or \
                msg.child_frame_id not in ODOM_BODY_FRAMES + ODOM_WORLD_FRAMES:
            s.counters["odometry_rejected"] += 1
            if s.counters["odometry_rejected"] in (1, 10, 100, 1000):
                s.event(mavlink.MAV_SEVERITY_WARNING, f"Odometry rejected: frames {msg.frame_id}/{msg.child_frame_id}")
            return []
        if getattr(msg, "quality", 0) < s.params["BRG_ODOM_QMIN"]:
            # the companion's "failed" (0; MAVLink's -1): not a velocity source, it simply does not refresh
            s.counters["odometry_low_quality"] += 1
            return []
        est = s.filter.estimate
        roll, pitch, yaw = est.roll_rad, est.pitch_rad, est.yaw_rad
        if np.all(np.isfinite(q)) and abs(np.linalg.norm(q) - 1.0) < QUAT_NORM_TOLERANCE:
            roll, pitch, yaw = euler_from_R(R_from_quat_wxyz(q / np.linalg.norm(q)))
            # the tilt from the odometry's attitude (the camera's rotation, good through a push), not only the
            # accelerometer's direction: after a 1.5 m/s push (paper 003's hover) the accelerometer-levelled tilt
            # put the IMU's prediction 0.5-1.2 m/s behind the true velocity, the gate refused the good odometry for
            # 2 s and the vehicle landed
            s.filter.correct_tilt(now_s, roll, pitch, s.params["BRG_ATT_ODOM_TAU"])
            s.filter.set_yaw(yaw)  # anchor the heading to the companion's local frame
        if msg.child_frame_id in ODOM_BODY_FRAMES:
            v_h = R_hq(roll, pitch) @ v  # body FRD -> H (paper 000: H is yaw-aligned, level)
        else:
            v_h = Rz(-yaw) @ v  # local NED -> H
        if not self._velocity_plausible(now_s, v_h):
            return []
        s.v_h_odom = v_h
        s.dv_h_imu[:] = 0.0
        s.v_h_dead_reckoned = np.array(s.v_h_gate_ref if s.in_air else v_h, dtype=float)
        z = float(msg.z) if math.isfinite(msg.z) else None
        reset = s.odom_reset_counter is not None and msg.reset_counter != s.odom_reset_counter
        s.odom_reset_counter = int(msg.reset_counter)
        if s.in_air and z is not None and (reset or s.z_ground_m is None):
            # the odometry's frame began (or was reset) in the air: anchor it so the height stays continuous
            # (a frame that merely paused, the same reset counter, keeps its anchor: it is the better height)
            s.z_ground_m = z + s.height_m
        s.odom_z_m = z
        p_ned = np.array([msg.x, msg.y, msg.z], dtype=float)
        s.odom_p_ned_m = p_ned if np.all(np.isfinite(p_ned)) else None
        s.odom_time_s = now_s
        if not s.odom_ok:
            s.odom_ok = True
            self.odometry_ok_event()
        if s.blind and s.in_air:
            # the climb so far was measured by the IMU (s.height_m); an anchor taken on the ground from an odometry
            # that was drifting there (its height is only held to the floor once the camera sees it, in the air)
            # can put the odometry's height far from it: CI flew a take-off that ended at once "at 0.99 m" with
            # the vehicle 0.28 m up. Beyond TKO_REANCHOR_M the odometry is re-anchored to the measured climb.
            if z is not None and s.z_ground_m is not None and \
                    abs(-(z - s.z_ground_m) - s.height_m) > TKO_REANCHOR_M:
                s.event(mavlink.MAV_SEVERITY_WARNING,   # STATUSTEXT: 50 characters
                        f"Odometry height {-(z - s.z_ground_m):.2f} m, climbed {s.height_m:.2f}")
                s.z_ground_m = z + s.height_m
            s.blind = False
            if s.mode == FlightMode.TAKEOFF:
                s.takeoff_phase = TakeoffPhase.CLOSED_LOOP
            s.event(mavlink.MAV_SEVERITY_INFO, f"Odometry at {s.height_m:.2f} m: closed loop")
        return []

    def _disagrees_with_drag(self, now_s: float, v_h: np.ndarray) -> float | None:
        """The drag gate (BRG_ODOM_DGATE): the odometry's horizontal velocity, through the same low-pass as the
        drag's force reading, against the drag's velocity (learnt from this bridge's odometry only, never the
        nominal). The IMU gate catches jumps; an odometry that reads slower and slower at full quality passes it: in
        front of the black partition it read 0.0-0.1 m/s for a second with the vehicle at 0.1-0.3 m/s (the drag said
        so), and the vehicle came to 0.41 m of the partition in TELEOP. Returns the disagreement (m/s) once it has
        lasted BRG_ODOM_DGATE_T: the odometry's velocity is refused until it agrees again (a refusal that lasts is an
        odometry loss, with its brake); None while they agree."""
        s = self.state
        dt = None if s.odom_lp_time_s is None else now_s - s.odom_lp_time_s
        s.odom_lp_time_s = now_s
        fresh = dt is None or not 0.0 <= dt <= IMU_PREDICTION_HORIZON_S   # a gap restarts the low-pass
        s.odom_v_h_lp = low_pass(None if fresh else s.odom_v_h_lp, np.asarray(v_h, dtype=float)[:2],
                                 0.0 if dt is None else dt, s.drag.force_tau_s)
        drag = self.drag_velocity_h(s.filter.estimate, nominal=False)
        if drag is None:
            s.drag_disagree_since_s = None
            return None
        disagreement = math.hypot(float(s.odom_v_h_lp[0] - drag[0]), float(s.odom_v_h_lp[1] - drag[1]))
        s.drag_disagreement_max_m_s = max(s.drag_disagreement_max_m_s, disagreement)
        gate = s.params["BRG_ODOM_DGATE"]
        if gate <= 0.0 or disagreement <= gate:
            s.drag_disagree_since_s = None
            return None
        if s.drag_disagree_since_s is None:
            s.drag_disagree_since_s = now_s
        return disagreement if now_s - s.drag_disagree_since_s >= s.params["BRG_ODOM_DGATE_T"] else None

    def _velocity_plausible(self, now_s: float, v_h: np.ndarray) -> bool:
        """The velocity gate (BRG_ODOM_VGATE, like EKF2's innovation gates): in the air, an odometry velocity is used
        only if it is within the gate (horizontally) of the gate's reference: the IMU's prediction, pulled a share
        (BRG_ODOM_VGATE_K) toward each accepted odometry velocity; with nothing accepted within BRG_ODOM_LOSS_T (a
        start, a re-acquisition), the IMU's dead reckoning (which the level, braked flight without odometry keeps
        near the truth).

        Near the floor the camera has nothing in range and the odometry's velocity can turn to garbage: in LAND on
        the floor it read metres per second that were not there, and the tracker chasing them threw a vehicle
        across the room at 4 m/s (campaign seed 2031, flight 1), or 3 m at 2 m/s from 0.46 m up in a loaded demo.
        Re-acquired in front of a dark partition, it ramped 0 -> 0.9 m/s in 0.15 s with the vehicle still, each
        sample within the gate of the one before: when the reference was the last accepted sample it walked along,
        the tracker braked against the phantom and flew the vehicle 4 m backward into a wall. A refused sample is
        counted (STATUSTEXT on the 1st, 10th, 100th, 1000th); a refusal that lasts is an odometry loss (the
        commander's BRG_ODOM_LOSS_T), with its brake and level descent."""
        s = self.state
        gate = s.params["BRG_ODOM_VGATE"]
        if not s.in_air:
            s.v_h_gate_ref = np.array(v_h, dtype=float)
            s.odom_v_h_lp = None
            s.drag_disagree_since_s = None
            return True
        off_drag_m_s = self._disagrees_with_drag(now_s, v_h)
        if off_drag_m_s is not None:
            s.counters["odometry_drag_gated"] += 1
            if s.counters["odometry_drag_gated"] in (1, 10, 100, 1000):
                s.event(mavlink.MAV_SEVERITY_WARNING, f"Odometry velocity refused: {off_drag_m_s:.1f} m/s off the drag")
            return False
        recent = s.odom_time_s is not None and now_s - s.odom_time_s <= s.params["BRG_ODOM_LOSS_T"]
        reference = s.v_h_gate_ref if recent else s.v_h_dead_reckoned
        jump = math.hypot(float(v_h[0] - reference[0]), float(v_h[1] - reference[1]))
        vz_off = self._vertical_disagreement(float(v_h[2]))
        if (gate <= 0.0 or jump <= gate) and vz_off is None:
            s.v_h_gate_ref = reference + s.params["BRG_ODOM_VGATE_K"] * (np.asarray(v_h, dtype=float) - reference)
            return True
        s.counters["odometry_gated"] += 1
        if recent:   # the estimate the tracker flies on falls back to the reference, not the last accepted sample
            s.v_h_odom = np.array(s.v_h_gate_ref, dtype=float)
            s.dv_h_imu[:] = 0.0
        if vz_off is not None:
            s.counters["odometry_vz_gated"] += 1
            if s.counters["odometry_vz_gated"] in (1, 10, 100, 1000):
                s.event(mavlink.MAV_SEVERITY_WARNING, f"Odometry climb refused: {vz_off:.1f} m/s off the baro")
        elif s.counters["odometry_gated"] in (1, 10, 100, 1000):
            s.event(mavlink.MAV_SEVERITY_WARNING, f"Odometry velocity refused: {jump:.1f} m/s off the IMU")
        return False

    def _vertical_disagreement(self, vz_odom_m_s: float) -> float | None:
        """The vertical gate (BRG_ODOM_VZGATE): how far the odometry's vertical velocity (H, NED) is from the
        barometer-fused estimate's (:mod:`firmware_bridge.vertical_estimator`; 0 while it is pinned to the ground
        under lift-off thrust), if farther than the gate; None if within it, or the gate is off, or the estimate
        has no fresh baro reading, or (outside a take-off) it reads under VZ_GATE_MIN_HEIGHT_M.

        The odometry's first frames after lift-off can follow a floor's texture instead of the floor: a campaign
        flight's read 0.2-1.5 m/s of descent while the vehicle climbed at 0.2-0.7 m/s, the horizontal gate let the
        first samples through (they were 0.1 m/s off horizontally), the take-off switched to closed loop on them
        and the tracker climbed against the phantom descent to 1.25 m/s (seed 777, flight 2); another ended its
        take-off "complete at 0.95 m" 0.2 m up (CI, seed 20261201, flight 2). In the same eight flights the
        baro-fused estimate stayed within 0.05 m/s of the truth through every take-off, and the odometry's
        accepted samples within 0.34 m/s of it (its first, lagging the lift-off) and within 0.25 m/s in offboard
        flight."""
        gate = self.state.params["BRG_ODOM_VZGATE"]
        vz_ref = self._vz_reference()
        if gate <= 0.0 or vz_ref is None:
            return None
        off = abs(vz_odom_m_s - vz_ref)
        return off if off > gate else None

    def _vz_reference(self) -> float | None:
        """The vertical velocity (H, NED) the odometry's is checked against: 0 while the thrust is under lift-off
        (the ground holds the vehicle), the barometer-fused estimate's in a take-off or above VZ_GATE_MIN_HEIGHT_M
        on the barometer; None without a fresh baro reading, or lower outside a take-off."""
        s = self.state
        vertical = s.vertical.estimate
        if vertical.pinned:
            return 0.0
        if not vertical.baro_fused or (s.mode != FlightMode.TAKEOFF and vertical.height_m < VZ_GATE_MIN_HEIGHT_M):
            return None
        return vertical.vz_m_s

    def odometry_ok_event(self) -> None:
        if self.state.in_air:
            self.state.event(mavlink.MAV_SEVERITY_INFO, "Odometry ok")
        else:  # on the ground odometry comes and goes (the camera sees the floor too close): the health bit says it
            log.info("odometry ok")

    def _reject_setpoint(self, text: str) -> None:
        """Count a refused setpoint; STATUSTEXT on the 1st, 10th, 100th, 1000th."""
        self.state.counters["setpoint_rejected"] += 1
        if self.state.counters["setpoint_rejected"] in (1, 10, 100, 1000):
            self.state.event(mavlink.MAV_SEVERITY_WARNING, text)
