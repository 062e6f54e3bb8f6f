"""The ground-station endpoint's gate (issue 16): signing, the sender allowlist and what a refusal gets.

The ground-station endpoint is hostile; the autopilot link is internal (the bridge on the same board, or PX4
over its serial port) and has none of this.

* Signing (``security`` in the config): :meth:`GcsSecurity.enable_signing` sets MAVLink 2 signing up on the
  codec that packs what the companion sends and on the link's own codec, where pymavlink checks signatures
  and refuses replays (unsigned, wrong-key and replayed packets reach the daemon as BAD_DATA).
* The allowlist: state-changing messages only from the listed system ids and the vehicle's own, which the
  daemon learns from the autopilot's heartbeat (:meth:`GcsSecurity.on_system_id`).
* Refusals (pure: the replies are returned, the clock is injected): a refused command is answered
  COMMAND_ACK DENIED, and the sender told by a STATUSTEXT at most once per sender and kind every 2 s (a
  script streams at 20 Hz).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

from companion.guard import RateLimit
from companion.modes import StatusText
from companion.outbound import GcsReply
from quadlink.errors import QuadlinkError
from quadlink.mavlink import mavlink
from quadlink.mavlink.security import SecurityConfig, SenderAllowlist, enable_signing

log = logging.getLogger("companion.daemon")

COMMAND_KINDS = ("COMMAND_LONG", "COMMAND_INT")


def _denied(msg: Any, src_component: int | None) -> GcsReply:
    """COMMAND_ACK DENIED for the command ``msg``, to its sender, as ``src_component`` (None: the companion)."""
    ack = mavlink.MAVLink_command_ack_message(msg.command, mavlink.MAV_RESULT_DENIED, 0, 0, msg.get_srcSystem(),
                                              msg.get_srcComponent())
    return GcsReply(ack, src_component)


class GcsSecurity:
    """Who may talk to the companion's ground-station endpoint. ``sysid``/``compid``: the companion's ids
    (the system id changes with :meth:`on_system_id`); ``clock``: monotonic seconds, paces the refusal
    STATUSTEXTs. Reading the key (``SecurityConfig.key``) happens here: ConfigError for a bad key file or a
    required signing without a key."""

    def __init__(self, cfg: SecurityConfig, sysid: int, compid: int, clock: Callable[[], float]) -> None:
        self._cfg = cfg
        self._compid = compid
        self.allowlist: SenderAllowlist = cfg.allowlist(sysid)
        self._key = cfg.key()
        self._refusal_limit = RateLimit(clock)

    @property
    def signing(self) -> bool:
        return self._key is not None

    def enable_signing(self, tx_codec: Any, rx_codec: Any | None, wall: Callable[[], float]) -> None:
        """Sign what ``tx_codec`` packs and check what ``rx_codec`` (the link's, ``mavfile.mav``) parses, when
        a key is configured; ``wall``: Unix time, the signing timestamps' epoch."""
        if self._key is None:
            return
        if rx_codec is None or not hasattr(rx_codec, "signing"):
            raise QuadlinkError("signing configured but the ground-station link has no MAVLink codec to check it")
        require = self._cfg.require_signing
        enable_signing(tx_codec, self._key, require, link_id=0, unix_time_s=wall())
        enable_signing(rx_codec, self._key, require, link_id=0, unix_time_s=wall())
        log.info("ground-station endpoint: MAVLink 2 signing %s", "required" if require else "optional")

    def on_system_id(self, sysid: int) -> None:
        """The vehicle's system id changed: it is the one always allowed."""
        self.allowlist = self._cfg.allowlist(sysid)

    def permits(self, msg: Any) -> bool:
        return self.allowlist.permits(msg)

    def refuse_sender(self, msg: Any) -> list[GcsReply | StatusText]:
        """A state-changing message from a system id not on the allowlist: nothing executed or forwarded; a
        command is answered DENIED as the component it targeted."""
        kind, src = msg.get_type(), msg.get_srcSystem()
        out: list[GcsReply | StatusText] = []
        if kind in COMMAND_KINDS:
            target = msg.target_component
            out.append(_denied(msg, None if target in (0, self._compid) else target))
        if self._refusal_limit.allow((src, kind)):
            out.append(StatusText(mavlink.MAV_SEVERITY_WARNING,
                                  f"companion: {kind} from sysid {src} refused (not allowed)"))
        return out

    def refuse_forward(self, msg: Any, ap_compid: int) -> list[GcsReply | StatusText]:
        """A ground-station message for the autopilot (component ``ap_compid``) with a non-finite value: not
        forwarded; a command is answered DENIED as the component it targeted."""
        kind, src = msg.get_type(), msg.get_srcSystem()
        out: list[GcsReply | StatusText] = []
        if kind in COMMAND_KINDS:
            out.append(_denied(msg, msg.target_component or ap_compid))
        if self._refusal_limit.allow((src, kind, "non-finite")):
            out.append(StatusText(mavlink.MAV_SEVERITY_WARNING, f"companion: {kind} not forwarded: non-finite value"))
        return out
