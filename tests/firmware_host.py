"""The FlightCtrl firmware's pure C modules, host-compiled (``make -C firmware host``) and loaded with ctypes.

The tests drive the very C that runs on the ATmega1284P (``firmware/src/*.c`` without ``src/hw``) through the
flat API of ``firmware/host/qlfc_host.c``; the wrappers here only convert arguments. ``load_firmware_lib``
builds once per session (``firmware_lib`` fixture in ``tests/conftest.py``).
"""

from __future__ import annotations

import ctypes
import shutil
import subprocess
from collections.abc import Sequence
from functools import cache
from pathlib import Path

import pytest

FIRMWARE = Path(__file__).resolve().parent.parent / "firmware"
LIB_PATH = FIRMWARE / "build" / "host" / "libqlfc.so"

c_u8p = ctypes.POINTER(ctypes.c_uint8)
c_u16p = ctypes.POINTER(ctypes.c_uint16)
c_i16p = ctypes.POINTER(ctypes.c_int16)
c_i32p = ctypes.POINTER(ctypes.c_int32)
c_u32p = ctypes.POINTER(ctypes.c_uint32)
c_fp = ctypes.POINTER(ctypes.c_float)
vp = ctypes.c_void_p

_SIGNATURES: dict[str, tuple[object, list[object]]] = {
    "ql_mk_encode": (ctypes.c_uint8, [c_u8p, ctypes.c_uint8, ctypes.c_char, c_u8p, ctypes.c_uint8]),
    "qlh_decoder_size": (ctypes.c_size_t, []),
    "ql_mk_decoder_init": (None, [vp]),
    "qlh_decoder_feed": (ctypes.c_int, [vp, c_u8p, ctypes.c_int, c_u8p, ctypes.c_int, ctypes.c_int]),
    "qlh_decoder_stats": (None, [vp, c_u32p]),
    "qlh_pack_imu": (ctypes.c_int, [c_u8p, c_u16p, c_u16p, ctypes.c_uint16]),
    "qlh_unpack_imu": (ctypes.c_int, [c_u8p, ctypes.c_int, c_u16p]),
    "qlh_pack_setpoint": (ctypes.c_int, [c_u8p, ctypes.c_int16, ctypes.c_int16, ctypes.c_int16, ctypes.c_uint16,
                                         ctypes.c_uint8, ctypes.c_uint8]),
    "qlh_unpack_setpoint": (ctypes.c_int, [c_u8p, ctypes.c_int, c_i32p]),
    "qlh_pack_status": (ctypes.c_int, [c_u8p, ctypes.c_uint8, ctypes.c_uint8, ctypes.c_uint16, ctypes.c_uint16,
                                       ctypes.c_uint32, ctypes.c_uint32, ctypes.c_uint8]),
    "qlh_pack_baro": (ctypes.c_int, [c_u8p, ctypes.c_int32, ctypes.c_int16, ctypes.c_uint32, ctypes.c_uint8,
                                     ctypes.c_uint8]),
    "qlh_pack_data3d": (ctypes.c_int, [c_u8p, c_i16p, c_u8p, c_u8p]),
    "ql_pack_version": (ctypes.c_uint8, [c_u8p, c_u8p]),
    "ql_pack_debug": (ctypes.c_uint8, [c_u8p, c_u8p, c_i16p]),
    "ql_pack_label": (ctypes.c_uint8, [c_u8p, ctypes.c_uint8, ctypes.c_char_p]),
    "ql_pack_u8": (ctypes.c_uint8, [c_u8p, ctypes.c_uint8]),
    "ql_sin_q12": (ctypes.c_int16, [ctypes.c_int32]),
    "ql_cos_q12": (ctypes.c_int16, [ctypes.c_int32]),
    "ql_atan2_q24": (ctypes.c_int32, [ctypes.c_int32, ctypes.c_int32]),
    "ql_isqrt32": (ctypes.c_uint32, [ctypes.c_uint32]),
    "qlh_att_size": (ctypes.c_size_t, []),
    "ql_attitude_init": (None, [vp]),
    "ql_attitude_update": (None, [vp, c_u16p, c_u16p, ctypes.c_uint8, ctypes.c_uint8]),
    "qlh_att_get": (None, [vp, c_i32p]),
    "qlh_baro_size": (ctypes.c_size_t, []),
    "ql_baro_init": (None, [vp]),
    "ql_baro_update": (None, [vp, c_u16p, ctypes.c_uint8]),
    "qlh_baro_get": (None, [vp, c_i32p]),
    "ql_baro_pressure_pa": (ctypes.c_uint32, [vp]),
    "qlh_params_size": (ctypes.c_size_t, []),
    "ql_params_defaults": (None, [vp]),
    "qlh_params_get": (None, [vp, c_fp]),
    "qlh_params_set_gain": (None, [vp, ctypes.c_int, ctypes.c_float]),
    "ql_crc16": (ctypes.c_uint16, [c_u8p, ctypes.c_uint16]),
    "ql_params_load": (ctypes.c_uint8, [vp, c_u8p, ctypes.c_uint16]),
    "ql_params_store": (ctypes.c_uint16, [vp, c_u8p]),
    "qlh_ctrl_size": (ctypes.c_size_t, []),
    "ql_ctrl_init": (None, [vp, vp]),
    "ql_ctrl_reset": (None, [vp]),
    "qlh_ctrl_step": (None, [vp, vp, c_fp, ctypes.c_int, c_i32p, c_i32p, c_fp]),
    "qlh_ctrl_integ": (None, [vp, c_fp]),
    "qlh_mix": (None, [vp, ctypes.c_float, c_fp, c_fp]),
    "qlh_motor_byte": (ctypes.c_int, [vp, ctypes.c_float]),
    "qlh_safety_size": (ctypes.c_size_t, []),
    "ql_safety_init": (None, [vp, vp]),
    "qlh_safety_on_setpoint": (ctypes.c_int, [vp, vp, ctypes.c_int16, ctypes.c_int16, ctypes.c_int16,
                                              ctypes.c_uint16, ctypes.c_uint8, ctypes.c_uint8, ctypes.c_uint32]),
    "qlh_safety_step": (ctypes.c_int, [vp, vp, ctypes.c_uint32, ctypes.c_float, ctypes.c_int, ctypes.c_int, c_fp]),
    "qlh_safety_state": (None, [vp, c_i32p]),
    "ql_hover_thrust_fraction": (ctypes.c_float, [vp]),
    "qlh_board_new": (vp, [c_u8p, ctypes.c_int]),
    "qlh_board_free": (None, [vp]),
    "qlh_board_set_room": (None, [vp, ctypes.c_int, ctypes.c_int]),
    "qlh_board_rx": (None, [vp, c_u8p, ctypes.c_int]),
    "qlh_board_tick": (None, [vp, c_u16p, c_u16p, c_u16p, ctypes.c_uint16]),
    "qlh_board_take": (ctypes.c_int, [vp, ctypes.c_int, c_u8p, ctypes.c_int]),
    "qlh_board_state": (None, [vp, c_i32p]),
    "qlh_board_set_busy": (None, [vp, ctypes.c_uint16, ctypes.c_uint16]),
}


@cache
def load_firmware_lib() -> ctypes.CDLL:
    """Build ``firmware/build/host/libqlfc.so`` (make is incremental) and load it with typed signatures."""
    if shutil.which("make") is None or shutil.which("gcc") is None:
        pytest.skip("make and gcc are needed to build the firmware's host library")
    done = subprocess.run(["make", "-C", str(FIRMWARE), "host"], capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise RuntimeError(f"make -C firmware host failed:\n{done.stdout}\n{done.stderr}")
    lib = ctypes.CDLL(str(LIB_PATH))
    for name, (restype, argtypes) in _SIGNATURES.items():
        fn = getattr(lib, name)
        fn.restype = restype
        fn.argtypes = argtypes
    return lib


def u8(data: bytes | Sequence[int]) -> ctypes.Array[ctypes.c_uint8]:
    raw = bytes(data)
    return (ctypes.c_uint8 * max(1, len(raw))).from_buffer_copy(raw + (b"\x00" if not raw else b""))


def u16(values: Sequence[int]) -> ctypes.Array[ctypes.c_uint16]:
    return (ctypes.c_uint16 * len(values))(*[int(v) for v in values])


def f32(values: Sequence[float]) -> ctypes.Array[ctypes.c_float]:
    return (ctypes.c_float * len(values))(*[float(v) for v in values])


def blob(lib: ctypes.CDLL, size_fn: str) -> ctypes.Array[ctypes.c_uint8]:
    """Zeroed storage for one opaque C struct, sized by the library itself."""
    return (ctypes.c_uint8 * int(getattr(lib, size_fn)()))()


def c_encode(lib: ctypes.CDLL, address: int, command: str, payload: bytes) -> bytes:
    out = (ctypes.c_uint8 * 256)()
    n = lib.ql_mk_encode(out, address, command.encode(), u8(payload), len(payload))
    return bytes(out[:n])


class CDecoder:
    """``ql_mk_decoder_t`` fed byte by byte (``batch=0``) or in chunks of ``batch`` bytes through
    ``ql_mk_decoder_feed_buf`` (the firmware's main loop: 32); frames come back as (address, command, payload)."""

    STAT_NAMES = ("frames_ok", "bad_checksum", "overlong", "invalid_chars", "malformed", "truncated",
                  "garbage_bytes", "dropped_bytes", "pending_bytes")

    def __init__(self, lib: ctypes.CDLL, batch: int = 0) -> None:
        self.lib = lib
        self.batch = batch
        self.state = blob(lib, "qlh_decoder_size")
        lib.ql_mk_decoder_init(self.state)

    def feed(self, data: bytes) -> list[tuple[int, str, bytes]]:
        out = (ctypes.c_uint8 * (len(data) + 64))()
        n = self.lib.qlh_decoder_feed(self.state, u8(data), len(data), out, len(out), self.batch)
        frames, pos = [], 0
        for _ in range(n):
            addr, cmd, length = out[pos], chr(out[pos + 1]), out[pos + 2]
            frames.append((addr, cmd, bytes(out[pos + 3:pos + 3 + length])))
            pos += 3 + length
        return frames

    def stats(self) -> dict[str, int]:
        raw = (ctypes.c_uint32 * 9)()
        self.lib.qlh_decoder_stats(self.state, raw)
        return dict(zip(self.STAT_NAMES, raw, strict=True))


class CBoard:
    """The whole board core (``ql_fc_t``): port-1 bytes in, ADC sweeps per tick, captured port output."""

    def __init__(self, lib: ctypes.CDLL, image: bytes | None = None) -> None:
        self.lib = lib
        self.ptr = lib.qlh_board_new(u8(image) if image is not None else None, len(image or b""))

    def close(self) -> None:
        if self.ptr:
            self.lib.qlh_board_free(self.ptr)
            self.ptr = None

    def rx(self, data: bytes) -> None:
        self.lib.qlh_board_rx(self.ptr, u8(data), len(data))

    def tick(self, accel: Sequence[int] = (512, 512, 256), gyro: Sequence[int] = (512, 512, 512),
             baro: Sequence[int] | int = 600, battery: int = 645) -> None:
        counts = [baro] * 8 if isinstance(baro, int) else list(baro)
        self.lib.qlh_board_tick(self.ptr, u16(accel), u16(gyro), u16(counts), battery)

    def take(self, port: int) -> bytes:
        out = (ctypes.c_uint8 * 65536)()
        n = self.lib.qlh_board_take(self.ptr, port, out, len(out))
        return bytes(out[:n])

    def set_room(self, port: int, room: int) -> None:
        self.lib.qlh_board_set_room(self.ptr, port, room)

    def state(self) -> dict[str, int]:
        raw = (ctypes.c_int32 * 12)()
        self.lib.qlh_board_state(self.ptr, raw)
        names = ("armed", "failsafe", "flight_state", "m1", "m2", "m3", "m4", "p1_tx_dropped", "p2_tx_dropped",
                 "tick", "params_ok", "rx_frames_dropped")
        return dict(zip(names, raw, strict=True))
