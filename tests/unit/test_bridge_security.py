"""The bridge's ground-station side under hostile senders (issue 16): the sender allowlist on every link and
MAVLink 2 signing on the ground-station links, through the daemon's own dispatch of received bytes (each
link's real pymavlink codec, as ``BridgeDaemon.open`` wires it) into the real Autopilot."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from click.testing import CliRunner
from memory_links import MemoryConn

from firmware_bridge.daemon import BridgeConfig, BridgeDaemon
from quadlink.cli import main
from quadlink.mavlink import mavlink
from quadlink.mavlink.security import SecurityConfig, enable_signing, write_key
from quadlink.vehicle import VehicleConfig

FORCE = 21196.0


def _daemon(tmp_path: Path, security: SecurityConfig | None = None) -> BridgeDaemon:
    config = BridgeConfig(mavlink_urls=("udpout:127.0.0.1:31500", "udpout:127.0.0.1:31501"),
                          params_file=str(tmp_path / "p.yaml"), security=security or SecurityConfig())
    daemon = BridgeDaemon(config, VehicleConfig())
    daemon.mavlinks = [MemoryConn(1, 1), MemoryConn(1, 1)]
    daemon.enable_signing()
    return daemon


def _packet(sysid: int, msg: Any, key: bytes | None = None) -> bytes:
    tx = mavlink.MAVLink(None, sysid, 190)
    if key is not None:
        enable_signing(tx, key, require=False)
    return bytes(msg.pack(tx))


def _received(daemon: BridgeDaemon, link: int) -> list[Any]:
    rx = mavlink.MAVLink(None)
    rx.robust_parsing = True
    return rx.parse_buffer(bytes(daemon.mavlinks[link].data)) or []


def _in_flight(daemon: BridgeDaemon) -> None:
    ap = daemon.autopilot
    ap.armed_cmd, ap.in_air = True, True


def _disarm(target: int = 1) -> Any:
    return mavlink.MAVLink_command_long_message(1, target, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 0.0, FORCE,
                                                0, 0, 0, 0, 0)


def test_forced_disarm_in_flight_from_sysid_77_is_refused(tmp_path: Path) -> None:
    daemon = _daemon(tmp_path)
    _in_flight(daemon)
    for _ in range(5):
        daemon._dispatch(("mav", 1, _packet(77, _disarm())))
    assert daemon.autopilot.armed_cmd and daemon.stats.refused_senders == 5
    replies = _received(daemon, 1)
    acks = [m for m in replies if m.get_type() == "COMMAND_ACK"]
    assert len(acks) == 5 and all(m.result == mavlink.MAV_RESULT_DENIED and m.target_system == 77 for m in acks)
    assert sum(m.get_type() == "STATUSTEXT" and "sysid 77 refused" in m.text for m in replies) == 1   # rate-limited
    # reading stays open to anyone; the operator's (sysid 255) forced disarm is executed
    daemon._dispatch(("mav", 1, _packet(77, mavlink.MAVLink_param_request_read_message(1, 1, b"", 0))))
    assert any(m.get_type() == "PARAM_VALUE" for m in _received(daemon, 1))
    daemon._dispatch(("mav", 1, _packet(255, _disarm())))
    assert not daemon.autopilot.armed_cmd


def test_signed_ground_station_link_refuses_unsigned_wrong_key_and_replay(tmp_path: Path) -> None:
    key = write_key(tmp_path / "k")
    daemon = _daemon(tmp_path, SecurityConfig(signing_key_file=str(tmp_path / "k"), require_signing=True))
    _in_flight(daemon)
    daemon._dispatch(("mav", 1, _packet(255, _disarm())))             # unsigned
    daemon._dispatch(("mav", 1, _packet(255, _disarm(), bytes(32))))  # the wrong key
    assert daemon.autopilot.armed_cmd
    signed = _packet(255, _disarm(), key)
    daemon._dispatch(("mav", 1, signed))
    assert not daemon.autopilot.armed_cmd                              # the operator's signed command
    _in_flight(daemon)
    daemon._dispatch(("mav", 1, signed))                               # the same packet replayed
    assert daemon.autopilot.armed_cmd
    # the bridge signs what it sends on that link; link 0 (the companion's, internal) stays unsigned
    assert daemon.mavlinks[1].mav.signing.sign_outgoing and not daemon.mavlinks[0].mav.signing.sign_outgoing
    daemon._dispatch(("mav", 0, _packet(1, _disarm())))                # the companion (own sysid), unsigned
    assert not daemon.autopilot.armed_cmd


def test_bridge_cli_signing_errors_are_one_line(tmp_path: Path) -> None:
    result = CliRunner().invoke(main, ["bridge", "--require-signing", "--duration", "0.1"])
    assert result.exit_code == 2 and "signing key" in result.output
    result = CliRunner().invoke(main, ["bridge", "--signing-key", str(tmp_path / "none.key"), "--duration", "0.1"])
    assert result.exit_code == 2 and "none.key" in result.output


@pytest.mark.parametrize("ids", [[0], [256]])
def test_allowlist_ids_are_checked(tmp_path: Path, ids: list[int]) -> None:
    from quadlink.errors import ConfigError

    with pytest.raises(ConfigError):
        _daemon(tmp_path, SecurityConfig(allowed_sender_sysids=tuple(ids)))
