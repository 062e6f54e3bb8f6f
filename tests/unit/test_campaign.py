"""Issue 15, the parts of a campaign that need no flight: the seeded draws (arenas, start poses, operator
sessions, vehicle and sensors), the offboard client's setpoints, the safety envelope from a truth log
written by the SITL's own encoder, the port slots, and the report."""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import numpy as np
import pytest

from harness.campaign.draws import CAMERA_TILT_DEG, StarvationRange, draw_flight, write_flight_files
from harness.campaign.offboard_client import plan_end_s, setpoint_at
from harness.campaign.report import summarize, summary_text, write_campaign
from harness.campaign.runner import CampaignOptions, FlightResult, flight_ports, progress_line
from harness.campaign.safety import envelope, read_truth
from harness.campaign.sessions import MOTION_OFFSET_RAD, generate_session
from harness.demo.cli import PORT_BLOCK_SIZE, PORT_NAMES, FlightSpec, Ports, compare_reports
from harness.demo.metrics import touchdown_m_s
from quadlink.config import load_config
from quadlink.mavlink import mavlink
from quadlink.mavlink.setpoint_masks import TM_VELOCITY_YAW_RATE
from quadlink.mavlink.tlog import TlogWriter
from quadlink.vehicle import load_vehicle
from sim_sitl.config import RoomConfig, ScenarioConfig, SceneObject, StartPose, load_scenario, load_sitl_config
from sim_sitl.scenario_gen import LAYOUTS, clearance_2d, generate_procedural, generate_scenario, nearest_obstacle_2d
from sim_sitl.truth import TruthEncoder
from teleop.devices.script import ScriptConfig, build_script


def test_same_seed_same_files_and_draws(tmp_path: Path) -> None:
    a = write_flight_files(draw_flight(11, 4, 40.0, offboard_share=0.5), tmp_path / "a")
    b = write_flight_files(draw_flight(11, 4, 40.0, offboard_share=0.5), tmp_path / "b")
    for name in ("scenario.yaml", "operator.yaml", "vehicle.yaml", "draws.json"):
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes(), name
    assert a.sitl.read_text().replace(str(tmp_path / "a"), "") == b.sitl.read_text().replace(str(tmp_path / "b"), "")
    other = draw_flight(11, 5, 40.0)
    assert other.record["sitl_seed"] != draw_flight(11, 4, 40.0).record["sitl_seed"]


def test_flight_draws_are_the_seed_sequence_children() -> None:
    """Flight i uses SeedSequence(S).spawn(N)[i], whatever N."""
    children = np.random.SeedSequence(3).spawn(6)
    d = draw_flight(3, 5, 30.0)
    assert tuple(d.record["seed_sequence"]["spawn_key"]) == children[5].spawn_key
    sitl_ss = children[5].spawn(4)[3]
    assert d.record["sitl_seed"] == int(np.random.default_rng(sitl_ss).integers(0, 2**31 - 1))


@pytest.mark.parametrize("layout", LAYOUTS)
def test_procedural_arenas_within_the_envelope_of_the_issue(layout: str, tmp_path: Path) -> None:
    for seed in range(15):
        scenario, got = generate_procedural(np.random.default_rng(seed), "t", layout)
        assert got == layout
        nx, ny = scenario.room.size_m
        assert 4.0 <= nx <= 12.0 and 4.0 <= ny <= 12.0
        columns = [o for o in scenario.objects if o.name.startswith("column")]
        boxes = [o for o in scenario.objects if o.name.startswith("box")]
        assert len(columns) <= 5 and len(boxes) <= 5
        if layout == "low-ceiling":
            assert scenario.room.height_m <= 2.4
        for o in scenario.objects:  # everything inside the room, standing on the floor or hanging from the ceiling
            assert abs(o.position_m[0]) < nx / 2 and abs(o.position_m[1]) < ny / 2
            h = o.size_m[2] if o.kind == "box" else o.height_m
            bottom, top = -o.position_m[2] - h / 2, -o.position_m[2] + h / 2
            assert bottom == pytest.approx(0.0, abs=1e-3) or top == pytest.approx(scenario.room.height_m, abs=1e-3)


def test_arena_yaml_is_what_the_sitl_loads(tmp_path: Path) -> None:
    for i in range(10):
        d = draw_flight(2, i, 40.0)
        files = write_flight_files(d, tmp_path / str(i))
        assert load_scenario(str(files.scenario)) == d.scenario
        sitl = load_sitl_config(files.sitl)
        assert load_scenario(sitl.scenario) == d.scenario
        vehicle = load_vehicle(sitl.vehicle)
        assert vehicle.mass_kg == pytest.approx(d.record["vehicle"]["mass_kg"])
        assert sitl.seed == d.record["sitl_seed"]


def test_start_pose_in_free_space_and_fixed_members_drawn() -> None:
    layouts = set()
    for i in range(60):
        arena = generate_scenario(np.random.default_rng(i), "t")
        layouts.add(arena.record["layout"])
        s = arena.scenario
        assert clearance_2d(s, s.start.position_m) >= 0.5
        assert arena.record["start_clearance_m"] == pytest.approx(clearance_2d(s, s.start.position_m))
    assert {"fixed:paper-arena", "fixed:office"} <= layouts and set(LAYOUTS) <= layouts


def test_clearance_against_hand_geometry() -> None:
    room = RoomConfig(size_m=(10.0, 8.0))
    s = ScenarioConfig(room=room, objects=(
        SceneObject(kind="cylinder", name="c", position_m=(3.0, 0.0, -1.5), radius_m=0.5, height_m=3.0),
        SceneObject(kind="box", name="b", position_m=(-2.0, 0.0, -0.5), size_m=(2.0, 1.0, 1.0), yaw_deg=90.0)))
    d, point, name = nearest_obstacle_2d(s, (0.0, 0.0))
    assert name == "b" and d == pytest.approx(1.5)  # turned 90 deg: its 1 m side faces north
    assert point == pytest.approx((-1.5, 0.0))
    d, _, name = nearest_obstacle_2d(s, (3.0, 3.0))
    assert name == "wall-east" and d == pytest.approx(1.0)
    d, _, name = nearest_obstacle_2d(s, (3.0, 1.0))
    assert name == "c" and d == pytest.approx(0.5)
    # the 1 m box is below the flight band: not a target for the operator, still counted for the start
    d, _, name = nearest_obstacle_2d(s, (-2.0, 1.5), band_m=(1.2, 1.6))
    assert name != "b"
    assert clearance_2d(s, (-2.0, 1.5)) == pytest.approx(0.5)


def test_vehicle_and_sensor_draws_within_bounds() -> None:
    nominal = load_vehicle("vehicle")
    R0 = np.asarray(nominal.camera.R_qc)
    for i in range(20):
        d = draw_flight(5, i, 40.0)
        assert 0.9 * nominal.mass_kg <= d.vehicle["mass_kg"] <= 1.1 * nominal.mass_kg
        R = np.asarray(d.vehicle["camera"]["R_qc"])
        assert R.T @ R == pytest.approx(np.eye(3), abs=1e-5)
        angle_deg = math.degrees(math.acos(np.clip((np.trace(R @ R0.T) - 1) / 2, -1, 1)))
        assert angle_deg <= math.sqrt(3) * CAMERA_TILT_DEG + 1e-6
        v = d.record["vehicle"]
        assert 0.5 <= v["depth_noise_scale"] <= 2.0 and 0.5 <= v["accel_bias_sigma_scale"] <= 2.0


def test_haptic_session_is_a_valid_teleop_script_that_fits_the_flight() -> None:
    from quadlink.config import from_dict

    for i in range(10):
        d = draw_flight(9, i, 45.0, offboard_share=0.0)
        assert d.session.kind == "haptic"
        script = build_script(from_dict(ScriptConfig, d.session.script))
        assert script.end_s <= 45.0 + 1e-6
        names = [name for _, name in script.presses]
        assert names[:2] == ["arm", "takeoff"] and names[-1] == "land"
        assert max(abs(f) for seg in script.segments for f in seg.force_d_n) <= 1.6 * 1.1 + 1e-9


def test_push_nearest_aims_the_direction_of_motion_at_the_nearest_obstacle() -> None:
    room = RoomConfig(size_m=(10.0, 10.0))
    s = ScenarioConfig(room=room, start=StartPose((0.0, 0.0), 0.0), objects=(
        SceneObject(kind="cylinder", name="col", position_m=(0.0, 2.0, -1.5), radius_m=0.25, height_m=3.0),))
    found = 0
    for seed in range(40):
        session = generate_session(np.random.default_rng(seed), s, 60.0)
        for m in session.record["manoeuvres"]:
            if m["kind"] != "push_nearest" or m["from_m"] != [0.0, 0.0]:
                continue
            found += 1
            assert m["target"] == "col"
            heading = math.radians(m["heading_deg"]) + m["turn_yaw_rate_rad_s"] * m["turn_s"]
            direction = heading + MOTION_OFFSET_RAD + math.radians(m["direction_deg"])
            want = math.pi / 2 + math.radians(m["approach_offset_deg"])  # east, plus the drawn angle
            assert math.cos(direction - want) == pytest.approx(1.0, abs=1e-4)
    assert found > 5


def test_offboard_plan_timeline_and_masks() -> None:
    d = next(draw_flight(4, i, 40.0, offboard_share=1.0) for i in range(50))
    plan = d.session.script
    assert d.session.kind == "offboard"
    assert setpoint_at(plan, plan["takeoff_s"] - 0.01) is None
    first = plan["segments"][0]
    sp = setpoint_at(plan, plan["takeoff_s"] + 1e-3)
    assert sp is not None and sp.frame == mavlink.MAV_FRAME_BODY_NED
    assert sp.vx_m_s == first["forward_m_s"]
    assert sp.yaw_rate_rad_s == pytest.approx(math.radians(first["yawspeed_deg_s"]))
    assert setpoint_at(plan, plan_end_s(plan) + 1e-3) is None
    # velocity and yaw rate used, position, acceleration and yaw ignored (what MAVSDK's set_velocity_body sends)
    assert TM_VELOCITY_YAW_RATE == 0b0000_0101_1100_0111
    mav = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
    buf = mav.set_position_target_local_ned_encode(0, 1, 191, sp.frame, sp.type_mask, 0, 0, 0, sp.vx_m_s,
                                                   sp.vy_m_s, sp.vz_m_s, 0, 0, 0, 0, sp.yaw_rate_rad_s).pack(mav)
    msg = mavlink.MAVLink(None).parse_char(buf)
    assert msg.coordinate_frame == mavlink.MAV_FRAME_BODY_NED and msg.type_mask == TM_VELOCITY_YAW_RATE


def _truth_log(path: Path, heights_m: list[float], obstacle_m: list[float]) -> None:
    """A truth log made by the SITL's encoder in the 6 m room of these tests, started at its centre (CoM 0.1 m above
    the floor): the vehicle climbs and flies north so that the north wall (x = 3 m) is ``obstacle_m`` away."""
    enc = TruthEncoder()
    w = TlogWriter(path)
    for k, (h, d) in enumerate(zip(heights_m, obstacle_m)):
        for pkt in enc.encode(k * 0.02, np.array([3.0 - d, 0.0, -(h - 0.1)]), np.zeros(3), np.eye(3), np.zeros(3),
                              min(h, d), d):
            w.write(pkt, 0.0)
    w.close()


def test_envelope_adds_the_ceiling_to_the_truth_distance(tmp_path: Path) -> None:
    s = ScenarioConfig(room=RoomConfig(size_m=(6.0, 6.0), height_m=2.5))
    heights = list(np.linspace(0.1, 2.2, 100))
    obstacle = list(np.linspace(2.0, 1.0, 100))
    _truth_log(tmp_path / "truth.tlog", heights, obstacle)
    env = envelope(read_truth(tmp_path / "truth.tlog"), s)
    assert env.min_ceiling_m == pytest.approx(0.3, abs=1e-3)  # 2.5 m room, CoM at 2.2 m
    assert env.min_nonfloor_m == pytest.approx(0.3, abs=1e-3) and env.surface == "ceiling"
    assert env.min_obstacle_m == pytest.approx(1.0, abs=0.006)
    assert env.max_height_m == pytest.approx(2.2, abs=1e-3)
    _truth_log(tmp_path / "t2.tlog", [1.0] * 50, list(np.linspace(1.0, 0.35, 50)))
    env = envelope(read_truth(tmp_path / "t2.tlog"), s)
    assert env.surface == "obstacle" and env.min_nonfloor_m == pytest.approx(0.35, abs=0.006)


def _landing(cut_height_m: float, hop_m: float = 0.0, rate_hz: float = 50.0) -> tuple[np.ndarray, np.ndarray]:
    """Truth at ``rate_hz`` (local NED, z = 0 resting): up to 1.2 m, down at 0.5 m/s, the thrust cut
    ``cut_height_m`` above the floor (1.7 m/s^2 more: 0.83 x hover), then ``hop_m`` up and down again at 0.2 m/s."""
    dt, z, v, zs = 1.0 / rate_hz, 0.0, 0.0, []
    zs += [0.0] * 50 + list(np.linspace(0.0, -1.2, 120)) + [-1.2] * 50
    z, v = -1.2, 0.5
    while z < 0.0:
        if -z <= cut_height_m:
            v += 1.7 * dt
        z += v * dt
        zs.append(min(z, 0.0))
    zs += [0.0] * 20
    if hop_m > 0:
        zs += list(np.linspace(0.0, -hop_m, 10)) + list(np.arange(-hop_m, 0.0, 0.2 * dt)) + [0.0] * 20
    zs_a = np.asarray(zs)
    return np.arange(zs_a.size) * dt, np.column_stack([np.zeros_like(zs_a), np.zeros_like(zs_a), zs_a])


def test_touchdown_speed_is_the_last_landings_impact() -> None:
    t, p = _landing(0.0)
    assert touchdown_m_s(t, p) == pytest.approx(0.5, abs=0.02)
    t, p = _landing(0.15)          # the thrust cut 0.15 m up: sqrt(0.5^2 + 2 x 1.7 x 0.15) = 0.86 m/s
    assert touchdown_m_s(t, p) == pytest.approx(math.sqrt(0.25 + 2 * 1.7 * 0.15), abs=0.04)
    t, p = _landing(0.15, hop_m=0.05)   # a hop after the impact: the last landing's, at 0.2 m/s
    assert touchdown_m_s(t, p) == pytest.approx(0.2, abs=0.02)
    assert math.isnan(touchdown_m_s(t[:200], p[:200]))             # still in the air at the end
    assert math.isnan(touchdown_m_s(t[:40], p[:40]))               # never left the floor
    assert math.isnan(touchdown_m_s(np.zeros(0), np.zeros((0, 3))))


def test_port_slots_and_blocks_never_share_a_port() -> None:
    sets = [set(Ports(flight_ports(3000, k)).as_dict().values()) for k in range(40)]
    assert all(len(s) == len(PORT_NAMES) for s in sets)
    for a, b in itertools.combinations(sets, 2):
        assert not a & b
    blocks = [set(Ports(base=20000 + PORT_BLOCK_SIZE * k).as_dict().values()) for k in range(10)]
    for a, b in itertools.combinations(blocks, 2):
        assert not a & b
    assert Ports(base=20000).mk1 == 20000 and Ports(base=20000).http == 20008 and Ports(7).truth == 14567


def test_flight_spec_resolves_moved_folders(tmp_path: Path) -> None:
    (tmp_path / "scenario.yaml").write_text("name: x\n")
    (tmp_path / "operator.yaml").write_text("steps: []\n")
    spec = FlightSpec("/gone/scenario.yaml", "operator.yaml", 30.0, sitl_config=None).resolve(tmp_path)
    assert spec.scenario == str(tmp_path / "scenario.yaml") and spec.script == str(tmp_path / "operator.yaml")
    assert FlightSpec("paper-arena", "x", 1.0).resolve(tmp_path).scenario == "paper-arena"


def test_compare_reports_finds_the_differing_metrics() -> None:
    a = {"velocity_rmse_m_s": {"x": 0.01, "y": math.nan}, "setpoint_count": 10, "cpu_core_s_per_sim_s": {"a": 1.0}}
    b = {"velocity_rmse_m_s": {"x": 0.02, "y": math.nan}, "setpoint_count": 10, "cpu_core_s_per_sim_s": {"a": 2.0}}
    assert compare_reports(a, b) == [("velocity_rmse_m_s.x", 0.01, 0.02)]
    assert compare_reports(a, a) == []


def test_report_summary_from_flight_envelopes(tmp_path: Path) -> None:
    s = ScenarioConfig(room=RoomConfig(size_m=(6.0, 6.0), height_m=2.5))
    results = []
    for k, closest in enumerate((0.9, 0.42, 0.3, 1.2, 0.6, 0.5)):
        path = tmp_path / f"t{k}.tlog"
        _truth_log(path, [1.0] * 20, list(np.linspace(2.0, closest, 20)))
        env = envelope(read_truth(path), s)
        results.append(FlightResult(k, "ok", 2 if k == 1 else 1, str(tmp_path / f"flight-{k:04d}"),
                                    report={"velocity_rmse_m_s": {"x": 0.01 * k, "y": 0.0},
                                            "setpoint_gaps_over_100ms": int(k == 3),
                                            "flying_time_s": 2.5 if k == 4 else 30.0},
                                    envelope={"min_nonfloor_m": env.min_nonfloor_m, "surface": env.surface,
                                              "max_height_m": 1.0, "touchdown_m_s": 0.35 + 0.1 * k},
                                    draws={"sitl_seed": k}))
    campaign = summarize(results, CampaignOptions(6, 1, tmp_path), 600.0)
    s_ = campaign["summary"]
    assert s_["min_nonfloor_distance_m"] == pytest.approx(0.3, abs=0.006)
    assert s_["share_below_target"] == pytest.approx(1 / 6) and s_["share_below_safe_distance"] == pytest.approx(2 / 6)
    assert [w["index"] for w in s_["worst"]] == [2, 1, 5, 4, 0]
    assert s_["worst"][0]["replay"] == f"quadlink demo --replay {tmp_path / 'flight-0002'}"
    assert s_["retried"] == [1] and s_["share_with_setpoint_gaps"] == pytest.approx(1 / 6)
    assert s_["flights_per_hour"] == pytest.approx(36.0)
    assert "flight    2: 0.300 m" in summary_text(campaign)
    # a flight that came down in its take-off (2.5 s airborne) is listed: its session was not flown
    assert s_["landed_in_takeoff"] == [4] and s_["did_not_take_off"] == []
    assert "landed in the take-off, under 5 s airborne [4]" in summary_text(campaign)
    # the landings' impact speeds 0.35-0.85 m/s: the two over 0.7 m/s listed
    assert s_["touchdown_m_s_max"] == pytest.approx(0.85) and s_["touchdowns_over_bound"] == [4, 5]
    assert "fastest 0.85 m/s; over 0.7 m/s: [4, 5]" in summary_text(campaign)


def test_a_starved_campaigns_report_is_written_with_its_starvation_range(tmp_path: Path) -> None:
    """``quadlink campaign --realtime --cpu-share`` flew its flights, then failed to write campaign.json: the
    starvation range (a dataclass) was not JSON. The options are written with the range's fields."""
    import json

    path = tmp_path / "t.tlog"
    _truth_log(path, [1.0] * 20, list(np.linspace(2.0, 0.8, 20)))
    env = envelope(read_truth(path), ScenarioConfig(room=RoomConfig(size_m=(6.0, 6.0), height_m=2.5)))
    result = FlightResult(0, "ok", 1, str(tmp_path / "flight-0000"), report={"flying_time_s": 20.0},
                          envelope={"min_nonfloor_m": env.min_nonfloor_m, "surface": env.surface, "max_height_m": 1.0},
                          draws={"starvation": {"cpu_cores": 0.35, "busy_neighbours": 1}})
    options = CampaignOptions(1, 5, tmp_path, realtime=True, deterministic=False,
                              starve=StarvationRange(0.35, 0.35, 1.0))
    write_campaign([result], options, 60.0)
    written = json.loads((tmp_path / "campaign.json").read_text())
    assert written["options"]["starve"] == {"cores_lo": 0.35, "cores_hi": 0.35, "contention_p": 1.0}
    assert written["options"]["out_dir"] == str(tmp_path)
    assert written["summary"]["min_nonfloor_distance_m"] == pytest.approx(0.8, abs=0.006)


def test_progress_line_eta() -> None:
    line = progress_line(2, 8, 2, 0, 0, 120.0)
    assert "2/8" in line and "ETA 06:00" in line and "elapsed 02:00" in line
    assert "ETA --:--" in progress_line(0, 8, 2, 0, 0, 10.0)


def test_sitl_config_written_for_a_flight_is_complete(tmp_path: Path) -> None:
    d = draw_flight(1, 0, 40.0)
    files = write_flight_files(d, tmp_path)
    cfg = load_sitl_config(files.sitl)
    assert cfg.camera_noise.depth_sigma_per_m2 == pytest.approx(0.0025 * d.record["vehicle"]["depth_noise_scale"])
    assert load_config(files.scenario, ScenarioConfig).start == d.scenario.start


def test_the_companion_gets_the_operators_room_height_entry_not_the_truth(tmp_path: Path) -> None:
    """Issue 29: the room's height reaches the companion as an operator's entry with its error, or not at all."""
    import yaml

    from harness.demo.cli import companion_config_for_room
    from sim_sitl.config import load_scenario

    true_m = load_scenario("paper-arena").room.height_m
    entered = yaml.safe_load(companion_config_for_room(tmp_path / "a", "paper-arena", 0.07).read_text())
    assert entered["reference"]["room_height_m"] == pytest.approx(true_m + 0.07)
    unknown = yaml.safe_load(companion_config_for_room(tmp_path / "b", "paper-arena", None).read_text())
    assert unknown["reference"]["room_height_m"] is None


def test_the_entry_is_the_lowest_overhead_a_soffit_under_the_ceiling(tmp_path: Path) -> None:
    """Campaign 24, flight 27 (0.106 m under a soffit): the operator enters the lowest overhead, as the guide asks (the
    camera never sees above the vehicle), so the campaign's entry is the soffit's underside plus the error."""
    import yaml

    from harness.campaign.draws import scenario_to_dict
    from harness.demo.cli import companion_config_for_room
    from sim_sitl.config import load_scenario
    from sim_sitl.scenario_gen import generate_procedural, lowest_overhead_m

    soffits = []
    for seed in range(60):
        scenario, _ = generate_procedural(np.random.default_rng(seed), f"soffit-{seed}", layout="low-ceiling")
        under = [-o.position_m[2] - o.size_m[2] / 2 for o in scenario.objects if o.name == "soffit"]
        assert len(under) == 1
        assert lowest_overhead_m(scenario) == pytest.approx(min(under[0], scenario.room.height_m))
        soffits.append(scenario.room.height_m - under[0])
    assert min(soffits) >= 0.29   # each hangs 0.3-0.7 m below its ceiling: the entry is lower than the room
    path = tmp_path / "soffit.yaml"
    path.write_text(yaml.safe_dump(scenario_to_dict(scenario)))
    entered = yaml.safe_load(companion_config_for_room(tmp_path / "c", str(path), -0.05).read_text())
    assert entered["reference"]["room_height_m"] == pytest.approx(round(under[0] - 0.05, 2))
    # an object standing on the floor is not overhead
    assert lowest_overhead_m(load_scenario("paper-arena")) == load_scenario("paper-arena").room.height_m


def test_campaign_draws_the_room_height_entry_error_per_flight() -> None:
    from harness.campaign.draws import ROOM_HEIGHT_ENTRY_ERROR_M, draw_flight

    errors = [draw_flight(7, i, 20.0).room_height_error_m for i in range(40)]
    assert errors == [draw_flight(7, i, 20.0).room_height_error_m for i in range(40)]   # reproducible from the seed
    known = [e for e in errors if e is not None]
    assert 0 < len(errors) - len(known) < 20 and all(abs(e) <= ROOM_HEIGHT_ENTRY_ERROR_M for e in known)
    assert max(known) - min(known) > ROOM_HEIGHT_ENTRY_ERROR_M   # spread over the range, not one value
    assert draw_flight(7, 3, 20.0).record["room_height_entry_error_m"] == errors[3]



def test_sessions_fly_every_direction_relative_to_the_camera() -> None:
    """Issue 29: scripts push along, diagonally, across and against the camera's axis; a haptic operator along it or
    backing against it (eq. 2 allows nothing else); and a script's body velocity points where the plan says."""
    from harness.campaign.sessions import MOTION_OFFSET_RAD, direction_label

    seen: dict[str, set[str]] = {"haptic": set(), "offboard": set()}
    for i in range(30):
        for share in (0.0, 1.0):
            d = draw_flight(11, i, 60.0, offboard_share=share)
            for m in d.session.record["manoeuvres"]:
                if m["kind"] in ("push_nearest", "slide_wall", "drive"):
                    seen[d.session.kind].add(m["direction"])
                    assert m["direction"] == direction_label(m["direction_deg"])
            if d.session.kind == "offboard":
                moving = [(st, seg) for st, seg in zip(
                    [st for m in d.session.record["manoeuvres"] for st in m["steps"] if st[3] > 0],
                    d.session.script["segments"]) if st[0] > 0]
                for (_fwd, _, _, _, rel_deg), seg in moving:
                    a = math.atan2(seg["right_m_s"], seg["forward_m_s"])
                    assert math.cos(a - MOTION_OFFSET_RAD - math.radians(rel_deg)) == pytest.approx(1.0, abs=1e-3)
    assert seen["offboard"] == {"along", "diagonal", "across", "against"}
    assert seen["haptic"] == {"along", "against"}


def test_the_report_tabulates_clearance_by_manoeuvre_and_direction(tmp_path: Path) -> None:
    """Issue 29: each planned manoeuvre's window of the truth is judged; a weak direction shows as its own row."""
    import json

    import yaml

    from harness.campaign.manoeuvres import flight_manoeuvres, table, table_text
    from sim_sitl.scenario_gen import scenario_to_dict

    s = ScenarioConfig(room=RoomConfig(size_m=(6.0, 6.0), height_m=2.5))
    rows = []
    for k, (near_along, near_across) in enumerate(((1.5, 0.35), (1.2, 0.6))):
        folder = tmp_path / f"flight-{k:04d}"
        folder.mkdir()
        # 0..0.48 s: the along push ends near_along from the wall; 0.5..0.98 s: the across push comes to near_across
        obstacle = list(np.linspace(2.0, near_along, 25)) + list(np.linspace(1.0, near_across, 25))
        _truth_log(folder / "truth.tlog", [1.0] * 50, obstacle)
        (folder / "scenario.yaml").write_text(yaml.safe_dump(scenario_to_dict(s)))
        plan = [{"kind": "push_nearest", "direction": "along", "t_plan_s": 0.0, "steps": [[1, 0, 0, 0.48, 0.0]]},
                {"kind": "push_nearest", "direction": "across", "t_plan_s": 0.5, "steps": [[1, 0, 0, 0.48, 90.0]]}]
        (folder / "draws.json").write_text(json.dumps({"operator": {"manoeuvres": plan}}))
        rows += flight_manoeuvres(folder, k)
    got = {(r["manoeuvre"], r["direction"]): r for r in table(rows)}
    assert got[("push_nearest", "along")]["min_clearance_m"] == pytest.approx(1.2, abs=0.01)
    assert got[("push_nearest", "across")]["min_clearance_m"] == pytest.approx(0.35, abs=0.01)
    assert got[("push_nearest", "across")]["worst_flight"] == 0 and got[("push_nearest", "across")]["count"] == 2
    assert "across" in table_text(table(rows))
