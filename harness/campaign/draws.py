"""Every random choice of one campaign flight, from its seed (pure but for :func:`write_flight_files`).

Flight ``i`` of a campaign with seed ``S`` draws from ``SeedSequence(S).spawn(N)[i]`` (the same as
``SeedSequence(S, spawn_key=(i,))``, so a flight's draws do not depend on N), split again into independent
streams for the arena, the operator, the vehicle and sensors, and the SITL's own seed. The draws go into
the flight's folder as the files the parts load (``scenario.yaml``, ``operator.yaml``, ``vehicle.yaml``,
``sitl.yaml``) and as one record, ``draws.json``.

Vehicle and sensor draws (the SITL's truth; the companion keeps its nominal model, so each is a model or
calibration error the stack must tolerate):

* mass ``mass_kg`` x U(0.9, 1.1) (``configs/vehicle.yaml``);
* camera mount ``camera.R_qc`` turned by U(-2, 2) deg about each body axis (``configs/vehicle.yaml``);
* IMU bias spreads ``imu_noise.accel_bias_init_m_s2`` and ``gyro_bias_init_rad_s`` x U(0.5, 2) (the
  biases themselves are drawn by the SITL from its seed, which is drawn here too; ``configs/sitl.yaml``);
* depth noise ``camera_noise.depth_sigma_per_m2`` (basic model) and the Xtion model's disparity noise
  ``camera_noise.xtion.disparity_sigma_px`` x U(0.5, 2) (``configs/sitl.yaml``, whose model is ``xtion``);
* a procedural arena's objects dark or specular (no return for the Xtion) with probability 0.15 each; glass, which
  the camera sees through, is drawn only by ``configs/scenarios/xtion-hazards.yaml`` (a known limit: docs/limits);
* the room height the operator enters into the companion (``reference.room_height_m``): the truth + U(-0.1, 0.1) m,
  or nothing at all (p = 0.15: only the altitude fence holds).

A real-time campaign can also starve the companion board (issue 30, ``quadlink campaign --realtime --cpu-share``):
the bridge's and the companion's CPU share, U(lo, hi) cores, and a busy neighbour beside the stack with a given
probability (:class:`Starvation`, from a sixth stream: the other draws stay as they were).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from harness.campaign.sessions import Session, generate_session
from quadlink import CONFIG_DIR
from sim_sitl.config import CameraNoiseConfig, ImuNoiseConfig, ScenarioConfig
from sim_sitl.scenario_gen import generate_scenario, scenario_to_dict

MASS_SPREAD = 0.10
CAMERA_TILT_DEG = 2.0
IMU_BIAS_SCALE = (0.5, 2.0)
DEPTH_NOISE_SCALE = (0.5, 2.0)
HAZARD_MATERIAL_P = 0.15
CAMPAIGN_HAZARDS = ("dark", "specular")
ROOM_HEIGHT_ENTRY_ERROR_M = 0.10  # +- of the operator's entry of the room's height
ROOM_HEIGHT_UNKNOWN_P = 0.15       # share of flights whose operator entered no height
CPU_SHARE_CORES = (0.3, 1.0)       # issue 30: the companion board's CPU share, cores (the campaign's default range)
CONTENTION_P = 0.5                 # share of starved flights with a busy process beside the stack


@dataclass(frozen=True)
class StarvationRange:
    """What a starved campaign draws from: the CPU share in ``[cores_lo, cores_hi]`` cores, a busy neighbour with
    probability ``contention_p``."""

    cores_lo: float = CPU_SHARE_CORES[0]
    cores_hi: float = CPU_SHARE_CORES[1]
    contention_p: float = CONTENTION_P

    def __post_init__(self) -> None:
        if not 0.01 <= self.cores_lo <= self.cores_hi <= 64.0:
            raise ValueError(f"a CPU share range of {self.cores_lo}..{self.cores_hi} cores is out of order or range "
                             "(0.01..64)")
        if not 0.0 <= self.contention_p <= 1.0:
            raise ValueError(f"a contention probability of {self.contention_p} is not in 0..1")


@dataclass(frozen=True)
class Starvation:
    """One flight's starved board: the bridge and the companion share ``cores`` of CPU (CFS bandwidth control,
    :class:`harness.cpu_share.CpuShare`), and ``busy_neighbours`` processes spin beside the stack."""

    cores: float
    busy_neighbours: int


def draw_starvation(rng: np.random.Generator, spread: StarvationRange) -> Starvation:
    cores = round(float(rng.uniform(spread.cores_lo, spread.cores_hi)), 3)
    return Starvation(cores, int(rng.random() < spread.contention_p))


def draw_room_height_error(rng: np.random.Generator) -> float | None:
    """The operator's entry of the room's height minus the truth (m); None: not entered."""
    if rng.random() < ROOM_HEIGHT_UNKNOWN_P:
        return None
    return round(float(rng.uniform(-ROOM_HEIGHT_ENTRY_ERROR_M, ROOM_HEIGHT_ENTRY_ERROR_M)), 3)


def _rot(axis: int, a_rad: float) -> np.ndarray:
    c, s = math.cos(a_rad), math.sin(a_rad)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    R = np.eye(3)
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    return R


def mount_turned(R_qc: list[list[float]], tilt_deg_xyz: list[float]) -> list[list[float]]:
    """The camera mount ``R_qc`` turned in the body frame by ``tilt_deg_xyz`` about x, then y, then z (YAML data)."""
    t = [math.radians(a) for a in tilt_deg_xyz]
    dR = _rot(2, t[2]) @ _rot(1, t[1]) @ _rot(0, t[0])
    R = dR @ np.asarray(R_qc, dtype=float)
    return [[round(float(v), 9) for v in row] for row in R]


@dataclass(frozen=True)
class FlightDraws:
    index: int
    campaign_seed: int
    scenario: ScenarioConfig
    session: Session
    vehicle: dict[str, Any]  # the vehicle config (YAML data) the SITL flies
    sitl: dict[str, Any]  # the SITL config (YAML data), without the file paths
    record: dict[str, Any]  # draws.json
    room_height_error_m: float | None = None  # the companion's room height entry - the truth; None: not entered
    starvation: Starvation | None = None  # a starved companion board (a real-time campaign's draw); None: not starved


def draw_flight(campaign_seed: int, index: int, duration_s: float, offboard_share: float = 0.0,
                fixed_share: float = 0.2, starve: StarvationRange | None = None) -> FlightDraws:
    seq = np.random.SeedSequence(campaign_seed, spawn_key=(index,))
    # a new stream leaves the others as they were (spawn(n)'s first children do not depend on n)
    arena_ss, operator_ss, vehicle_ss, sitl_ss, entry_ss, starve_ss = seq.spawn(6)
    arena = generate_scenario(np.random.default_rng(arena_ss), f"campaign-{campaign_seed}-{index:04d}", fixed_share,
                              HAZARD_MATERIAL_P, CAMPAIGN_HAZARDS)
    op_rng = np.random.default_rng(operator_ss)
    offboard = bool(op_rng.random() < offboard_share)
    session = generate_session(op_rng, arena.scenario, duration_s, offboard=offboard)
    vehicle, sitl, vehicle_record = draw_vehicle_and_sensors(vehicle_ss, sitl_ss)
    record = {
        "campaign_seed": campaign_seed, "index": index, "seed_sequence": {"entropy": seq.entropy,
                                                                          "spawn_key": list(seq.spawn_key)},
        "arena": arena.record, "operator": session.record, **vehicle_record,
    }
    room_height_error_m = draw_room_height_error(np.random.default_rng(entry_ss))
    record["room_height_entry_error_m"] = room_height_error_m
    starvation = draw_starvation(np.random.default_rng(starve_ss), starve) if starve is not None else None
    if starvation is not None:
        record["starvation"] = {"cpu_cores": starvation.cores, "busy_neighbours": starvation.busy_neighbours}
    return FlightDraws(index, campaign_seed, arena.scenario, session, vehicle, sitl, record, room_height_error_m,
                       starvation)


def draw_vehicle_and_sensors(vehicle_ss: np.random.SeedSequence, sitl_ss: np.random.SeedSequence,
                             ) -> tuple[dict[str, Any], dict[str, Any], dict[str, Any]]:
    """The vehicle config and the SITL config (YAML data, without file paths) of one flight, and their record
    (``vehicle`` and ``sitl_seed`` of draws.json): mass, camera mount, IMU bias spreads, depth noise, SITL seed."""
    rng = np.random.default_rng(vehicle_ss)
    vehicle = yaml.safe_load((CONFIG_DIR / "vehicle.yaml").read_text())
    mass_scale = float(rng.uniform(1 - MASS_SPREAD, 1 + MASS_SPREAD))
    vehicle["mass_kg"] = round(vehicle["mass_kg"] * mass_scale, 6)
    tilt_deg = [float(x) for x in rng.uniform(-CAMERA_TILT_DEG, CAMERA_TILT_DEG, 3)]
    vehicle["camera"]["R_qc"] = mount_turned(vehicle["camera"]["R_qc"], tilt_deg)
    imu_nominal, cam_nominal = ImuNoiseConfig(), CameraNoiseConfig()
    accel_scale, gyro_scale = (float(x) for x in rng.uniform(*IMU_BIAS_SCALE, 2))
    depth_scale = float(rng.uniform(*DEPTH_NOISE_SCALE))
    sitl = yaml.safe_load((CONFIG_DIR / "sitl.yaml").read_text())
    sitl_seed = int(np.random.default_rng(sitl_ss).integers(0, 2**31 - 1))
    sitl["seed"] = sitl_seed
    sitl.setdefault("imu_noise", {})
    sitl["imu_noise"]["accel_bias_init_m_s2"] = imu_nominal.accel_bias_init_m_s2 * accel_scale
    sitl["imu_noise"]["gyro_bias_init_rad_s"] = imu_nominal.gyro_bias_init_rad_s * gyro_scale
    sitl.setdefault("camera_noise", {})
    sitl["camera_noise"]["depth_sigma_per_m2"] = cam_nominal.depth_sigma_per_m2 * depth_scale
    sitl["camera_noise"].setdefault("xtion", {})
    sitl["camera_noise"]["xtion"]["disparity_sigma_px"] = cam_nominal.xtion.disparity_sigma_px * depth_scale
    record = {"vehicle": {"mass_scale": mass_scale, "mass_kg": vehicle["mass_kg"], "camera_tilt_deg_xyz": tilt_deg,
                          "accel_bias_sigma_scale": accel_scale, "gyro_bias_sigma_scale": gyro_scale,
                          "depth_noise_scale": depth_scale},
              "sitl_seed": sitl_seed}
    return vehicle, sitl, record


@dataclass(frozen=True)
class FlightFiles:
    scenario: Path
    operator: Path  # not written for an experiment flight (its ground-station client is the experiment's)
    vehicle: Path
    sitl: Path
    draws: Path


def write_flight_files(draws: FlightDraws, folder: Path) -> FlightFiles:
    """Write the configs the parts load, and ``draws.json``, into ``folder``."""
    files = write_sitl_files(draws.scenario, draws.vehicle, draws.sitl, draws.record, folder)
    files.operator.write_text(yaml.safe_dump(draws.session.script, sort_keys=False))
    return files


def write_sitl_files(scenario: ScenarioConfig, vehicle: dict[str, Any], sitl: dict[str, Any],
                     record: dict[str, Any], folder: Path) -> FlightFiles:
    """``scenario.yaml``, ``vehicle.yaml``, ``sitl.yaml`` (naming the other two) and ``draws.json`` in ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    files = FlightFiles(folder / "scenario.yaml", folder / "operator.yaml", folder / "vehicle.yaml",
                        folder / "sitl.yaml", folder / "draws.json")
    files.scenario.write_text(yaml.safe_dump(scenario_to_dict(scenario), sort_keys=False))
    files.vehicle.write_text(yaml.safe_dump(vehicle, sort_keys=False))
    sitl = {**sitl, "vehicle": str(files.vehicle.resolve()), "scenario": str(files.scenario.resolve())}
    files.sitl.write_text(yaml.safe_dump(sitl, sort_keys=False))
    files.draws.write_text(json.dumps(record, indent=2) + "\n")
    return files
