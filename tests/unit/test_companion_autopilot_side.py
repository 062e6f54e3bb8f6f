"""The companion's autopilot side on its own (unit tier): the autopilot's time as the companion knows it and
the TIMESYNC with it (companion.timesync), and the perception stage (companion.perception_stage)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from companion.guard import ErrorCounter
from companion.perception_stage import PerceptionStage
from companion.stats import Stats
from companion.timesync import AutopilotTime, TimeSync
from quadlink.camera import CameraIntrinsics, RgbdFrame
from quadlink.mavlink import mavlink

pytestmark = pytest.mark.unit

SYSID, AP_COMPID = 1, 1


def wire(msg: Any, src_system: int = SYSID, src_component: int = AP_COMPID) -> Any:
    """``msg`` as the companion gets it: packed by the sender's codec, parsed by a receiver's."""
    (out,) = mavlink.MAVLink(None).parse_buffer(bytes(msg.pack(mavlink.MAVLink(None, src_system, src_component))))
    return out


def clock() -> float:
    return 0.0


def test_the_autopilot_timesync_request_is_answered_with_our_clock() -> None:
    ts = TimeSync()
    reply = ts.on_message(wire(mavlink.MAVLink_timesync_message(0, 777), SYSID, AP_COMPID), 2.0)
    assert reply is not None and (reply.tc1, reply.ts1) == (2_000_000_000, 777)
    assert ts.on_message(wire(mavlink.MAVLink_timesync_message(5_000_000_000, 1_990_000_000)), 2.0) is None
    assert ts.offset_ns is not None


def test_the_autopilot_time_runs_on_from_the_last_imu_sample_else_the_last_frame() -> None:
    t = AutopilotTime(TimeSync(), "autopilot", start_wall_s=10.0)
    assert t.estimate_s(12.5) == pytest.approx(2.5)   # nothing yet: the time since the start
    assert t.on_frame(40.0, wall_s=13.0) == 40.0      # the camera stamps in the autopilot's time already
    assert t.estimate_s(13.25) == pytest.approx(40.25)
    t.on_imu(40.1, wall_s=13.05)
    assert t.estimate_s(13.25) == pytest.approx(40.3)


def test_local_camera_stamps_are_mapped_through_the_autopilot_timesync_once_known() -> None:
    ts = TimeSync()
    t = AutopilotTime(ts, "local", start_wall_s=0.0)
    assert t.on_frame(5.0, wall_s=5.0) == 5.0   # no estimate yet: taken as they come
    # our request at 5.000 s, answered with the autopilot's 105.005 s, back at 5.010 s: offset +100 s
    ts.on_message(wire(mavlink.MAVLink_timesync_message(105_005_000_000, 5_000_000_000), SYSID, AP_COMPID), 5.01)
    assert t.on_frame(6.0, wall_s=6.0) == pytest.approx(106.0, abs=1e-6)
    assert t.frame_stamp_s == pytest.approx(106.0, abs=1e-6) and t.frame_wall_s == 6.0


class Pipe:
    def __init__(self) -> None:
        self.imu: list[float] = []
        self.fail = False

    def on_imu(self, stamp_s: float, gyro: np.ndarray, accel: np.ndarray) -> None:
        if self.fail:
            raise ValueError("bad sample")
        self.imu.append(stamp_s)

    def on_frame(self, frame: RgbdFrame) -> Any:
        if self.fail:
            raise np.linalg.LinAlgError("singular")
        return frame.seq


def frame(seq: int, size: int = 8) -> RgbdFrame:
    K = CameraIntrinsics(6.0, 6.0, 4.0, 4.0, size, size)
    return RgbdFrame(seq, seq * 0.1, np.zeros((size, size, 3), np.uint8), np.ones((size, size), np.float32), K,
                     np.eye(3), np.zeros(3))


def test_perception_starts_on_the_first_frame_and_refuses_a_changed_camera() -> None:
    pipes: list[Pipe] = []
    stats, errors = Stats(), ErrorCounter(clock)
    stage = PerceptionStage(lambda f: pipes.append(Pipe()) or pipes[-1], stats, errors)
    stage.on_imu(0.0, np.zeros(3), np.zeros(3))   # before the first frame: nothing to feed
    assert stage.on_frame(frame(1)) == 1 and len(pipes) == 1
    stage.on_imu(0.15, np.zeros(3), np.zeros(3))
    assert pipes[0].imu == [0.15]
    assert stage.on_frame(frame(2, size=16)) is None and errors.by_where == {"camera frame": 1}
    pipes[0].fail = True
    assert stage.on_frame(frame(3)) is None
    stage.on_imu(0.3, np.zeros(3), np.zeros(3))
    assert stats.pipeline_errors == 3 and len(pipes) == 1
