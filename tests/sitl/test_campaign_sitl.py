"""Issue 15: campaigns fly the real stack. A 3-flight campaign through the local Ray (all three at once), two demo
flights at once on disjoint port blocks, and whether the same seed gives the same flight.

Each flight's metrics are checked against its own truth log and its own arena: the truth stream's
distance to the nearest wall or object at the start must be the distance the arena's geometry gives at
the drawn start pose, which differs from flight to flight, so a crossed port or folder would show.
"""

from __future__ import annotations

import json
import os
import threading
from pathlib import Path
from typing import Any

import pytest

from companion.replay import replay_journal
from firmware_bridge.replay import replay_bridge_journal
from harness.campaign.draws import StarvationRange, draw_flight
from harness.campaign.runner import CampaignOptions, fly, run_campaign
from harness.campaign.safety import envelope, read_truth
from harness.cpu_share import CpuShare, CpuShareUnavailable
from harness.demo.cli import (
    BRIDGE_JOURNAL_NAME,
    JOURNAL_NAME,
    PORT_BLOCK_SIZE,
    TELEOP_JOURNAL_NAME,
    compare_reports,
    run_demo,
)
from harness.demo.report import compute_report, load_flight
from harness.machine_speed import REFERENCE_WORK_CPU_S, starved_cores, work_cpu_s
from harness.ports import PORT_SLOT_STRIDE, free_port_base, free_port_offset
from quadlink import CONFIG_DIR
from quadlink.config import load_config
from quadlink.mavlink import mavlink
from quadlink.mavlink.tlog import read_tlog
from quadlink.safety import CLEARANCE_BOUND_M
from sim_sitl.config import ScenarioConfig, load_scenario
from sim_sitl.scenario_gen import nearest_obstacle_2d
from teleop.replay import replay_teleop_journal

pytestmark = pytest.mark.sitl

# the campaign helper's port lane (offsets 3000-3900), one slice per test process
OFFSET = free_port_offset(slots=3)   # harness.ports: free now, reserved for this session
COM_UP_M = 0.1  # the SITL's body rests with its centre 0.1 m above the floor


def _last_armed(bridge_tlog: Path) -> bool | None:
    """The armed flag of the autopilot's last HEARTBEAT in the bridge's log (None: none)."""
    armed = None
    for _, m in read_tlog(bridge_tlog):
        if m.get_type() == "HEARTBEAT" and m.get_srcComponent() == mavlink.MAV_COMP_ID_AUTOPILOT1:
            armed = bool(m.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
    return armed


def _start_distance(truth: Path) -> float:
    series = read_truth(truth)
    return float(series.obstacle_m[0])


def _assert_own_truth(folder: Path, scenario: ScenarioConfig) -> None:
    """The flight's truth log is its own: the first truth distance is its arena's at its start."""
    want, _, _ = nearest_obstacle_2d(scenario, scenario.start.position_m, band_m=(COM_UP_M, COM_UP_M))
    assert _start_distance(folder / "truth.tlog") == pytest.approx(want, abs=0.03)


def test_three_flight_campaign_on_local_ray(tmp_path: Path) -> None:
    # 30 s flights that manoeuvre (issue 29): each is judged (every non-floor surface, the whole flight) and moved.
    # All three at once (Ray gives each a third of the machine's CPUs): two at once and then the third alone left
    # a core idle for the third's ~45 s; deterministic lock-step flights do not care how slowly they fly
    options = CampaignOptions(3, 20261201, tmp_path, duration_s=30.0, parallel=3, port_offset=OFFSET,
                              cpus_per_flight=(os.cpu_count() or 1) / 3)
    seen = []
    results = run_campaign(options, on_result=seen.append, echo=lambda s: None)
    assert sorted(r.index for r in results) == [0, 1, 2] and len(seen) == 3
    starts = []
    excursions: list[float] = []
    for r in results:
        folder = Path(r.folder)
        assert r.status == "ok", r.failure
        assert r.attempts == 1
        scenario = load_config(folder / "scenario.yaml", ScenarioConfig)
        assert json.loads((folder / "draws.json").read_text()) == draw_flight(options.seed, r.index, 30.0).record
        _assert_own_truth(folder, scenario)
        starts.append(_start_distance(folder / "truth.tlog"))
        # the metrics in the result are computed from this folder's logs
        again = compute_report(load_flight(folder), None, str(folder / "scenario.yaml"))
        assert compare_reports(again, r.report) == []
        assert r.envelope == pytest.approx({**r.envelope, **vars(envelope(read_truth(folder / "truth.tlog"),
                                                                          scenario))})
        assert r.report["flying_time_s"] > 10.0
        assert r.envelope["min_nonfloor_m"] >= CLEARANCE_BOUND_M, (r.index, r.envelope)
        excursions.append(r.report["mobility"]["max_excursion_m"])
        # every flight ends on the ground: a session that ends in the air flies on until the failsafe lands it
        assert _last_armed(folder / "bridge.tlog") is False
    assert len({round(s, 2) for s in starts}) == 3  # three arenas: a crossed log would not match its arena
    # the flights manoeuvred (a campaign of vehicles that never moved would pass any clearance check); two flights of
    # these draws move only 0.06-0.25 m: their pushes go where the camera has not looked, which the companion holds
    print(f"excursions from the start: {[round(e, 2) for e in excursions]} m")
    assert max(excursions) > 0.5, excursions
    # the three flew at once, on different port slots
    assert len({r.port_offset for r in results}) == 3
    assert max(r.t_start_unix_s for r in results) < min(r.t_end_unix_s for r in results)


@pytest.mark.slow   # CI: the three-flight campaign above already flies three at once on separate port slots
def test_two_flights_at_once_on_disjoint_port_blocks(tmp_path: Path) -> None:
    base = free_port_base(2 * PORT_BLOCK_SIZE)  # two blocks of PORT_BLOCK_SIZE ports
    script = CONFIG_DIR / "teleop_scripts" / "demo_short.yaml"
    results: dict[str, dict] = {}
    errors: list[BaseException] = []

    def one(name: str, scenario: str, port_base: int) -> None:
        try:
            results[name] = run_demo(scenario, 15.0, tmp_path / name, script, port_base=port_base,
                                     progress_every_s=60.0)
        except BaseException as exc:  # noqa: BLE001 - reported by the main thread
            errors.append(exc)

    threads = [threading.Thread(target=one, args=("a", "paper-arena", base)),
               threading.Thread(target=one, args=("b", "office", base + PORT_BLOCK_SIZE))]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=900)
    assert not errors, errors
    for name, scenario in (("a", "paper-arena"), ("b", "office")):
        assert results[name]["failure"] is None
        _assert_own_truth(tmp_path / name, load_scenario(scenario))
        sitl_log = (tmp_path / name / "logs" / "sitl.log").read_text()
        port = base if name == "a" else base + PORT_BLOCK_SIZE
        assert f"127.0.0.1:{port}" in sitl_log  # the block's first port is this SITL's port 1


def _payloads(tlog: Path) -> list[bytes]:
    return [bytes(m.get_msgbuf()) for _, m in read_tlog(tlog)]


def test_same_seed_twice_gives_identical_metrics(tmp_path: Path) -> None:
    """The deterministic lock-step (quadlink/lockstep.py): the same draw flown twice is the same flight, bit for
    bit, although the two flights see different wall-clock timing: they fly at once, on two port slots, each beside
    the other's processes on the machine's two cores (and the second journals its inputs)."""
    results: dict[str, Any] = {}
    errors: list[BaseException] = []

    def one(name: str, slot: int, journal: bool) -> None:
        try:
            options = CampaignOptions(1, 77, tmp_path / name, duration_s=25.0, port_offset=OFFSET, journal=journal)
            results[name] = fly(options, 0, slot, 1)
        except BaseException as exc:  # noqa: BLE001 - reported by the test's thread
            errors.append(exc)

    # the second also journals its companion's inputs (--journal): journaling must not change the flight
    threads = [threading.Thread(target=one, args=("a", 0, False)), threading.Thread(target=one, args=("b", 1, True))]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=900)
    assert not errors, errors
    first, second = results["a"], results["b"]
    assert first.port_offset != second.port_offset
    assert max(first.t_start_unix_s, second.t_start_unix_s) < min(first.t_end_unix_s, second.t_end_unix_s), \
        "the two flew at once"
    assert first.status == second.status == "ok", (first.failure, second.failure)
    assert first.draws == second.draws
    for name in ("scenario.yaml", "operator.yaml", "vehicle.yaml"):
        assert (Path(first.folder) / name).read_bytes() == (Path(second.folder) / name).read_bytes()
    assert first.report["flying_time_s"] > 5.0
    assert compare_reports(first.report, second.report) == []
    assert first.envelope == second.envelope
    # not just the figures: every message of the truth, the companion's and the autopilot's logs
    for log in ("truth.tlog", "companion.tlog", "bridge.tlog"):
        a, b = _payloads(Path(first.folder) / log), _payloads(Path(second.folder) / log)
        assert len(a) > 1000 and a == b, log
    # and the journals re-run their processes byte for byte (issue 28): the companion, the bridge, the ground station
    # (the longer journaled flight, with the commands' exit statuses, is test_companion_journal_sitl.py: slow)
    assert not (Path(first.folder) / JOURNAL_NAME).exists()
    replay = replay_journal(Path(second.folder) / JOURNAL_NAME)
    assert replay.divergence is None and replay.by_kind.get("FRAME", 0) > 300, replay
    bridge = replay_bridge_journal(Path(second.folder) / BRIDGE_JOURNAL_NAME)
    assert bridge.identical and bridge.writes_compared > 5000, bridge.summary()
    assert first.draws["operator"]["kind"] == "haptic"   # the draw this test pins: a ground station to re-run
    teleop = replay_teleop_journal(Path(second.folder) / TELEOP_JOURNAL_NAME)
    assert teleop.identical and teleop.writes_compared > 1000, teleop.summary()


@pytest.mark.slow   # a 25 s real-time flight: CI's time (it left CI on 39d0bc8 when its share was in absolute cores
#                     and this machine ran ~2x slower than when the share was chosen)
def test_a_starved_real_time_campaign_flight_holds_its_share_and_reports_its_latency(tmp_path: Path) -> None:
    """Issue 30: a campaign flight in real time with the bridge and the companion held to 0.35 core of the machine
    that validated it (scaled to this machine's speed now, harness/machine_speed.py) beside a busy process (the draw
    pinned to one share): the share was applied (the kernel throttled it), the companion's data age is in the
    report, and the honest judge finds the envelope kept."""
    try:
        with CpuShare(1.0):
            pass
    except CpuShareUnavailable as exc:
        pytest.skip(f"no CPU share can be set here: {exc}")
    work_s = work_cpu_s()
    cores = starved_cores(work_s)
    print(f"share {cores} core (the work took {work_s:.3f} s, {REFERENCE_WORK_CPU_S:.3f} s at the reference)")
    options = CampaignOptions(1, 20261205, tmp_path, duration_s=25.0, parallel=1,
                              port_offset=OFFSET + 2 * PORT_SLOT_STRIDE, deterministic=False, realtime=True,
                              starve=StarvationRange(cores, cores, 1.0))
    (r,) = run_campaign(options, echo=lambda s: None)
    assert r.status == "ok", r.failure
    assert r.draws["starvation"] == {"cpu_cores": cores, "busy_neighbours": 1}
    share = r.report["cpu_share"]
    assert share["cores"] == cores and share["throttled_s"] > 0.0, share
    age = r.report["data_age_ms"]
    assert age["samples"] >= 15 and 0.0 < age["p50"] < age["max"], age
    # a mobility bound: starved, the odometry may be lost in the air and the bridge lands (its failsafe), and the
    # share and the latency are measured all the same. Flying time on this machine (7 flights of 9cfe9de's odometry,
    # six here and CI's on 2730ab3): 13.9-15.4 s in 4, 7.3-9.2 s in 3 (odometry lost in the air, landed, clearance
    # 0.92-1.08 m); it was > 10 s in the CI runs before 2026-12-06
    assert r.report["flying_time_s"] > 5.0
    assert r.envelope["min_nonfloor_m"] >= CLEARANCE_BOUND_M, r.envelope
