"""The shared MAVLink parameter service (quadlink.mavlink.param_service) with the bridge's table and a
generic integer table: bytewise encoding as PX4's PARAM_ENCODE_BYTEWISE, bounds, types, addressing."""

from __future__ import annotations

import math
import struct

import pytest

from firmware_bridge.params import PARAM_SPECS, ParamTable
from quadlink.mavlink import mavlink
from quadlink.mavlink.param_service import (
    ParamError,
    ParamService,
    ParamSpec,
    decode_param_value,
    encode_param_value,
)
from quadlink.mavlink.param_service import ParamTable as GenericTable

GCS = mavlink.MAVLink(None, 255, 190)
SPECS = (ParamSpec("COUNT", 3, 0, 10, "", "an INT32 count", mavlink.MAV_PARAM_TYPE_INT32),
         ParamSpec("MODE", 1, 0, 2, "", "a UINT8 selector", mavlink.MAV_PARAM_TYPE_UINT8),
         ParamSpec("GAIN", 0.5, 0.0, 2.0, "1/s", "a gain"))


def wire(encoded):
    return GCS.decode(bytearray(encoded.pack(GCS)))


def service(specs=SPECS, compid=191):
    table = GenericTable(specs)
    return table, ParamService(table, mavlink.MAVLink(None, 1, compid), 1, compid)


def test_int32_values_travel_bytewise_like_px4():
    assert struct.pack("<f", encode_param_value(7, mavlink.MAV_PARAM_TYPE_INT32)) == struct.pack("<i", 7)
    assert decode_param_value(struct.unpack("<f", struct.pack("<i", -5))[0], mavlink.MAV_PARAM_TYPE_INT32) == -5
    assert encode_param_value(0.25, mavlink.MAV_PARAM_TYPE_REAL32) == 0.25
    table, svc = service()
    seven = struct.unpack("<f", struct.pack("<i", 7))[0]
    reply = svc.handle(0.0, wire(GCS.param_set_encode(1, 191, b"COUNT", seven, mavlink.MAV_PARAM_TYPE_INT32)))
    assert table["COUNT"] == 7 and reply.changed == "COUNT" and not reply.refused
    echo = wire(reply.to_all[0])
    assert echo.param_type == mavlink.MAV_PARAM_TYPE_INT32
    assert decode_param_value(echo.param_value, echo.param_type) == 7


def test_out_of_range_int_and_type_mismatch_are_refused_with_the_unchanged_value():
    table, svc = service()
    eleven = encode_param_value(11, mavlink.MAV_PARAM_TYPE_INT32)
    for value, ptype in ((eleven, mavlink.MAV_PARAM_TYPE_INT32), (7.0, mavlink.MAV_PARAM_TYPE_REAL32)):
        reply = svc.handle(0.0, wire(GCS.param_set_encode(1, 191, b"COUNT", value, ptype)))
        assert reply.refused and reply.to_all == [] and len(reply.to_sender) == 1
        assert decode_param_value(wire(reply.to_sender[0]).param_value, mavlink.MAV_PARAM_TYPE_INT32) == 3
        assert reply.events and reply.events[0][0] == mavlink.MAV_SEVERITY_WARNING
    assert table["COUNT"] == 3 and not table.dirty and svc.refused_sets == 2


def test_list_read_and_addressing():
    table, svc = service()
    listed = [wire(m) for m in svc.handle(0.0, wire(GCS.param_request_list_encode(1, 191))).to_sender]
    assert [m.param_id for m in listed] == ["COUNT", "MODE", "GAIN"]
    assert [m.param_index for m in listed] == [0, 1, 2] and all(m.param_count == 3 for m in listed)
    assert svc.handle(0.0, wire(GCS.param_request_list_encode(1, 1))).to_sender == []  # another component
    assert svc.handle(0.0, wire(GCS.param_request_list_encode(2, 0))).to_sender == []  # another system
    read = svc.handle(0.0, wire(GCS.param_request_read_encode(1, 0, b"", 2))).to_sender
    assert wire(read[0]).param_id == "GAIN"
    assert svc.handle(0.0, wire(GCS.param_request_read_encode(1, 0, b"", 9))).to_sender == []
    unknown = svc.handle(0.0, wire(GCS.param_set_encode(1, 191, b"NOPE", 1.0, mavlink.MAV_PARAM_TYPE_REAL32)))
    assert unknown.to_sender == [] and unknown.to_all == [] and "Unknown parameter NOPE" in unknown.events[0][1]


def test_specs_are_checked_and_every_bridge_param_has_a_unit_and_bounds():
    with pytest.raises(ParamError):
        ParamSpec("X", 5.0, 0.0, 1.0, "", "default out of bounds")
    with pytest.raises(ParamError):
        ParamSpec("A_NAME_LONGER_THAN_16", 0.0, 0.0, 1.0, "", "too long")
    with pytest.raises(ParamError):
        ParamSpec("I", 0.5, 0, 1, "", "fractional int", mavlink.MAV_PARAM_TYPE_INT32)
    for spec in PARAM_SPECS:
        assert spec.param_type == mavlink.MAV_PARAM_TYPE_REAL32 and spec.min <= spec.default <= spec.max
        assert spec.description and spec.unit is not None


def test_parameter_file_values_are_bounded_and_non_finite_ignored():
    table = ParamTable({"MPC_TILTMAX_AIR": 1000.0, "MIS_TAKEOFF_ALT": math.nan, "NOT_A_PARAM": 1.0})
    assert table["MPC_TILTMAX_AIR"] == 60.0 and table["MIS_TAKEOFF_ALT"] == 1.0
