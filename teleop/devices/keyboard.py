"""Keyboard operator for the virtual device: keys push the handle, digits press buttons.

    w / s   push forward / backward        a / d   push left / right (yaw)
    r / f   push up / down                 space   release
    1 arm   2 take-off   3 land   0 disarm   p pan-scan on/off   q quit

A key pushes with ``force_n`` for ``hold_s`` (terminal key repeat keeps it pushed while held).
Reads the terminal in cbreak mode in one thread (select with a timeout, so it stops promptly).
"""

from __future__ import annotations

import os
import select
import sys
import threading
import time
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from quadlink.errors import QuadlinkError
from teleop.devices.script import DIRECTIONS_D
from teleop.devices.virtual import OperatorSource

KEY_PUSH = {"w": "forward", "s": "backward", "a": "left", "d": "right", "r": "up", "f": "down"}
KEY_BUTTON = {"1": "arm", "2": "takeoff", "3": "land", "0": "disarm", "p": "pan_scan_toggle", "q": "quit"}


class KeyboardOperator(OperatorSource):
    def __init__(self, force_n: float = 2.0, hold_s: float = 0.6,
                 clock: Callable[[], float] = time.monotonic) -> None:
        if not sys.stdin.isatty():
            raise QuadlinkError("--device keyboard needs an interactive terminal on stdin")
        import termios
        import tty

        self._clock = clock
        self.force_n = force_n
        self.hold_s = hold_s
        self._fd = sys.stdin.fileno()
        self._saved = termios.tcgetattr(self._fd)
        tty.setcbreak(self._fd)
        self._lock = threading.Lock()
        self._force = np.zeros(3)
        self._until = 0.0
        self._presses: list[str] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="keyboard", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            ready, _, _ = select.select([self._fd], [], [], 0.1)
            if not ready:
                continue
            key = os.read(self._fd, 1).decode(errors="ignore").lower()
            with self._lock:
                if key in KEY_PUSH:
                    self._force = np.array(DIRECTIONS_D[KEY_PUSH[key]]) * self.force_n
                    self._until = self._clock() + self.hold_s
                elif key == " ":
                    self._until = 0.0
                elif key in KEY_BUTTON:
                    self._presses.append(KEY_BUTTON[key])

    def force_at(self, t_s: float) -> NDArray[np.float64]:
        with self._lock:
            return self._force.copy() if self._clock() < self._until else np.zeros(3)

    def presses_between(self, t0_s: float, t1_s: float) -> tuple[str, ...]:
        with self._lock:
            presses, self._presses = tuple(self._presses), []
        return presses

    def close(self) -> None:
        import termios

        self._stop.set()
        self._thread.join(timeout=1.0)
        termios.tcsetattr(self._fd, termios.TCSADRAIN, self._saved)
