"""Every port a flight listens on, and free ones for flights that share a machine (issue 28).

A demo flight's ports are the defaults (:data:`DEFAULT_PORTS`) shifted by an *offset*, or a contiguous block from
a *base*; a campaign's slot ``k`` flies at ``offset + PORT_SLOT_STRIDE * k``. :func:`free_port_offset` finds an
offset whose every port (of every slot asked for) nobody listens on, TCP or UDP, and reserves it for the rest of the
process: the SITL tests ask it for theirs instead of picking numbers by hand, so two flights never meet on a port.
"""

from __future__ import annotations

import random
import socket
import threading
from collections.abc import Callable
from dataclasses import dataclass

PORT_NAMES = ("mk1", "mk2", "camera", "image", "autopilot", "gcs_bridge", "vehicle", "truth", "http",
              "vehicle_netem", "image_netem", "lockstep")
#: ``vehicle_netem`` / ``image_netem``: the impaired ground link's ends (harness.demo.link)
DEFAULT_PORTS = {"mk1": 5760, "mk2": 5761, "camera": 5762, "image": 5770, "autopilot": 14540, "gcs_bridge": 14551,
                 "vehicle": 14555, "truth": 14560, "http": 8080, "vehicle_netem": 14557, "image_netem": 5771,
                 "lockstep": 5763}
PORT_BLOCK_SIZE = len(PORT_NAMES)  # ports per flight with ``base``
PORT_SLOT_STRIDE = 25   # offsets between a campaign's slots: every group of default ports spans < 25 ports
# the highest default port shifted stays below Linux's ephemeral range (32768-60999), where the kernel picks the
# ports of outgoing connections and unbound UDP senders
MAX_OFFSET = 32768 - 1 - max(DEFAULT_PORTS.values())


@dataclass(frozen=True)
class Ports:
    """Every port of a demo flight: the defaults shifted by ``offset``, or, with ``base``, the contiguous block
    ``base .. base + PORT_BLOCK_SIZE - 1`` (in :data:`PORT_NAMES` order), so several stacks can share a machine."""

    offset: int = 0
    base: int | None = None

    def __getattr__(self, name: str) -> int:
        if name not in DEFAULT_PORTS:
            raise AttributeError(name)
        if self.base is not None:
            return self.base + PORT_NAMES.index(name)
        return DEFAULT_PORTS[name] + self.offset

    def as_dict(self) -> dict[str, int]:
        return {name: getattr(self, name) for name in PORT_NAMES}


_reserved: set[int] = set()
_lock = threading.Lock()


def port_is_free(port: int) -> bool:
    """Nobody listens on ``port``, TCP or UDP, on any address (a bind without SO_REUSEADDR succeeds)."""
    for kind in (socket.SOCK_STREAM, socket.SOCK_DGRAM):
        with socket.socket(socket.AF_INET, kind) as s:
            try:
                s.bind(("0.0.0.0", port))
            except OSError:
                return False
    return True


def free_port(kind: int = socket.SOCK_STREAM) -> int:
    """A port the kernel picks as free now (TCP or UDP ``kind``), for one listener outside the demo's table."""
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def offset_ports(offset: int, slots: int = 1) -> list[int]:
    """Every port of ``slots`` flights on the demo's ports shifted by ``offset`` (a campaign's slot stride)."""
    return [p + offset + PORT_SLOT_STRIDE * k for k in range(slots) for p in DEFAULT_PORTS.values()]


def free_port_offset(slots: int = 1, rng: random.Random | None = None, attempts: int = 400) -> int:
    """An offset at which ``slots`` flights (slot ``k`` at ``offset + PORT_SLOT_STRIDE k``) find every port free and
    not reserved by an earlier call in this process; it is reserved from now on. Candidates are multiples of the
    slot stride from 1000 up, drawn at random (``rng``) so that separate processes seldom try the same; a port taken
    between this check and the flight's start is the flight's error (it names the port), never a silent clash."""
    if slots < 1:
        raise ValueError(f"slots must be >= 1, got {slots}")
    rng = rng or random.Random()
    top = (MAX_OFFSET - PORT_SLOT_STRIDE * (slots - 1)) // PORT_SLOT_STRIDE
    offset = _reserve_first(lambda: PORT_SLOT_STRIDE * rng.randrange(40, top),
                            lambda offset: offset_ports(offset, slots), attempts)
    if offset is None:
        raise RuntimeError(f"no port offset with {slots} free slot(s) found in {attempts} tries")
    return offset


def free_port_base(count: int, rng: random.Random | None = None, attempts: int = 400) -> int:
    """A base for ``count`` contiguous ports (``Ports(base=...)`` blocks of :data:`PORT_BLOCK_SIZE`), every one
    free and not reserved by an earlier call in this process; reserved from now on. Drawn from 20000-32767 (above
    the offset lanes' ports, below the ephemeral range)."""
    if count < 1:
        raise ValueError(f"count must be >= 1, got {count}")
    rng = rng or random.Random()
    base = _reserve_first(lambda: rng.randrange(20000, 32768 - count), lambda base: list(range(base, base + count)),
                          attempts)
    if base is None:
        raise RuntimeError(f"no {count} contiguous free ports found in {attempts} tries")
    return base


def _reserve_first(draw: Callable[[], int], ports_of: Callable[[int], list[int]], attempts: int) -> int | None:
    """The first drawn candidate whose ports are all free and unreserved, its ports reserved; None after
    ``attempts``."""
    for _ in range(attempts):
        candidate = draw()
        ports = ports_of(candidate)
        with _lock:
            if _reserved.intersection(ports) or not all(port_is_free(p) for p in ports):
                continue
            _reserved.update(ports)
        return candidate
    return None
