"""Issue 14 in the SITL: where the vehicle lands. A low box (0.4 m tall, textured) stands in an open room; the
vehicle flies over it at its take-off height (0.7 m above the box top: outside the safe distance, so it passes
over) and is told to land there.

* A ground station's LAND over the box is refused (COMMAND_ACK DENIED and a STATUSTEXT), sent to the companion
  (pymavlink, compid 191) and sent to the autopilot by MAVSDK's ``action.land()`` (both APIs, unmodified), which
  the companion intercepts while it flies the vehicle. The vehicle stays in the air. Moved off the box, the same
  LAND is accepted and the vehicle lands on the floor.
* A failsafe landing over the box (the operator's MANUAL_CONTROL stops; heartbeats go on) first moves clear of
  it and lands on the floor.
* (``-m slow``) A script's LAND over ground the camera never saw (campaign 7575's flight 14) is accepted, moves to
  seen ground and lands on the floor.

Where the vehicle ends up is judged from the SITL's truth and the scenario's geometry, not from the companion.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from flight_harness import (
    LOADED_MACHINE,
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

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(900)]

OFFSET = free_port_offset(slots=2)   # harness.ports: free now, reserved for this session
BOX_CENTRE_XY_M = np.array([1.4, 0.0])
BOX_HALF_M = 0.4          # 0.8 m x 0.8 m, 0.4 m tall
MIN_CLEARANCE_M = 0.40
LANDED_ABOVE_FLOOR_M = 0.15   # the body centre rests 0.1 m above the floor on its gear; on the box: 0.5 m


def _scenario(tmp_path: Path) -> str:
    """An 8 m x 8 m room, the start 2.4 m south of the box, the camera facing it."""
    scenario = {
        "name": "low-box", "description": "a low box in an open room (tests/sitl/test_landing_sitl.py)",
        "room": {"size_m": [8.0, 8.0], "height_m": 3.0, "floor_texture": "carpet", "wall_texture": "concrete"},
        # the operator's forward (the pan-scan's mean camera axis, 67.5 deg right of the start yaw) at the box
        "start": {"position_m": [-1.0, 0.0], "yaw_deg": -67.5},
        "objects": [{"kind": "box", "name": "low-box", "position_m": [float(BOX_CENTRE_XY_M[0]), 0.0, -0.2],
                     "size_m": [2 * BOX_HALF_M, 2 * BOX_HALF_M, 0.4], "texture": "checker",
                     "color": [0.85, 0.75, 0.4]}],
    }
    path = tmp_path / "low-box.yaml"
    path.write_text(yaml.safe_dump(scenario))
    return str(path)


def _companion_config(tmp_path: Path) -> Path:
    """The shipped perception (the hidden floor on: a matte box's side seen edge-on returns nothing, and must not keep
    the vehicle from flying over the box) with the loaded machine's link timeouts."""
    return companion_config_with(tmp_path, **LOADED_MACHINE)


def _over_box(p_arena_ned_m: np.ndarray) -> bool:
    return bool(np.all(np.abs(p_arena_ned_m[:2] - BOX_CENTRE_XY_M) <= BOX_HALF_M))


def _turn_toward(f: Flight, target_xy_m: np.ndarray) -> int:
    """The operator's yaw command (MANUAL_CONTROL ``y``, > 0 = turn right) that turns the vehicle's direction of
    travel toward a point, as an operator watching the vehicle does: eq. (2) moves only along the operator's direction,
    so a drift off the line is steered out by turning it. Truth steers the harness's operator only, as a person's
    eyes would; nothing of it reaches the vehicle."""
    s = f.log.samples[-1] if f.log.samples else None
    if s is None or float(np.hypot(*s.v_ned_m_s[:2])) < 0.15:
        return 0
    to_target = target_xy_m - s.p_arena_ned_m[:2]
    err_rad = np.arctan2(to_target[1], to_target[0]) - np.arctan2(s.v_ned_m_s[1], s.v_ned_m_s[0])
    err_rad = (err_rad + np.pi) % (2 * np.pi) - np.pi
    return int(np.clip(800.0 * err_rad, -250, 250))


def _fly_over_the_box(f: Flight) -> None:
    f.take_off()
    f.run_for(2.0, lambda: f.manual(0))
    # toward a point on the box's centre line past it, so the aim stays steady as the vehicle reaches the box
    aim_xy_m = BOX_CENTRE_XY_M + np.array([1.0, 0.0])
    f.run_for(30.0, lambda: f.manual(400, _turn_toward(f, aim_xy_m)),
              until=lambda: f.p_arena[0] >= BOX_CENTRE_XY_M[0] - 0.1)
    reached = f.p_arena.round(2)
    f.run_for(4.0, lambda: f.manual(0))
    # CI ended 0.14 m short of the box's edge and 0.65 m to its side once, and 0.41 m to its side once (the operator
    # pushed straight on without steering; since the board flies on its own attitude estimate the direction of travel
    # wanders by some degrees): the operator now steers as it pushes; say where the push ended and what the companion
    # said, to tell a block from a drift
    assert _over_box(f.p_arena), (f"not over the box: at {f.p_arena.round(2)}, the push ended at {reached} "
                                  f"(t {f.t_s:.1f} s); modes {f.log.modes}; status {f.log.statustexts[-8:]}")
    assert -f.p_arena[2] > 0.9, f"flying at {-f.p_arena[2]:.2f} m"


def _land_ack(f: Flight, target_compid: int, timeout_s: float = 5.0) -> int:
    """NAV_LAND from the harness's ground station; the result of its COMMAND_ACK."""
    n = len(f.log.acks)
    f.gcs.mav.command_long_send(1, target_compid, mavlink.MAV_CMD_NAV_LAND, 0, 0, 0, 0, 0, 0, 0, 0)
    f.run_for(timeout_s, lambda: f.manual(0),
              until=lambda: any(a[0] == mavlink.MAV_CMD_NAV_LAND for a in f.log.acks[n:]))
    acks = [a for a in f.log.acks[n:] if a[0] == mavlink.MAV_CMD_NAV_LAND]
    assert acks, f"no COMMAND_ACK for NAV_LAND to compid {target_compid}"
    return acks[0][1]


def _mavsdk_land(f: Flight, api: str, out_dir: Path) -> str:
    """MAVSDK's ``action.land()`` (a LAND to the autopilot) from a second ground station: its result's name."""
    url = f"udpout://127.0.0.1:{f.ports.vehicle}"
    seen: dict[str, str] = {}

    async def native(script: ClientScript) -> None:
        from mavsdk.asyncio import ComponentType, Configuration, Mavsdk
        from mavsdk.asyncio.plugins.action.action import ActionAsync, ActionError

        script.step("connect")
        async with Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION)) as m:
            await m.add_any_connection(url)
            system = await m.first_autopilot(timeout_s=30.0)
            assert system is not None, "MAVSDK did not find the vehicle behind the companion"
            script.step("land")
            try:
                await ActionAsync(system).land()
                seen["result"] = "SUCCESS"
            except ActionError as exc:
                seen["result"] = str(exc)

    async def classic(script: ClientScript) -> None:
        from mavsdk_grpc.action import ActionError

        script.step("connect")
        drone = await connect_classic(server)
        async for state in drone.core.connection_state():
            if state.is_connected:
                break
        script.step("land")
        try:
            await drone.action.land()
            seen["result"] = "SUCCESS"
        except ActionError as exc:
            seen["result"] = str(exc)

    hold = lambda: f.manual(0)  # noqa: E731   the harness's operator holds the vehicle meanwhile
    if api == "native":
        ClientScript(f).run(native, hold)
    else:
        log = out_dir / "mavsdk_server.log"
        with mavsdk_server(url, log) as server:
            ClientScript(f, logs=(log,)).run(classic, hold)
    return seen["result"]


def _assert_landed_on_the_floor(f: Flight, since_s: float) -> None:
    f.run_for(60.0, None, until=lambda: not f.armed and -f.p_arena[2] < LANDED_ABOVE_FLOOR_M)
    f.run_for(1.0, None)
    print(f"landed at {f.p_arena.round(2)}; {f.log.summary(since_s)}; status: {f.log.statustexts[-6:]}")
    assert not f.armed, f"not disarmed; at {f.p_arena.round(2)}"
    assert -f.p_arena[2] < LANDED_ABOVE_FLOOR_M, f"rests {-f.p_arena[2]:.2f} m up, at {f.p_arena.round(2)}"
    assert not _over_box(f.p_arena)
    s = f.log.min_surface(since_s)
    assert s is not None and s.clearance.surface_m >= MIN_CLEARANCE_M, f.log.summary(since_s)


def test_a_ground_station_land_over_a_box_is_refused_and_accepted_beside_it(tmp_path: Path) -> None:
    with flight(tmp_path, scenario=_scenario(tmp_path), offset=OFFSET,
                companion_config=_companion_config(tmp_path)) as f:
        _fly_over_the_box(f)
        t0 = f.t_s
        assert _land_ack(f, 191) == mavlink.MAV_RESULT_DENIED
        assert any("land refused: object below" in t for t in f.log.statustexts), f.log.statustexts[-5:]
        results = {}
        if _has("mavsdk.asyncio"):
            results["native"] = _mavsdk_land(f, "native", tmp_path)
        if _has("mavsdk_grpc"):
            results["classic"] = _mavsdk_land(f, "classic", tmp_path)
        print(f"MAVSDK action.land() over the box: {results}")
        assert results, "no MAVSDK API installed"
        assert all("DENIED" in r.upper() for r in results.values()), results
        f.run_for(3.0, lambda: f.manual(0))
        # it stayed up (no landing): over the box, or drifted off its edge by the hold's few tenths (CI once 0.2 m
        # past the edge while the two MAVSDK clients connected, the board flying on its own attitude estimate)
        near_box = bool(np.all(np.abs(f.p_arena[:2] - BOX_CENTRE_XY_M) <= BOX_HALF_M + 0.3))
        assert f.armed and -f.p_arena[2] > 0.9 and near_box, f"did not stay up: {f.p_arena.round(2)}"
        assert f.mode == MODE_TELEOP
        # off the box (its far edge at x = 1.8 m; the footprint 0.4 m): the same landing is accepted
        f.run_for(30.0, lambda: f.manual(400), until=lambda: f.p_arena[0] >= 2.6)
        f.run_for(3.0, lambda: f.manual(0))
        assert _land_ack(f, 191) == mavlink.MAV_RESULT_ACCEPTED
        _assert_landed_on_the_floor(f, t0)


def test_a_failsafe_landing_over_a_box_moves_clear_first(tmp_path: Path) -> None:
    with flight(tmp_path, scenario=_scenario(tmp_path), offset=OFFSET + PORT_SLOT_STRIDE,
                companion_config=_companion_config(tmp_path)) as f:
        _fly_over_the_box(f)
        t0 = f.t_s
        f.run_for(120.0, None, until=lambda: not f.armed)   # the operator stops; heartbeats go on
        _assert_landed_on_the_floor(f, t0)
        assert any("clear" in t.lower() for t in f.log.statustexts), f.log.statustexts[-8:]


def _has(module: str) -> bool:
    import importlib.util

    try:
        return importlib.util.find_spec(module) is not None
    except ModuleNotFoundError:
        return False


@pytest.mark.slow
def test_a_scripted_land_over_unseen_ground_is_accepted_and_lands_on_seen_ground(tmp_path: Path) -> None:
    """Issue 30: a LAND is refused only for an object under the footprint. Campaign 21's flight 14 (seed 7575, an
    offboard script in a random arena) asks for LAND where 40 % of the footprint's ground was never seen; it used
    to be refused, and the vehicle landed only after the script's silence brought the failsafe 10 s later. Now the
    LAND is accepted, the vehicle moves to seen ground and lands, the whole flight 0.40 m from every surface."""
    from harness.campaign.runner import CampaignOptions, fly
    from harness.campaign.safety import read_truth

    options = CampaignOptions(1, 7575, tmp_path, duration_s=40.0, offboard_share=0.25, first_index=14,
                              port_offset=OFFSET)
    result = fly(options, 14, 0, 1)
    assert result.status == "ok", result.failure
    folder = Path(result.folder)
    log = (folder / "logs" / "companion.log").read_text()
    assert "ground-station land: ground below not seen" in log and "moving clear" in log, log[-2000:]
    assert "land refused" not in log
    assert "HOLD -> LAND (ground-station land)" in log and "LAND -> IDLE (landed)" in log
    assert "no fresh command" not in log   # landed on the script's LAND, not on the failsafe's
    truth = read_truth(folder / "truth.tlog")
    assert float(truth.obstacle_m.min()) >= MIN_CLEARANCE_M
    assert -truth.p_local_ned_m[-1, 2] < LANDED_ABOVE_FLOOR_M   # on the floor (the start's level), not on a top
