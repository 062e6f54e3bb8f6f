"""Open MAVLink endpoints by pymavlink URL (``udpin:``, ``udpout:``, ``tcp:``, ``tcpin:``, serial).

This is the one place that touches pymavlink's ``mavutil`` (a module with global dialect state):
it registers the quadlink dialect where mavutil looks for dialects and returns an ordinary
``mavfile`` speaking MAVLink 2, so MAVProxy users' URLs work unchanged.
"""

from __future__ import annotations

import logging
import sys
from typing import Any

from quadlink.errors import LinkError
from quadlink.mavlink import DIALECT_NAME, mavlink

log = logging.getLogger(__name__)

_URL_PREFIXES = ("udpin:", "udpout:", "udp:", "udpbcast:", "tcp:", "tcpin:", "/dev/", "COM")


def _install_dialect() -> Any:
    import pymavlink.dialects.v20 as v20
    from pymavlink import mavutil

    sys.modules[f"pymavlink.dialects.v20.{DIALECT_NAME}"] = mavlink
    setattr(v20, DIALECT_NAME, mavlink)
    if mavutil.current_dialect != DIALECT_NAME:
        mavutil.set_dialect(DIALECT_NAME)
    return mavutil


def open_mavlink(url: str, source_system: int = 255, source_component: int = 0, **kwargs: Any) -> Any:
    """Open a MAVLink 2 endpoint with the quadlink dialect; raise :class:`LinkError` with the reason.

    ``url`` uses pymavlink's syntax, e.g. ``udpin:0.0.0.0:14540``, ``udpout:127.0.0.1:14550``,
    ``tcp:127.0.0.1:5760``, ``/dev/ttyUSB0`` (with ``baud=`` in kwargs) or ``/dev/ttyUSB0:57600``.
    """
    if not url.startswith(_URL_PREFIXES):
        raise LinkError(f"{url}: not a MAVLink URL (use udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT, "
                        "tcpin:HOST:PORT or a serial device)")
    mavutil = _install_dialect()
    device, baud = url, kwargs.pop("baud", 115200)
    if url.startswith(("/dev/", "COM")) and url.count(":") == 1:
        device, _, baud_text = url.partition(":")
        baud = int(baud_text)
    try:
        conn = mavutil.mavlink_connection(device, baud=baud, source_system=source_system,
                                          source_component=source_component, dialect=DIALECT_NAME,
                                          robust_parsing=True, **kwargs)
    except (OSError, ValueError) as exc:  # serial.SerialException is an OSError
        raise LinkError(f"{url}: cannot open MAVLink endpoint: {exc}") from exc
    conn.mav.robust_parsing = True
    log.info("MAVLink endpoint %s open (sysid %d compid %d)", url, source_system, source_component)
    return conn


def open_replay_mavlink(source_system: int = 255, source_component: int = 0) -> Any:
    """A MAVLink 2 endpoint with no socket, for a journal's replay: its reads hand over the datagrams queued in
    ``incoming`` (a deque), in order, then nothing; what is sent is kept in ``written``. Otherwise an ordinary
    ``mavfile`` of the quadlink dialect (the same parser and encoder as :func:`open_mavlink`'s)."""
    import collections

    mavutil = _install_dialect()

    class ReplayMavfile(mavutil.mavfile):  # type: ignore[misc, name-defined]
        def __init__(self) -> None:
            super().__init__(None, "replay", source_system=source_system, source_component=source_component,
                             input=False)
            self.incoming: collections.deque[bytes] = collections.deque()
            self.written: list[bytes] = []

        def recv(self, n: int | None = None) -> bytes:
            return self.incoming.popleft() if self.incoming else b""

        def write(self, buf: bytes) -> None:
            self.written.append(bytes(buf))

        def close(self) -> None:
            pass

    conn = ReplayMavfile()
    conn.mav.robust_parsing = True
    return conn
