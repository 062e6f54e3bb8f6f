"""The companion as a participant of the deterministic lock-step (:mod:`quadlink.lockstep`): its counted links.

With ``quadlink companion --lockstep tcp://HOST:PORT`` the daemon joins the SITL's coordinator as
``"companion"``; from then on it reads each input only up to the count the step announces and reports, in each
DONE, how many datagrams it has sent on each output (the loop itself: :meth:`companion.daemon.Companion.run`).
This module is those edges, and nothing of the flight:

* the two pymavlink links, each wrapped in :class:`quadlink.lockstep.CountedMavlink` (datagrams sent and
  arrived counted; ``allow`` caps what pymavlink is handed, the early ones queued for their step);
* :class:`CountedCamera`: the camera input with the frames handed to the daemon counted, which is what the
  SITL's ``sitl>companion.camera`` counts.
* :class:`LockstepLinks` and :func:`join_lockstep`: the coordinator's connection, the counted links, which
  frames a step handles (those the *previous* step announced: see :attr:`LockstepLinks.frames_due`), and the
  registration. The camera stream is connected before the hello: a frame the SITL publishes before our
  camera client exists would be counted and never come.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from companion.cameras import CameraInput
from quadlink.camera import RgbdFrame
from quadlink.lockstep import CountedMavlink, LockstepClient, LockstepError

log = logging.getLogger("companion.daemon")

NAME = "companion"
AUTOPILOT_IN = "bridge>companion"        # datagrams on the autopilot link (the bridge's MAVLink endpoint 0)
GCS_IN = "operator>companion"            # datagrams on the ground-station link
CAMERA_IN = "sitl>companion.camera"      # camera frames (the SITL's stream)
AUTOPILOT_OUT = "companion>bridge"
GCS_OUT = "companion>operator"
CAMERA_CONNECT_TIMEOUT_S = 5.0   # the SITL serves its camera stream before its coordinator: seconds are plenty
COORDINATOR_TIMEOUT_S = 30.0     # how long the daemon waits for the SITL to serve its coordinator
RETRY_S = 0.1


class CountedCamera:
    """The camera input, counting the frames handed to the daemon (``received``). Frames read while waiting for
    the stream to connect (before the hello: there should be none) are held and handed over first."""

    def __init__(self, camera: CameraInput) -> None:
        self.camera = camera
        self.received = 0
        self._held: deque[RgbdFrame] = deque()

    def connect(self, timeout_s: float, stop: threading.Event | None = None,
                clock: Callable[[], float] = time.monotonic) -> bool:
        """Wait up to ``timeout_s`` (wall) for the camera to connect (the stream connects on its first read)."""
        deadline = clock() + timeout_s
        while not self.camera.connected and clock() < deadline and not (stop is not None and stop.is_set()):
            frame = self.camera.read(0.05)
            if frame is not None:
                self._held.append(frame)
        return self.camera.connected

    def take(self, block_s: float) -> RgbdFrame | None:
        """The next frame, waiting up to ``block_s`` (wall) for it; counted."""
        frame = self._held.popleft() if self._held else self.camera.read(block_s)
        if frame is not None:
            self.received += 1
        return frame


@dataclass
class LockstepLinks:
    """What the daemon needs to be a lock-step participant: the coordinator's connection and its counted links.

    ``frames_due``: the camera count of the previous step, the frames the current step handles. A frame
    rendered during chunk ``k`` is stamped inside it, while the HIGHRES_IMU that reaches us in step ``k`` only
    covers chunk ``k - 1``; one step later the IMU has caught up with the frame (what the wall-clock loop's
    bounded wait for the IMU achieves by waiting), so frames are handled one step after their announcement.
    """

    client: LockstepClient
    autopilot: CountedMavlink
    gcs: CountedMavlink
    camera: CountedCamera
    frames_due: int | None = None

    def sent(self) -> dict[str, int]:
        """The DONE's counts: datagrams sent so far on each output link."""
        return {AUTOPILOT_OUT: self.autopilot.sent, GCS_OUT: self.gcs.sent}

    def close(self) -> None:
        """Leave the lock-step (the coordinator goes on without us); the links are the daemon's to close."""
        self.client.close()


def connect_coordinator(url: str, stop: threading.Event | None = None,
                        timeout_s: float = COORDINATOR_TIMEOUT_S,
                        clock: Callable[[], float] = time.monotonic) -> LockstepClient:
    """The coordinator's connection, waiting up to ``timeout_s`` (wall) for the SITL to serve it, and looking at
    ``stop`` meanwhile (:class:`~quadlink.lockstep.LockstepError` when it is set or the time is up)."""
    deadline = clock() + timeout_s
    while True:
        try:
            return LockstepClient(url, NAME, connect_timeout_s=0.0)
        except LockstepError:
            if clock() >= deadline:
                raise
        if stop is not None and stop.wait(RETRY_S):
            raise LockstepError(f"{url}: stopped while waiting for the lock-step coordinator")
        if stop is None:
            time.sleep(RETRY_S)


def join_lockstep(url: str, autopilot: Any, gcs: Any, camera: CameraInput, stop: threading.Event | None = None,
                  camera_connect_timeout_s: float = CAMERA_CONNECT_TIMEOUT_S,
                  coordinator_timeout_s: float = COORDINATOR_TIMEOUT_S) -> LockstepLinks:
    """Connect to the coordinator at ``url`` (:func:`connect_coordinator`), count the two pymavlink links and the
    camera, connect the camera, and register (nothing sent yet: all zero). ``autopilot`` and ``gcs`` are the
    pymavlink connections the daemon is then given."""
    client = connect_coordinator(url, stop, coordinator_timeout_s)
    try:
        counted = CountedCamera(camera)
        if not counted.connect(camera_connect_timeout_s, stop):
            log.warning("lock-step: camera not connected after %.0f s; frames the SITL counts before it connects "
                        "would never come", camera_connect_timeout_s)
        links = LockstepLinks(client, CountedMavlink(autopilot), CountedMavlink(gcs), counted)
        client.hello(links.sent())
    except BaseException:
        client.close()
        raise
    return links
