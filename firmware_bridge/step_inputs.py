"""The bridge's inputs in the deterministic lock-step (:mod:`quadlink.lockstep`), cut at each step's counts.

Pure (no I/O, no clock): the daemon's main thread feeds it the reader threads' queue items as they come
(:meth:`StepInputs.add`) and, once a STEP's announced counts have all arrived, takes the step's share
(:meth:`StepInputs.take`) in a fixed order, so what the bridge handles in step ``k`` depends only on what its
senders had sent when the coordinator announced step ``k``, never on when the bytes reached this process:

* ``companion>bridge``: datagrams on MAVLink endpoint 0 (one reader item per datagram). Exactly the
  announced number is handled; any that came early are held back for the step that announces them.
* ``sitl>bridge.cmd`` / ``sitl>bridge.imu``: bytes of MK port 1 / port 2. The SITL writes nothing more
  until every participant has answered, so the received bytes never exceed the count; a surplus means the
  counts and the bytes disagree, and is an error rather than a guess.
* the other MAVLink endpoints (ground stations) are not in the lock-step: what has arrived is handled.
"""

from __future__ import annotations

import collections
from typing import Any

from quadlink.lockstep import LockstepError, Step

# the bridge's links (quadlink.lockstep.LINKS)
LINK_COMPANION_IN = "companion>bridge"
LINK_MK_CMD_IN = "sitl>bridge.cmd"
LINK_MK_IMU_IN = "sitl>bridge.imu"
LINK_MK_OUT = "bridge>sitl"
LINK_COMPANION_OUT = "bridge>companion"
LOCKSTEP_NAME = "bridge"
COMPANION_ENDPOINT = 0  # the MAVLink endpoint that faces the companion (the lock-step's datagram link)

_MK_LINKS = {"cmd": LINK_MK_CMD_IN, "imu": LINK_MK_IMU_IN}


class StepInputs:
    """What the reader threads delivered, sorted by link, with the cumulative counts the STEPs refer to."""

    def __init__(self) -> None:
        self.datagrams: collections.deque[bytes] = collections.deque()  # endpoint 0: received, not handled
        self.datagrams_received = 0  # endpoint-0 datagrams received so far (handled + held back)
        self.datagrams_handled = 0
        self.others: list[tuple[Any, ...]] = []  # the other endpoints' items, in arrival order
        self.mk_pending = {"cmd": bytearray(), "imu": bytearray()}  # MK bytes received, not handled
        self.mk_received = {"cmd": 0, "imu": 0}  # MK bytes received so far per port
        self._mk_first_read_wall: dict[str, float | None] = {"cmd": None, "imu": None}

    def received(self, link: str) -> int:
        """Units received so far on one of the bridge's input links."""
        if link == LINK_COMPANION_IN:
            return self.datagrams_received
        for kind, name in _MK_LINKS.items():
            if link == name:
                return self.mk_received[kind]
        raise KeyError(link)

    def add(self, item: tuple[Any, ...]) -> bool:
        """Sort one reader item (:class:`firmware_bridge.links.LinkReaders`); False for an error report
        (``"link"``, ``"mavbad"``), which is not a step input: the caller handles it where it comes."""
        kind = item[0]
        if kind == "mav":
            if item[1] == COMPANION_ENDPOINT:
                self.datagrams.append(item[2])
                self.datagrams_received += 1
            else:
                self.others.append(item)
            return True
        if kind in self.mk_pending:
            data, read_wall = item[1], item[2]
            if not self.mk_pending[kind]:
                self._mk_first_read_wall[kind] = read_wall
            self.mk_pending[kind] += data
            self.mk_received[kind] += len(data)
            return True
        return False

    def take(self, step: Step) -> list[tuple[Any, ...]]:
        """The step's share as reader items, in the canonical order: the endpoint-0 datagrams (in arrival
        order), the other endpoints' items, all MK port-1 bytes, all MK port-2 bytes.

        The caller has waited for the announced counts; a link without a count (its sender is not in the
        lock-step) gives what has arrived. :class:`LockstepError` if a count is not reached or MK bytes
        exceed it.
        """
        out: list[tuple[Any, ...]] = []
        expected = step.count(LINK_COMPANION_IN)
        n = len(self.datagrams) if expected is None else expected - self.datagrams_handled
        if not 0 <= n <= len(self.datagrams):  # not all there yet, or a count that went back
            raise LockstepError(f"lock-step step {step.index}: {LINK_COMPANION_IN}: {expected} datagrams "
                                f"announced, {self.datagrams_received} received, {self.datagrams_handled} handled")
        for _ in range(n):
            out.append(("mav", COMPANION_ENDPOINT, self.datagrams.popleft()))
        self.datagrams_handled += n
        out.extend(self.others)
        self.others = []
        for kind, link in _MK_LINKS.items():
            expected = step.count(link)
            received = self.mk_received[kind]
            if expected is not None and received != expected:
                raise LockstepError(f"lock-step step {step.index}: {link}: {received} bytes received, "
                                    f"{expected} announced")
            pending = self.mk_pending[kind]
            if pending:
                out.append((kind, bytes(pending), self._mk_first_read_wall[kind]))
                pending.clear()
                self._mk_first_read_wall[kind] = None
        return out
