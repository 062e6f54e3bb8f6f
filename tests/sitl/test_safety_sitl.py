"""Issue 14 in the SITL: every source of motion through the companion, the minimum *true* clearance to walls,
objects and the ceiling (tests/flight_harness.py, from the scene geometry) and the distance travelled.

Each flight asserts clearance >= 0.40 m with d_safe = 0.45 m (the floor is exempt) and that it got where it
was sent: within 0.6 m of the wall it was pushed at, or its commanded distance when nothing is in the way.
CI flights are short (<= ~40 s of flight), one of them in real time; the longer ones are marked slow.
"""

from __future__ import annotations

import asyncio
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from flight_harness import (
    LOADED_MACHINE,
    MODE_HOLD,
    MODE_TELEOP,
    ClientScript,
    Flight,
    companion_config_with,
    connect_classic,
    flight,
    mavsdk_server,
)

from harness.ports import PORT_SLOT_STRIDE, free_port_offset
from quadlink.mavlink import mavlink

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(1200)]

MIN_CLEARANCE_M = 0.40
# the start of paper-arena: (-3, 0) facing south; the south wall (x = -5) and its poster (x = -4.95) ahead
POSTER_FACE_X_M = -4.95
OFFSET = free_port_offset(slots=11)   # harness.ports: free now, reserved for this session


def _offset(k: int) -> int:
    return OFFSET + PORT_SLOT_STRIDE * k


def _assert_clear(f: Flight, since_s: float) -> float:
    """Clearance over the whole flight, take-off and touchdown included (harness.judge); ``since_s`` is where the
    manoeuvre under test began, printed for the record."""
    s = f.log.min_surface()
    assert s is not None, "never flew"
    print(f.log.summary(), f"(manoeuvre from t={since_s:.1f} s)")
    assert s.clearance.surface_m >= MIN_CLEARANCE_M, f.log.summary()
    return s.clearance.surface_m


# ---------------------------------------------------------------- pymavlink operator
# The finding of this round's honest board (issue 29): with the board on its own attitude estimate the slide came to
# 0.216 m (CI), 0.348, 0.364, 0.477, 0.501 m (Xtion camera) and 0.186, 0.192, 0.522 m (basic camera) from the wall;
# a failing run's log (0.36 m) showed the reference cut to zero for 6 s while the velocity loop crept 3-6 cm/s toward
# the wall. Fixed by holding the place where the safety layer blocks the push (companion/position_hold.py):
# 0.495-0.630 m over seven runs (six runs of the code before the fix, on the same day and machine, 0.47-0.56 m: the
# creep did not come every time, so these runs alone do not prove the fix; the hold's unit test bounds the creep).
# docs/changelog.md.
def test_operator_pushes_along_the_south_wall_into_the_corner(tmp_path: Path) -> None:
    """The case of issue 14 (0.30 m before): x = 700 forward at 50 Hz for 30 s from the start. alpha points
    south-west: the vehicle reaches the south wall obliquely, slides west along it, ends in the corner.
    An oblique push presses on the wall with only its normal part (and box-d's top lies under the path), so
    the slide runs farther from the wall than a head-on push rests: "along the wall" is within 1 m of it.
    Since the repulsion no longer pushes toward where the map has not looked, the vehicle may instead come to
    rest beside box-d, 2 m west of its start, with the operator still pushing (1 CI run in 3): it must have gone
    west along the wall by 1 m either way, and stopped neither blocked at the start nor short of the wall."""
    with flight(tmp_path, offset=_offset(0)) as f:
        f.take_off()
        t0, p0 = f.t_s, f.p_arena.copy()
        f.run_for(30.0, lambda: f.manual(700))
        _assert_clear(f, t0)
        near_wall = [s for s in f.log.flying() if s.t_s >= t0 and s.p_arena_ned_m[0] < POSTER_FACE_X_M + 1.0]
        assert near_wall, "never reached the south wall"
        went_west = max(p0[1] - s.p_arena_ned_m[1] for s in near_wall)
        assert went_west > 1.0, f"did not go west along the wall ({went_west:.2f} m from the start)"
        # pushed into the corner it gets within 0.65 m of a wall (no over-blocking). Widened from 0.6 m with the hold:
        # the vehicle now rests where the layer stopped it instead of creeping on; closest to a wall over seven runs
        # 0.495, 0.501, 0.523, 0.531, 0.546, 0.550, 0.630 m
        closest_wall = min(s.clearance.wall_m for s in f.log.flying() if s.t_s >= t0)
        assert closest_wall <= 0.65, f"kept {closest_wall:.2f} m from the walls"
        assert np.linalg.norm(f.p_arena[:2] - p0[:2]) > 2.0


def test_operator_climbing_at_full_deflection_stops_below_the_ceiling(tmp_path: Path) -> None:
    """Issue 14: 15 s of full climb in paper-arena (3 m ceiling) reached 2.80 m (0.10 m to the ceiling)."""
    config = companion_config_with(tmp_path, reference={"room_height_m": 3.0, "max_height_m": None},
                                   **LOADED_MACHINE)
    with flight(tmp_path, offset=_offset(1), companion_config=config) as f:
        f.take_off()
        t0 = f.t_s
        f.run_for(15.0, lambda: f.manual(0, 0, 1000))
        f.run_for(3.0, lambda: f.manual(0, 0, 1000))
        _assert_clear(f, t0)
        top = min(s.p_arena_ned_m[2] for s in f.log.flying())
        assert -top > 2.3, f"climb blocked early at {-top:.2f} m"     # reaches the ceiling's safe distance


def test_script_stops_sending_and_the_operator_overrides_it(tmp_path: Path) -> None:
    """A pymavlink script streams body-frame velocity (no mode switch): the companion flies it; the operator's
    climb out of the dead-band overrides it; when the script goes silent the vehicle hovers. The operator entered
    paper-arena's 3.0 m (without an entry the companion assumes a 2.0 m room and the climb stops at 1.55 m)."""
    config = companion_config_with(tmp_path, reference={"room_height_m": 3.0})
    with flight(tmp_path, offset=_offset(2), companion_config=config) as f:
        f.take_off()
        t0 = f.t_s

        def script(vx: float, yaw_rate: float = 0.0) -> None:
            f.gcs.mav.set_position_target_local_ned_send(0, 1, 1, mavlink.MAV_FRAME_BODY_NED, 1479, 0, 0, 0,
                                                         vx, 0.0, 0.0, 0, 0, 0, 0, yaw_rate)

        # backward, into the camera's blind side (the map has never looked north): refused, the vehicle holds
        p0 = f.p_arena.copy()
        f.run_for(3.0, lambda: script(-0.3))
        blind = float(np.linalg.norm(f.p_arena[:2] - p0[:2]))
        assert blind < 0.3, f"flew {blind:.2f} m where the camera had not looked"
        # the script turns round (0.6 rad/s for 5.2 s: ~180 deg, the camera sweeping the north), then flies
        # forward (north, open space for ~3 m) at 0.3 m/s for 5 s: 1.5 m
        f.run_for(5.2, lambda: script(0.0, 0.6))
        p0 = f.p_arena.copy()
        f.run_for(5.0, lambda: script(0.3))
        travelled = float(np.linalg.norm(f.p_arena[:2] - p0[:2]))
        assert travelled > 0.8 * 1.5, f"script moved {travelled:.2f} m of 1.5 m"
        # the operator climbs (handle up): the script is overridden — no horizontal progress, altitude rises
        p1 = f.p_arena.copy()

        def both() -> None:
            script(0.3)
            f.manual(0, 0, 900)

        f.run_for(3.0, both)
        assert f.p_arena[2] < p1[2] - 0.3, "the operator's climb did not take over"
        assert np.linalg.norm(f.p_arena[:2] - p1[:2]) < 0.5
        # the script goes silent (and the operator centres the handle): hover
        f.run_for(3.0, lambda: f.manual(0))     # the script's timeout (2 s here, 1 s by default) passes
        p2 = f.p_arena.copy()
        f.run_for(4.0, lambda: f.manual(0))
        assert np.linalg.norm(f.p_arena - p2) < 0.3, f"drifted {np.linalg.norm(f.p_arena - p2):.2f} m"
        assert f.mode == MODE_TELEOP
        _assert_clear(f, t0)


# ---------------------------------------------------------------- MAVSDK through the companion
def _fly_mavsdk(f: Flight, api: str, out_dir: Path) -> dict[str, Any]:
    """arm, takeoff, offboard set_velocity_body(0.5, 0, 0, 0) for 20 s toward the wall 2 m ahead; backward
    0.4 m/s for 3 s (the camera's blind side: held); turn round at 36 deg/s for 5 s, forward 0.4 m/s for 5 s
    into the open space the camera swept; offboard.stop(), land -- in a thread with its own event loop
    (flight_harness.ClientScript: each step has a deadline in simulated time)."""
    seen: dict[str, Any] = {}
    url = f"udpout://127.0.0.1:{f.ports.vehicle}"

    async def native(script: ClientScript) -> None:
        from mavsdk.asyncio import ComponentType, Configuration, Mavsdk
        from mavsdk.asyncio.plugins.action.action import ActionAsync
        from mavsdk.asyncio.plugins.offboard.offboard import OffboardAsync, VelocityBodyYawspeed
        from mavsdk.asyncio.plugins.telemetry.telemetry import FlightMode, TelemetryAsync

        script.step("connect")
        async with Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION)) as m:
            await m.add_any_connection(url)
            system = await m.first_autopilot(timeout_s=30.0)
            assert system is not None, "MAVSDK did not find the vehicle behind the companion"
            tel, action, off = TelemetryAsync(system), ActionAsync(system), OffboardAsync(system)
            await _flight_plan(script, seen, f, tel.subscribe_flight_mode, FlightMode, action, off,
                               VelocityBodyYawspeed)

    async def classic(script: ClientScript) -> None:
        from mavsdk_grpc.offboard import VelocityBodyYawspeed
        from mavsdk_grpc.telemetry import FlightMode

        script.step("connect")
        drone = await connect_classic(server)
        await asyncio.wait_for(_first(drone.core.connection_state(), lambda s: s.is_connected), 60.0)
        await _flight_plan(script, seen, f, drone.telemetry.flight_mode, FlightMode, drone.action, drone.offboard,
                           VelocityBodyYawspeed)

    # the harness's own ground station keeps sending heartbeats (so it keeps receiving TELEOP_FEEDBACK):
    # MAVSDK shares the companion's endpoint with it, as with any second ground station
    if api == "native":
        ClientScript(f).run(native)
    else:
        with mavsdk_server(url, out_dir / "mavsdk_server.log") as server:
            ClientScript(f, logs=(out_dir / "mavsdk_server.log",)).run(classic)
    f.run_for(3.0, None)
    return seen


async def _flight_plan(script: ClientScript, seen: dict[str, Any], f: Flight, flight_modes: Any, FlightMode: Any,
                       action: Any, off: Any, Velocity: Any) -> None:
    """The same plan in both APIs (their action, offboard and flight-mode calls have the same shape)."""
    script.step("arm")
    await action.arm()
    script.step("takeoff")
    await action.takeoff()
    await _until(flight_modes(), lambda mode: mode == FlightMode.HOLD, 120.0)
    await _until_true(lambda: f.mode in (MODE_TELEOP, MODE_HOLD), 60.0)   # hold: no source yet
    script.step("offboard.start")
    await off.set_velocity_body(Velocity(0.0, 0.0, 0.0, 0.0))
    await off.start()
    seen["mode"] = await _until(flight_modes(), lambda mode: mode == FlightMode.OFFBOARD, 10.0)
    script.step("toward the wall")
    seen["t_wall0"], seen["p_wall0"] = f.t_s, f.p_arena.copy()
    await off.set_velocity_body(Velocity(0.5, 0.0, 0.0, 0.0))
    await script.sim_wait(20.0)
    seen["p_wall1"], seen["t_wall1"] = f.p_arena.copy(), f.t_s
    seen["offboard_still"] = await off.is_active()
    script.step("backward (blind side)")
    await off.set_velocity_body(Velocity(-0.4, 0.0, 0.0, 0.0))   # blind side: held
    await script.sim_wait(3.0)
    seen["p_blind"] = f.p_arena.copy()
    script.step("turn round")
    await off.set_velocity_body(Velocity(0.0, 0.0, 0.0, 36.0))   # turn round: 180 deg
    await script.sim_wait(5.0)
    script.step("forward (free)")
    seen["t_free0"], seen["p_free0"] = f.t_s, f.p_arena.copy()
    await off.set_velocity_body(Velocity(0.4, 0.0, 0.0, 0.0))
    await script.sim_wait(5.0)
    seen["p_free1"], seen["t_free1"] = f.p_arena.copy(), f.t_s
    script.step("offboard.stop")
    await off.stop()
    seen["stop_mode"] = await _until(flight_modes(), lambda mode: mode == FlightMode.HOLD, 10.0)
    script.step("land")
    await action.land()


async def _first(gen: Any, pred: Any) -> Any:
    async for value in gen:
        if pred(value):
            return value
    return None


async def _until(gen: Any, pred: Any, timeout_s: float) -> Any:
    return await asyncio.wait_for(_first(gen, pred), timeout_s)


async def _until_true(pred: Any, timeout_s: float) -> None:
    t0 = time.monotonic()
    while not pred():
        if time.monotonic() - t0 > timeout_s:
            raise TimeoutError("condition not met")
        await asyncio.sleep(0.1)


def _check_mavsdk(f: Flight, seen: dict[str, Any]) -> None:
    # toward the wall: stops outside the safe distance, near it
    _assert_clear(f, seen["t_wall0"])
    rest = float(seen["p_wall1"][0] - POSTER_FACE_X_M)
    gap = min(s.clearance.surface_m for s in f.log.samples if seen["t_wall0"] <= s.t_s <= seen["t_wall1"])
    print(f"offboard into the wall: moved {seen['p_wall0'][0] - seen['p_wall1'][0]:.2f} m, came {gap:.2f} m from the "
          f"nearest surface, rests {rest:.2f} m from the poster's plane; free leg "
          f"{np.linalg.norm(seen['p_free1'][:2] - seen['p_free0'][:2]):.2f} m of 2.0 m")
    # how near it came (not where it rests: body-forward at the pan-scan's mean heading, up to ~35 deg off the wall's
    # normal, the layer takes away only the closing part and the vehicle slides along the wall, past the poster's
    # edge at y = -1 m; CI on 7e89097 came 0.65 m from the poster and rested 0.76 m from its plane at y = -1.47 m).
    # Nearest surface on the leg: 0.65 m (CI, 7e89097), 0.62 and 0.53 m locally (7e89097); before the hidden floor
    # the rest gap was 0.47-0.60 m (nine runs) and 0.72 m once in CI. The bound stays 0.75 m; a stalled approach
    # (nothing nearer than ~1.7 m) still fails
    assert gap <= 0.75, f"came no nearer than {gap:.2f} m to the wall"
    # backward, where the camera has not looked: refused (PX4's CP_GO_NO_DATA = 0 for scripts)
    blind = float(np.linalg.norm(seen["p_blind"][:2] - seen["p_wall1"][:2]))
    assert blind < 0.3, f"flew {blind:.2f} m into the camera's blind side"
    assert seen["offboard_still"], "MAVSDK left offboard (the mode report did not say OFFBOARD)"
    # nothing in the way: the commanded distance (0.4 m/s for 5 s of simulated time)
    commanded = 0.4 * (seen["t_free1"] - seen["t_free0"])
    moved = float(np.linalg.norm(seen["p_free1"][:2] - seen["p_free0"][:2]))
    assert moved >= 0.8 * commanded, f"moved {moved:.2f} m of {commanded:.2f} m"


def test_mavsdk_native_offboard_into_a_wall_through_the_companion(tmp_path: Path) -> None:
    pytest.importorskip("mavsdk.asyncio")
    with flight(tmp_path, offset=_offset(3)) as f:
        seen = _fly_mavsdk(f, "native", tmp_path)
        _check_mavsdk(f, seen)


def test_mavsdk_classic_offboard_into_a_wall_through_the_companion(tmp_path: Path) -> None:
    pytest.importorskip("mavsdk_grpc")
    with flight(tmp_path, offset=_offset(4)) as f:
        seen = _fly_mavsdk(f, "classic", tmp_path)
        _check_mavsdk(f, seen)


def test_operator_push_in_real_time(tmp_path: Path) -> None:
    """The push toward the south wall with the SITL paced in real time (not lock-step), on the shipped failsafe
    timeouts (no LOADED_MACHINE margins): safe, and it got there (a vehicle that never moved would be safe too)."""
    with flight(tmp_path, offset=_offset(5), lockstep=False, shipped_timeouts=True) as f:
        f.take_off()
        t0, p0 = f.t_s, f.p_arena.copy()
        f.run_for(30.0, lambda: f.manual(700))
        _assert_clear(f, t0)
        moved = float(np.linalg.norm(f.p_arena[:2] - p0[:2]))
        gap = min(s.clearance.surface_m for s in f.log.samples if s.t_s >= t0)
        assert moved > 1.0, f"moved {moved:.2f} m toward the wall"
        assert gap <= 0.65, f"stopped {gap:.2f} m from the nearest surface (the wall is reachable to ~0.5 m)"


def _land_beside_the_wall_classic(f: Flight, out_dir: Path) -> dict[str, Any]:
    """Issue 30, as a scripted user flew it: MAVSDK classic, body-forward toward the south wall until it rests near
    it, offboard.stop(), action.land(): the LAND must be accepted (a wall beside the vehicle is not below it)."""
    seen: dict[str, Any] = {}
    url = f"udpout://127.0.0.1:{f.ports.vehicle}"

    async def classic(script: ClientScript) -> None:
        from mavsdk_grpc.offboard import VelocityBodyYawspeed
        from mavsdk_grpc.telemetry import FlightMode

        script.step("connect")
        drone = await connect_classic(server)
        await asyncio.wait_for(_first(drone.core.connection_state(), lambda s: s.is_connected), 60.0)
        script.step("arm")
        await drone.action.arm()
        script.step("takeoff")
        await drone.action.takeoff()
        await _until(drone.telemetry.flight_mode(), lambda mode: mode == FlightMode.HOLD, 120.0)
        await _until_true(lambda: f.mode in (MODE_TELEOP, MODE_HOLD), 60.0)
        script.step("offboard.start")
        await drone.offboard.set_velocity_body(VelocityBodyYawspeed(0.0, 0.0, 0.0, 0.0))
        await drone.offboard.start()
        script.step("toward the wall")
        await drone.offboard.set_velocity_body(VelocityBodyYawspeed(0.5, 0.0, 0.0, 0.0))
        await script.sim_wait(20.0)
        seen["p_rest"] = f.p_arena.copy()
        script.step("offboard.stop")
        await drone.offboard.stop()
        await _until(drone.telemetry.flight_mode(), lambda mode: mode == FlightMode.HOLD, 10.0)
        script.step("land")
        seen["t_land"] = f.t_s
        await drone.action.land()   # raises ActionError on COMMAND_DENIED
        seen["land_accepted"] = True

    with mavsdk_server(url, out_dir / "mavsdk_server.log") as server:
        ClientScript(f, logs=(out_dir / "mavsdk_server.log",)).run(classic)
    f.run_for(20.0, None, until=lambda: f.log.touchdown(seen["t_land"]) is not None and f.t_s > seen["t_land"] + 2)
    return seen


@pytest.mark.parametrize("run", [0, *(pytest.param(k, marks=pytest.mark.slow) for k in range(1, 10))])
def test_mavsdk_land_beside_a_wall_is_accepted_and_lands(tmp_path: Path, run: int) -> None:
    """LAND at rest 0.45-0.6 m from the south wall's poster: accepted, and the vehicle lands clear of it. One run in CI;
    ``-m slow`` flies the other nine (the issue's 10 of 10)."""
    pytest.importorskip("mavsdk_grpc")
    with flight(tmp_path, offset=_offset(6 + run % 4)) as f:
        seen = _land_beside_the_wall_classic(f, tmp_path)
        gap = float(seen["p_rest"][0] - POSTER_FACE_X_M)
        print(f"run {run}: rested {gap:.2f} m from the poster; {f.log.summary()}")
        assert seen.get("land_accepted"), "LAND refused"
        assert f.log.touchdown(seen["t_land"]) is not None, "accepted, but never came down"
        _assert_clear(f, seen["t_land"])
