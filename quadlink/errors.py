"""Exception types shared by every part of the stack (STYLE.md rule 9: specific, never bare)."""


class QuadlinkError(Exception):
    """Base class: an error the command line reports as one line and a non-zero exit."""


class ConfigError(QuadlinkError):
    """A configuration file is missing, unreadable, or has an unknown/ill-typed key."""


class ProtocolError(QuadlinkError):
    """A wire-protocol violation (MK frame, MAVLink message, camera stream record)."""


class LinkError(QuadlinkError):
    """A link could not be opened or died (missing device, refused connection, bad URL)."""


class LinkTimeout(LinkError):
    """A read or a handshake on a link did not complete in time."""
