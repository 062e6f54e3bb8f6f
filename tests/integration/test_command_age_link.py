"""Stale commands are dropped over a delayed link (issue 18): a pymavlink operator that stamps its commands
(COMMAND_STAMP + MANUAL_CONTROL, TIMESYNC answered) talks to the real companion daemon through the real
netem UDP proxy; at 300 ms one way with a 0.2 s command age nothing it sends moves the vehicle, at 10 ms
everything does."""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from test_companion_daemon import Rig  # the daemon rig on loopback (real links, real camera stream)

from companion.config import CompanionConfig, LinksConfig, ModeParams, PanScanConfig, TimingConfig
from companion.modes import Mode
from harness.netem import Impairment, UdpProxy
from quadlink.mavlink import mavlink
from quadlink.mavlink.timesync import NS, answer_fields, is_request

pytestmark = pytest.mark.integration

MAX_AGE_S = 0.2
FORWARD = (600, 0, 500)


class StampingOperator:
    """What teleop.link does, in a few lines: stamp every MANUAL_CONTROL and answer the companion's TIMESYNC
    at once (a thread owns the ground station's socket, so a loaded machine does not inflate the round trip)."""

    def __init__(self, rig: Rig) -> None:
        self.rig, self.mav = rig, rig.gcs.link.mav
        self.answered = 0
        rig.gcs.poll = lambda: None          # type: ignore[method-assign]  # the thread reads the socket now
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            m = self.rig.gcs.link.recv_msg()
            if m is None:
                time.sleep(0.001)
                continue
            if m.get_type() == "TIMESYNC" and m.get_srcComponent() == 191 and is_request(m.tc1):
                self.mav.timesync_send(*answer_fields(m.ts1, int(time.monotonic() * NS)))
                self.answered += 1
            elif m.get_type() != "BAD_DATA":
                self.rig.gcs.received.append(m)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)

    def send(self, manual: tuple[int, int, int]) -> None:
        self.mav.command_stamp_send(int(time.monotonic() * 1e6), mavlink.MAVLINK_MSG_ID_MANUAL_CONTROL, 1, 191)
        self.mav.manual_control_send(1, manual[0], manual[1], manual[2], 0, 0)

    def frames(self, n: int, manual: tuple[int, int, int] = FORWARD) -> None:
        for _ in range(n):
            self.send(manual)
            self.rig.frame()


def fly_through(tmp_path: Path, delay_ms: float) -> tuple[Rig, list[Any]]:
    cfg = CompanionConfig(links=LinksConfig(max_command_age_s=MAX_AGE_S, gcs_timesync_period_s=0.25),
                          timing=TimingConfig(camera_timeout_s=5.0),   # a loaded machine: frames ~1 s apart
                          pan_scan=PanScanConfig(enabled=False),
                          modes=ModeParams(gcs_timeout_s=0.5, gcs_land_timeout_s=1.5, takeoff_min_s=0.3))
    proxies: list[UdpProxy] = []

    def via(port: int) -> int:
        proxies.append(UdpProxy(("127.0.0.1", 0), ("127.0.0.1", port), Impairment(delay_ms=delay_ms), seed=1).start())
        return proxies[0].listen_address[1]

    rig = Rig(tmp_path, cfg=cfg, gcs_via=via)
    return rig, proxies


def test_commands_older_than_the_age_are_dropped_at_300ms(tmp_path: Path) -> None:
    rig, proxies = fly_through(tmp_path, 300.0)
    op = StampingOperator(rig)
    try:
        op.frames(60)                              # ~2-3 s: TIMESYNC settles, every command arrives 300 ms old
        d = rig.daemon
        sync = next(iter(d.gcs_sync.values()))
        assert op.answered >= 3 and sync.offset_ns is not None
        assert 0.6 <= sync.rtt_percentile_s(50) <= 0.75           # both ways through the proxy

        c = d.command_age.counts
        assert c.stale >= 20 and c.stamped == 0, c  # the first ones were taken by arrival time (no offset yet)
        assert d.command_age.age_percentile_s(50) == pytest.approx(0.3, abs=0.06)
        # the vehicle: takeoff through the same link, then it never gets a fresh command: HOLD, then LAND
        rig.gcs.link.mav.command_long_send(1, 191, mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 0, 1.0)
        seen: list[Mode] = []
        t_end = time.monotonic() + 40.0   # generous: a loaded machine runs this rig at a few frames per second
        while time.monotonic() < t_end and Mode.LAND not in seen:
            op.frames(1)
            seen.append(d.modes.mode)
        assert Mode.HOLD in seen and Mode.LAND in seen, seen
        assert seen.index(Mode.HOLD) < seen.index(Mode.LAND)
        in_control = [m for m in rig.ap.of_type("SET_POSITION_TARGET_LOCAL_NED")]
        assert in_control and max(abs(m.vx) for m in in_control) < 1e-6   # the forward command never flew
        # the figures reach the ground station (NAMED_VALUE_INT, also in the companion's tlog)
        named = {m.name: m.value for m in rig.gcs.of_type("NAMED_VALUE_INT")}
        assert named.get("CMD_STALE", 0) >= 20
    finally:
        op.close()
        rig.close()
        for p in proxies:
            p.close()


def test_the_same_commands_fly_at_10ms(tmp_path: Path) -> None:
    rig, proxies = fly_through(tmp_path, 10.0)
    op = StampingOperator(rig)
    try:
        op.frames(30, manual=(0, 0, 500))
        rig.gcs.link.mav.command_long_send(1, 191, mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 0, 1.0)
        for _ in range(60):
            op.frames(1, manual=(0, 0, 500))
            if rig.daemon.modes.mode == Mode.TELEOP:
                break
        assert rig.daemon.modes.mode == Mode.TELEOP
        n_before = len(rig.ap.of_type("SET_POSITION_TARGET_LOCAL_NED"))
        op.frames(30)
        c = rig.daemon.command_age.counts
        assert c.stamped > 50 and c.stale == 0, c
        assert rig.daemon.command_age.age_percentile_s(50) < 0.1
        assert rig.daemon.modes.mode == Mode.TELEOP
        vx = np.array([m.vx for m in rig.ap.of_type("SET_POSITION_TARGET_LOCAL_NED")[n_before:]])
        assert vx.size > 10 and np.median(vx) > 0.1                       # the forward command flies
    finally:
        op.close()
        rig.close()
        for p in proxies:
            p.close()
