"""What leaves the companion: the replies its services return, and the one edge that packs and writes them.

The ground-station services (:mod:`companion.gcs_commands`, :mod:`companion.params`' :class:`ParamService`,
:mod:`companion.security`) are pure: they return what is to be sent, as these values, and the daemon hands
them to :class:`Outbox` in order (with the mode machine's :class:`~companion.modes.StatusText` and
:class:`~companion.modes.AutopilotRequest` actions):

* :class:`GcsReply` — a message for the ground stations, packed (and signed, when configured) as this
  system's companion, or as another of its components (the acks answered for the autopilot);
* :class:`AutopilotAck` — a reply made as the autopilot itself would make it, packed with its identity;
* :class:`ToAutopilot` — a message for the autopilot from the companion (its TIMESYNC answers, the acked
  commands: :mod:`companion.autopilot_input`).

With signing on the ground-station endpoint, everything the ground stations receive is signed with the
link's key, the autopilot's traffic the companion forwards included (re-packed with its sender's ids and
sequence number, as a signing router must: a station that requires signing drops unsigned packets).

:class:`Outbox` is the I/O: one bad value drops one message (counted, logged once in a while), a link
hiccup never stops the loop, nothing non-finite goes to the autopilot, and every packet goes to the tlog.
"""

from __future__ import annotations

import copy
import logging
import struct
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from companion.guard import ErrorCounter, non_finite_fields
from companion.interfaces import MavLink
from companion.modes import AutopilotRequest, StatusText
from companion.stats import Stats
from quadlink.mavlink import mavlink
from quadlink.mavlink.statustext import ChunkIds, statustext_messages

log = logging.getLogger("companion.daemon")


@dataclass(frozen=True)
class GcsReply:
    """``msg`` for the ground stations from ``src_component`` of this system (None: the companion itself)."""

    msg: Any
    src_component: int | None = None


@dataclass(frozen=True)
class AutopilotAck:
    """``msg`` for the ground stations as the autopilot would send it (its system and component id, unsigned)."""

    msg: Any


@dataclass(frozen=True)
class ToAutopilot:
    """``msg`` for the autopilot from the companion."""

    msg: Any


Output = StatusText | AutopilotRequest | GcsReply | AutopilotAck | ToAutopilot


class Outbox:
    """Packs and writes for the daemon. Owns the three codecs: the companion's (to the autopilot), the
    ground stations' (signed when :meth:`companion.security.GcsSecurity.enable_signing` set it up) and one
    that speaks as the autopilot (its forwarded heartbeats with the companion's mode, its mode acks)."""

    def __init__(self, autopilot: MavLink, gcs: MavLink, sysid: int, compid: int, ap_compid: int,
                 errors: ErrorCounter, stats: Stats, tlog: Any | None, wall: Callable[[], float]) -> None:
        self.autopilot, self.gcs = autopilot, gcs
        self.errors, self.stats, self.tlog, self.wall = errors, stats, tlog, wall
        self.codec = mavlink.MAVLink(None, sysid, compid)
        self.codec.robust_parsing = True
        self.gcs_codec = mavlink.MAVLink(None, sysid, compid)   # packs (and signs) for ground stations
        self._ap_codec = mavlink.MAVLink(None, sysid, ap_compid)   # replies made for the autopilot
        self.statustext_ids = ChunkIds()

    def set_system_id(self, sysid: int) -> None:
        """The vehicle's system id, learned from the autopilot's heartbeat."""
        self.codec.srcSystem = self.gcs_codec.srcSystem = sysid

    def log_packet(self, buf: bytes) -> None:
        if self.tlog is not None:
            self.tlog.write(buf, self.wall())

    @property
    def signing_gcs(self) -> bool:
        return bool(self.gcs_codec.signing.sign_outgoing)

    def _send(self, link: MavLink, msg: Any, codec: Any) -> None:
        try:
            buf = bytes(msg.pack(codec))
        except (struct.error, OverflowError, ValueError, TypeError) as exc:  # one bad value drops one message
            self.errors.record(f"packing {msg.get_type()}", exc)
            return
        codec.seq = (codec.seq + 1) % 256
        try:
            link.write(buf)
        except OSError as exc:  # a link hiccup must never stop the loop
            log.debug("send %s failed: %s", msg.get_type(), exc)
        self.log_packet(buf)

    def to_autopilot(self, msg: Any) -> None:
        bad = non_finite_fields(msg)
        if bad:   # never reaches the autopilot (the setpoint path holds before this: frame_step.setpoint_velocity)
            self.stats.non_finite_dropped += 1
            self.errors.record(f"non-finite {msg.get_type()}", ValueError(", ".join(bad)))
            return
        self._send(self.autopilot, msg, self.codec)

    def status_text(self, st: StatusText) -> None:
        """``st`` logged and sent to the ground stations as STATUSTEXT (a text over the field's 50 bytes in
        MAVLink 2 chunks)."""
        level = logging.WARNING if st.severity <= mavlink.MAV_SEVERITY_WARNING else logging.INFO
        log.log(level, "%s", st.text)
        for msg in statustext_messages(st.severity, st.text, self.statustext_ids.next()):
            self.to_gcs(msg)

    def to_gcs(self, msg: Any, src_component: int | None = None) -> None:
        """Pack (signed when configured) and send to the ground stations; ``src_component`` answers for another
        component of this system (the autopilot's acks)."""
        if src_component is None:
            self._send(self.gcs, msg, self.gcs_codec)
            return
        own, self.gcs_codec.srcComponent = self.gcs_codec.srcComponent, src_component
        try:
            self._send(self.gcs, msg, self.gcs_codec)
        finally:
            self.gcs_codec.srcComponent = own

    def _pack_as(self, msg: Any, src_system: int, src_component: int, seq: int | None) -> bytes:
        """``msg`` packed as another sender (the autopilot) with the ground stations' signing, when on."""
        codec = self.gcs_codec if self.signing_gcs else self._ap_codec
        own = codec.srcSystem, codec.srcComponent, codec.seq
        codec.srcSystem, codec.srcComponent = src_system, src_component
        codec.seq = own[2] if seq is None else seq    # a forwarded message keeps its sender's sequence number
        try:
            return bytes(msg.pack(codec))
        finally:
            codec.srcSystem, codec.srcComponent, codec.seq = own
            if seq is None and codec is self._ap_codec:   # the replies made for the autopilot count their own
                self._ap_codec.seq = (own[2] + 1) % 256

    def to_gcs_as(self, msg: Any, src_system: int, src_component: int) -> bool:
        """``msg`` to the ground stations packed as ``src_system``/``src_component`` (the autopilot) and not in
        the tlog (as the autopilot's forwarded traffic). Written?"""
        try:
            self.gcs.write(self._pack_as(msg, src_system, src_component, None))
            return True
        except (struct.error, OverflowError, ValueError, TypeError) as exc:
            self.errors.record(f"packing {msg.get_type()}", exc)
            return False
        except OSError as exc:
            log.debug("sending %s as %d/%d failed: %s", msg.get_type(), src_system, src_component, exc)
            return False

    def forward(self, link: MavLink, msg: Any) -> bool:
        """A received message on to ``link`` as it came: its own bytes, or to signed ground stations re-packed
        and signed with its sender's ids and sequence number. Written?"""
        buf = msg.get_msgbuf()
        if link is self.gcs and self.signing_gcs and not msg.get_type().startswith("UNKNOWN"):
            try:
                # a copy: packing rewrites a message's buffer, and the received one may be logged or routed on
                buf = self._pack_as(copy.copy(msg), msg.get_srcSystem(), msg.get_srcComponent(), msg.get_seq())
            except (struct.error, OverflowError, ValueError, TypeError, AttributeError) as exc:
                self.errors.record(f"re-signing {msg.get_type()}", exc)
        try:
            link.write(buf)
            return True
        except OSError as exc:
            log.debug("routing %s failed: %s", msg.get_type(), exc)
            return False
