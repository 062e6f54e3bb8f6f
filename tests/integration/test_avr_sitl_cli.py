"""``quadlink sitl --board avr``: a clear one-line error without an ELF; with the firmware, a run whose port 2
carries its 500 Hz ``I`` stream."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest
from avr_firmware import REPO, firmware_elf  # noqa: F401  (fixture)

pytestmark = pytest.mark.timeout(300)


def sitl(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "quadlink.cli", "sitl", "--no-camera", "--truth", "none",
                           "--port1", "0", "--port2", "0", *args], capture_output=True, text=True, timeout=240,
                          cwd=REPO, check=False)


def test_missing_elf_is_a_one_line_error(tmp_path: Path) -> None:
    proc = sitl("--board", "avr", "--firmware-elf", str(tmp_path / "none.elf"), "--duration", "1")
    assert proc.returncode != 0
    errors = [line for line in proc.stderr.splitlines() if "error" in line.lower()]
    assert len(errors) == 1
    assert "none.elf not found: build it with make -C firmware" in errors[0]
    assert "Traceback" not in proc.stderr


def test_board_choice_is_validated() -> None:
    proc = sitl("--board", "fpga", "--duration", "1")
    assert proc.returncode != 0 and "fpga" in proc.stderr


def test_sitl_runs_the_firmware_binary(firmware_elf: Path) -> None:  # noqa: F811
    proc = sitl("--board", "avr", "--firmware-elf", str(firmware_elf), "--duration", "3", "--speed", "0")
    assert proc.returncode == 0, proc.stderr[-2000:]
    log = proc.stdout + proc.stderr
    assert "board avr" in log
    m = re.search(r"IMU frames (\d+) \(dropped (\d+)\)", log)
    assert m is not None, log[-2000:]
    frames, dropped = int(m.group(1)), int(m.group(2))
    assert 1490 - 30 <= frames <= 1500 and dropped == 0  # 3 s at 500 Hz, the first frame a tick in
