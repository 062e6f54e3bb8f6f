"""Issue 18: a short demo flight over an impaired ground link (netem proxies for MAVLink and the image stream,
150 ms one way, 30 ms jitter, 5 % loss, the passivity controller on): the vehicle flies the short script, its
safety and estimation figures hold against the SITL's truth, and the report carries the link figures measured
by the station (TIMESYNC round trip), the proxy (loss) and the companion (command ages)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from harness.demo.cli import run_demo
from harness.demo.link import LinkImpairment
from harness.ports import free_port_offset
from quadlink import CONFIG_DIR

pytestmark = [pytest.mark.sitl, pytest.mark.slow]   # ~40 s simulated, minutes of wall time on a loaded machine

OFFSET = free_port_offset()   # harness.ports: free now, reserved for this session


def test_short_flight_over_a_delayed_lossy_link(tmp_path: Path) -> None:
    out = tmp_path / "report"
    link = LinkImpairment(delay_ms=150.0, jitter_ms=30.0, loss=0.05, seed=3)
    report = run_demo("paper-arena", duration_s=40.0, out_dir=out,
                      script=CONFIG_DIR / "teleop_scripts" / "demo_short.yaml", lockstep=True,
                      port_offset=OFFSET, progress_every_s=10.0, link=link)
    assert report["failure"] is None and not report["interrupted"]
    assert report["flying_time_s"] > 5.0
    assert report["min_true_clearance_m"] >= 0.40
    assert report["setpoint_gaps_over_100ms"] == 0
    lk = report["link"]
    # round trip: both directions of 150 ms through the proxy, plus the loops' scheduling
    assert 300.0 <= lk["rtt_ms"]["p50"] <= 450.0
    # loss: the proxy's own count, near the configured 5 % over thousands of datagrams
    assert lk["loss"]["uplink_packets"] > 1000
    assert 0.03 <= lk["loss"]["uplink"] <= 0.07
    # the companion aged the stamped commands: ~150 ms one way, nearly all accepted under the 0.5 s age
    c = lk["commands"]
    assert c["accepted"] > 500 and c["stale"] <= 0.01 * c["accepted"]
    assert 120.0 <= c["age_p50_ms"] <= 300.0
    # the force port stayed passive within epsilon with the controller on
    assert lk["passivity"]["min_observed_j"] >= -1e-3
    assert report["targets"]["passivity_min_observed_energy_j"]["pass"]
    assert (out / "handle_delay.png").stat().st_size > 10_000
    assert json.loads((out / "link.json").read_text())["impairment"]["delay_ms"] == 150.0
