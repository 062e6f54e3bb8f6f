"""The command lines of a flight's vehicle processes, one builder per part, on a flight's ports
(:class:`harness.ports.Ports`): the demo (and through it the campaign, the falsification search and paper 003) and
every SITL test start the SITL, the bridge and the companion from these (issue 28: one flight harness), each as a
:class:`harness.demo.orchestrator.ProcessSpec` for the orchestrator's :class:`~harness.demo.orchestrator.Stack`.

A port is named as in :data:`harness.ports.PORT_NAMES` (``"autopilot"``, ``"gcs_bridge"``, ``"vehicle"``, ...), so a
part's links follow the flight's ports wherever they were allocated.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from harness.demo.orchestrator import ProcessSpec
from harness.ports import Ports


def _lockstep_url(ports: Ports) -> str:
    return f"tcp://127.0.0.1:{ports.lockstep}"


@dataclass(frozen=True)
class SitlPart:
    """``quadlink sitl``: the vehicle, its board and camera, the truth stream to the ``truth`` port (the judge's,
    never the vehicle's)."""

    scenario: str | None = "paper-arena"   # None: configs/sitl.yaml's
    lockstep: bool = True                  # the plain lock-step (the SITL paced by the setpoints and frames)
    deterministic: bool = False            # instead, serve the deterministic lock-step on the ``lockstep`` port
    end_after_operator_s: float = 0.0      # deterministic: end this long after the operator left (or its disarm)
    camera: bool = True
    truth: bool = True
    speed: float | None = None             # the lock-step's pace (1: real time); None: the SITL's default
    duration_s: float | None = 400.0       # None: until stopped
    config: str | None = None              # the SITL's configuration file (None: configs/sitl.yaml)
    board: str | None = None               # "avr": the FlightCtrl firmware's binary in simavr
    firmware_elf: Path | None = None
    truth_tlog: Path | None = None         # the truth as sent, written by the SITL (the judge's record)
    ready_after_s: float = 4.0

    def spec(self, ports: Ports) -> ProcessSpec:
        a = ["sitl", "--port1", str(ports.mk1), "--port2", str(ports.mk2), "--camera-port", str(ports.camera)]
        if self.scenario is not None:
            a += ["--scenario", self.scenario]
        # without truth, say so: the SITL's default sends it to the demo's truth port, where another flight's judge
        # may be listening (a test's SITL polluted a demo's truth track so)
        a += ["--truth", f"udpout:127.0.0.1:{ports.truth}" if self.truth else "none"]
        if self.truth_tlog is not None:
            a += ["--truth-tlog", str(self.truth_tlog)]
        if not self.camera:
            a.append("--no-camera")
        if self.duration_s is not None:
            a += ["--duration", f"{self.duration_s:g}"]
        if self.config is not None:
            a += ["--config", self.config]
        if self.board is not None:
            a += ["--board", self.board]
        if self.firmware_elf is not None:
            a += ["--firmware-elf", str(self.firmware_elf)]
        if self.deterministic:
            a += ["--lockstep-port", str(ports.lockstep), "--end-after-operator", f"{self.end_after_operator_s:g}"]
        elif self.lockstep:
            a.append("--lockstep")
        if self.speed is not None:
            a += ["--speed", f"{self.speed:g}"]
        return ProcessSpec("sitl", tuple(a), ready_after_s=self.ready_after_s)


@dataclass(frozen=True)
class BridgePart:
    """``quadlink bridge`` on the SITL's MK ports, sending MAVLink to the ``outputs`` ports in order (the first is
    its first ``--mavlink`` endpoint); ``params``: its parameter file (it writes PARAM_SETs back to it)."""

    params: Path | None = None
    outputs: tuple[str, ...] = ("autopilot", "gcs_bridge")
    journal: Path | None = None            # its input journal (quadlink replay-bridge)
    tlog: Path | None = None               # what it sent to the ground station (``gcs_bridge``), as sent
    deterministic: bool = False            # a participant of the deterministic lock-step
    ready_after_s: float = 2.0

    def spec(self, ports: Ports) -> ProcessSpec:
        a = ["bridge", "--mk-cmd", f"socket://127.0.0.1:{ports.mk1}", "--mk-imu", f"socket://127.0.0.1:{ports.mk2}"]
        for name in self.outputs:
            a += ["--mavlink", f"udpout:127.0.0.1:{getattr(ports, name)}"]
        if self.params is not None:
            a += ["--params", str(self.params)]
        if self.journal is not None:
            a += ["--journal", str(self.journal)]
        if self.tlog is not None:
            a += ["--tlog", str(self.tlog)]
        if self.deterministic:
            a += ["--lockstep", _lockstep_url(ports)]
        return ProcessSpec("bridge", tuple(a), ready_after_s=self.ready_after_s)


@dataclass(frozen=True)
class CompanionPart:
    """``quadlink companion`` taking the autopilot's MAVLink on the port named ``autopilot`` and the ground stations'
    on ``vehicle``; ``camera``: its camera URL, ``{port}`` the SITL's camera stream port (with no camera in the SITL
    nothing answers there); ``config``: its configuration file (None: the shipped one)."""

    config: Path | None = None
    autopilot: str = "autopilot"
    camera: str = "tcp://127.0.0.1:{port}"
    image_stream: bool = False             # the operator image stream on the ``image`` port (else none)
    tlog: Path | None = None
    signing_key: Path | None = None        # the ground link signed with this key, unsigned packets refused
    record_frames: Path | None = None
    journal: Path | None = None            # its input journal (quadlink replay-companion; ~12 MB/s)
    deterministic: bool = False
    ready_after_s: float = 3.0

    def spec(self, ports: Ports) -> ProcessSpec:
        a = ["companion"]
        if self.config is not None:
            a += ["--config", str(self.config)]
        a += ["--autopilot", f"udpin:127.0.0.1:{getattr(ports, self.autopilot)}",
              "--gcs", f"udpin:127.0.0.1:{ports.vehicle}", "--camera", self.camera.format(port=ports.camera),
              "--image-port", str(ports.image) if self.image_stream else "0"]
        if self.tlog is not None:
            a += ["--tlog", str(self.tlog)]
        if self.signing_key is not None:
            a += ["--signing-key", str(self.signing_key), "--require-signing"]
        if self.record_frames is not None:
            a += ["--record-frames", str(self.record_frames)]
        if self.journal is not None:
            a += ["--journal", str(self.journal)]
        if self.deterministic:
            a += ["--lockstep", _lockstep_url(ports)]
        return ProcessSpec("companion", tuple(a), ready_after_s=self.ready_after_s)
