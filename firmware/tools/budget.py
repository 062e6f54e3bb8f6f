#!/usr/bin/env python3
"""Print the firmware's flash, RAM and stack budget (run by `make`).

Flash = .text + .data, RAM = .data + .bss (avr-size). Stack: the static frames of -fstack-usage (.su files)
along the deepest call chain from main found in the disassembly (call/rcall/jmp/rjmp to functions), plus the
deepest interrupt handler's chain on top (interrupts do not nest here). Library routines without a .su entry
(libgcc float/long arithmetic, avr-libc) are counted at LIB_FRAME_BYTES each level.
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

RAM_BYTES = 16384
FLASH_BYTES = 131072
RETURN_ADDRESS_BYTES = 2  # 16-bit PC on the ATmega1284P (64 K words)
LIB_FRAME_BYTES = 12  # libgcc/avr-libc routines push at most a few registers


def section_sizes(elf: str) -> dict[str, int]:
    out = subprocess.run(["avr-size", "-A", elf], check=True, capture_output=True, text=True).stdout
    sizes = {}
    for line in out.splitlines():
        parts = line.split()
        if len(parts) >= 2 and parts[0].startswith(".") and parts[1].isdigit():
            sizes[parts[0]] = int(parts[1])
    return sizes


def stack_frames(build: Path) -> dict[str, int]:
    frames: dict[str, int] = {}
    for su in build.rglob("*.su"):
        for line in su.read_text().splitlines():
            loc, size, _kind = line.split("\t")
            frames[loc.rsplit(":", 1)[-1]] = max(frames.get(loc.rsplit(":", 1)[-1], 0), int(size))
    return frames


def call_graph(elf: str) -> dict[str, set[str]]:
    dis = subprocess.run(["avr-objdump", "-d", elf], check=True, capture_output=True, text=True).stdout
    graph: dict[str, set[str]] = {}
    current = None
    for line in dis.splitlines():
        m = re.match(r"^[0-9a-f]+ <([^>]+)>:$", line)
        if m:
            current = m.group(1)
            graph.setdefault(current, set())
            continue
        m = re.search(r"\s(r?call|r?jmp)\s.*<([^>+]+)>", line)
        if m and current and m.group(2) != current:
            graph[current].add(m.group(2))
    return graph


def deepest(fn: str, graph: dict[str, set[str]], frames: dict[str, int],
            seen: tuple[str, ...] = ()) -> tuple[int, list[str]]:
    if fn in seen:
        return 0, [fn + " (recursion!)"]
    best, path = 0, []
    for callee in graph.get(fn, ()):
        depth, sub = deepest(callee, graph, frames, (*seen, fn))
        if depth + RETURN_ADDRESS_BYTES > best:
            best, path = depth + RETURN_ADDRESS_BYTES, sub
    return frames.get(fn, LIB_FRAME_BYTES) + best, [fn, *path]


def main() -> None:
    elf, build = sys.argv[1], Path(sys.argv[2])
    sizes = section_sizes(elf)
    flash = sizes.get(".text", 0) + sizes.get(".data", 0)
    ram = sizes.get(".data", 0) + sizes.get(".bss", 0) + sizes.get(".noinit", 0)
    frames = stack_frames(build)
    graph = call_graph(elf)
    main_depth, main_path = deepest("main", graph, frames)
    isrs = [f for f in graph if f.startswith("__vector_")]
    isr_depth, isr_path = max((deepest(f, graph, frames) for f in isrs), default=(0, []))
    stack = main_depth + RETURN_ADDRESS_BYTES + isr_depth
    print(f"flash: {flash} B of {FLASH_BYTES} ({100.0 * flash / FLASH_BYTES:.1f} %)")
    print(f"RAM (static .data + .bss): {ram} B of {RAM_BYTES} ({100.0 * ram / RAM_BYTES:.1f} %)")
    print(f"stack (worst case): {stack} B = main chain {main_depth} B + interrupt {isr_depth} B + return address")
    print(f"  main chain: {' > '.join(main_path)}")
    print(f"  interrupt:  {' > '.join(isr_path)}")
    print(f"RAM left for the stack: {RAM_BYTES - ram} B (margin {RAM_BYTES - ram - stack} B)")


if __name__ == "__main__":
    main()
