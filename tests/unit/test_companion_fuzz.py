"""Property tests of every MAVLink handler of the companion (issue 16), in-process: the real daemon
(:class:`companion.daemon.Companion`: router, parameter service, command handling, mode machine, the frame
step) on in-memory links, fed real pymavlink messages (packed by a sender's codec, parsed by a receiver's) with
arbitrary field values: NaN, infinities, huge, negative, out-of-range enums and ids.

Properties, for any sequence of such messages from the ground station and the autopilot:

* no exception reaches the daemon's last-resort guard (every bad input is refused by validation, not by luck);
* every message the companion sends to the autopilot decodes and holds no non-finite value (the NaNs MAVLink
  defines — a command's unused params, ODOMETRY's unknown covariance — aside), setpoints above all, and none
  had to be dropped for one;
* every parameter stays finite and inside its bounds (companion.params.PARAM_SPECS);
* the setpoint stream goes on: each camera frame still produces one setpoint.

The example count is the ``quadlink`` hypothesis profile's (tests/conftest.py; QUADLINK_FUZZ_EXAMPLES).
"""

from __future__ import annotations

import itertools
import math
from collections import deque
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from integration.test_companion_daemon import FakePipeline  # the daemon rig's stand-in perception

from companion.config import CompanionConfig, PanScanConfig
from companion.daemon import Companion
from companion.guard import non_finite_fields
from companion.modes import Mode
from companion.params import PARAM_NAMES, PARAM_SPECS
from quadlink.camera import CameraIntrinsics, RgbdFrame
from quadlink.mavlink import mavlink

pytestmark = pytest.mark.fuzz

SYSID, COMPID, AP_COMPID = 1, 191, 1


class MemLink:
    """An in-memory MAVLink endpoint: ``inbox`` of parsed messages, ``sent`` raw packets."""

    def __init__(self) -> None:
        self.inbox: deque[Any] = deque()
        self.sent: list[bytes] = []

    def recv_msg(self) -> Any:
        return self.inbox.popleft() if self.inbox else None

    def write(self, buf: bytes) -> None:
        self.sent.append(bytes(buf))

    def close(self) -> None:
        pass


class MemCamera:
    """Frames handed over one per ``read`` when queued (the real stream's records are validated upstream)."""

    def __init__(self) -> None:
        self.frames: deque[RgbdFrame] = deque()
        self.connected = True

    def read(self, timeout_s: float) -> RgbdFrame | None:
        return self.frames.popleft() if self.frames else None

    def ack(self, seq: int) -> None:
        pass

    def close(self) -> None:
        pass


class StepClock:
    """Monotonic fake time: each reading advances 1 ms (so every bounded wait ends)."""

    def __init__(self) -> None:
        self._ticks = itertools.count()

    def __call__(self) -> float:
        return next(self._ticks) * 1e-3


K = CameraIntrinsics(6.0, 6.0, 4.0, 4.0, 8, 8)
R_QC = np.eye(3)


def _frame(seq: int, stamp_s: float) -> RgbdFrame:
    return RgbdFrame(seq, stamp_s, np.zeros((8, 8, 3), np.uint8), np.ones((8, 8), np.float32), K, R_QC, np.zeros(3))


def _wire(msg: Any, src_system: int, src_component: int) -> Any:
    """``msg`` as the receiver gets it: packed by the sender's codec, parsed by ours (float32 on the wire)."""
    tx = mavlink.MAVLink(None, src_system, src_component)
    rx = mavlink.MAVLink(None)
    rx.robust_parsing = True
    (out,) = rx.parse_buffer(bytes(msg.pack(tx)))
    return out


# ---- strategies: any value the wire can carry -----------------------------------------------------------
f32 = st.floats(width=32)                       # NaN, +-inf, denormals (1e-40), +-3.4e38
huge_f32 = st.sampled_from([math.nan, math.inf, -math.inf, 3e38, -3e38, 1e-40, -1e-40, 0.0, -0.0, 1e30])
wire_float = st.one_of(f32, huge_f32)
u8 = st.integers(0, 255)
i16 = st.integers(-32768, 32767)
u16 = st.integers(0, 65535)
targets = st.sampled_from([0, SYSID, 2, 255])
components = st.sampled_from([0, AP_COMPID, COMPID, 190, 255])
commands = st.one_of(st.sampled_from([
    mavlink.MAV_CMD_COMPONENT_ARM_DISARM, mavlink.MAV_CMD_NAV_TAKEOFF, mavlink.MAV_CMD_NAV_LAND,
    mavlink.MAV_CMD_DO_SET_PARAMETER, mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
    mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH]), u16)
param_ids = st.one_of(st.sampled_from(PARAM_NAMES), st.text(alphabet=st.characters(min_codepoint=1, max_codepoint=127),
                                                            max_size=16))
param_values = st.one_of(wire_float, st.floats(-10.0, 10.0), st.sampled_from([0.0, 1.0, 0.1, 1.5, 3.0]))
senders = st.sampled_from([(255, 190), (245, 1), (SYSID, COMPID), (77, 1), (1, 1)])


def _gcs_message(draw: Any) -> Any:
    kind = draw(st.sampled_from(["MANUAL_CONTROL", "COMMAND_LONG", "PARAM_SET", "PARAM_REQUEST_READ",
                                 "PARAM_REQUEST_LIST", "SET_POSITION_TARGET_LOCAL_NED", "HEARTBEAT", "COMMAND_INT"]))
    if kind == "MANUAL_CONTROL":
        return mavlink.MAVLink_manual_control_message(draw(targets), draw(i16), draw(i16), draw(i16), draw(i16),
                                                      draw(u16))
    if kind == "COMMAND_LONG":
        cmd = draw(commands)
        if cmd == mavlink.MAV_CMD_DO_SET_PARAMETER and draw(st.booleans()):
            first = draw(st.sampled_from([float(i) for i in range(len(PARAM_NAMES) + 1)]))
            params = [first, draw(param_values)] + [draw(wire_float) for _ in range(5)]
        else:
            params = [draw(st.one_of(wire_float, st.sampled_from([0.0, 1.0, 21196.0]))) for _ in range(7)]
        return mavlink.MAVLink_command_long_message(draw(targets), draw(components), cmd, draw(u8), *params)
    if kind == "COMMAND_INT":
        return mavlink.MAVLink_command_int_message(draw(targets), draw(components), draw(u8), draw(commands), 0, 0,
                                                   *(draw(wire_float) for _ in range(4)),
                                                   draw(st.integers(-2**31, 2**31 - 1)),
                                                   draw(st.integers(-2**31, 2**31 - 1)), draw(wire_float))
    if kind == "PARAM_SET":
        return mavlink.MAVLink_param_set_message(draw(targets), draw(components), draw(param_ids).encode(),
                                                 draw(param_values),
                                                 draw(st.one_of(st.just(mavlink.MAV_PARAM_TYPE_REAL32), u8)))
    if kind == "PARAM_REQUEST_READ":
        return mavlink.MAVLink_param_request_read_message(draw(targets), draw(components), draw(param_ids).encode(),
                                                          draw(i16))
    if kind == "PARAM_REQUEST_LIST":
        return mavlink.MAVLink_param_request_list_message(draw(targets), draw(components))
    if kind == "SET_POSITION_TARGET_LOCAL_NED":
        return mavlink.MAVLink_set_position_target_local_ned_message(
            draw(st.integers(0, 2**32 - 1)), draw(targets), draw(components), draw(u8), draw(u16),
            *(draw(wire_float) for _ in range(11)))
    return mavlink.MAVLink_heartbeat_message(draw(u8), draw(u8), draw(u8), draw(st.integers(0, 2**32 - 1)), draw(u8),
                                             3)


def _autopilot_message(draw: Any, t_s: float) -> Any:
    kind = draw(st.sampled_from(["HIGHRES_IMU", "HEARTBEAT", "EXTENDED_SYS_STATE", "COMMAND_ACK", "TIMESYNC"]))
    if kind == "HIGHRES_IMU":
        stamp = draw(st.one_of(st.just(int(t_s * 1e6)), st.integers(0, 2**64 - 1)))
        return mavlink.MAVLink_highres_imu_message(stamp, *(draw(wire_float) for _ in range(13)), draw(u16))
    if kind == "HEARTBEAT":
        return mavlink.MAVLink_heartbeat_message(draw(u8), draw(u8), draw(u8), draw(st.integers(0, 2**32 - 1)),
                                                 draw(u8), 3)
    if kind == "EXTENDED_SYS_STATE":
        return mavlink.MAVLink_extended_sys_state_message(draw(u8), draw(u8))
    if kind == "COMMAND_ACK":
        return mavlink.MAVLink_command_ack_message(draw(commands), draw(u8), draw(u8), draw(i16 | st.integers(0, 0)),
                                                   draw(u8), draw(components))
    return mavlink.MAVLink_timesync_message(draw(st.integers(-2**63, 2**63 - 1)),
                                            draw(st.integers(-2**63, 2**63 - 1)))


@st.composite
def traffic(draw: Any) -> list[tuple[str, Any]]:
    """A burst per camera frame: messages from both sides, then the frame."""
    out: list[tuple[str, Any]] = []
    for k in range(draw(st.integers(1, 3))):
        for _ in range(draw(st.integers(0, 8))):
            if draw(st.booleans()):
                sysid, compid = draw(senders)
                out.append(("gcs", _wire(_gcs_message(draw), sysid, compid)))
            else:
                out.append(("autopilot", _wire(_autopilot_message(draw, 0.1 + k / 30), SYSID, AP_COMPID)))
        out.append(("frame", None))
    return out


def _flying_companion(scan_enabled: bool) -> tuple[Companion, MemLink, MemLink, MemCamera]:
    cfg = CompanionConfig(pan_scan=PanScanConfig(enabled=scan_enabled))
    ap, gcs, cam = MemLink(), MemLink(), MemCamera()
    pipeline = FakePipeline()
    daemon = Companion(cfg, ap, gcs, cam, lambda frame: pipeline, clock=StepClock(), wall=lambda: 1.79e9)
    # in the air, in TELEOP, with the operator's link alive: the handlers act on the setpoints
    ap.inbox.extend([
        _wire(mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4,
                                                mavlink.MAV_MODE_FLAG_SAFETY_ARMED, 0, mavlink.MAV_STATE_ACTIVE, 3),
              SYSID, AP_COMPID),
        _wire(mavlink.MAVLink_extended_sys_state_message(0, mavlink.MAV_LANDED_STATE_IN_AIR), SYSID, AP_COMPID)])
    daemon.modes.mode = Mode.TELEOP
    gcs.inbox.append(_wire(mavlink.MAVLink_manual_control_message(SYSID, 300, -200, 600, 100, 0), 255, 190))
    cam.frames.append(_frame(1, 0.05))
    daemon.step()
    return daemon, ap, gcs, cam


def _decoded(packets: list[bytes]) -> list[Any]:
    rx = mavlink.MAVLink(None)
    rx.robust_parsing = True
    out: list[Any] = []
    for p in packets:
        out.extend(rx.parse_buffer(p) or [])
    return out


@settings(deadline=None)
@given(traffic(), st.booleans())
def test_any_traffic_keeps_the_loop_and_the_autopilot_stream_sane(burst: list[tuple[str, Any]],
                                                                 scan_enabled: bool) -> None:
    daemon, ap, gcs, cam = _flying_companion(scan_enabled)
    seq, frames = 1, 0
    setpoints0 = daemon.stats.setpoints
    for side, msg in burst:
        if side == "gcs":
            gcs.inbox.append(msg)
        elif side == "autopilot":
            ap.inbox.append(msg)
        else:
            seq += 1
            frames += 1
            cam.frames.append(_frame(seq, 0.05 + seq / 30))
            daemon.step()
    daemon.step()

    assert daemon.stats.handler_errors == 0, daemon.errors.by_where
    assert daemon.errors.by_where == {}
    assert daemon.stats.non_finite_dropped == 0
    sent = _decoded(ap.sent)
    assert all(m.get_type() != "BAD_DATA" for m in sent)
    for m in sent:
        assert non_finite_fields(m, any_command=True) == [], (m.get_type(), non_finite_fields(m, any_command=True))
    sp = [m for m in sent if m.get_type() == "SET_POSITION_TARGET_LOCAL_NED"]
    assert all(math.isfinite(v) for m in sp for v in (m.vx, m.vy, m.vz, m.yaw_rate))
    assert daemon.stats.setpoints - setpoints0 >= frames   # one per frame at least (fallbacks may add)
    values = daemon.params.values()
    for spec in PARAM_SPECS:
        assert math.isfinite(values[spec.name]) and spec.min <= values[spec.name] <= spec.max
    # whatever the ground station received decodes too (no half-packed reply)
    assert all(m.get_type() != "BAD_DATA" for m in _decoded(gcs.sent))


@settings(deadline=None)
@given(st.sampled_from(PARAM_NAMES), param_values, st.sampled_from([SYSID, 0]), st.sampled_from([COMPID, 0]))
def test_param_set_is_applied_in_bounds_or_answered_with_the_unchanged_value(name: str, value: float, target: int,
                                                                          component: int) -> None:
    daemon, ap, gcs, cam = _flying_companion(True)
    before = daemon.params.values()
    gcs.sent.clear()
    gcs.inbox.append(_wire(mavlink.MAVLink_param_set_message(target, component, name.encode(), value,
                                                             mavlink.MAV_PARAM_TYPE_REAL32), 255, 190))
    daemon.step()
    replies = [m for m in _decoded(gcs.sent) if m.get_type() in ("PARAM_VALUE", "STATUSTEXT")]
    echoed = [m for m in replies if m.get_type() == "PARAM_VALUE" and m.param_id == name]
    after = daemon.params.values()
    spec = dict((s.name, s) for s in PARAM_SPECS)[name]
    wire_value = float(np.float32(value))
    if spec.refusal(wire_value) is None:
        assert after[name] == pytest.approx(wire_value) and echoed[-1].param_value == pytest.approx(wire_value)
    else:
        assert after == before
        assert echoed and (echoed[-1].param_value == pytest.approx(before[name]))
        assert any(m.get_type() == "STATUSTEXT" and f"{name} refused" in m.text for m in replies)
    assert {k: v for k, v in after.items() if k != name} == {k: v for k, v in before.items() if k != name}


def test_fuzz_rig_reaches_the_setpoint_path() -> None:
    """The rig is not vacuous: the operator's handle moves the setpoints it checks."""
    daemon, ap, gcs, cam = _flying_companion(False)
    ap.sent.clear()
    gcs.inbox.append(_wire(mavlink.MAVLink_manual_control_message(SYSID, 1000, 0, 500, 0, 0), 255, 190))
    cam.frames.append(_frame(2, 0.1))
    daemon.step()
    sp = [m for m in _decoded(ap.sent) if m.get_type() == "SET_POSITION_TARGET_LOCAL_NED"]
    assert sp and math.hypot(sp[-1].vx, sp[-1].vy) == pytest.approx(daemon.ref_params.k_v_m_s, abs=1e-4)


def test_imu_stamp_near_uint64_max_is_dropped_not_packed() -> None:
    """Found by the 5000-example soak: HIGHRES_IMU.time_usec = 2**64 - 1 became a TELEOP_FEEDBACK time_usec that
    no longer fit uint64 (a pack error, caught by the guard, one feedback lost); now the sample is refused."""
    daemon, ap, gcs, cam = _flying_companion(False)
    n_fb = daemon.stats.feedback
    ap.inbox.append(_wire(mavlink.MAVLink_highres_imu_message(2**64 - 1, 0, 0, -9.81, 0, 0, 0.1, 0, 0, 0, 0, 0, 0, 20,
                                                              0x3F), SYSID, AP_COMPID))
    daemon.step()
    assert daemon.errors.by_where == {} and daemon.stats.handler_errors == 0
    assert daemon.stats.feedback == n_fb or daemon.time.imu_stamp_s != (2**64 - 1) * 1e-6
