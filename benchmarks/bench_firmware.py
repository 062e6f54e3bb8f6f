"""The flight firmware in simavr: its 500 Hz loop's cycles, flash and RAM, the ``I`` stream, and the SITL's speed.

Targets (issue: the SITL flies the firmware binary): the loop's worst case <= 60 % of its 40,000-cycle budget
(20 MHz / 500 Hz), measured from the loop-busy pin PB0's edges (``firmware/HARDWARE.md``); no ``I`` frame lost or
late; the SITL with ``--board avr`` at >= 1x real time on this 2-core machine, beside ``--board model``.

Phases, each a fresh vehicle (pybullet) flown in process with the same seed by scripted 100 Hz setpoints:
``ground`` (disarmed on the floor), ``hover`` (armed, climbed, holding hover thrust) and ``steps`` (roll and pitch
steps of 0.15 rad). Real-time factors are given on the wall clock (this machine is shared: load average printed)
and on this process's CPU time (what one dedicated core gives). The SITL figure runs ``Sitl`` itself, unpaced,
no camera, no client (disarmed: the firmware sleeps between ticks). ``--profile`` adds where the armed loop's
cycles go, by function (simavr counts every instruction's cycles; sleep excluded).

    python benchmarks/bench_firmware.py [--elf firmware/build/quadlink-fc.elf] [--seconds 10] [--profile]
"""

from __future__ import annotations

import argparse
import bisect
import dataclasses
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from quadlink.mk.messages import AttitudeSetpoint, encode_message  # noqa: E402
from quadlink.vehicle import load_vehicle  # noqa: E402
from sim_sitl.avr_board import DEFAULT_ELF, AvrBoard  # noqa: E402
from sim_sitl.config import load_scenario, load_sitl_config  # noqa: E402
from sim_sitl.firmware import AttitudeCommand  # noqa: E402
from sim_sitl.vehicle_sim import SimVehicle  # noqa: E402

BUDGET_CYCLES = 40_000
LOOP_TARGET = 0.60
FLASH_BYTES, RAM_BYTES = 128 * 1024, 16 * 1024
GROUND_S = 2.0


def script(phase: str, t: float, hover: float) -> tuple[float, float, float, float, bool]:
    if phase == "ground" or t < GROUND_S:
        return 0.0, 0.0, 0.0, 0.0, False
    if t < GROUND_S + 1.0:
        return 0.0, 0.0, 0.0, hover * 1.1, True
    if phase == "steps":
        k = int((t - GROUND_S - 1.0) / 0.5) % 4
        return (0.15, -0.15, 0.0, 0.0)[k], (0.0, 0.0, 0.15, -0.15)[k], 0.0, hover, True
    return 0.0, 0.0, 0.0, hover, True


@dataclasses.dataclass
class PhaseResult:
    busy: np.ndarray
    frames: int
    lost: int
    late: int
    max_lag_cycles: int
    imu_hz: float
    sim_s: float
    wall_s: float
    cpu_s: float
    profile: dict[int, int]


def fly(phase: str, seconds: float, elf: Path | None, profile: bool = False) -> PhaseResult:
    vehicle, cfg = load_vehicle(), load_sitl_config()
    sim = SimVehicle(vehicle, cfg, load_scenario("empty"), np.random.default_rng(1))
    board = None
    if elf is not None:
        board = AvrBoard(elf, vehicle, cfg.baro, np.random.default_rng(3), sim.tick_s)
        sim.board = board
    total_s = GROUND_S + 1.0 + seconds if phase != "ground" else seconds
    measure_from = total_s - seconds
    prof: dict[int, int] = {}
    wall0 = cpu0 = 0.0
    try:
        for k in range(round(total_s / sim.tick_s)):
            t = sim.t_s
            if abs(t - measure_from) < 1e-9:
                wall0, cpu0 = time.perf_counter(), time.process_time()
                if board is not None:
                    board.loop.busy_cycles.clear()
                    if profile:
                        board.mcu.profile(True)
            if k % 5 == 0:
                roll, pitch, yaw_rate, thrust, armed = script(phase, t, vehicle.hover_thrust_fraction)
                if board is not None:
                    board.on_port1(encode_message(AttitudeSetpoint(roll, pitch, yaw_rate, thrust, armed, k // 5)))
                else:
                    sim.on_setpoint(AttitudeCommand(roll, pitch, yaw_rate, thrust, armed, (k // 5) & 0xFF))
            sim.tick()
        wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
        if board is None:
            return PhaseResult(np.zeros(0), 0, 0, 0, 0, 0.0, seconds, wall, cpu, {})
        if profile:
            prof = board.mcu.take_profile()
        s = board.imu_stream.stats
        assert s.first_cycle is not None
        hz = (s.frames - 1) / ((s.last_cycle - s.first_cycle) / 20e6) if s.frames > 1 else 0.0
        return PhaseResult(np.array(board.loop.busy_cycles), s.frames, s.lost, s.late, s.max_lag_cycles, hz,
                           seconds, wall, cpu, prof)
    finally:
        sim.close()
        if board is not None:
            board.close()


def sitl_rtf(board: str, elf: Path, seconds: float) -> tuple[float, float]:
    from sim_sitl.runner import Sitl, SitlOptions

    cfg = dataclasses.replace(load_sitl_config(), board=board, firmware_elf=str(elf))  # type: ignore[arg-type]
    sitl = Sitl(SitlOptions(config=cfg, port1=0, port2=0, camera=False, truth_url=None, speed=0.0,
                            duration_s=seconds, progress_every_s=1e9))
    try:
        wall0, cpu0 = time.perf_counter(), time.process_time()
        sitl.run()
        return seconds / (time.perf_counter() - wall0), seconds / (time.process_time() - cpu0)
    finally:
        sitl.stop()


def sizes(elf: Path) -> tuple[int, int]:
    out = subprocess.run(["avr-size", "-A", str(elf)], capture_output=True, text=True, check=True).stdout
    sec = {m.group(1): int(m.group(2)) for m in re.finditer(r"^(\.\w+)\s+(\d+)", out, re.M)}
    return sec.get(".text", 0) + sec.get(".data", 0), sec.get(".data", 0) + sec.get(".bss", 0)


def by_function(elf: Path, prof: dict[int, int]) -> list[tuple[str, int]]:
    out = subprocess.run(["avr-nm", "-n", "-S", str(elf)], capture_output=True, text=True, check=True).stdout
    syms = []
    for line in out.splitlines():
        parts = line.split()
        if len(parts) == 4 and parts[2] in "tTwW":
            syms.append((int(parts[0], 16), int(parts[1], 16), parts[3]))
    syms.sort()
    starts = [s[0] for s in syms]
    acc: dict[str, int] = {}
    for addr, cycles in prof.items():
        i = bisect.bisect_right(starts, addr) - 1
        name = syms[i][2] if i >= 0 and addr < syms[i][0] + syms[i][1] else f"0x{addr:05x}"
        acc[name] = acc.get(name, 0) + cycles
    return sorted(acc.items(), key=lambda kv: -kv[1])


def pct(x: float) -> str:
    return f"{100.0 * x:.1f} %"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--elf", default=os.environ.get("QUADLINK_FC_ELF", str(DEFAULT_ELF)))
    ap.add_argument("--seconds", type=float, default=10.0, help="simulated seconds measured per phase")
    ap.add_argument("--sitl-seconds", type=float, default=10.0)
    ap.add_argument("--profile", action="store_true", help="where the armed loop's cycles go, by function")
    args = ap.parse_args()
    elf = Path(args.elf)
    if not elf.is_file():
        print(f"error: firmware ELF {elf} not found: build it with make -C firmware", file=sys.stderr)
        return 1
    print(f"firmware {elf}; load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    flash, ram = sizes(elf)
    print(f"flash {flash} B = {pct(flash / FLASH_BYTES)} of 128 KiB; static RAM {ram} B = {pct(ram / RAM_BYTES)} of "
          f"16 KiB (the stack uses the rest)")
    results = {}
    for phase in ("ground", "hover", "steps"):
        avr = fly(phase, args.seconds, elf, profile=args.profile and phase == "steps")
        model = fly(phase, args.seconds, None)
        results[phase] = avr
        b = avr.busy
        over = int(np.sum(b >= BUDGET_CYCLES))
        worst = b.max() / BUDGET_CYCLES if b.size else float("nan")
        print(f"[{phase}] loop busy (PB0) over {b.size} ticks: p50 {np.percentile(b, 50):.0f} cycles "
              f"({pct(np.percentile(b, 50) / BUDGET_CYCLES)}), p99 {np.percentile(b, 99):.0f} "
              f"({pct(np.percentile(b, 99) / BUDGET_CYCLES)}), max {b.max():.0f} ({pct(worst)}; target <= "
              f"{pct(LOOP_TARGET)}: {'met' if worst <= LOOP_TARGET else 'NOT met'}); ticks over budget {over}")
        print(f"[{phase}] I stream: {avr.frames} frames, {avr.imu_hz:.2f} Hz (target 500.00), lost {avr.lost}, "
              f"late {avr.late} (worst lag {avr.max_lag_cycles / 20e3:.2f} ms behind the 2 ms grid)")
        print(f"[{phase}] in-process flight, real-time factor: avr {avr.sim_s / avr.wall_s:.2f} wall, "
              f"{avr.sim_s / avr.cpu_s:.2f} CPU | model {model.sim_s / model.wall_s:.2f} wall, "
              f"{model.sim_s / model.cpu_s:.2f} CPU | avr/model CPU cost x{avr.cpu_s / model.cpu_s:.2f}")
    rtf = {}
    for board in ("model", "avr"):
        rtf[board] = wall, cpu = sitl_rtf(board, elf, args.sitl_seconds)
        print(f"SITL --board {board} (unpaced, no camera, disarmed, {args.sitl_seconds:.0f} s sim): real-time factor "
              f"{wall:.2f} wall, {cpu:.2f} CPU (target >= 1x)")
    print(f"SITL avr / model real-time factor: x{rtf['avr'][0] / rtf['model'][0]:.2f} wall, "
          f"x{rtf['avr'][1] / rtf['model'][1]:.2f} CPU")
    if args.profile:
        prof = results["steps"].profile
        total = sum(prof.values())
        print(f"[steps] where the cycles go ({total / (args.seconds * 20e6):.1%} of the CPU's cycles awake):")
        for name, cycles in by_function(elf, prof)[:15]:
            print(f"  {name:32s} {cycles / total:6.1%}  {cycles / (args.seconds * 500):8.0f} cycles per tick")
    return 0


if __name__ == "__main__":
    sys.exit(main())
