"""Command mapping: q -> MANUAL_CONTROL (eqs. (2)-(3)), dead-band, workspace scaling; buttons -> commands."""

from __future__ import annotations

import numpy as np
import pytest

from quadlink.mavlink import mavlink
from teleop.commands import CommandTracker
from teleop.config import CommandsConfig, DeviceConfig, MappingConfig
from teleop.mapping import map_device_to_command, mapping_gains, shape_axis

DEV = DeviceConfig(workspace_m=(0.08, 0.06, 0.05))
MAP = MappingConfig(deadband_m=(0.005, 0.004, 0.003))


def test_rest_is_neutral():
    cmd = map_device_to_command(np.zeros(3), MAP, DEV)
    assert (cmd.x, cmd.y, cmd.z, cmd.r) == (0, 0, 500, 0)


def test_deadband_and_full_scale():
    assert shape_axis(0.0049, 0.005, 0.08) == 0.0
    assert shape_axis(-0.0049, 0.005, 0.08) == 0.0
    assert shape_axis(0.005 + 0.075 / 2, 0.005, 0.08) == pytest.approx(0.5)
    assert shape_axis(0.2, 0.005, 0.08) == 1.0
    assert shape_axis(-0.2, 0.005, 0.08) == -1.0
    assert shape_axis(float("nan"), 0.005, 0.08) == 0.0


def test_axes_signs_and_ranges():
    fwd = map_device_to_command(np.array([0.08, 0.0, 0.0]), MAP, DEV)
    assert fwd.x == 1000 and fwd.r == 0 and fwd.z == 500
    back = map_device_to_command(np.array([-1.0, 0.0, 0.0]), MAP, DEV)
    assert back.x == -1000
    right = map_device_to_command(np.array([0.0, 0.06, 0.0]), MAP, DEV)
    assert right.y == 1000 and right.r == 0           # eq. (3) in NED, on the companion's axis (y)
    paper = map_device_to_command(np.array([0.0, 0.06, 0.0]), MappingConfig(yaw_sign=-1.0, yaw_axis="r"), DEV)
    assert paper.r == -1000 and paper.y == 0          # the paper's psi_d' = -k_psi q_y on the r axis
    up = map_device_to_command(np.array([0.0, 0.0, -0.05]), MAP, DEV)   # z_D is down: lifting = climb
    assert up.z == 1000
    down = map_device_to_command(np.array([0.0, 0.0, 0.05]), MAP, DEV)
    assert down.z == 0
    half = map_device_to_command(np.array([0.005 + 0.0375, 0.0, 0.0]), MAP, DEV)
    assert half.x == 500


def test_mapping_is_monotonic_and_continuous():
    qs = np.linspace(-0.1, 0.1, 2001)
    xs = np.array([map_device_to_command(np.array([q, 0, 0]), MAP, DEV).x for q in qs])
    assert np.all(np.diff(xs) >= 0)
    assert np.max(np.abs(np.diff(xs))) <= 2     # no jump at the dead-band edge


def test_gains():
    g = mapping_gains(MAP, DEV)
    assert g.k_v_xy_per_s == pytest.approx(MAP.max_speed_m_s / (0.075 * 0.97))
    assert g.k_psi_rad_s_m == pytest.approx(MAP.max_yaw_rate_rad_s / (0.056 * 0.97))
    with pytest.raises(ValueError):
        mapping_gains(MappingConfig(deadband_m=(0.1, 0.0, 0.0)), DEV)


def test_buttons_to_commands_with_acks_and_retries():
    tracker = CommandTracker(CommandsConfig(ack_timeout_s=1.0, retries=2))
    arm = tracker.build("arm")
    assert arm is not None and arm.command == mavlink.MAV_CMD_COMPONENT_ARM_DISARM and arm.params[0] == 1.0
    assert (arm.target_system, arm.target_component) == (1, 191)     # through the companion's modes
    tracker.submit(arm, 0.0)
    assert tracker.poll(0.5) == ([], [])
    resend, failed = tracker.poll(1.1)
    assert len(resend) == 1 and resend[0].confirmation == 1 and not failed
    result = tracker.on_command_ack(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, mavlink.MAV_RESULT_ACCEPTED, 1.2)
    assert result is not None and result.accepted and "ACCEPTED" in result.text
    assert tracker.pending == ()
    # a denied land, and a takeoff that is never acknowledged
    tracker.submit(tracker.build("land"), 2.0)  # type: ignore[arg-type]
    denied = tracker.on_command_ack(mavlink.MAV_CMD_NAV_LAND, mavlink.MAV_RESULT_DENIED, 2.1)
    assert denied is not None and not denied.accepted and "DENIED" in denied.text
    takeoff = tracker.build("takeoff")
    assert takeoff is not None and takeoff.params[6] == CommandsConfig().takeoff_altitude_m
    tracker.submit(takeoff, 3.0)
    failures = []
    for t in np.arange(3.0, 8.0, 0.1):
        failures += tracker.poll(float(t))[1]
    assert len(failures) == 1 and "no ack after 3 tries" in failures[0].text
    # unrelated acks are ignored
    assert tracker.on_command_ack(mavlink.MAV_CMD_NAV_TAKEOFF, mavlink.MAV_RESULT_ACCEPTED, 9.0) is None


def test_pan_scan_toggle_is_a_param_set_on_the_companion():
    tracker = CommandTracker(CommandsConfig())
    on = tracker.build("pan_scan_toggle", pan_scan_on=False)
    off = tracker.build("pan_scan_toggle", pan_scan_on=True)
    assert on is not None and off is not None
    assert on.kind == "param_set" and on.param_id == "PANSCAN_EN" and on.param_value == 1.0
    assert on.target_component == 191 and off.param_value == 0.0
    tracker.submit(on, 0.0)
    rejected = tracker.on_param_value("PANSCAN_EN", 0.0, 0.1)
    assert rejected is not None and not rejected.accepted
    tracker.submit(off, 1.0)
    ok = tracker.on_param_value("PANSCAN_EN", 0.0, 1.1)
    assert ok is not None and ok.accepted
