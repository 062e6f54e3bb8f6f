"""Randomized operator sessions (issue 15), pure: a ``numpy.random.Generator`` and an arena in, a session out.

Two kinds of operator:

* **haptic** — a teleop script (the format of ``configs/teleop_scripts/*.yaml``, read by
  ``teleop/devices/script.py``) for the virtual device: forces on the handle in D (x forward speed,
  y yaw rate, z down), flown through MANUAL_CONTROL;
* **offboard** — a list of velocity setpoints for :mod:`harness.campaign.offboard_client`, the way a
  MAVSDK script flies (``set_velocity_body`` / ``set_velocity_ned``), sent as SET_POSITION_TARGET_LOCAL_NED
  to the companion's ground-station endpoint.

Both are built from the same manoeuvres: drive, turn, climb, push into the nearest obstacle at a random
angle and speed (sometimes turning while it pushes), slide along a wall. Each moving manoeuvre has a direction of
motion relative to the camera's axis (issue 29: the unseen flank must be flown, not just admitted): a haptic
operator moves along the axis (eq. 2) or backs against it (the handle pulled back); a script flies any body
direction: along, diagonally (+-45 deg), across (+-90 deg) or against (180 deg) the camera's axis. The record labels
each manoeuvre with it, and the campaign's report tabulates clearance by manoeuvre x direction.

The generator aims the pushes open-loop: it dead-reckons the
vehicle's planned position and heading with the nominal gains of the mapping (``configs/teleop.yaml``:
full deflection 1.6 N = 0.6 m/s, 0.8 rad/s, 0.4 m/s climb) and the camera's direction of motion (45 deg
right of the heading, ``configs/vehicle.yaml`` R_qc). The plan is written into the draws; the flown path
differs (repulsion, pan-scan), which is the point of a push.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from sim_sitl.config import ScenarioConfig
from sim_sitl.scenario_gen import nearest_obstacle_2d

FULL_DEFLECTION_N = 1.6  # virtual device: workspace 0.08 m x spring K_f 20 N/m
MAX_SPEED_M_S = 0.6
MAX_YAW_RATE_RAD_S = 0.8
MAX_CLIMB_M_S = 0.4
MOTION_OFFSET_RAD = math.radians(45.0)  # the camera (and the direction of motion alpha) looks right of the heading
TAKEOFF_S = 10.0  # arm at 2 s, take-off at 3 s, 1 m reached by ~13 s
LANDING_S = 8.0
MANOEUVRES = ("drive", "turn", "climb", "push_nearest", "slide_wall")
#: directions of motion relative to the camera's axis (deg) and their labels; a haptic operator has only 0 and 180
DIRECTIONS_DEG = {0.0: "along", 45.0: "diagonal", -45.0: "diagonal", 90.0: "across", -90.0: "across",
                  180.0: "against"}
HAPTIC_AGAINST_P = 0.25      # a haptic push or drive backs into it this often
PUSH_TURN_P = 0.3            # a push turns while it pushes this often


def direction_label(rel_deg: float) -> str:
    """along / diagonal / across / against, for a direction of motion ``rel_deg`` from the camera's axis."""
    a = abs((rel_deg + 180.0) % 360.0 - 180.0)
    return "along" if a < 22.5 else "diagonal" if a < 67.5 else "across" if a < 112.5 else "against"


def _draw_direction_deg(rng: np.random.Generator, offboard: bool) -> float:
    if offboard:
        return float(rng.choice(list(DIRECTIONS_DEG)))
    return 180.0 if rng.random() < HAPTIC_AGAINST_P else 0.0


def _wrap(a_rad: float) -> float:
    return (a_rad + math.pi) % (2 * math.pi) - math.pi


@dataclass
class _Plan:
    """Dead-reckoned plan state: position (arena north, east, m), heading (rad), height (m)."""

    x_m: float
    y_m: float
    yaw_rad: float
    up_m: float = 1.0


@dataclass(frozen=True)
class Session:
    kind: str  # "haptic" | "offboard"
    script: dict[str, Any]  # teleop script YAML (haptic) or offboard plan (offboard)
    record: dict[str, Any] = field(default_factory=dict)


def _speed_fraction(force_n: float) -> float:
    return min(1.0, abs(force_n) / FULL_DEFLECTION_N)


def _aim(plan: _Plan, target_bearing_rad: float, rng: np.random.Generator,
         rel_rad: float = 0.0) -> tuple[float, float, float]:
    """Turn (signed yaw rate rad/s, duration s) so that the direction of motion, ``rel_rad`` from the camera's
    axis, points at the bearing."""
    heading = target_bearing_rad - MOTION_OFFSET_RAD - rel_rad
    delta = _wrap(heading - plan.yaw_rad)
    rate = float(rng.uniform(0.3, 0.7)) * math.copysign(1.0, delta)
    return rate, abs(delta) / abs(rate), heading


def generate_session(rng: np.random.Generator, scenario: ScenarioConfig, duration_s: float,
                     offboard: bool = False) -> Session:
    """A session that fills ``duration_s`` of simulated time: take off, manoeuvres, land."""
    start = scenario.start
    plan = _Plan(start.position_m[0], start.position_m[1], math.radians(start.yaw_deg))
    ceiling_m = scenario.room.height_m
    t = TAKEOFF_S
    budget_s = max(0.0, duration_s - TAKEOFF_S - LANDING_S)
    moves: list[dict[str, Any]] = []  # (kind, parameters) in a frame-neutral form, then rendered per operator
    while t < TAKEOFF_S + budget_s - 1.0:
        kind = str(rng.choice(MANOEUVRES, p=[0.2, 0.15, 0.15, 0.3, 0.2]))
        remaining = TAKEOFF_S + budget_s - t
        m: dict[str, Any] = {"kind": kind, "t_plan_s": round(t, 2),
                             "from_m": [round(plan.x_m, 2), round(plan.y_m, 2)],
                             "heading_deg": round(math.degrees(plan.yaw_rad), 1)}
        rel_deg = _draw_direction_deg(rng, offboard) if kind in ("drive", "push_nearest", "slide_wall") else 0.0
        rel = math.radians(rel_deg)
        m.update(direction_deg=rel_deg, direction=direction_label(rel_deg))
        if kind == "drive":
            fwd = float(rng.uniform(0.3, 1.0))
            m.update(speed_fraction=round(fwd, 3), duration_s=round(min(float(rng.uniform(2.0, 6.0)), remaining), 2))
            steps = [("move", fwd, 0.0, 0.0, m["duration_s"], rel)]
        elif kind == "turn":
            rate = float(rng.uniform(0.2, 1.0)) * float(rng.choice([1.0, -1.0]))
            m.update(yaw_fraction=round(rate, 3), duration_s=round(min(float(rng.uniform(1.0, 5.0)), remaining), 2))
            steps = [("move", 0.0, rate, 0.0, m["duration_s"], 0.0)]
        elif kind == "climb":
            # toward the ceiling at up to full deflection, or back down (never below 0.5 m planned)
            climb = rng.random() < 0.65 or plan.up_m < 0.9
            up = float(rng.uniform(0.4, 1.0)) if climb else -float(rng.uniform(0.3, 0.8))
            m.update(climb_fraction=round(up, 3), duration_s=round(min(float(rng.uniform(2.0, 8.0)), remaining), 2),
                     ceiling_m=ceiling_m)
            steps = [("move", 0.0, 0.0, up, m["duration_s"], 0.0)]
        else:
            d_m, point, name = nearest_obstacle_2d(scenario, (plan.x_m, plan.y_m))
            bearing = math.atan2(point[1] - plan.y_m, point[0] - plan.x_m)
            if kind == "push_nearest":
                off = float(rng.uniform(-60.0, 60.0))  # angle of approach to the surface normal
                speed = float(rng.uniform(0.4, 1.0))
            else:  # slide along the wall: approach at a grazing angle, yawing slowly along it
                off = float(rng.uniform(55.0, 80.0)) * float(rng.choice([1.0, -1.0]))
                speed = float(rng.uniform(0.5, 1.0))
            rate, turn_s, _ = _aim(plan, bearing + math.radians(off), rng, rel)
            push_s = min(remaining - turn_s, float(rng.uniform(1.5, 3.5)) + d_m / (speed * MAX_SPEED_M_S))
            if kind == "slide_wall":
                push_yaw = 0.1 * math.copysign(1.0, off)
            else:   # sometimes turning while it pushes (the map must follow the turn)
                push_yaw = float(rng.uniform(-0.4, 0.4)) if rng.random() < PUSH_TURN_P else 0.0
            m.update(target=name, target_distance_m=round(d_m, 2), approach_offset_deg=round(off, 1),
                     speed_fraction=round(speed, 3), turn_yaw_rate_rad_s=round(rate, 3),
                     turn_s=round(turn_s, 2), push_s=round(max(push_s, 0.0), 2), push_yaw_fraction=round(push_yaw, 3))
            steps = [("move", 0.0, rate / MAX_YAW_RATE_RAD_S, 0.0, turn_s, 0.0)]
            if push_s > 0.5:
                steps.append(("move", speed, push_yaw, 0.0, push_s, rel))
        hands_off_s = round(float(rng.uniform(0.5, 2.0)), 2)
        steps.append(("move", 0.0, 0.0, 0.0, hands_off_s, 0.0))
        steps = _clip_steps(steps, remaining)
        # [fwd, yaw, up, duration_s, direction_deg]: fwd the speed fraction along the direction of motion
        m["steps"] = [[round(float(v), 3) for v in s[1:5]] + [round(math.degrees(s[5]), 1)] for s in steps]
        for _, fwd, yaw, up, dur, rel_step in steps:
            _advance(plan, fwd, yaw, up, dur, scenario, rel_step)
            t += dur
        m["to_m"] = [round(plan.x_m, 2), round(plan.y_m, 2)]
        moves.append(m)
    kind = "offboard" if offboard else "haptic"
    record: dict[str, Any] = {"kind": kind, "duration_s": duration_s, "manoeuvres": moves}
    script = _offboard_plan(moves, duration_s) if offboard else _teleop_script(moves, rng)
    return Session(kind, script, record)


Step = tuple[str, float, float, float, float, float]   # kind, fwd, yaw, up, duration_s, direction (rad)


def _clip_steps(steps: list[Step], budget_s: float) -> list[Step]:
    """The steps cut to ``budget_s`` of total duration (the landing keeps its time)."""
    out = []
    left = budget_s
    for kind, fwd, yaw, up, dur, rel in steps:
        if left <= 1e-3:
            break
        out.append((kind, fwd, yaw, up, min(dur, left), rel))
        left -= min(dur, left)
    return out


def _advance(plan: _Plan, fwd: float, yaw: float, up: float, dur_s: float, scenario: ScenarioConfig,
             rel_rad: float = 0.0) -> None:
    """Nominal kinematics of the plan (clamped to the room: the vehicle cannot leave it); the motion is
    ``rel_rad`` from the camera's axis."""
    n = max(1, int(dur_s / 0.1))
    dt = dur_s / n
    nx, ny = scenario.room.size_m
    for _ in range(n):
        plan.yaw_rad = _wrap(plan.yaw_rad + yaw * MAX_YAW_RATE_RAD_S * dt)
        direction = plan.yaw_rad + MOTION_OFFSET_RAD + rel_rad
        step_m = fwd * MAX_SPEED_M_S * dt
        plan.x_m = float(np.clip(plan.x_m + step_m * math.cos(direction), -nx / 2 + 0.5, nx / 2 - 0.5))
        plan.y_m = float(np.clip(plan.y_m + step_m * math.sin(direction), -ny / 2 + 0.5, ny / 2 - 0.5))
        plan.up_m = float(np.clip(plan.up_m + up * MAX_CLIMB_M_S * dt, 0.5, scenario.room.height_m - 0.3))


def _teleop_script(moves: list[dict[str, Any]], rng: np.random.Generator) -> dict[str, Any]:
    """The virtual device's script: forces in D (N) that deflect the handle by the planned fractions."""
    steps: list[dict[str, Any]] = [{"wait_s": 2.0}, {"button": "arm"}, {"wait_s": 1.0}, {"button": "takeoff"},
                                   {"wait_s": TAKEOFF_S - 3.0}]
    for m in moves:
        for fwd, yaw, up, dur, rel_deg in m["steps"]:
            if dur <= 0:
                continue
            if fwd == 0 and yaw == 0 and up == 0:
                steps.append({"release": True, "duration_s": dur})
            else:
                # a little more than the fraction: the handle sits where spring and push balance; against the
                # camera's axis is the handle pulled back (eq. 2 has no other direction)
                along = fwd * (-1.0 if abs(rel_deg) > 90.0 else 1.0)
                steps.append({"force_d_n": [round(along * FULL_DEFLECTION_N * 1.1, 3),
                                            round(yaw * FULL_DEFLECTION_N * 1.1, 3),
                                            round(-up * FULL_DEFLECTION_N * 1.1, 3)], "duration_s": dur})
    if rng.random() < 0.25:  # sometimes the operator switches the pan-scan off (part of the arena of issue 14)
        steps.insert(5, {"button": "pan_scan_off"})
    steps += [{"button": "land"}, {"wait_s": LANDING_S}]
    return {"name": "campaign session", "steps": steps}


def _offboard_plan(moves: list[dict[str, Any]], duration_s: float) -> dict[str, Any]:
    """Velocity setpoints as a MAVSDK script sends them: BODY_NED (forward/right/down, yaw rate) segments."""
    segments = []
    for m in moves:
        for fwd, yaw, up, dur, rel_deg in m["steps"]:
            if dur <= 0:
                continue
            # the body frame's forward is the heading; the camera looks 45 deg right, and the motion is rel_deg
            # from the camera's axis: split the speed into forward and right
            v = fwd * MAX_SPEED_M_S
            a = MOTION_OFFSET_RAD + math.radians(rel_deg)
            segments.append({"frame": "body", "forward_m_s": round(v * math.cos(a), 3),
                             "right_m_s": round(v * math.sin(a), 3),
                             "down_m_s": round(-up * MAX_CLIMB_M_S, 3) + 0.0,
                             "yawspeed_deg_s": round(math.degrees(yaw * MAX_YAW_RATE_RAD_S), 2),
                             "duration_s": dur})
    return {"name": "campaign offboard session", "takeoff_s": TAKEOFF_S, "landing_s": LANDING_S,
            "duration_s": duration_s, "segments": segments}
