"""The classic MAVSDK API's ``mavsdk_server`` (the binary ``mavsdk-grpc`` ships) as a test's client: started on a
free gRPC port, its output in a log, stopped when the block ends. Shared by the tiers (the flight harness's client
scripts, the companion daemon's integration test)."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from harness.ports import free_port


class MavsdkServer:
    """The classic API's ``mavsdk_server`` (the one mavsdk_grpc ships) for :func:`mavsdk_server`: on a free gRPC port
    (``port``), its output in ``log_path``; started by :meth:`start` (:func:`connect_classic` calls it from the client
    script's thread, while the harness runs the flight)."""

    def __init__(self, system_url: str, log_path: Path) -> None:
        self.system_url = system_url
        self.log_path = log_path
        self.port = free_port()
        self._proc: Any = None

    def start(self) -> None:
        import subprocess
        from importlib.resources import files

        if self._proc is not None:
            return
        binary = files("mavsdk_grpc") / "bin" / "mavsdk_server"
        with open(self.log_path, "wb") as log:
            self._proc = subprocess.Popen([str(binary), "-p", str(self.port), self.system_url], stdout=log,
                                          stderr=subprocess.STDOUT)

    def stop(self) -> None:
        import subprocess

        if self._proc is None:
            return
        self._proc.terminate()
        try:
            self._proc.wait(5.0)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait(5.0)


@contextlib.contextmanager
def mavsdk_server(system_url: str, log_path: Path) -> Iterator[MavsdkServer]:
    """A :class:`MavsdkServer`, stopped when the block ends (a server left running holds its port and keeps talking to
    the companion). It is started by :func:`connect_classic` in the client script, not here: mavsdk_server declares
    the vehicle found once only, at the first HEARTBEAT it hears, and only if it has heard the autopilot (compid 1)
    by then; started while the lock-step flight stood still between the harness's steps, it heard the companion's
    own heartbeat before anything of the paused autopilot, and never opened its gRPC port (CI on ``1c055a8``: stuck
    in connect, "Component Autopilot added" after "Discovered component Companion Computer")."""
    server = MavsdkServer(system_url, log_path)
    try:
        yield server
    finally:
        server.stop()
