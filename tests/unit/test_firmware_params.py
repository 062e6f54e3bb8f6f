"""The firmware's EEPROM parameter image (C, host build): CRC-16/CCITT-FALSE, defaults on a bad image."""

from __future__ import annotations

import ctypes

import pytest
from firmware_host import blob, u8


def crc16_ccitt_false(data: bytes) -> int:
    """Reference CRC-16/CCITT-FALSE: poly 0x1021, init 0xFFFF, no reflection, no final xor."""
    crc = 0xFFFF
    for b in data:
        crc ^= b << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) & 0xFFFF if crc & 0x8000 else (crc << 1) & 0xFFFF
    return crc


def test_crc16_check_value(firmware_lib: ctypes.CDLL) -> None:
    assert firmware_lib.ql_crc16(u8(b"123456789"), 9) == 0x29B1  # the catalogue's check value
    data = bytes(range(256)) * 2
    assert firmware_lib.ql_crc16(u8(data), len(data)) == crc16_ccitt_false(data)


def _image(lib: ctypes.CDLL, params: ctypes.Array[ctypes.c_uint8]) -> bytearray:
    n = ctypes.c_int.in_dll(lib, "qlh_params_image_len").value
    out = (ctypes.c_uint8 * n)()
    assert lib.ql_params_store(params, out) == n
    return bytearray(out)


def _gains(lib: ctypes.CDLL, params: ctypes.Array[ctypes.c_uint8]) -> list[float]:
    out = (ctypes.c_float * 25)()
    lib.qlh_params_get(params, out)
    return list(out)


def test_image_round_trip_and_bad_crc_loads_defaults(firmware_lib: ctypes.CDLL) -> None:
    lib = firmware_lib
    p = blob(lib, "qlh_params_size")
    lib.ql_params_defaults(p)
    defaults = _gains(lib, p)
    lib.qlh_params_set_gain(p, 0, 9.5)  # angle kp: a tuned value must survive the image
    tuned = _gains(lib, p)
    assert tuned[0] == 9.5 and tuned[1:] == defaults[1:]
    image = _image(lib, p)
    stored_crc = image[-2] | image[-1] << 8
    assert stored_crc == crc16_ccitt_false(bytes(image[:-2]))

    loaded = blob(lib, "qlh_params_size")
    assert lib.ql_params_load(loaded, u8(image), len(image)) == 1
    assert _gains(lib, loaded) == tuned

    for flip in (0, len(image) // 2, len(image) - 1):  # any corrupted byte, CRC bytes included
        bad = bytearray(image)
        bad[flip] ^= 0x40
        target = blob(lib, "qlh_params_size")
        assert lib.ql_params_load(target, u8(bad), len(bad)) == 0
        assert _gains(lib, target) == defaults
    blank = bytes([0xFF]) * len(image)  # an erased EEPROM
    assert lib.ql_params_load(blob(lib, "qlh_params_size"), u8(blank), len(blank)) == 0
    assert lib.ql_params_load(blob(lib, "qlh_params_size"), u8(image[:-1]), len(image) - 1) == 0


def test_a_valid_image_with_another_version_loads_defaults(firmware_lib: ctypes.CDLL) -> None:
    lib = firmware_lib
    p = blob(lib, "qlh_params_size")
    lib.ql_params_defaults(p)
    p[0] = 99  # the version word (first field, little-endian)
    image = _image(lib, p)  # a correct CRC over the wrong version
    target = blob(lib, "qlh_params_size")
    assert lib.ql_params_load(target, u8(image), len(image)) == 0
    assert _gains(lib, target)[-1] == pytest.approx(1.0)  # QL_PARAMS_VERSION
