"""``AvrSim``: an ATmega1284P at 20 MHz in simavr running one ELF, driven in whole chunks (ctypes over ``shim.c``).

Everything is in cycles of the MCU clock; the caller owns time. Per chunk: set the ADC pins, queue port-1 bytes,
:meth:`run_until` a cycle, then take what came out (UART bytes with the cycle their stop bit left, PB edges, the
BL-Ctrl bytes). The pins and addresses are ``firmware/HARDWARE.md``'s.
"""

from __future__ import annotations

import ctypes
from dataclasses import dataclass
from pathlib import Path

from quadlink.errors import QuadlinkError
from sim_sitl.avr.build import build

MCU = "atmega1284p"
F_CPU_HZ = 20_000_000
AVCC_MV = 5000
ADC_CHANNELS = 8
MOTORS = 4
EEPROM_BYTES = 4096

# simavr's cpu states (sim_avr.h)
CPU_DONE = 6
CPU_CRASHED = 7
CPU_STOPPED = 1

_u8p = ctypes.POINTER(ctypes.c_uint8)
_u16p = ctypes.POINTER(ctypes.c_uint16)
_u32p = ctypes.POINTER(ctypes.c_uint32)
_u64p = ctypes.POINTER(ctypes.c_uint64)

_SIGNATURES: dict[str, tuple[object, list[object]]] = {
    "qs_new": (ctypes.c_void_p, [ctypes.c_char_p, ctypes.c_char_p, ctypes.c_uint32, ctypes.c_char_p, ctypes.c_int]),
    "qs_free": (None, [ctypes.c_void_p]),
    "qs_reset": (None, [ctypes.c_void_p]),
    "qs_cycle": (ctypes.c_uint64, [ctypes.c_void_p]),
    "qs_state": (ctypes.c_int, [ctypes.c_void_p]),
    "qs_run_until": (ctypes.c_int, [ctypes.c_void_p, ctypes.c_uint64]),
    "qs_set_adc_mv": (None, [ctypes.c_void_p, ctypes.c_int, ctypes.c_uint32]),
    "qs_set_adc_counts": (None, [ctypes.c_void_p, _u16p, ctypes.c_int]),
    "qs_uart_take": (ctypes.c_int, [ctypes.c_void_p, ctypes.c_int, _u8p, _u64p, ctypes.c_int]),
    "qs_uart_tx_overflow": (ctypes.c_uint32, [ctypes.c_void_p, ctypes.c_int]),
    "qs_uart_cycles_per_byte": (ctypes.c_uint32, [ctypes.c_void_p, ctypes.c_int]),
    "qs_uart0_send": (ctypes.c_int, [ctypes.c_void_p, ctypes.c_char_p, ctypes.c_int]),
    "qs_uart0_pending": (ctypes.c_int, [ctypes.c_void_p]),
    "qs_uart0_fed": (ctypes.c_uint32, [ctypes.c_void_p]),
    "qs_uart0_last_received": (ctypes.c_uint64, [ctypes.c_void_p]),
    "qs_motors": (None, [ctypes.c_void_p, _u8p, _u32p, _u64p]),
    "qs_twi_nacked": (ctypes.c_uint32, [ctypes.c_void_p]),
    "qs_edges_take": (ctypes.c_int, [ctypes.c_void_p, _u64p, _u8p, _u8p, ctypes.c_int]),
    "qs_edges_overflow": (ctypes.c_uint32, [ctypes.c_void_p]),
    "qs_portb": (ctypes.c_int, [ctypes.c_void_p, ctypes.c_int]),
    "qs_profile": (None, [ctypes.c_void_p, ctypes.c_int]),
    "qs_profile_take": (ctypes.c_int, [ctypes.c_void_p, _u32p, ctypes.c_int]),
    "qs_eeprom_size": (ctypes.c_int, [ctypes.c_void_p]),
    "qs_eeprom_read": (ctypes.c_int, [ctypes.c_void_p, _u8p, ctypes.c_int]),
    "qs_eeprom_write": (ctypes.c_int, [ctypes.c_void_p, ctypes.c_char_p, ctypes.c_int]),
}

_lib: ctypes.CDLL | None = None


class AvrSimError(QuadlinkError):
    """simavr could not load the ELF, or the MCU crashed."""


def _library() -> ctypes.CDLL:
    global _lib
    if _lib is None:
        lib = ctypes.CDLL(str(build()))
        for name, (restype, argtypes) in _SIGNATURES.items():
            fn = getattr(lib, name)
            fn.restype = restype
            fn.argtypes = argtypes
        _lib = lib
    return _lib


def mv_for_count(count: int) -> int:
    """The smallest input (mV) for which simavr's ADC (``count = mV * 1023 // AVCC``) reads ``count``."""
    c = min(max(int(count), 0), 1023)
    return -(-c * AVCC_MV // 1023)


@dataclass(frozen=True)
class Motors:
    """The four BL-Ctrls: the last byte each was written, how many bytes it got, the cycle of its last byte."""

    bytes: tuple[int, int, int, int]
    writes: tuple[int, int, int, int]
    last_cycle: tuple[int, int, int, int]


@dataclass(frozen=True)
class Edge:
    cycle: int
    pin: int  # PORTB bit
    level: int


class AvrSim:
    """One MCU. ``close()`` frees it (also usable as a context manager)."""

    def __init__(self, elf: str | Path, frequency_hz: int = F_CPU_HZ) -> None:
        self._lib = _library()
        path = Path(elf)
        if not path.is_file():
            raise AvrSimError(f"no firmware ELF at {path}")
        err = ctypes.create_string_buffer(256)
        handle = self._lib.qs_new(str(path).encode(), MCU.encode(), frequency_hz, err, len(err))
        if not handle:
            raise AvrSimError(err.value.decode(errors="replace"))
        self._h: int | None = handle
        self.frequency_hz = frequency_hz
        self._buf8 = (ctypes.c_uint8 * 16384)()
        self._buf64 = (ctypes.c_uint64 * 16384)()
        self._pins = (ctypes.c_uint8 * 4096)()
        self._levels = (ctypes.c_uint8 * 4096)()
        # per-tick exchanges reuse these (no ctypes allocation per call)
        self._counts = (ctypes.c_uint16 * ADC_CHANNELS)()
        self._motor_bytes = (ctypes.c_uint8 * MOTORS)()
        self._motor_writes = (ctypes.c_uint32 * MOTORS)()
        self._motor_cycles = (ctypes.c_uint64 * MOTORS)()

    def __enter__(self) -> AvrSim:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        if self._h is not None:
            self._lib.qs_free(self._h)
            self._h = None

    @property
    def handle(self) -> int:
        if self._h is None:
            raise AvrSimError("the simulated MCU is closed")
        return self._h

    # ------------------------------------------------------------------ time
    @property
    def cycle(self) -> int:
        return int(self._lib.qs_cycle(self.handle))

    def run_until(self, cycle: int) -> None:
        """Run until the cycle counter reaches ``cycle``; AvrSimError if the MCU crashed or stopped."""
        state = self._lib.qs_run_until(self.handle, cycle)
        if state in (CPU_CRASHED, CPU_DONE, CPU_STOPPED):
            raise AvrSimError(f"the MCU {'crashed' if state == CPU_CRASHED else 'stopped (sleep with interrupts off)'}"
                              f" at cycle {self.cycle}")

    def run_for(self, cycles: int) -> None:
        self.run_until(self.cycle + cycles)

    def reset(self) -> None:
        """The reset pin: RAM, registers and peripherals restart; EEPROM and the cycle counter do not."""
        self._lib.qs_reset(self.handle)

    # ------------------------------------------------------------------ pins
    def set_adc_mv(self, channel: int, millivolts: int) -> None:
        if not 0 <= channel < ADC_CHANNELS:
            raise ValueError(f"ADC channel {channel} (0..7)")
        self._lib.qs_set_adc_mv(self.handle, channel, max(0, min(AVCC_MV, int(millivolts))))

    def set_adc_count(self, channel: int, count: int) -> None:
        """Drive the channel with the voltage an ideal 10-bit converter reads as ``count``."""
        self.set_adc_mv(channel, mv_for_count(count))

    def set_adc_counts(self, counts: list[int]) -> None:
        """ADC0..len(counts)-1 at once (one call): as :meth:`set_adc_count` on each channel."""
        if len(counts) > ADC_CHANNELS:
            raise ValueError(f"{len(counts)} ADC channels (0..7)")
        buf = self._counts
        for channel, count in enumerate(counts):
            buf[channel] = min(max(int(count), 0), 1023)
        self._lib.qs_set_adc_counts(self.handle, buf, len(counts))

    def take_edges(self) -> list[Edge]:
        """PB0/PB1 edges since the last call, oldest first."""
        n = self._lib.qs_edges_take(self.handle, self._buf64, self._pins, self._levels, len(self._pins))
        return [Edge(c, p, v) for c, p, v in zip(self._buf64[:n], self._pins[:n], self._levels[:n], strict=True)]

    @property
    def edges_lost(self) -> int:
        return int(self._lib.qs_edges_overflow(self.handle))

    def portb(self, pin: int) -> int:
        return int(self._lib.qs_portb(self.handle, pin))

    # ------------------------------------------------------------------ UARTs
    def take_tx(self, port: int) -> tuple[bytes, list[int]]:
        """Bytes USART``port`` sent since the last call and the cycle each one's stop bit left the pin."""
        n = self._lib.qs_uart_take(self.handle, port, self._buf8, self._buf64, len(self._buf8))
        return ctypes.string_at(self._buf8, n), self._buf64[:n]

    def tx_lost(self, port: int) -> int:
        return int(self._lib.qs_uart_tx_overflow(self.handle, port))

    def cycles_per_byte(self, port: int) -> int:
        """The UART's byte time as the firmware configured it (start + data + parity + stop bits)."""
        return int(self._lib.qs_uart_cycles_per_byte(self.handle, port))

    def send_port1(self, data: bytes) -> int:
        """Queue bytes for USART0's receiver (they enter one byte time apart); returns how many fit."""
        return int(self._lib.qs_uart0_send(self.handle, bytes(data), len(data)))

    @property
    def port1_pending(self) -> int:
        return int(self._lib.qs_uart0_pending(self.handle))

    @property
    def port1_fed(self) -> int:
        return int(self._lib.qs_uart0_fed(self.handle))

    @property
    def port1_last_received_cycle(self) -> int:
        """The cycle at which the last byte fed to USART0 had completely arrived (its stop bit)."""
        return int(self._lib.qs_uart0_last_received(self.handle))

    # ------------------------------------------------------------------ TWI
    def motors(self) -> Motors:
        b, w, c = self._motor_bytes, self._motor_writes, self._motor_cycles
        self._lib.qs_motors(self.handle, b, w, c)
        return Motors(tuple(b), tuple(w), tuple(c))  # type: ignore[arg-type]

    @property
    def twi_nacked(self) -> int:
        return int(self._lib.qs_twi_nacked(self.handle))

    # ------------------------------------------------------------------ profile
    def profile(self, on: bool) -> None:
        """Count the cycles each instruction takes from now (sleep excluded); off frees the counters."""
        self._lib.qs_profile(self.handle, int(on))

    def take_profile(self) -> dict[int, int]:
        """Cycles per flash byte address since the last take (only addresses that ran)."""
        words = 1 << 16
        buf = (ctypes.c_uint32 * words)()
        n = self._lib.qs_profile_take(self.handle, buf, words)
        return {2 * i: int(buf[i]) for i in range(n) if buf[i]}

    # ------------------------------------------------------------------ EEPROM
    def eeprom(self) -> bytes:
        size = self._lib.qs_eeprom_size(self.handle)
        buf = (ctypes.c_uint8 * size)()
        n = self._lib.qs_eeprom_read(self.handle, buf, size)
        return bytes(buf[:n])

    def set_eeprom(self, data: bytes) -> None:
        self._lib.qs_eeprom_write(self.handle, bytes(data), len(data))
