"""The quadlink MAVLink dialect (common.xml + TELEOP_FEEDBACK) and how every part opens links with it.

``from quadlink.mavlink import mavlink`` is the generated dialect module: message classes, enums and
the I/O-free ``mavlink.MAVLink(file, srcSystem, srcComponent)`` codec (``parse_buffer``/``pack``).
The whole stack speaks MAVLink 2 only; importing this package selects it for pymavlink.
"""

import os

os.environ.setdefault("MAVLINK20", "1")  # before pymavlink.mavutil is imported anywhere

from quadlink.mavlink.generated import quadlink as mavlink  # noqa: E402

DIALECT_NAME = "quadlink"

__all__ = ["mavlink", "DIALECT_NAME"]
