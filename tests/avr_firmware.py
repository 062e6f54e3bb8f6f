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
