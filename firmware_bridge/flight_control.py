"""Flight-control service: the 100 Hz step (closed loop on the odometry, blind take-off and landing before
any odometry, heading hold, touchdown detection). Pure: time is ``now_s``, the board command is returned.

Every :class:`~firmware_bridge.state.BoardCommand` is finite by construction (its constructor refuses
NaN/inf); :meth:`FlightControlService._finish` is the one place a tracker output becomes a board command.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from firmware_bridge.commander import CommanderService
from firmware_bridge.geometric_tracker import GeometricTracker
from firmware_bridge.modes import FlightMode
from firmware_bridge.offboard import OffboardService
from firmware_bridge.state import AttitudeSetpoint, BlindDescent, BoardCommand, BridgeState
from firmware_bridge.velocity_tracker import AttitudeCommand
from quadlink.frames import GRAVITY_M_S2, Rz, wrap_pi
from quadlink.mavlink import mavlink
from quadlink.mk.flags import BoardFlightState

MAX_HEADING_ERROR_RAD = 0.5
HOVER_LEARN_TAU_S = 1.0  # low-pass of the thrust in the open-loop climb: the hover thrust actually needed
GROUND_CONTACT_ACCEL_M_S2 = 0.3  # below hover thrust, less vertical acceleration than this = the ground carries it
TKO_HEIGHT_DISAGREE_M = 0.3  # take-off: integrated climb above the odometry's height by this much is told
BLIND_DESCENT_EXTRA_S = 3.0  # the blind descent probes for the ground after height / rate + this
DESCENT_THRUST_TAU_S = 0.3  # the blind descent's thrust, low-passed: what it holds past the floor it reads
BARO_REREF_MIN_HEIGHT_M = 0.5  # the odometry's height references the baro above this (the camera's 0.5 m range)
FLOOR_READ_M = 0.01  # the baro-fused height reads the floor (the estimator holds it at 0; the baro's pull, mm)
BARO_STILL_M_S = 0.15  # the board's baro climb rate under this (in size) is "not descending" (its failsafe's ground
                       # speed, firmware/src/params.c failsafe_ground_speed_m_s)
FLOOR_HOLD_NO_RATE_S = 0.6  # without the board's climb rate (an older board, a stale frame) the hold lasts this long
DESCENT_SEEN_FRACTION = 0.6  # of BRG_OL_LAND_SPD: the baro's climb rate reads a descent under way
FLOOR_HOLD_GAIN_S_M = 0.3   # the held thrust's trim per m/s of climb-rate error (the board's failsafe_climb_gain)
FLOOR_HOLD_TRIM = 0.1       # at most +-10 % of the held thrust
# odometry lost in the air: the horizontal velocity it last saw (plus the IMU's integral since) is braked for this
# long before the attitude goes level. Campaign 2, flight 16: levelled at once, the vehicle slid 0.19 m on landing
# to 0.21 m of a box. Longer, and the accelerometer's bias (~0.05 m/s^2) would steer it instead.
ODOM_LOST_BRAKE_S = 1.0
ODOM_LOST_BRAKE_TILT_RAD = 0.15   # ~1.5 m/s^2: 0.4 m/s braked in under 0.3 s
POSITION_HOLD_GAIN_1_S = 1.0      # LAND's, TAKEOFF's, LOITER's position hold: m/s back per m from where it began
POSITION_HOLD_MAX_M_S = 0.15
POSITION_HOLD_REANCHOR_M = 0.5    # farther than this from the anchor (an odometry reset): a new anchor
# the board's level: it holds its own attitude estimate, whose error (its accelerometer's bias, the drag it reads as
# tilt, its gyro bias times its filter's 8 s) is 0.5-2 deg; campaign 20261217's flight 6 came down the last 0.3 m of
# its landing "level" at 2 deg of true roll and slid 0.07 m toward a partition. In steady flight on odometry the
# command minus the bridge's estimate (pulled to the odometry's tilt) is that error: commanded, it is level by the
# bridge's estimate
LEVEL_TRIM_TAU_S = 2.0
LEVEL_TRIM_STEADY_RAD_S = 0.1     # learnt only while the roll and pitch rates are below this (the board has settled)
# the board's level error grows with its gyro's bias drift since the arming (its filter holds the bias learnt on the
# ground; the error is the drift times the filter's 8 s): in the SITL's model (0.0005 rad/s per sqrt(s)) one sigma is
# 2.9 deg after 150 s and 7 deg after 15 minutes, and a 150 s hover learnt 7.7 deg (draw 1 of the long-hover landings).
# Capped at 5 deg, the blind descent flew 2-3 deg off level and slid 0.82 m
LEVEL_TRIM_MAX_RAD = math.radians(15.0)
DRAG_HOLD_TILT_RAD = 0.1          # the hold on the drag's velocity corrects a slide of tenths of m/s: ~1 m/s^2 is ample
# (the brake's and the hold's tilt are bounded around the level, :meth:`FlightControlService._level`, not around the
# board's zero: its zero is off by the board's level error, which the tracker's integral carries)
RESTING_THRUST_S = 0.3  # "resting on something": the thrust under the touchdown test's this long. A descent's start
                        # cuts it for ~0.1 s in the air (the odometry lost in a hover: the brake was dropped for good)
CONTROL_DT_S = 0.01  # nominal step (every 5th IMU sample); the measured dt is bounded to [1 ms, 100 ms]
YAW_TRACK_GAIN_1_S = 2.0  # an absolute yaw target is tracked through the yaw-rate command


class FlightControlService:
    """The control step over the shared :class:`~firmware_bridge.state.BridgeState`: owns the height, the heading
    setpoint, the take-off climb's and the blind flight's bookkeeping (climb, learnt hover thrust, descent), the
    touchdown and auto-disarm timers and the last commands. Uses the commander (failsafes, mode changes,
    disarming) and the offboard service (the velocity estimate, the setpoints in H)."""

    def __init__(self, state: BridgeState, commander: CommanderService, offboard: OffboardService) -> None:
        self.state = state
        self.commander = commander
        self.offboard = offboard

    def control_step(self, now_s: float) -> BoardCommand:
        """The 100 Hz step: failsafes, mode logic, the velocity tracker; the board's next setpoint."""
        s = self.state
        dt = CONTROL_DT_S if s.control_time_s is None else min(max(now_s - s.control_time_s, 1e-3), 0.1)
        s.control_time_s = now_s
        self._note_thrust(now_s)
        self.commander.check_links(now_s)
        self._update_height(dt)
        est = s.filter.estimate
        if not s.in_air or (not s.odom_ok and not s.blind) or \
                (s.mode == FlightMode.OFFBOARD and s.att_sp is not None):
            s.yaw_sp_rad = None  # heading hold only in velocity control (or the blind climb) in the air
        if not s.armed_cmd:
            s.in_air = False
            s.blind = False
            s.takeoff_phase = None
            s.blind_descent = None
            s.reset_trackers()
            s.apply_tracker_selection()
            s.on_ground_armed_since_s = None
            return self._board(BoardCommand(0.0, 0.0, 0.0, 0.0, False))
        if not s.in_air:
            # armed on the ground: motors at idle, level, nothing integrates (PX4's "landed" state)
            s.reset_trackers()
            s.apply_tracker_selection()
            s.dv_h_imu[:] = 0.0
            if s.on_ground_armed_since_s is None:
                s.on_ground_armed_since_s = now_s
            timeout = s.params["COM_DISARM_PRFLT"]
            if timeout > 0 and now_s - s.on_ground_armed_since_s > timeout:
                self.commander.disarm(now_s, "Auto-disarm: no takeoff")
                return self._board(BoardCommand(0.0, 0.0, 0.0, 0.0, False))
            if s.mode == FlightMode.LAND:
                self.commander.disarm(now_s, "Landed, disarming")
                return self._board(BoardCommand(0.0, 0.0, 0.0, 0.0, False))
            return self._board(BoardCommand(0.0, 0.0, 0.0, 0.0, True))
        s.on_ground_armed_since_s = None

        # ---- no odometry: take-off phase 1, or the landing that ends it (no odometry yet in this flight), or
        # odometry lost in the air: first brake the slide on the IMU's dead reckoning for ODOM_LOST_BRAKE_S, then
        # the same blind descent (level, thrust capped at hover, touchdown on ground contact)
        if not s.odom_ok and not (s.mode == FlightMode.OFFBOARD and s.att_sp is not None):
            v_ref = np.array([0.0, 0.0, s.params["MPC_LAND_SPEED"]])
            # not while resting on something: thrust below the touchdown test's (campaign 4, flight 14 sat in LAND
            # on the floor, its odometry's velocity garbage, and a brake on it skidded the vehicle 0.16 m)
            # ... nor at the floor on the barometer (campaign seed 2031 flight 13: on the floor in LAND, thrust still
            # near hover, the odometry lost: the brake on a garbage velocity slid the vehicle 0.9 m into a column)
            resting = self._resting_thrust() \
                or self._level_landing()
            braking = s.odom_lost_s is not None and now_s - s.odom_lost_s < ODOM_LOST_BRAKE_S and not resting
            if resting:
                s.odom_lost_s = None   # no brake later in this loss either
            if s.blind and not braking:
                return self._blind_step(now_s, dt, est)
            v_est = s.v_h_dead_reckoned.copy()
            drag = None if resting else self.offboard.drag_velocity_h(est)
            if drag is not None:   # the brake acts on what the drag says (no tilt error in it)
                v_est[:2] = drag[:2]
            if not (braking and np.all(np.isfinite(v_est[:2]))):
                v_est[:2] = 0.0
            if s.vertical.estimate.baro_fused:   # the barometer keeps the vertical speed from drifting (issue 30)
                v_est[2] = s.vertical.vz_m_s
            cmd = s.pid_tracker.update(dt, v_ref, 0.0, v_est, est.roll_rad, est.pitch_rad)
            if not braking:
                roll, pitch = (0.0, 0.0) if resting else self._level()
                cmd = AttitudeCommand(roll, pitch, 0.0, cmd.thrust_fraction, cmd.a_des_h_m_s2, cmd.saturated)
            else:   # a gentle brake: the velocity it acts on is a dead reckoning
                roll, pitch = self._tilt_around_level(cmd, ODOM_LOST_BRAKE_TILT_RAD)
                cmd = AttitudeCommand(roll, pitch, 0.0, cmd.thrust_fraction, cmd.a_des_h_m_s2, cmd.saturated)
            self._detect_touchdown(now_s, cmd, abs(float(v_est[2])))
            return self._finish(cmd)

        if s.mode == FlightMode.OFFBOARD and s.att_sp is not None:
            return self._finish(self._attitude_command(s.att_sp, est))
        if s.mode == FlightMode.LAND and self._level_landing():
            # the landing's last part is flown as the blind descent: level, on the barometer, down to the ground
            # contact test. Near the floor the camera has nothing in range to track: campaign seed 2031 flight 1
            # sat bouncing on the floor in LAND for 5 s (its odometry's vertical speed never quiet enough for the
            # touchdown test), then its odometry's velocity went to garbage and the tracker, chasing it, threw the
            # vehicle across the room at 4 m/s into a wall (0.24 m)
            return self._blind_step(now_s, dt, est)

        v_ref = np.zeros(3)
        yaw_rate = 0.0
        a_ref: np.ndarray | None = None
        if s.mode == FlightMode.OFFBOARD and s.vel_sp is not None:
            v_ref, yaw_rate = self.offboard.velocity_reference(s.vel_sp, est.yaw_rad)
            dv, a_ref = self.offboard.trajectory_terms(s.vel_sp, est.yaw_rad, now_s)
            v_ref = v_ref + dv
        elif s.mode == FlightMode.TAKEOFF:
            # the climb ends when the odometry's height or its integrated climb rate says it is high enough:
            # a height stuck or drifting (a campaign flight's odometry position moved 0.3 m while its velocity,
            # and the vehicle, climbed 3 m into the ceiling) cannot carry the vehicle past the target
            s.tko_climbed_m -= float(self.offboard.v_est_h(now_s)[2]) * dt
            height = max(s.height_m, s.tko_climbed_m)
            if s.tko_climbed_m > s.height_m + TKO_HEIGHT_DISAGREE_M and not s.tko_disagree_told:
                s.tko_disagree_told = True
                s.event(mavlink.MAV_SEVERITY_WARNING,   # STATUSTEXT: 50 characters
                        f"Takeoff: odometry height {s.height_m:.2f}, climbed {s.tko_climbed_m:.2f} m")
            remaining = s.takeoff_target_m - height
            v_ref[2] = -min(s.params["MPC_TKO_SPEED"], max(1.0 * remaining, 0.1))
            # on odometry the climb holds where it began, as LAND does (PX4's take-off holds its position): a
            # velocity loop asked for zero let a 0.16 m/s drift from the blind lift-off die out over 5 s, 0.26 m
            # more toward a wall the camera did not face (campaign 24, flight 25: 0.65 m from it at the start, 0.356)
            v_ref[:2] = self._position_hold(est.yaw_rad)
            if remaining <= 0.05:
                s.event(mavlink.MAV_SEVERITY_INFO, f"Takeoff complete at {height:.2f} m")
                s.takeoff_phase = None
                self.commander.set_mode(FlightMode.LOITER, now_s, "takeoff complete")
                v_ref[2] = 0.0
        elif s.mode == FlightMode.LAND:
            v_ref[2] = s.params["MPC_LAND_SPEED"]
            v_ref[:2] = self._position_hold(est.yaw_rad)
        elif s.fs_hover_until_s is not None and now_s >= s.fs_hover_until_s:
            s.fs_hover_until_s = None
            s.event(mavlink.MAV_SEVERITY_WARNING, "Failsafe: hover done, landing")
            self.commander.set_mode(FlightMode.LAND, now_s, "failsafe")
        if s.mode == FlightMode.LOITER:
            # PX4's Hold holds its place: the hover after a take-off, a ground station's HOLD and the failsafe hover of
            # a stalled companion (BRG_FS_HOVER_T) flew a velocity loop asked for zero, which creeps (3-8 cm/s) and
            # stays wherever a push left it (0.41 m off after 6 s of a steady 0.3 N push in the point-mass test)
            v_ref[:2] = self._position_hold(est.yaw_rad)
        sp = s.vel_sp
        if s.mode == FlightMode.OFFBOARD and sp is not None and sp.yaw_rate_rad_s is None and sp.yaw_rad is not None:
            s.yaw_sp_rad = None  # an absolute yaw target is tracked in velocity_reference
        else:
            yaw_rate = self._heading_hold(dt, yaw_rate, est.yaw_rad)
        v_est = self.offboard.v_est_h(now_s)
        if isinstance(s.tracker, GeometricTracker):  # eq. (4)'s a_d feed-forward (the PID tracker has none)
            cmd = s.tracker.update(dt, v_ref, yaw_rate, v_est, est.roll_rad, est.pitch_rad, a_ref_h=a_ref)
        else:
            cmd = s.tracker.update(dt, v_ref, yaw_rate, v_est, est.roll_rad, est.pitch_rad)
        if s.mode == FlightMode.LAND:
            self._detect_touchdown(now_s, cmd, abs(v_est[2]))
        self._learn_level_trim(dt, est)
        return self._finish(cmd)

    def _blind_step(self, now_s: float, dt: float, est: Any) -> BoardCommand:
        """Flight before any odometry: level (roll = pitch = 0), heading hold on the gyro, vertical velocity
        tracked on the accelerometer-only estimate, thrust under a ceiling. TAKEOFF climbs at BRG_TKO_OL_SPD
        toward the take-off height (thrust ramped up to hover x (1 + BRG_TKO_THR_MRG) over BRG_TKO_RAMP_T)
        until odometry arrives, at most BRG_TKO_OL_ALT (estimated) or BRG_TKO_OL_T; then, or in any other
        mode, it descends at BRG_OL_LAND_SPD with the thrust capped at the hover thrust learnt in the climb
        (it can not climb on a drifting estimate). Once the estimate says ground (height 0, or the descent
        took BLIND_DESCENT_EXTRA_S longer than height / rate) the cap drops to BRG_FS_DESC_THR x hover: in the
        air the vehicle then accelerates downwards, on the ground the accelerometer shows nothing, which is
        the touchdown test that does not depend on the drifting velocity."""
        s = self.state
        p = s.params
        hover_prior = s.pid_tracker.hover_thrust_fraction
        margin = p["BRG_TKO_THR_MRG"]
        vz_est = s.vertical.vz_m_s
        elapsed = 0.0
        if s.mode == FlightMode.TAKEOFF:
            elapsed = now_s - (s.takeoff_start_s if s.takeoff_start_s is not None else now_s)
            height = s.vertical.height_m
            if height >= p["BRG_TKO_OL_ALT"] or elapsed >= p["BRG_TKO_OL_T"]:
                s.event(mavlink.MAV_SEVERITY_CRITICAL,
                        f"No odometry in takeoff ({elapsed:.1f}s, {height:.2f}m): land")
                s.failsafe_reason = "no odometry in takeoff"
                s.takeoff_phase = None
                self.commander.set_mode(FlightMode.LAND, now_s, "no odometry in takeoff")
        elif s.mode != FlightMode.LAND:
            s.event(mavlink.MAV_SEVERITY_CRITICAL, "No odometry: landing")
            self.commander.set_mode(FlightMode.LAND, now_s, "no odometry")
        if s.mode == FlightMode.TAKEOFF:
            s.tko_climbed_m = s.vertical.height_m   # the closed-loop phase integrates on from here
            remaining = s.takeoff_target_m - s.vertical.height_m
            vz_ref = -min(p["BRG_TKO_OL_SPD"], max(remaining, 0.0))  # slows into the target, then holds
            ceiling = hover_prior * (1.0 + margin)
            ramp_s = p["BRG_TKO_RAMP_T"]
            if ramp_s > 0 and s.tko_ramp_start_s is not None:
                ceiling *= min(1.0, (now_s - s.tko_ramp_start_s) / ramp_s)
        probing = False
        floor_hold: float | None = None
        if s.mode != FlightMode.TAKEOFF:
            vz_ref = p["BRG_OL_LAND_SPD"]
            if s.blind_descent is None:
                s.blind_descent = BlindDescent(now_s, s.vertical.height_m, s.last_board_command.thrust)
            descent = s.blind_descent
            learned = s.hover_thrust_learned if s.hover_thrust_learned is not None else hover_prior
            if descent.floor_s is None:
                # the thrust that would hold the descent's speed: the command, less what it accelerated the vehicle
                # by (thrust ~ g - a_down). The plain command's low-pass held a descent that was still speeding up
                # (the estimate read the floor 1.5 s into it: 0.47 m/s there, 0.62 at the touchdown, SITL)
                a_down = s.vertical.estimate.accel_z_m_s2
                scale = GRAVITY_M_S2 / min(max(GRAVITY_M_S2 - a_down, 0.5 * GRAVITY_M_S2), 1.5 * GRAVITY_M_S2)
                descent.thrust_lp += (s.last_board_command.thrust * scale - descent.thrust_lp) * min(
                    1.0, dt / DESCENT_THRUST_TAU_S)
            # latched at the read: the baro's pull lifts the held estimate over FLOOR_READ_M now and then (0.014-0.019
            # m), and each time the loop's cut was back (campaign 20261211 flight 4: 0.48 -> 0.40, 0.70 m/s)
            if s.vertical.estimate.baro_fused and (s.vertical.height_m <= FLOOR_READ_M or descent.floor_s is not None):
                # the estimate reads the floor, but the baro's height has drifted since the take-off (0.13-0.18 m
                # low at the floor in 4 of 8 SITL landings): the estimator stops its descent there, and the speed
                # loop, chasing the descent rate, cut the thrust and dropped the vehicle the rest of the way at up
                # to 0.77 m/s. So the thrust that held the descent (its low-pass: not a last step's spike) is held
                # on past the floor it reads, then the loop's cut is the ground test. Not the take-off's learnt hover
                # thrust nor the config's prior: the climb's low-pass had not settled (0.58-0.76 m/s held at it), and
                # the SITL's vehicle needs 0.49 where its config says 0.41
                if descent.floor_s is None:
                    descent.floor_s = now_s
                    s.event(mavlink.MAV_SEVERITY_INFO, f"Landing: baro reads the floor, hold {descent.thrust_lp:.2f}")
                # how far on: while the board's baro climb rate says the vehicle still descends. The drift since the
                # take-off moves the altitude, not its rate, and it grows with the flight (the SITL's random walk:
                # 0.27 m of one sigma after 2 min; a fixed 0.3 m band dropped a 0.45 m drift at 0.85 m/s). On the
                # floor the rate falls under BARO_STILL_M_S within ~0.4 s (the board's filter's lag); without a
                # fresh rate, or after BRG_OL_LAND_BAND, the hold ends as the fixed band did
                climb = s.vertical.estimate.baro_climb_m_s
                descending = not math.isfinite(climb) or climb < -BARO_STILL_M_S
                # the descent is under way once the rate reads most of the descent rate (a slower one, started by the
                # trim below from a hover, hovered about BARO_STILL_M_S and was taken for stopped in the air)
                descent.seen_descending = descent.seen_descending or (
                    math.isfinite(climb) and climb < -DESCENT_SEEN_FRACTION * vz_ref)
                if not descent.floor_still and not descending and descent.seen_descending:
                    descent.floor_still = True    # latched: the rate's noise does not restart the hold
                    s.event(mavlink.MAV_SEVERITY_INFO,
                            f"Landing: descent stopped {now_s - descent.floor_s:.2f} s below (climb {climb:+.2f})")
                if not descent.floor_still and now_s - descent.floor_s < p["BRG_OL_LAND_BAND"] / vz_ref and \
                        (math.isfinite(climb) or now_s - descent.floor_s < FLOOR_HOLD_NO_RATE_S):
                    # trimmed on the rate as the board's own failsafe descent is (firmware/src/safety.c), one way at a
                    # time: before the rate has seen a descent (the estimate at the floor in a hover) the trim may
                    # only lower the thrust, to start one; after, only raise it, against a descent faster than the
                    # rate. The rate lags ~0.5 s: trimmed both ways, a LAND's 0.4 m/s level part sped up to 0.52-0.53
                    # m/s at the touchdown in the unit model (0.49 one way)
                    trim = FLOOR_HOLD_GAIN_S_M * (-vz_ref - climb) if math.isfinite(climb) else 0.0
                    trim = max(trim, 0.0) if descent.seen_descending else min(trim, 0.0)
                    floor_hold = descent.thrust_lp * (1.0 + min(max(trim, -FLOOR_HOLD_TRIM), FLOOR_HOLD_TRIM))
            if s.vertical.estimate.baro_fused:
                # on the barometer the estimate cannot run away upward: the descent may use the thrust it needs
                # to hold its speed (a ceiling at the short take-off's learnt thrust dropped it at 1.2 m/s)
                ceiling = hover_prior * (1.0 + margin)
            else:
                ceiling = min(max(learned, hover_prior * (1.0 - margin)), hover_prior * (1.0 + margin))
            # with the board's barometer fused the height does not drift: the descent tracks its speed to the ground
            # and the touchdown test below ends it (issue 30: probing at 0.9 x hover touched down at 1.2 m/s); on the
            # accelerometer alone the estimate may run out early or late, so the descent probes for the ground
            overdue = now_s - descent.start_s > descent.height0_m / vz_ref + BLIND_DESCENT_EXTRA_S
            probing = not s.vertical.estimate.baro_fused and (s.vertical.height_m <= 0.0 or overdue)
            if probing:
                ceiling *= p["BRG_FS_DESC_THR"]
        if s.vertical.estimate.pinned:
            s.pid_tracker.reset()  # the ground carries the vehicle while the thrust ramps: nothing to integrate
        yaw_rate = self._heading_hold(dt, 0.0, est.yaw_rad)
        # horizontally: level, or, once the drag's velocity has been learnt in this flight, a hold on it (the
        # board's level is ~0.5-1 deg off its own estimate: 0.1-0.3 m/s of slide), down to the floor the estimate
        # reads, never on or at the ground nor while resting on something (thrust under the touchdown test's: a
        # tilt there skids the vehicle). Through the level part of a landing too: after a 150 s hover the trim
        # was 2 deg off the board's level error (learnt in the pan-scan's swing), and the last 0.3 m, flown on it
        # alone, sped a 0.2 m/s slide up to 0.45 (SITL, draw 1 of the long-hover landings)
        at_floor = s.blind_descent is not None and s.blind_descent.floor_s is not None
        drag = None if s.vertical.estimate.pinned or at_floor or self._resting_thrust() \
            else self.offboard.drag_velocity_h(est)
        v_est = np.array([0.0, 0.0, vz_est]) if drag is None else np.array([drag[0], drag[1], vz_est])
        cmd = s.pid_tracker.update(dt, np.array([0.0, 0.0, vz_ref]), yaw_rate, v_est, est.roll_rad, est.pitch_rad)
        thrust = min(cmd.thrust_fraction if floor_hold is None else floor_hold, ceiling)
        # level by the bridge's estimate in the air; on or at the ground the board's own level (a tilt there skids)
        roll, pitch = (0.0, 0.0) if s.vertical.estimate.pinned or self._resting_thrust() else self._level()
        if drag is not None:
            roll, pitch = self._tilt_around_level(cmd, DRAG_HOLD_TILT_RAD)
        cmd = AttitudeCommand(roll, pitch, cmd.yaw_rate_rad_s, thrust, cmd.a_des_h_m_s2,
                              cmd.saturated or thrust < cmd.thrust_fraction)
        if s.mode == FlightMode.TAKEOFF and not s.vertical.estimate.pinned:
            # what the climb needs, tilt-compensated: the descent's thrust ceiling
            level = thrust * math.cos(est.roll_rad) * math.cos(est.pitch_rad)
            if s.hover_thrust_learned is None:
                s.hover_thrust_learned = level
            s.hover_thrust_learned += (level - s.hover_thrust_learned) * dt / HOVER_LEARN_TAU_S
        if s.mode == FlightMode.LAND:
            ground = probing and thrust <= ceiling + 1e-6 and \
                abs(s.vertical.estimate.accel_z_m_s2) < GROUND_CONTACT_ACCEL_M_S2
            self._detect_touchdown(now_s, cmd, abs(vz_est), ground_contact=ground)
        return self._finish(cmd)

    def _position_hold(self, yaw_rad: float) -> np.ndarray:
        """LAND, TAKEOFF and LOITER on odometry hold the place where they began (PX4's land, take-off and Hold hold
        their position), not only v = 0: a velocity loop asked for zero creeps (3-8 cm/s seen), and a vertical descent
        beside a box came 0.10 m nearer it (campaign seed 2031 flight 22). In H, at most POSITION_HOLD_MAX_M_S;
        re-anchored after a jump and at every mode change (:meth:`CommanderService.set_mode`)."""
        s = self.state
        p = s.odom_p_ned_m
        if p is None or not np.all(np.isfinite(p[:2])):
            s.hold_anchor_ned_m = None
            return np.zeros(2)
        if s.hold_anchor_ned_m is None or float(np.linalg.norm(p[:2] - s.hold_anchor_ned_m)) > POSITION_HOLD_REANCHOR_M:
            s.hold_anchor_ned_m = p[:2].copy()
        e_ned = np.array([p[0] - s.hold_anchor_ned_m[0], p[1] - s.hold_anchor_ned_m[1], 0.0])
        v_h = -POSITION_HOLD_GAIN_1_S * (Rz(-yaw_rad) @ e_ned)[:2]
        speed = float(np.linalg.norm(v_h))
        return v_h * (POSITION_HOLD_MAX_M_S / speed) if speed > POSITION_HOLD_MAX_M_S else v_h

    def _level(self) -> tuple[float, float]:
        """The (roll, pitch) to command for level flight: the trim learnt in this flight (0 before any; 0 with
        BRG_LVL_TRIM off)."""
        s = self.state
        if s.params["BRG_LVL_TRIM"] <= 0.0:
            return 0.0, 0.0
        return float(s.level_trim_rad[0]), float(s.level_trim_rad[1])

    def _tilt_around_level(self, cmd: AttitudeCommand, tilt_rad: float) -> tuple[float, float]:
        """The command's (roll, pitch) within ``tilt_rad`` of the level (:meth:`_level`)."""
        level_roll, level_pitch = self._level()
        return (min(max(cmd.roll_rad, level_roll - tilt_rad), level_roll + tilt_rad),
                min(max(cmd.pitch_rad, level_pitch - tilt_rad), level_pitch + tilt_rad))

    def _learn_level_trim(self, dt: float, est: Any) -> None:
        """Low-pass the board's level error, the last command minus the bridge's estimate, while the odometry is
        good and the attitude steady, in the air and not in the level landing (see LEVEL_TRIM_TAU_S)."""
        s = self.state
        if not s.odom_ok or s.vertical.estimate.pinned or self._resting_thrust() or self._level_landing() \
                or max(abs(est.rollspeed_rad_s), abs(est.pitchspeed_rad_s)) > LEVEL_TRIM_STEADY_RAD_S:
            return
        c = s.last_board_command
        error = np.array([c.roll_rad - est.roll_rad, c.pitch_rad - est.pitch_rad])
        if not np.all(np.isfinite(error)):
            return
        s.level_trim_rad += min(dt / LEVEL_TRIM_TAU_S, 1.0) * (error - s.level_trim_rad)
        np.clip(s.level_trim_rad, -LEVEL_TRIM_MAX_RAD, LEVEL_TRIM_MAX_RAD, out=s.level_trim_rad)

    def _note_thrust(self, now_s: float) -> None:
        """Since when the last thrust has been under the touchdown test's (LNDMC_THR_MAX x hover), for
        :meth:`_resting_thrust`."""
        s = self.state
        if s.last_board_command.thrust >= s.params["LNDMC_THR_MAX"] * s.tracker.hover_thrust_fraction:
            s.low_thrust_since_s = None
        elif s.low_thrust_since_s is None:
            s.low_thrust_since_s = now_s

    def _resting_thrust(self) -> bool:
        """The thrust has been under the touchdown test's for RESTING_THRUST_S: resting on something."""
        s = self.state
        return s.low_thrust_since_s is not None and s.control_time_s is not None \
            and s.control_time_s - s.low_thrust_since_s >= RESTING_THRUST_S

    def _level_landing(self) -> bool:
        """The barometer-fused height is below BRG_LAND_LVL_ALT (0: never): a landing flies the rest level, and a
        brake on a lost odometry's last velocity is not started (the vehicle is at the floor, perhaps on it)."""
        s = self.state
        floor_m = s.params["BRG_LAND_LVL_ALT"]
        return floor_m > 0.0 and s.vertical.estimate.baro_fused and s.vertical.height_m < floor_m

    def _heading_hold(self, dt: float, yaw_rate_ref: float, yaw_rad: float) -> float:
        """Yaw rate tracked through a heading setpoint (like PX4's yaw control): the setpoint integrates the
        reference rate, and the heading error (yaw anchored to the odometry) adds ``MC_YAW_P`` * error, so a
        zero yaw rate holds the heading instead of letting the board's rate loop drift."""
        s = self.state
        if s.yaw_sp_rad is None:
            s.yaw_sp_rad = yaw_rad
        s.yaw_sp_rad = wrap_pi(s.yaw_sp_rad + yaw_rate_ref * dt)
        error = wrap_pi(s.yaw_sp_rad - yaw_rad)
        if abs(error) > MAX_HEADING_ERROR_RAD:  # do not wind up behind a saturated or blocked yaw
            s.yaw_sp_rad = wrap_pi(yaw_rad + math.copysign(MAX_HEADING_ERROR_RAD, error))
            error = math.copysign(MAX_HEADING_ERROR_RAD, error)
        return yaw_rate_ref + s.params["MC_YAW_P"] * error

    def _finish(self, cmd: AttitudeCommand) -> BoardCommand:
        s = self.state
        s.last_command = cmd
        values = (cmd.roll_rad, cmd.pitch_rad, cmd.yaw_rate_rad_s, cmd.thrust_fraction)
        if not all(math.isfinite(v) for v in values):
            # cannot happen with finite inputs (every boundary checks them); if it does, fly level at the
            # last finite thrust rather than send a NaN or nothing (the board would cut or failsafe)
            s.counters["nonfinite_commands"] = s.counters.get("nonfinite_commands", 0) + 1
            s.event(mavlink.MAV_SEVERITY_CRITICAL, "Non-finite control output: level hold")
            s.reset_trackers()
            return self._board(BoardCommand(0.0, 0.0, 0.0, s.last_board_command.thrust, s.armed_cmd))
        return self._board(BoardCommand(cmd.roll_rad, cmd.pitch_rad, cmd.yaw_rate_rad_s, cmd.thrust_fraction,
                                        s.armed_cmd))

    def _board(self, command: BoardCommand) -> BoardCommand:
        self.state.last_board_command = command
        return command

    def _attitude_command(self, sp: AttitudeSetpoint, est: Any) -> AttitudeCommand:
        g = self.state.tracker.gains
        roll = min(max(sp.roll_rad, -g.max_tilt_rad), g.max_tilt_rad)
        pitch = min(max(sp.pitch_rad, -g.max_tilt_rad), g.max_tilt_rad)
        if sp.yaw_rate_rad_s is not None:
            yaw_rate = sp.yaw_rate_rad_s
        elif sp.yaw_rad is not None:
            yaw_rate = YAW_TRACK_GAIN_1_S * wrap_pi(sp.yaw_rad - est.yaw_rad)
        else:
            yaw_rate = 0.0
        yaw_rate = min(max(yaw_rate, -g.max_yaw_rate_rad_s), g.max_yaw_rate_rad_s)
        thrust = self.state.tracker.hover_thrust_fraction if sp.thrust is None else sp.thrust
        thrust = min(max(thrust, 0.0), g.thrust_max_fraction)
        return AttitudeCommand(roll, pitch, yaw_rate, thrust)

    def _update_height(self, dt: float) -> None:
        s = self.state
        if s.blind:
            s.height_m = s.vertical.height_m
        elif s.z_ground_m is not None and s.odom_z_m is not None:
            s.height_m = -(s.odom_z_m - s.z_ground_m)
            if s.odom_ok and s.in_air and s.mode != FlightMode.LAND and s.height_m >= BARO_REREF_MIN_HEIGHT_M:
                # the odometry's height keeps the baro's reference: its drift would move the floor a landing's level
                # descent reads (a 150 s hover: 0.06-0.51 m low in the SITL). Not in a landing nor near the floor,
                # where the camera sees too little (the odometry is the worse height there)
                s.vertical.reference_height(s.height_m, dt, s.params["BRG_BARO_REF_T"])
        elif s.in_air:
            s.height_m -= float(self.offboard.v_est_h(s.control_time_s or 0.0)[2]) * dt
        else:
            s.height_m = 0.0

    def _detect_touchdown(self, now_s: float, cmd: AttitudeCommand, vz_abs_m_s: float,
                          ground_contact: bool = False) -> None:
        """Low vertical speed with low thrust (or the board saying landed), or ``ground_contact`` (thrust
        below hover without vertical acceleration, flight without odometry), held for LNDMC_TIME_S."""
        s = self.state
        p = s.params
        board_landed = (s.board_link_ok and s.board_status is not None
                        and s.board_status.flight_state == BoardFlightState.LANDED)
        low_thrust = cmd.thrust_fraction < p["LNDMC_THR_MAX"] * s.tracker.hover_thrust_fraction
        if ground_contact or (vz_abs_m_s < p["LNDMC_Z_VEL_MAX"] and (low_thrust or board_landed)):
            if s.touchdown_since_s is None:
                s.touchdown_since_s = now_s
            elif now_s - s.touchdown_since_s >= p["LNDMC_TIME_S"]:
                s.in_air = False
                self.commander.disarm(now_s, "Landed, disarming")
        else:
            s.touchdown_since_s = None
