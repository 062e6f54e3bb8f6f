"""Typed YAML configuration: every kind of bad input gives one line naming the file and key."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import pytest

from quadlink.config import find_config, from_dict, load_config, to_dict
from quadlink.errors import ConfigError
from quadlink.vehicle import VehicleConfig, load_vehicle


@dataclass(frozen=True)
class Inner:
    gain: float = 1.0
    mode: Literal["a", "b"] = "a"


@dataclass(frozen=True)
class Outer:
    name: str
    count: int = 3
    enabled: bool = True
    inner: Inner = field(default_factory=Inner)
    offsets_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    tags: list[str] = field(default_factory=list)
    limit: float | None = None


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "cfg.yaml"
    path.write_text(text)
    return path


def test_loads_values_and_defaults(tmp_path: Path) -> None:
    cfg = load_config(write(tmp_path, "name: x\ninner: {gain: 2}\noffsets_m: [1, 2.5, 3]\n"), Outer)
    assert cfg == Outer(name="x", inner=Inner(gain=2.0), offsets_m=(1.0, 2.5, 3.0))
    assert isinstance(cfg.inner.gain, float)
    assert from_dict(Outer, to_dict(cfg)) == cfg


@pytest.mark.parametrize(
    ("text", "key", "fragment"),
    [
        ("name: x\ncuont: 3\n", "cuont", "unknown key"),
        ("name: x\ninner: {gian: 1}\n", "inner.gian", "unknown key"),
        ("name: x\ncount: 2.5\n", "count", "expected an integer"),
        ("name: x\nenabled: 1\n", "enabled", "true/false"),
        ("name: x\ninner: {gain: fast}\n", "inner.gain", "expected a number"),
        ("name: x\ninner: {mode: c}\n", "inner.mode", "must be one of"),
        ("name: x\noffsets_m: [1, 2]\n", "offsets_m", "expected 3 items"),
        ("count: 2\n", "name", "required key is missing"),
        ("name: x\nlimit: fast\n", "limit", "expected"),
    ],
)
def test_bad_keys_name_file_and_key(tmp_path: Path, text: str, key: str, fragment: str) -> None:
    path = write(tmp_path, text)
    with pytest.raises(ConfigError) as info:
        load_config(path, Outer)
    message = str(info.value)
    assert str(path) in message and f"'{key}'" in message and fragment in message
    assert "\n" not in message


def test_missing_file_and_bad_yaml(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "nope.yaml", Outer)
    with pytest.raises(ConfigError, match="cannot read YAML"):
        load_config(write(tmp_path, "name: [unclosed\n"), Outer)


def test_vehicle_config_is_consistent() -> None:
    vehicle = load_vehicle()
    defaults = VehicleConfig()  # the YAML states the defaults explicitly
    assert (vehicle.motor, vehicle.camera, vehicle.battery) == (defaults.motor, defaults.camera, defaults.battery)
    assert vehicle.imu.accel_lsb_m_s2 == pytest.approx(0.0039 * 9.80665, rel=1e-5)
    assert np.degrees(vehicle.imu.gyro_lsb_rad_s) == pytest.approx(0.586, rel=1e-5)
    # 10-bit ADC: full scale of +-2 g and +-300 deg/s
    assert 512 * vehicle.imu.accel_lsb_m_s2 == pytest.approx(2 * 9.80665, rel=0.01)
    assert np.degrees(512 * vehicle.imu.gyro_lsb_rad_s) == pytest.approx(300, rel=0.01)
    R = vehicle.camera.R_qc_matrix
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-5)
    # optical axis 45 deg right and 30 deg down in FRD
    axis = R @ np.array([0.0, 0.0, 1.0])
    assert np.degrees(np.arctan2(axis[1], axis[0])) == pytest.approx(45.0, abs=0.1)
    assert np.degrees(np.arcsin(axis[2])) == pytest.approx(30.0, abs=0.1)
    assert 0.4 < vehicle.hover_thrust_fraction < 0.6


def test_rotation_check_rejects_bad_extrinsics(tmp_path: Path) -> None:
    path = write(tmp_path, "camera:\n  R_qc: [[1, 0, 0], [0, 1, 0], [0, 0, 2]]\n")
    with pytest.raises(ConfigError, match="camera.*rotation"):
        load_config(path, VehicleConfig)


def test_find_config_lists_known_names() -> None:
    assert find_config("vehicle").name == "vehicle.yaml"
    with pytest.raises(ConfigError, match="known in"):
        find_config("no-such-config")


# --- hostile files (issue 16): each of these gave a traceback or was silently accepted -------------

@pytest.mark.parametrize(
    ("text", "key", "fragment"),
    [
        ("name: x\ninner: {gain: .nan}\n", "inner.gain", "finite"),
        ("name: x\ninner: {gain: .inf}\n", "inner.gain", "finite"),
        ("name: x\ninner: {gain: -.inf}\n", "inner.gain", "finite"),
        ("name: x\ncount: " + "9" * 400 + "\n", "count", "out of range"),
        ("name: x\ninner: {gain: " + "9" * 400 + "}\n", "inner.gain", "out of range"),
        ("name: x\n1: a\nzz: b\n", "1", "unknown key"),
    ],
)
def test_hostile_values_are_one_clear_error(tmp_path: Path, text: str, key: str, fragment: str) -> None:
    with pytest.raises(ConfigError) as info:
        load_config(write(tmp_path, text), Outer)
    message = str(info.value)
    assert "cfg.yaml" in message and f"'{key}'" in message and fragment in message
    assert "\n" not in message and len(message) < 400


def test_duplicate_keys_are_refused_with_their_line(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"cfg.yaml: .*duplicate key 'count' \(line 3\)"):
        load_config(write(tmp_path, "name: x\ncount: 1\ncount: 2\n"), Outer)
    with pytest.raises(ConfigError, match="duplicate key 'gain'"):
        load_config(write(tmp_path, "name: x\ninner:\n  gain: 1\n  gain: 2\n"), Outer)


def test_non_utf8_file_is_one_clear_error(tmp_path: Path) -> None:
    path = tmp_path / "cfg.yaml"
    path.write_bytes(b"name: caf\xe9\n")
    with pytest.raises(ConfigError, match=r"cfg.yaml: not UTF-8"):
        load_config(path, Outer)


@dataclass(frozen=True)
class Rated:
    rate_hz: float = 10.0
    mass_kg: float = 1.0
    offset_m: float = 0.0


@pytest.mark.parametrize(("text", "key"), [("rate_hz: 0\n", "rate_hz"), ("rate_hz: -5\n", "rate_hz"),
                                           ("mass_kg: -1\n", "mass_kg"), ("mass_kg: 0.0\n", "mass_kg")])
def test_rates_and_masses_must_be_positive(tmp_path: Path, text: str, key: str) -> None:
    with pytest.raises(ConfigError, match=rf"'{key}': must be > 0"):
        load_config(write(tmp_path, text), Rated)
    assert load_config(write(tmp_path, "offset_m: -1\n"), Rated).offset_m == -1.0  # other units may be negative


@pytest.mark.parametrize(("text", "key"), [
    ("mass_kg: -1\n", "mass_kg"),
    ("imu: {rate_hz: 0}\n", "imu.rate_hz"),
    ("battery: {cells: 0}\n", "battery"),
])
def test_vehicle_config_refuses_impossible_vehicles(tmp_path: Path, text: str, key: str) -> None:
    with pytest.raises(ConfigError, match=rf"'{key}'"):
        load_config(write(tmp_path, text), VehicleConfig)


def test_every_shipped_config_still_loads() -> None:
    from companion.config import load_companion_config
    from quadlink import CONFIG_DIR
    from sim_sitl.config import load_scenario, load_sitl_config
    from teleop.config import load_teleop_config

    load_vehicle()
    load_companion_config()
    load_sitl_config()
    load_teleop_config()
    for scenario in sorted((CONFIG_DIR / "scenarios").glob("*.yaml")):
        load_scenario(str(scenario))
