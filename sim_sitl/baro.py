"""The board's pressure sensor (pure; rng injected): height -> static pressure -> MPX4115A -> amplifier -> ADC6 volts.

Laws (``firmware/HARDWARE.md``): the International Standard Atmosphere's troposphere,
``P = P0 (1 - L h / T0)^(g M / (R L))``; the MPX4115A's transfer function ``V_sensor = Vs (0.009 P_kPa - 0.095)``
(Vs = 5.0 V); the board's amplifier ``V_adc = 2.5 + 10 (V_sensor - 4.05)``, clamped to the 0..5 V rails. On top
of the true pressure: the sensor's offset error (drawn once), a random-walk drift (temperature, weather) and
white noise (the sensor's output noise seen through the x10 amplifier), all in pascals.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

ADC_REF_V = 5.0   # the board's ADC reference (AVCC), firmware/HARDWARE.md


def adc_count(volts: float) -> int:
    """The 10-bit conversion of ``firmware/HARDWARE.md``: round(V / 5.0 V x 1024), clamped 0..1023."""
    return min(1023, max(0, round(volts / ADC_REF_V * 1024.0)))


SEA_LEVEL_PA = 101_325.0
SEA_LEVEL_K = 288.15
LAPSE_K_M = 0.0065
BARO_EXPONENT = 5.25588  # g M / (R L) for dry air
SUPPLY_V = 5.0
RAIL_LOW_V, RAIL_HIGH_V = 0.0, 5.0
AMP_OFFSET_V, AMP_GAIN, AMP_CENTRE_V = 2.5, 10.0, 4.05


def pressure_pa(altitude_m: float, sea_level_pa: float = SEA_LEVEL_PA) -> float:
    """Static pressure of the standard atmosphere at ``altitude_m`` above mean sea level (troposphere)."""
    return sea_level_pa * (1.0 - LAPSE_K_M * altitude_m / SEA_LEVEL_K) ** BARO_EXPONENT


def sensor_v(p_pa: float) -> float:
    """MPX4115A output (V) at ``p_pa`` (its nominal transfer function, 5.0 V supply)."""
    return SUPPLY_V * (0.009 * p_pa / 1000.0 - 0.095)


def amplified_v(v_sensor: float) -> float:
    """The board's amplifier stage and the ADC's rails: what ADC6 sees (V)."""
    return min(RAIL_HIGH_V, max(RAIL_LOW_V, AMP_OFFSET_V + AMP_GAIN * (v_sensor - AMP_CENTRE_V)))


def pressure_from_adc_v(v_adc: float) -> float:
    """The inverse of :func:`amplified_v` o :func:`sensor_v` inside the rails (Pa): what a firmware computes."""
    v_sensor = (v_adc - AMP_OFFSET_V) / AMP_GAIN + AMP_CENTRE_V
    return (v_sensor / SUPPLY_V + 0.095) / 0.009 * 1000.0


@dataclass(frozen=True)
class BaroConfig:
    """The pressure sensor's site and error model."""

    site_altitude_m: float = 120.0  # the arena floor above mean sea level (mid-range of the amplifier)
    sea_level_pa: float = SEA_LEVEL_PA  # the day's weather
    offset_sigma_pa: float = 150.0  # sensor offset error, drawn once (the firmware zeroes at arming)
    drift_pa_sqrt_s: float = 0.3  # random-walk drift density (about 2.5 cm/sqrt(s) of height)
    noise_pa: float = 4.0  # white noise per sample (about 0.35 m)


class BaroModel:
    """Call :meth:`measure` once per sample with the true height above the arena floor; returns ADC6's volts."""

    def __init__(self, cfg: BaroConfig, rng: np.random.Generator) -> None:
        self.cfg = cfg
        self.rng = rng
        self.offset_pa = float(rng.normal(0.0, cfg.offset_sigma_pa))
        self.drift_pa = 0.0
        self.last_pressure_pa = math.nan  # what the sensor measured (with its errors), for tests and logs

    def measure(self, height_m: float, dt_s: float) -> float:
        c = self.cfg
        self.drift_pa += c.drift_pa_sqrt_s * math.sqrt(max(dt_s, 0.0)) * float(self.rng.standard_normal())
        p = pressure_pa(c.site_altitude_m + height_m, c.sea_level_pa) + self.offset_pa + self.drift_pa \
            + c.noise_pa * float(self.rng.standard_normal())
        self.last_pressure_pa = p
        return amplified_v(sensor_v(p))
