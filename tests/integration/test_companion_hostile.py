"""The companion's ground-station endpoint under hostile input (issue 16), end to end on loopback: the daemon
with real UDP links, the real camera stream, a fake PX4-like autopilot (tests/test_companion_daemon.py's rig)
and ground stations that are signed, unsigned, signed with the wrong key, or not on the allowlist."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from test_companion_daemon import Rig

from companion.modes import Mode
from companion.params import PARAM_NAMES
from quadlink.mavlink import mavlink
from quadlink.mavlink.connection import open_mavlink
from quadlink.mavlink.security import SecurityConfig, enable_signing, write_key

pytestmark = pytest.mark.integration
ARM = mavlink.MAV_CMD_COMPONENT_ARM_DISARM
FORCE = 21196.0


class Client:
    """Another ground station on the companion's endpoint (own system id, optional signing key)."""

    def __init__(self, rig: Rig, sysid: int, key: bytes | None = None, link_id: int = 0) -> None:
        self.link = open_mavlink(f"udpout:127.0.0.1:{rig.daemon.gcs.port.getsockname()[1]}", sysid, 190)
        if key is not None:
            enable_signing(self.link.mav, key, require=False, link_id=link_id)
        self.received: list[Any] = []

    def poll(self) -> None:
        while (m := self.link.recv_msg()) is not None:
            if m.get_type() != "BAD_DATA":
                self.received.append(m)

    def of_type(self, kind: str) -> list[Any]:
        return [m for m in self.received if m.get_type() == kind]

    def close(self) -> None:
        self.link.close()


@pytest.fixture
def key(tmp_path: Path) -> tuple[Path, bytes]:
    path = tmp_path / "vehicle.key"
    return path, write_key(path)


@pytest.fixture
def signed_rig(tmp_path: Path, key: tuple[Path, bytes]) -> Any:
    r = Rig(tmp_path, security=SecurityConfig(signing_key_file=str(key[0]), require_signing=True))
    enable_signing(r.gcs.link.mav, key[1], require=False)   # the operator's station has the key
    yield r
    r.close()


def _setpoints(rig: Rig) -> list[Any]:
    return rig.ap.of_type("SET_POSITION_TARGET_LOCAL_NED")


def _arm_commands(rig: Rig) -> list[Any]:
    return [m for m in rig.ap.of_type("COMMAND_LONG") if m.command == ARM]


def test_signed_station_flies_while_unsigned_and_wrong_key_are_refused(signed_rig: Rig) -> None:
    rig = signed_rig
    unsigned = Client(rig, 255)                      # same system id as the operator: only the key tells them apart
    wrong = Client(rig, 255, key=bytes(32), link_id=1)
    try:
        # the intruders try first, on the ground: arm the autopilot and the companion, set a parameter
        for c in (unsigned, wrong):
            c.link.mav.command_long_send(1, 1, ARM, 0, 1, 0, 0, 0, 0, 0, 0)
            c.link.mav.command_long_send(1, 191, mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 0, 1.0)
            c.link.mav.param_set_send(1, 191, b"CMP_K_V", 2.5, mavlink.MAV_PARAM_TYPE_REAL32)
        for _ in range(5):
            rig.frame(manual=(0, 0, 500))
        assert not _arm_commands(rig) and rig.daemon.modes.mode == Mode.IDLE
        assert rig.daemon.ref_params.k_v_m_s == pytest.approx(0.6)
        assert rig.daemon.stats.gcs_bad_data >= 6   # refused by the signature check, counted

        # the signed operator takes off through the companion and drives forward
        rig.take_off()
        arms = _arm_commands(rig)
        assert arms and all(m.get_srcComponent() == 191 for m in arms)   # the companion's, not an intruder's
        k_v = rig.daemon.ref_params.k_v_m_s
        n0 = len(_setpoints(rig))
        for _ in range(6):
            rig.frame(manual=(1000, 0, 500))
        moving = _setpoints(rig)[n0 + 2:]
        assert moving and all(math.hypot(m.vx, m.vy) == pytest.approx(k_v, abs=1e-4) for m in moving)

        # the intruders' handles are ignored: with the operator centred, the vehicle holds still
        manual0 = rig.daemon.stats.manual_controls
        n0 = len(_setpoints(rig))
        for _ in range(6):
            for c in (unsigned, wrong):
                c.link.mav.manual_control_send(1, 1000, 1000, 1000, 0, 0)
                c.link.mav.command_long_send(1, 1, ARM, 0, 0, FORCE, 0, 0, 0, 0, 0)   # forced disarm
            rig.frame(manual=(0, 0, 500))
        held = _setpoints(rig)[n0 + 2:]
        assert held and all(abs(m.vx) < 1e-6 and abs(m.vy) < 1e-6 for m in held)
        assert rig.daemon.stats.manual_controls - manual0 == 6   # the operator's six, none of theirs
        assert not [m for m in _arm_commands(rig) if m.param1 == 0.0]
        assert rig.daemon.modes.mode == Mode.TELEOP

        # the operator's signed commands are executed, and the companion's replies to it are signed
        rig.gcs.link.mav.param_set_send(1, 191, b"CMP_K_V", 0.5, mavlink.MAV_PARAM_TYPE_REAL32)
        rig.frame(manual=(0, 0, 500))
        rig.frame(manual=(0, 0, 500))
        assert rig.daemon.ref_params.k_v_m_s == pytest.approx(0.5)
        assert rig.gcs.link.mav.signing.goodsig_count > 0
    finally:
        unsigned.close()
        wrong.close()


def test_replayed_signed_packet_is_refused(signed_rig: Rig) -> None:
    rig = signed_rig
    for _ in range(3):
        rig.frame(manual=(0, 0, 500))
    captured = bytes(mavlink.MAVLink_param_set_message(1, 191, b"CMP_K_V", 0.3, mavlink.MAV_PARAM_TYPE_REAL32)
                     .pack(rig.gcs.link.mav))   # what an eavesdropper records off the air
    rig.gcs.link.write(captured)
    rig.frame(manual=(0, 0, 500))
    assert rig.daemon.ref_params.k_v_m_s == pytest.approx(0.3)
    rig.gcs.link.mav.param_set_send(1, 191, b"CMP_K_V", 0.5, mavlink.MAV_PARAM_TYPE_REAL32)
    rig.frame(manual=(0, 0, 500))
    assert rig.daemon.ref_params.k_v_m_s == pytest.approx(0.5)
    bad0 = rig.daemon.stats.gcs_bad_data
    rig.gcs.link.write(captured)   # replayed: its timestamp is not newer than the stream's last
    rig.frame(manual=(0, 0, 500))
    rig.frame(manual=(0, 0, 500))
    assert rig.daemon.ref_params.k_v_m_s == pytest.approx(0.5)
    assert rig.daemon.stats.gcs_bad_data == bad0 + 1


@pytest.fixture
def rig(tmp_path: Path) -> Any:
    r = Rig(tmp_path)
    yield r
    r.close()


def test_forced_disarm_in_flight_from_sysid_77_is_refused(rig: Rig) -> None:
    """Issue 16: a forced disarm (21196) from sysid 77 was accepted. Now: not forwarded, DENIED, STATUSTEXT."""
    rig.take_off()
    intruder = Client(rig, 77)
    try:
        intruder.link.mav.command_long_send(1, 1, ARM, 0, 0, FORCE, 0, 0, 0, 0, 0)
        intruder.link.mav.command_long_send(1, 191, mavlink.MAV_CMD_NAV_LAND, 0, 0, 0, 0, 0, 0, 0, 0)
        intruder.link.mav.param_set_send(1, 191, b"PANSCAN_AMP", 1.0, mavlink.MAV_PARAM_TYPE_REAL32)
        intruder.link.mav.param_request_list_send(1, 191)   # reading stays open to anyone
        for _ in range(20):
            intruder.link.mav.manual_control_send(1, 1000, 0, 500, 0, 0)
        for _ in range(4):
            rig.frame(manual=(0, 0, 500))
        intruder.poll()
        assert not [m for m in _arm_commands(rig) if m.param1 == 0.0], "forced disarm reached the autopilot"
        assert rig.daemon.modes.mode == Mode.TELEOP and rig.ap.armed
        assert all(abs(m.vx) < 1e-6 and abs(m.vy) < 1e-6 for m in _setpoints(rig)[-3:])
        acks = {(m.command, m.get_srcComponent()): m.result for m in intruder.of_type("COMMAND_ACK")}
        assert acks[(ARM, 1)] == mavlink.MAV_RESULT_DENIED                  # answered as the autopilot it targeted
        assert acks[(mavlink.MAV_CMD_NAV_LAND, 191)] == mavlink.MAV_RESULT_DENIED
        texts = [m.text for m in intruder.of_type("STATUSTEXT")]
        assert any("sysid 77 refused" in t for t in texts)
        assert sum("MANUAL_CONTROL from sysid 77" in t for t in texts) == 1   # rate-limited, not 20
        assert rig.daemon.scan_params.amplitude_rad_s == pytest.approx(0.6)
        assert {m.param_id for m in intruder.of_type("PARAM_VALUE")} == set(PARAM_NAMES)
        assert rig.daemon.stats.refused_senders >= 23
    finally:
        intruder.close()


def _ack(rig: Rig, command: int) -> int:
    acks = [m for m in rig.gcs.of_type("COMMAND_ACK", src_comp=191) if m.command == command]
    assert acks, f"no COMMAND_ACK for {command}"
    return int(acks[-1].result)


def test_hostile_values_from_an_allowed_station_never_stop_the_loop(rig: Rig) -> None:
    """The issue's crashes, over the real port, in flight with pan-scan on: each one is refused with a reply and
    the setpoint and feedback streams go on."""
    rig.take_off()
    rig.gcs.link.mav.param_set_send(1, 191, b"PANSCAN_EN", 1.0, mavlink.MAV_PARAM_TYPE_REAL32)
    rig.frame(manual=(0, 0, 500))
    assert rig.daemon.scan_params.enabled
    omega0 = rig.daemon.scan_params.omega_rad_s
    send = rig.gcs.link.mav
    index = float(PARAM_NAMES.index("CMP_K_V"))
    for bad_index in (math.nan, math.inf, -math.inf, 1e30, -1.0):   # int(round(nan)) ended the loop
        send.command_long_send(1, 191, mavlink.MAV_CMD_DO_SET_PARAMETER, 0, bad_index, 0.5, 0, 0, 0, 0, 0)
        rig.frame(manual=(0, 0, 500))
        assert _ack(rig, mavlink.MAV_CMD_DO_SET_PARAMETER) == mavlink.MAV_RESULT_DENIED
    send.command_long_send(1, 191, mavlink.MAV_CMD_DO_SET_PARAMETER, 0, index, math.nan, 0, 0, 0, 0, 0)
    rig.frame(manual=(0, 0, 500))
    assert _ack(rig, mavlink.MAV_CMD_DO_SET_PARAMETER) == mavlink.MAV_RESULT_DENIED
    # MAVSDK's NaN in the unused params of a good DO_SET_PARAMETER is fine
    send.command_long_send(1, 191, mavlink.MAV_CMD_DO_SET_PARAMETER, 0, index, 0.5, *(math.nan,) * 5)
    rig.frame(manual=(0, 0, 500))
    assert _ack(rig, mavlink.MAV_CMD_DO_SET_PARAMETER) == mavlink.MAV_RESULT_ACCEPTED
    assert rig.daemon.ref_params.k_v_m_s == pytest.approx(0.5)
    # ARM_DISARM param1 NaN is "unused", not "disarm"
    send.command_long_send(1, 191, ARM, 0, math.nan, math.nan, 0, 0, 0, 0, 0)
    rig.frame(manual=(0, 0, 500))
    assert _ack(rig, ARM) == mavlink.MAV_RESULT_DENIED and rig.daemon.modes.mode == Mode.TELEOP
    # PANSCAN_OMEGA = 1e-40 overflowed float32 in TELEOP_FEEDBACK; PANSCAN_AMP 3e38 reached the setpoints
    for name, value in ((b"PANSCAN_OMEGA", 1e-40), (b"PANSCAN_AMP", 3e38), (b"CMP_SAFE_DIST", math.inf)):
        send.param_set_send(1, 191, name, value, mavlink.MAV_PARAM_TYPE_REAL32)
    send.param_set_send(1, 191, b"CMP_K_V", 7, mavlink.MAV_PARAM_TYPE_INT32)   # wrong param_type
    n_sp, n_fb = len(_setpoints(rig)), len(rig.gcs.of_type("TELEOP_FEEDBACK"))
    for _ in range(6):
        rig.frame(manual=(0, 0, 500))
    values = {m.param_id: m.param_value for m in rig.gcs.of_type("PARAM_VALUE", src_comp=191)[-4:]}
    assert values == {"PANSCAN_OMEGA": pytest.approx(omega0), "PANSCAN_AMP": pytest.approx(0.6),
                      "CMP_SAFE_DIST": pytest.approx(0.45), "CMP_K_V": pytest.approx(0.5)}
    texts = [m.text for m in rig.gcs.of_type("STATUSTEXT")]
    assert all(any(f"{n} refused" in t for t in texts) for n in ("PANSCAN_OMEGA", "PANSCAN_AMP", "CMP_K_V"))
    # the loop went on: setpoints and feedback still flow, finite; the vehicle still flies
    sp = _setpoints(rig)[n_sp:]
    fb = rig.gcs.of_type("TELEOP_FEEDBACK")[n_fb:]
    assert len(sp) >= 5 and len(fb) >= 5
    assert all(np.isfinite([m.vx, m.vy, m.vz, m.yaw_rate]).all() for m in sp)
    assert rig.thread.is_alive() and rig.daemon.modes.mode == Mode.TELEOP
    assert rig.daemon.stats.handler_errors == 0 and rig.daemon.stats.non_finite_dropped == 0


def test_an_unexpected_exception_in_one_message_is_counted_and_the_loop_goes_on(rig: Rig) -> None:
    """Whatever a handler raises (here a bug injected into the parameter service), the loop survives it."""
    for _ in range(3):
        rig.frame(manual=(0, 0, 500))

    def broken(name: str, value: float) -> str | None:
        raise OverflowError("injected")

    rig.daemon.params.refusal = broken   # type: ignore[method-assign]
    for _ in range(5):
        rig.gcs.link.mav.param_set_send(1, 191, b"CMP_K_V", 0.5, mavlink.MAV_PARAM_TYPE_REAL32)
    n0 = len(_setpoints(rig))
    for _ in range(4):
        rig.frame(manual=(0, 0, 500))
    assert rig.daemon.stats.handler_errors == 5
    assert rig.daemon.errors.by_where == {"ground station PARAM_SET": 5}
    assert len(_setpoints(rig)) - n0 >= 3 and rig.thread.is_alive()
