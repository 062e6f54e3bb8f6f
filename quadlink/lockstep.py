"""Deterministic lock-step across processes (issue 15): the SITL steps, every part answers each step.

The plain lock-step (``quadlink sitl --lockstep``) gates the simulation on the bridge's setpoints and the
companion's camera acks, but every part still reads its links as bytes arrive and keeps its timers on the
wall clock: two flights of the same draws diverge as soon as the ground station's first request reaches the
vehicle a chunk earlier or later. The *deterministic* lock-step makes every part a function of the simulated
time and of what it received, in an order that does not depend on the machine:

* the SITL is the coordinator. It serves a TCP port and does not advance until every named participant
  (``bridge``, ``companion``, ``operator``) has registered. Then, per 10 ms chunk ``k``, it applies the
  bridge's bytes of step ``k - 1``, simulates the chunk, writes its serial bytes and camera frames, and sends
  every participant ``STEP k`` with the simulated time at the chunk's end and, for each of the participant's
  input links, how many units (bytes, datagrams, frames) its senders have sent on it so far. It waits for
  every participant's ``DONE k`` before the next chunk.
* a participant, on ``STEP k``: sets its clock to the step's time, reads each input link up to exactly the
  announced count (waiting for units still in flight, holding back any that arrived early), handles them in
  a fixed order of links, runs its timers, sends, and answers ``DONE k`` with how many units it has sent on
  each output link so far. It sends nothing outside a step.

So every message sent during step ``k`` is handled during step ``k + 1``, whatever the load: a synchronous
data flow with one chunk of latency on every link. Counting units, not waiting for quiet sockets, is what
makes it exact (a datagram still in the kernel is waited for, one that came early waits for its step).

A link is named ``"SENDER>RECEIVER"`` or ``"SENDER>RECEIVER.PORT"``: :data:`LINKS` lists the stack's. A
participant is sent the counts of the links whose receiver is its name; a link without a registered sender
has no count and is not waited for (a third-party client on it is served, but not deterministically).

Wire format: one JSON object per line. Participant to coordinator: ``{"hello": NAME, "sent": {...}}`` once,
then ``{"done": K, "sent": {...}}`` per step (with ``"last": true`` on the DONE of its last step);
coordinator to participant: ``{"step": K, "t_s": T, "expect": {...}}``, and ``{"end": REASON}`` when the
simulation ends normally (:class:`LockstepEnded`; a connection lost without it is a :class:`LockstepError`).

A participant leaves the lock-step with a last DONE (:meth:`LockstepClient.close` after
:meth:`~LockstepClient.done`: the operator at the end of its session), so it leaves at a step, not at a
moment; a connection that closes without one (a participant that died) leaves when the coordinator notices.
Its links keep their last counts.
"""

from __future__ import annotations

import collections
import json
import logging
import select
import socket
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

from quadlink.errors import LinkError

log = logging.getLogger(__name__)

PARTICIPANTS = ("bridge", "companion", "operator")
#: the stack's links (sender>receiver[.port]) and their unit
LINKS = {
    "sitl>bridge.cmd": "bytes (MK port 1)",
    "sitl>bridge.imu": "bytes (MK port 2)",
    "sitl>companion.camera": "frames",
    "bridge>sitl": "bytes (MK port 1)",
    "bridge>companion": "datagrams (MAVLink endpoint 0)",
    "companion>bridge": "datagrams",
    "companion>operator": "datagrams",
    "operator>companion": "datagrams",
}
STEP_WAIT_SLICE_S = 0.1  # a participant waiting for a step looks at its stop flag this often
DEFAULT_DONE_TIMEOUT_S = 30.0  # wall seconds a step may take before the coordinator gives up on the flight
DEFAULT_INPUT_TIMEOUT_S = 30.0  # wall seconds a participant waits for an announced unit before it gives up


class LockstepError(LinkError):
    """The deterministic lock-step cannot go on (a participant or a unit did not come in time, a bad message)."""


class LockstepEnded(LockstepError):
    """The simulation ended normally (its duration, or the flight's end): the participant stops, status 0."""


def receiver_of(link: str) -> str:
    """``"companion>bridge"`` -> ``"bridge"``; ``"sitl>bridge.imu"`` -> ``"bridge"``."""
    return link.partition(">")[2].partition(".")[0]


def parse_url(url: str) -> tuple[str, int]:
    """``tcp://HOST:PORT`` or ``HOST:PORT`` -> (host, port)."""
    text = url.removeprefix("tcp://")
    host, _, port = text.rpartition(":")
    try:
        return host or "127.0.0.1", int(port)
    except ValueError as exc:
        raise LinkError(f"{url}: not a lock-step address (use tcp://HOST:PORT)") from exc


@dataclass(frozen=True)
class Step:
    index: int
    t_s: float  # simulated time at the end of the chunk: the participant's clock during the step
    expect: dict[str, int]  # input link -> units its sender has sent so far

    def count(self, link: str) -> int | None:
        return self.expect.get(link)


def _encode(obj: dict[str, Any]) -> bytes:
    return (json.dumps(obj, separators=(",", ":")) + "\n").encode()


class _Lines:
    """Newline-delimited JSON from a socket (non-blocking reads into a buffer)."""

    def __init__(self) -> None:
        self.buf = bytearray()

    def feed(self, data: bytes) -> list[dict[str, Any]]:
        self.buf += data
        out: list[dict[str, Any]] = []
        while True:
            i = self.buf.find(b"\n")
            if i < 0:
                return out
            line, self.buf = bytes(self.buf[:i]), self.buf[i + 1:]
            try:
                obj = json.loads(line)
            except ValueError as exc:
                raise LockstepError(f"bad lock-step message {line[:80]!r}: {exc}") from exc
            if not isinstance(obj, dict):
                raise LockstepError(f"bad lock-step message {line[:80]!r}")
            out.append(obj)


# ---------------------------------------------------------------------------------------------- participant
class LockstepClient:
    """A participant's connection to the coordinator (blocking socket, bounded waits)."""

    def __init__(self, url: str, name: str, connect_timeout_s: float = 30.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.url, self.name = url, name
        self._clock = clock
        host, port = parse_url(url)
        deadline = clock() + connect_timeout_s
        while True:
            try:
                self.sock = socket.create_connection((host, port), timeout=2.0)
                break
            except OSError as exc:
                if clock() >= deadline:
                    raise LockstepError(f"{url}: no lock-step coordinator ({exc})") from exc
                time.sleep(0.1)
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._lines = _Lines()
        self._pending: list[dict[str, Any]] = []
        self.step: Step | None = None  # the step being handled (None before the first)
        self._done: dict[str, Any] | None = None  # this step's DONE, sent with the next next_step() or close()
        self.t_s = 0.0
        log.info("lock-step: %s joined the coordinator at %s", name, url)

    def hello(self, sent: dict[str, int]) -> None:
        self._send({"hello": self.name, "sent": sent})

    def clock(self) -> float:
        """The participant's clock: the current step's simulated time (0 before the first step)."""
        return self.t_s

    def next_step(self, timeout_s: float = STEP_WAIT_SLICE_S) -> Step | None:
        """The next STEP, or None if none came within ``timeout_s`` (look at the stop flag and call again).

        Raises :class:`LockstepError` when the coordinator is gone (the SITL ended or died).
        """
        self._flush_done()
        if not self._pending:
            self.sock.settimeout(timeout_s)
            try:
                data = self.sock.recv(65536)
            except TimeoutError:
                return None
            except OSError as exc:
                raise LockstepError(f"lock-step coordinator lost: {exc}") from exc
            if not data:
                raise LockstepError("lock-step coordinator closed the connection (the simulation ended)")
            self._pending.extend(self._lines.feed(data))
            if not self._pending:
                return None
        obj = self._pending.pop(0)
        if "end" in obj:
            raise LockstepEnded(f"the simulation ended: {obj['end']}")
        try:
            step = Step(int(obj["step"]), float(obj["t_s"]), {str(k): int(v) for k, v in obj["expect"].items()})
        except (KeyError, TypeError, ValueError) as exc:
            raise LockstepError(f"bad STEP message {obj!r}") from exc
        self.step, self.t_s = step, step.t_s
        return step

    def done(self, sent: dict[str, int]) -> None:
        """Answer the step. The DONE leaves with the next :meth:`next_step` (at once, in a participant's loop) or
        with :meth:`close`, marked as the participant's last: the coordinator then knows at this very step that
        it left, not when it happens to notice a closed connection (which would end a flight a step early or
        late, at the wall clock's whim)."""
        assert self.step is not None, "done() before a step"
        self._done = {"done": self.step.index, "sent": sent}

    def _flush_done(self, last: bool = False) -> None:
        if self._done is not None:
            msg, self._done = self._done, None
            self._send({**msg, "last": True} if last else msg)

    def _send(self, obj: dict[str, Any]) -> None:
        try:
            self.sock.sendall(_encode(obj))
        except OSError as exc:
            raise LockstepError(f"lock-step coordinator lost: {exc}") from exc

    def close(self) -> None:
        """Leave the lock-step: a DONE not yet sent goes as the last one (a participant that ends after its step);
        without one, the coordinator sees the connection close (a participant stopped mid-step)."""
        try:
            self._flush_done(last=True)
        except LockstepError:
            pass
        try:
            self.sock.close()
        except OSError:
            pass


def wait_for_units(received: Callable[[], int], expected: int | None, pump: Callable[[float], object],
                   what: str, timeout_s: float = DEFAULT_INPUT_TIMEOUT_S,
                   clock: Callable[[], float] = time.monotonic) -> None:
    """Call ``pump(block_s)`` (which reads the link, blocking up to ``block_s``) until ``received()`` reaches
    ``expected``; :class:`LockstepError` after ``timeout_s`` wall seconds. ``expected`` None: no wait."""
    if expected is None or received() >= expected:
        return
    deadline = clock() + timeout_s
    while received() < expected:
        remaining = deadline - clock()
        if remaining <= 0:
            raise LockstepError(f"lock-step: {what}: {received()} of {expected} units after {timeout_s:.0f} s")
        pump(min(remaining, 0.05))


class CountedMavlink:
    """A pymavlink UDP ``mavfile`` whose datagrams are counted, and whose reads stop at ``allow``.

    ``sent``: datagrams that left (a ``udpin`` endpoint that has not heard its peer yet sends nothing, and that
    is not counted). ``received``: datagrams that arrived (read from the socket); ``handed``: those given to
    pymavlink. With ``allow`` set, :meth:`recv` hands over nothing once ``handed`` reaches it, so ``recv_msg``
    returns only this step's messages (pymavlink keeps the unparsed rest of a datagram in its buffer and parses
    it on the next call); datagrams that came early wait in a queue for their step. :meth:`wait_readable`
    reads what has arrived into that queue: the pump of :func:`wait_for_units` on ``received``.
    """

    def __init__(self, conn: Any) -> None:
        self.conn = conn
        self.sent = 0
        self.received = 0
        self.handed = 0
        self.allow: int | None = None
        self._queue: collections.deque[bytes] = collections.deque()
        self._write, self._recv = conn.write, conn.recv
        conn.write = self.write
        conn.recv = self.recv

    def write(self, buf: bytes) -> Any:
        if self._has_peer():
            self.sent += 1
        return self._write(buf)

    def _has_peer(self) -> bool:
        """Whether a write leaves: a ``udpin`` endpoint sends to the peers it has heard (pymavlink's ``clients``,
        ``last_address`` in older versions); one peer per lock-step link."""
        if not getattr(self.conn, "udp_server", False):
            return True
        clients = getattr(self.conn, "clients", None)
        return bool(clients) if clients is not None else getattr(self.conn, "last_address", None) is not None

    def _read_arrived(self) -> None:
        while True:
            data = self._recv()
            if not data:
                return
            self.received += 1
            self._queue.append(bytes(data))

    def recv(self, n: int | None = None) -> Any:
        if self.allow is not None and self.handed >= self.allow:
            return b""
        if not self._queue:
            self._read_arrived()
            if not self._queue:
                return b""
        self.handed += 1
        return self._queue.popleft()

    def wait_readable(self, block_s: float) -> None:
        """Block up to ``block_s`` for a datagram, and queue what has arrived (the pump of :func:`wait_for_units`)."""
        if not self._queue:
            try:
                select.select([self.conn.fd], [], [], block_s)
            except (OSError, ValueError):
                time.sleep(block_s)
        self._read_arrived()


# ---------------------------------------------------------------------------------------------- coordinator
@dataclass
class _Peer:
    sock: socket.socket
    address: str
    lines: _Lines = field(default_factory=_Lines)
    name: str | None = None
    done: int = -1


class Coordinator:
    """The SITL's side: a non-blocking TCP server; :meth:`poll` must be called while the SITL waits."""

    def __init__(self, host: str, port: int, participants: Iterable[str]) -> None:
        self.participants = tuple(participants)
        self.listener = socket.create_server((host, port))
        self.listener.setblocking(False)
        self.host, self.port = host, self.listener.getsockname()[1]
        self.peers: list[_Peer] = []
        self.sent: dict[str, int] = {}  # link -> units sent so far (participants' and the SITL's own)
        self.left: set[str] = set()
        self.started = False

    @property
    def url(self) -> str:
        return f"tcp://{self.host}:{self.port}"

    @property
    def registered(self) -> set[str]:
        return {p.name for p in self.peers if p.name is not None}

    @property
    def active(self) -> list[_Peer]:
        return [p for p in self.peers if p.name is not None]

    def all_registered(self) -> bool:
        return set(self.participants) <= self.registered | self.left

    def expect_for(self, name: str) -> dict[str, int]:
        return {link: n for link, n in self.sent.items() if receiver_of(link) == name}

    def poll(self, timeout_s: float = 0.0) -> None:
        """Accept participants and read their messages (waits up to ``timeout_s`` for one)."""
        fds = [self.listener, *(p.sock for p in self.peers)]
        try:
            readable = select.select(fds, [], [], max(0.0, timeout_s))[0]
        except (OSError, ValueError):
            readable = fds
        if self.listener in readable:
            try:
                sock, addr = self.listener.accept()
                sock.setblocking(False)
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                self.peers.append(_Peer(sock, f"{addr[0]}:{addr[1]}"))
            except OSError:
                pass
        for peer in list(self.peers):
            if peer.sock not in readable:
                continue
            try:
                data = peer.sock.recv(65536)
            except (BlockingIOError, InterruptedError):
                continue
            except OSError:
                data = b""
            if not data:
                self._leave(peer)
                continue
            for obj in peer.lines.feed(data):
                self._on_message(peer, obj)

    def _on_message(self, peer: _Peer, obj: dict[str, Any]) -> None:
        sent = obj.get("sent", {})
        if "hello" in obj:
            name = str(obj["hello"])
            if name not in self.participants:
                log.warning("lock-step: %s registered as %r, which is not a participant; ignored", peer.address, name)
                self._leave(peer)
                return
            if name in self.registered:
                raise LockstepError(f"lock-step: a second {name} registered ({peer.address})")
            if self.started:
                raise LockstepError(f"lock-step: {name} registered after the simulation started; a deterministic "
                                    "flight needs every participant from the start")
            peer.name = name
            log.info("lock-step: %s registered (%d of %d)", name, len(self.registered), len(self.participants))
        elif "done" in obj:
            peer.done = int(obj["done"])
        else:
            raise LockstepError(f"lock-step: bad message from {peer.name or peer.address}: {obj!r}")
        for link, n in sent.items():
            if not str(link).startswith(f"{peer.name}>"):
                raise LockstepError(f"lock-step: {peer.name} reported link {link!r}, which it does not send on")
            self.sent[str(link)] = int(n)
        if obj.get("last"):
            self._leave(peer)

    def _leave(self, peer: _Peer) -> None:
        self.peers.remove(peer)
        try:
            peer.sock.close()
        except OSError:
            pass
        if peer.name is not None:
            self.left.add(peer.name)
            log.info("lock-step: %s left at its step %d", peer.name, peer.done)

    def send_step(self, index: int, t_s: float) -> None:
        self.started = True
        for peer in self.active:
            msg = _encode({"step": index, "t_s": t_s, "expect": self.expect_for(peer.name or "")})
            try:
                peer.sock.setblocking(True)
                peer.sock.sendall(msg)
                peer.sock.setblocking(False)
            except OSError:
                self._leave(peer)

    def all_done(self, index: int) -> bool:
        return all(p.done >= index for p in self.active)

    def waiting_for(self, index: int) -> list[str]:
        return [p.name or p.address for p in self.active if p.done < index]

    def close(self, reason: str | None = None) -> None:
        """Close every connection; with ``reason``, tell the participants the simulation ended normally."""
        for peer in self.peers:
            try:
                if reason is not None and peer.name is not None:
                    peer.sock.setblocking(True)
                    peer.sock.settimeout(1.0)
                    peer.sock.sendall(_encode({"end": reason}))
                peer.sock.close()
            except OSError:
                pass
        self.peers = []
        try:
            self.listener.close()
        except OSError:
            pass
