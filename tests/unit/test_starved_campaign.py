"""Issue 30, a starved campaign without a flight: the CPU-share draw, its options and CLI, the companion's data age
read back from its tlog, and the clearance-and-latency-by-share table."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import click
import numpy as np
import pytest

from harness.campaign.cli import parse_cpu_share
from harness.campaign.draws import StarvationRange, draw_flight
from harness.campaign.report import by_cpu_share, by_cpu_share_text
from harness.campaign.runner import CampaignOptions
from harness.demo.report import FlightLog, data_age_figures, load_flight
from quadlink.mavlink import mavlink
from quadlink.mavlink.tlog import TlogWriter


def test_the_starvation_draw_leaves_every_other_draw_as_it_was() -> None:
    plain = draw_flight(7, 3, 30.0)
    starved = draw_flight(7, 3, 30.0, starve=StarvationRange(0.3, 1.0, 0.5))
    assert plain.starvation is None and "starvation" not in plain.record
    assert starved.starvation is not None
    rest = {k: v for k, v in starved.record.items() if k != "starvation"}
    assert rest == plain.record
    assert starved.record["starvation"] == {"cpu_cores": starved.starvation.cores,
                                            "busy_neighbours": starved.starvation.busy_neighbours}


def test_the_cpu_share_is_drawn_over_its_range_and_the_neighbour_at_its_rate() -> None:
    spread = StarvationRange(0.3, 1.0, 0.5)
    draws = [draw_flight(11, i, 30.0, starve=spread).starvation for i in range(200)]
    cores = np.array([d.cores for d in draws if d is not None])
    busy = np.array([d.busy_neighbours for d in draws if d is not None])
    assert cores.size == 200 and cores.min() >= 0.3 and cores.max() <= 1.0
    assert cores.min() < 0.4 and cores.max() > 0.9          # the whole range is sampled, not one corner
    assert set(busy.tolist()) == {0, 1} and 0.35 < busy.mean() < 0.65
    assert [d.cores for d in draws[:5]] == [draw_flight(11, i, 30.0, starve=spread).starvation.cores  # type: ignore[union-attr]
                                            for i in range(5)]
    fixed = draw_flight(11, 4, 30.0, starve=StarvationRange(0.35, 0.35, 1.0)).starvation
    assert fixed is not None and fixed.cores == 0.35 and fixed.busy_neighbours == 1


@pytest.mark.parametrize("lo, hi, p", [(0.5, 0.3, 0.5), (0.0, 1.0, 0.5), (0.3, 1.0, 1.5), (math.nan, 1.0, 0.5)])
def test_a_range_out_of_order_or_bounds_is_refused(lo: float, hi: float, p: float) -> None:
    with pytest.raises(ValueError):
        StarvationRange(lo, hi, p)


def test_a_starved_campaign_flies_in_real_time_only(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="real time"):
        CampaignOptions(1, 0, tmp_path, starve=StarvationRange())
    assert CampaignOptions(1, 0, tmp_path, realtime=True, deterministic=False, starve=StarvationRange()).starve


def test_the_cli_parses_a_range_or_one_share_and_refuses_the_rest() -> None:
    assert parse_cpu_share("0.3:1.0", 0.5, True, "teleop") == StarvationRange(0.3, 1.0, 0.5)
    assert parse_cpu_share("0.35", 1.0, True, "teleop") == StarvationRange(0.35, 0.35, 1.0)
    with pytest.raises(click.UsageError, match="--realtime"):
        parse_cpu_share("0.3:1.0", 0.5, False, "teleop")
    with pytest.raises(click.UsageError, match="teleop"):
        parse_cpu_share("0.3:1.0", 0.5, True, "paper003-oval")
    for bad in ("fast", "0.3:1.0:2", "1.0:0.3", ""):
        with pytest.raises(click.BadParameter):
            parse_cpu_share(bad, 0.5, True, "teleop")


def test_the_companions_data_age_is_read_back_from_its_tlog(tmp_path: Path) -> None:
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=191)
    ages_s = [0.010, 0.020, 0.030, 0.040, 0.250]
    with TlogWriter(tmp_path / "companion.tlog") as w:
        for k, age in enumerate(ages_s):
            w.write(mavlink.MAVLink_named_value_float_message(k * 1000, b"DATA_AGE", age).pack(mav), 0.0)
            w.write(mavlink.MAVLink_named_value_int_message(k * 1000, b"LATE_HOLD", int(age > 0.2)).pack(mav), 0.0)
            w.write(mavlink.MAVLink_named_value_float_message(k * 1000, b"CMD_AGE50", 0.5).pack(mav), 0.0)
    flight = load_flight(tmp_path)
    assert flight.data_age_s.tolist() == pytest.approx(ages_s)
    fig = data_age_figures(flight)
    assert fig["p50"] == pytest.approx(30.0) and fig["max"] == pytest.approx(250.0)
    assert fig["samples"] == 5 and fig["late_hold_share"] == pytest.approx(0.2)
    assert data_age_figures(FlightLog()) == {}


def test_the_odometrys_counts_since_the_start_and_in_the_air_are_read_back_from_its_tlog(tmp_path: Path) -> None:
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=191)
    with TlogWriter(tmp_path / "companion.tlog") as w:
        for k, (total, air) in enumerate(((120, 0), (205, 3))):   # the last value of each name is the flight's
            w.write(mavlink.MAVLink_named_value_int_message(k * 1000, b"ODO_BRIDGE", total).pack(mav), 0.0)
            w.write(mavlink.MAVLink_named_value_int_message(k * 1000, b"AIR_BRIDGE", air).pack(mav), 0.0)
            w.write(mavlink.MAVLink_named_value_int_message(k * 1000, b"AIR_JUMP", k).pack(mav), 0.0)
    assert load_flight(tmp_path).odometry_counts == {"ODO_BRIDGE": 205, "AIR_BRIDGE": 3, "AIR_JUMP": 1}


def _row(cores: float, d: float, age: float, busy: int = 1) -> dict[str, Any]:
    return {"cpu_share_cores": cores, "busy_neighbours": busy, "min_nonfloor_distance_m": d,
            "data_age_p50_ms": age, "data_age_max_ms": 3 * age}


def test_the_table_bins_flights_by_cpu_share_and_counts_the_ones_below_the_bound() -> None:
    rows = [_row(0.31, 0.39, 40.0), _row(0.44, 0.52, 30.0, 0), _row(0.5, 0.55, 12.0), _row(0.95, 0.6, 8.0),
            {"cpu_share_cores": math.nan, "min_nonfloor_distance_m": 0.1}]   # not starved: in no row
    table = by_cpu_share(rows)
    assert [b["flights"] for b in table] == [2, 1, 1]
    low = table[0]
    assert low["min_nonfloor_distance_m"] == pytest.approx(0.39) and low["below_target"] == 1
    assert low["with_busy_neighbour"] == 1 and low["data_age_max_ms"] == pytest.approx(120.0)
    assert low["data_age_p50_ms_median"] == pytest.approx(35.0)
    assert by_cpu_share([rows[-1]]) == []
    assert "0.00-0.45" in by_cpu_share_text(table)
