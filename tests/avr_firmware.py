"""Test helpers for the simavr board: the shim's test program and the flight firmware's ELF.

``echo_elf`` builds ``integration/avr_fixture/echo.c`` with avr-gcc (skips if avr-gcc is missing).
``firmware_elf`` is the flight firmware: ``$QUADLINK_FC_ELF`` if set, else the repo's
``firmware/build/quadlink-fc.elf`` after ``make -C firmware`` (skips, with make's last line, if it cannot be built).
"""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parent
REPO = TESTS.parent
ECHO_SOURCE = TESTS / "integration" / "avr_fixture" / "echo.c"
FIRMWARE_DIR = REPO / "firmware"
FIRMWARE_ELF = FIRMWARE_DIR / "build" / "quadlink-fc.elf"


def need_simavr() -> None:
    if not Path("/usr/include/simavr/sim_avr.h").is_file():
        pytest.skip("libsimavr-dev is not installed (apt-get install libsimavr-dev libelf-dev)")


@pytest.fixture(scope="session")
def echo_elf(tmp_path_factory: pytest.TempPathFactory) -> Path:
    need_simavr()
    if shutil.which("avr-gcc") is None:
        pytest.skip("avr-gcc is not installed")
    out = tmp_path_factory.mktemp("avr") / "echo.elf"
    subprocess.run(["avr-gcc", "-mmcu=atmega1284p", "-DF_CPU=20000000UL", "-Os", "-Wall", "-Werror", "-o", str(out),
                    str(ECHO_SOURCE)], check=True, capture_output=True, text=True)
    return out


_built: dict[str, Path | str] = {}


def find_firmware_elf() -> Path | str:
    """The flight firmware's ELF, or the reason there is none."""
    explicit = os.environ.get("QUADLINK_FC_ELF")
    if explicit:
        return Path(explicit) if Path(explicit).is_file() else f"QUADLINK_FC_ELF={explicit} does not exist"
    if "elf" in _built:
        return _built["elf"]
    if not (FIRMWARE_DIR / "Makefile").is_file():
        reason: Path | str = f"no firmware to build ({FIRMWARE_DIR}/Makefile missing)"
    elif shutil.which("avr-gcc") is None or shutil.which("make") is None:
        reason = "avr-gcc or make is not installed"
    else:
        proc = subprocess.run(["make", "-C", str(FIRMWARE_DIR)], capture_output=True, text=True, check=False)
        lines = (proc.stderr or proc.stdout).strip().splitlines()
        reason = FIRMWARE_ELF if proc.returncode == 0 and FIRMWARE_ELF.is_file() else \
            f"make -C firmware failed: {lines[-1] if lines else proc.returncode}"
    _built["elf"] = reason
    return reason


@pytest.fixture(scope="session")
def firmware_elf() -> Path:
    need_simavr()
    found = find_firmware_elf()
    if isinstance(found, str):
        pytest.skip(f"the flight firmware cannot be built: {found}")
    return found


class Rig:
    """The flight firmware in simavr with its pins held as a board at rest, level, on the floor (no physics).

    ``run_ticks`` advances whole 2 ms ticks and collects: the ``I`` stream's statistics, every port-1 frame
    with the cycle its last byte left, the loop's busy cycles from PB0 and the motor bytes after each tick.
    """

    def __init__(self, elf: Path, battery_v: float = 12.6) -> None:
        from quadlink.mk.protocol import FrameDecoder
        from quadlink.vehicle import ImuConfig
        from sim_sitl.avr.sim import AvrSim
        from sim_sitl.avr_board import (
            CH_ACCEL,
            CH_BATTERY,
            CH_GYRO,
            CH_PRESSURE,
            ImuStreamMonitor,
            LoopTiming,
            adc_count,
            imu_volts,
        )
        from sim_sitl.baro import BaroConfig, amplified_v, pressure_pa, sensor_v

        self.mcu = AvrSim(elf)
        self.tick_cycles = 40_000
        self.monitor = ImuStreamMonitor(self.tick_cycles, 2 * self.tick_cycles)
        self.loop = LoopTiming()
        self.decoder = FrameDecoder()
        self.frames: list[tuple[object, int]] = []  # (decoded message, cycle)
        self.motor_log: list[tuple[int, tuple[int, ...]]] = []  # (cycle at the tick's end, bytes)
        imu = ImuConfig()
        for axis in range(3):
            self.mcu.set_adc_count(CH_GYRO + axis, 512)
            self.mcu.set_adc_count(CH_ACCEL + axis, 512)
        self.mcu.set_adc_count(CH_ACCEL + 2, adc_count(imu_volts(-9.80665, imu.accel_lsb_m_s2, imu.zero_count)))
        self.mcu.set_adc_count(CH_PRESSURE, adc_count(amplified_v(sensor_v(pressure_pa(BaroConfig().site_altitude_m)))))
        self.mcu.set_adc_count(CH_BATTERY, adc_count(battery_v / 4.0))

    def close(self) -> None:
        self.mcu.close()

    def run_ticks(self, n: int) -> None:
        from quadlink.mk.messages import decode_message
        from sim_sitl.avr_board import frames_with_cycles

        mcu = self.mcu
        for _ in range(n):
            target = (mcu.cycle // self.tick_cycles + 1) * self.tick_cycles
            mcu.run_until(target)
            for edge in mcu.take_edges():
                if edge.pin == 0:
                    self.loop.on_edge(edge.cycle, edge.level)
            self.monitor.feed(*mcu.take_tx(1))
            for frame, cycle in frames_with_cycles(self.decoder, *mcu.take_tx(0)):
                self.frames.append((decode_message(frame), cycle))
            self.motor_log.append((mcu.cycle, mcu.motors().bytes))

    def run_s(self, seconds: float) -> None:
        self.run_ticks(round(seconds * 500))

    def send(self, msg: object) -> None:
        from quadlink.mk.messages import encode_message

        self.mcu.send_port1(encode_message(msg))  # type: ignore[arg-type]

    def messages(self, kind: type, since_cycle: int = 0) -> list:
        return [m for m, c in self.frames if isinstance(m, kind) and c >= since_cycle]
