"""The bridge behind its IMU (a starved CPU): it merges the samples it is late for instead of queueing on, through
the daemon's own dispatch of the board's IMU bytes (real MK frames) into the real Autopilot; the attitude it
estimates is the one it estimates in time."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from memory_links import MemoryConn

from firmware_bridge.daemon import IMU_BEHIND_S, IMU_MERGE_MAX, BridgeConfig, BridgeDaemon
from quadlink.frames import GRAVITY_M_S2
from quadlink.mk import messages as mk
from quadlink.mk.protocol import ADDR_FC, encode_frame
from quadlink.vehicle import VehicleConfig

IMU_PERIOD_S = 0.002
YAW_RATE_RAD_S = 1.0


class _Board:
    """MK port 1 as the daemon writes it (the setpoints, counted)."""

    def __init__(self) -> None:
        self.bytes_written = 0

    def write(self, data: bytes) -> bool:
        self.bytes_written += len(data)
        return True

    def drop(self) -> None:
        pass


def _fly(tmp_path: Path, lags_s: list[float]) -> tuple[BridgeDaemon, list[Any]]:
    """One IMU sample per entry (a steady yaw at 1 rad/s, level), each handled ``lag`` after its bytes were read;
    the daemon and the HIGHRES_IMU messages it sent."""
    wall = [0.0]
    config = BridgeConfig(mavlink_urls=("udpout:127.0.0.1:31510",), params_file=str(tmp_path / "p.yaml"))
    daemon = BridgeDaemon(config, VehicleConfig(), clock=lambda: wall[0])
    daemon.attach_links(_Board(), [MemoryConn()])
    imu_cfg = VehicleConfig().imu
    for k, lag_s in enumerate(lags_s):
        read_s = k * IMU_PERIOD_S
        frame = encode_frame(ADDR_FC, "I", mk.ImuSample.from_si([0.0, 0.0, -GRAVITY_M_S2],
                                                                [0.0, 0.0, YAW_RATE_RAD_S], imu_cfg, k).pack())
        wall[0] = read_s + lag_s
        daemon._dispatch(("imu", frame, read_s))
    sent = [m for m in daemon.mavlinks[0].messages() if m.get_type() == "HIGHRES_IMU"]
    return daemon, sent


def _yaw_rad(daemon: BridgeDaemon) -> float:
    return daemon.autopilot.state.filter.estimate.yaw_rad


def test_behind_its_imu_the_bridge_merges_what_it_is_late_for_and_estimates_the_same_attitude(
        tmp_path: Path) -> None:
    n = 500   # 1 s
    on_time, sent_on_time = _fly(tmp_path / "a", [0.0] * n)
    # in time for 10 samples, then 100 ms late (a starved CPU), then caught up for the last 50
    late, sent_late = _fly(tmp_path / "b", [0.0] * 10 + [0.1] * (n - 60) + [0.0] * 50)
    # in time: every sample streamed, none merged
    assert len(sent_on_time) == n and on_time.stats.imu_merged == 0
    # 100 ms late: merged by IMU_MERGE_MAX (the 50 ms the estimators may step), each sample again once caught up
    assert late.stats.imu_merged >= (n - 60) * (1 - 1 / IMU_MERGE_MAX) - IMU_MERGE_MAX
    assert len(sent_late) <= 10 + (n - 60) / IMU_MERGE_MAX + 1 + 50
    assert [m.time_usec for m in sent_late[-50:]] == [k * 2000 for k in range(n - 50, n)]
    # the same heading: the merged samples' mean rate over their interval (the yaw integrates to 1 rad either way)
    assert abs(_yaw_rad(late) - _yaw_rad(on_time)) < 1e-3
    assert abs(_yaw_rad(on_time) - YAW_RATE_RAD_S * (n - 1) * IMU_PERIOD_S) < 0.02


def test_a_little_late_merges_what_it_is_late_for_and_in_time_nothing(tmp_path: Path) -> None:
    """Just past IMU_BEHIND_S (20 ms: 10 samples) the samples it is late for are merged (10 at a time: 50 Hz on),
    not IMU_MERGE_MAX's; a sample late by less is handled on its own."""
    daemon, sent = _fly(tmp_path, [IMU_BEHIND_S + 0.001] * 100)
    assert 9 <= len(sent) <= 11 and daemon.stats.imu_merged >= 80
    daemon, sent = _fly(tmp_path / "b", [IMU_BEHIND_S - 0.001] * 100)
    assert len(sent) == 100 and daemon.stats.imu_merged == 0
    assert math.isfinite(_yaw_rad(daemon))
