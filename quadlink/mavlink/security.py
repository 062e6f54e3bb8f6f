"""Who may talk to the vehicle: MAVLink 2 signing on ground-station links and an allowlist of senders.

Signing (MAVLink 2 message signing, as ArduPilot implements it): a 32-byte secret shared by the vehicle and
its ground stations signs every packet with a 48-bit SHA-256 truncation over the packet and a 10 µs
timestamp. pymavlink checks it on receipt; its per-stream timestamps refuse a replayed packet (a timestamp
not newer than the last one from that link, system and component) and a new stream more than a minute older
than our own clock. With ``require`` set, an unsigned packet is refused too, except the few messages radios
inject without a key (RADIO_STATUS), as ArduPilot does.

The key file holds the secret as 64 hex digits on its first line (``quadlink keygen FILE`` writes one, mode
0600); anything after ``#`` is a comment.

The allowlist is independent of signing: a state-changing message (arming, modes, take-off and landing,
parameters, setpoints) is executed only when its sender's system id is listed. Reading (parameter lists,
message requests) stays open to everyone, so a monitoring tool can watch.
"""

from __future__ import annotations

import os
import secrets
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from quadlink.errors import ConfigError
from quadlink.mavlink import mavlink

KEY_BYTES = 32
#: 10 µs ticks between the Unix epoch and MAVLink signing's epoch (2015-01-01 00:00 UTC)
SIGNING_EPOCH_UNIX_S = 1420070400
#: messages a radio may inject unsigned on a signed link (ArduPilot accepts these too)
UNSIGNED_ALLOWED_MSG_IDS = frozenset({mavlink.MAVLINK_MSG_ID_RADIO_STATUS})

#: the ground stations' usual system ids (QGroundControl and MAVProxy 255, MAVSDK 245) and the vehicle's own
DEFAULT_ALLOWED_SYSIDS = (1, 245, 255)

#: COMMAND_LONG / COMMAND_INT commands that change the vehicle's state (everything else only reads)
STATE_CHANGING_COMMANDS = frozenset({
    mavlink.MAV_CMD_COMPONENT_ARM_DISARM,
    mavlink.MAV_CMD_DO_SET_MODE,
    mavlink.MAV_CMD_NAV_TAKEOFF,
    mavlink.MAV_CMD_NAV_LAND,
    mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH,
    mavlink.MAV_CMD_NAV_LOITER_UNLIM,
    mavlink.MAV_CMD_DO_SET_PARAMETER,
    mavlink.MAV_CMD_DO_REPOSITION,
    mavlink.MAV_CMD_DO_CHANGE_SPEED,
    mavlink.MAV_CMD_DO_FLIGHTTERMINATION,
    mavlink.MAV_CMD_DO_MOTOR_TEST,
    mavlink.MAV_CMD_PREFLIGHT_CALIBRATION,
    mavlink.MAV_CMD_PREFLIGHT_STORAGE,
    mavlink.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN,
    mavlink.MAV_CMD_MISSION_START,
})
#: messages that change the vehicle's state by themselves
STATE_CHANGING_MESSAGES = frozenset({
    "SET_MODE", "PARAM_SET", "MANUAL_CONTROL", "SET_POSITION_TARGET_LOCAL_NED", "SET_POSITION_TARGET_GLOBAL_INT",
    "SET_ATTITUDE_TARGET", "MISSION_COUNT", "MISSION_ITEM", "MISSION_ITEM_INT", "MISSION_CLEAR_ALL",
    "MISSION_SET_CURRENT", "RC_CHANNELS_OVERRIDE", "PARAM_EXT_SET", "FILE_TRANSFER_PROTOCOL",
})


def is_state_changing(msg: Any) -> bool:
    """Whether executing ``msg`` would change the vehicle's state (arming, modes, motion, parameters)."""
    kind = msg.get_type()
    if kind in ("COMMAND_LONG", "COMMAND_INT"):
        return int(msg.command) in STATE_CHANGING_COMMANDS
    return kind in STATE_CHANGING_MESSAGES


@dataclass(frozen=True)
class SenderAllowlist:
    """System ids allowed to change the vehicle's state; ``None`` allows everyone (the allowlist is off)."""

    sysids: frozenset[int] | None = frozenset(DEFAULT_ALLOWED_SYSIDS)

    @classmethod
    def of(cls, sysids: Iterable[int] | None) -> SenderAllowlist:
        if sysids is None:
            return cls(None)
        ids = frozenset(int(s) for s in sysids)
        bad = sorted(s for s in ids if not 1 <= s <= 255)
        if bad:
            raise ConfigError(f"allowed sender system ids must be 1..255, got {bad}")
        return cls(ids)

    def including(self, sysid: int) -> SenderAllowlist:
        """This list plus ``sysid`` (the vehicle's own system id, learned from the autopilot's heartbeat)."""
        return self if self.sysids is None else SenderAllowlist(self.sysids | {int(sysid)})

    def permits(self, msg: Any) -> bool:
        """True if ``msg`` may be executed: it only reads, or its sender is listed."""
        if self.sysids is None or not is_state_changing(msg):
            return True
        return int(msg.get_srcSystem()) in self.sysids


@dataclass(frozen=True)
class SecurityConfig:
    """Who may talk to a ground-station-facing endpoint (the ``security:`` key of the companion's and the
    bridge's configs). ``signing_key_file``: sign that endpoint's traffic with this key and check what it
    receives (None: no signing); ``require_signing``: refuse unsigned packets (else accepted, so ground
    stations can move to signing one by one); ``allowed_sender_sysids``: who may change the vehicle's state
    besides the vehicle's own system id (null: everyone)."""

    signing_key_file: str | None = None
    require_signing: bool = False
    allowed_sender_sysids: tuple[int, ...] | None = (245, 255)

    def allowlist(self, own_sysid: int) -> SenderAllowlist:
        allow = SenderAllowlist.of(self.allowed_sender_sysids)
        return allow.including(own_sysid)

    def key(self) -> bytes | None:
        """The signing key (read now), or None; ConfigError if signing is required without a key."""
        if self.signing_key_file is None:
            if self.require_signing:
                raise ConfigError("require_signing needs a signing key file (quadlink keygen FILE)")
            return None
        return read_key(self.signing_key_file)


def read_key(path: str | Path) -> bytes:
    """The 32-byte secret in a key file (64 hex digits on the first non-comment line)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="ascii")
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read signing key: {exc}") from exc
    for line in text.splitlines():
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        try:
            key = bytes.fromhex(line)
        except ValueError as exc:
            raise ConfigError(f"{path}: signing key is not hex digits") from exc
        if len(key) != KEY_BYTES:
            raise ConfigError(f"{path}: signing key must be {KEY_BYTES} bytes (64 hex digits), got {len(key)}")
        return key
    raise ConfigError(f"{path}: no signing key in file")


def write_key(path: str | Path, key: bytes | None = None, overwrite: bool = False) -> bytes:
    """Create a key file (mode 0600) holding ``key`` or a fresh random one; returns the key."""
    path = Path(path)
    key = secrets.token_bytes(KEY_BYTES) if key is None else key
    if len(key) != KEY_BYTES:
        raise ValueError(f"a signing key is {KEY_BYTES} bytes")
    if path.exists() and not overwrite:
        raise ConfigError(f"{path}: exists (refusing to overwrite a signing key)")
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w", encoding="ascii") as f:
        f.write(f"{key.hex()}  # quadlink MAVLink 2 signing key: copy to the vehicle and every ground station\n")
    return key


def signing_timestamp(unix_time_s: float) -> int:
    """MAVLink signing's timestamp (10 µs ticks since 2015-01-01) for a Unix time."""
    return int(max(unix_time_s - SIGNING_EPOCH_UNIX_S, 0.0) * 100_000)


@dataclass
class SigningStats:
    """What the signing check let through and refused on one link (pymavlink's counters)."""

    good: int = 0
    bad: int = 0
    unsigned_accepted: int = 0
    refused: int = 0
    refused_by_id: dict[int, int] = field(default_factory=dict)


def enable_signing(mav: Any, key: bytes, require: bool, link_id: int = 0,
                   unix_time_s: float | None = None) -> None:
    """Sign everything ``mav`` (a pymavlink ``MAVLink`` codec) sends; check what it receives.

    ``require``: refuse unsigned packets (but :data:`UNSIGNED_ALLOWED_MSG_IDS`); otherwise accept them, so a
    vehicle can move its ground stations to signing one by one."""
    if len(key) != KEY_BYTES:
        raise ValueError(f"a signing key is {KEY_BYTES} bytes")

    def allow_unsigned(_mav: Any, msg_id: int) -> bool:
        return (not require) or msg_id in UNSIGNED_ALLOWED_MSG_IDS

    mav.signing.secret_key = key
    mav.signing.sign_outgoing = True
    mav.signing.link_id = int(link_id) & 0xFF
    mav.signing.timestamp = signing_timestamp(time.time() if unix_time_s is None else unix_time_s)
    mav.signing.allow_unsigned_callback = allow_unsigned


def signing_stats(mav: Any) -> SigningStats:
    s = mav.signing
    return SigningStats(good=s.goodsig_count, bad=s.badsig_count, unsigned_accepted=s.unsigned_count,
                        refused=s.reject_count)
