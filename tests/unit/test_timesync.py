"""The shared TIMESYNC estimator (quadlink.mavlink.timesync) over simulated links with jitter and loss."""

from __future__ import annotations

import numpy as np
import pytest

from harness.netem import Impairment, ImpairmentModel
from quadlink.mavlink import mavlink
from quadlink.mavlink.timesync import (
    TimesyncConfig,
    TimesyncEstimator,
    answer_fields,
    is_request,
    request_fields,
)

NS = 1_000_000_000


def _exchange(est: TimesyncEstimator, up: ImpairmentModel, down: ImpairmentModel, t_local_s: float,
              peer_offset_s: float) -> None:
    """One request at local time t through the impaired link; the peer answers with its clock."""
    tc1, ts1 = request_fields(int(t_local_s * NS))
    assert is_request(tc1)
    arrive = up.submit(t_local_s, 20)
    if arrive is None:
        return
    tc1, ts1 = answer_fields(ts1, int((arrive + peer_offset_s) * NS))   # the peer's clock at arrival
    back = down.submit(arrive, 20)
    if back is not None:
        est.on_response(tc1, ts1, int(back * NS))


def test_offset_and_rtt_through_a_jittery_lossy_link() -> None:
    # 150 ms each way, 30 ms jitter, 5 % loss, peer clock 1234.5 s ahead: the demo link
    imp = Impairment(delay_ms=150.0, jitter_ms=30.0, loss=0.05)
    rng = np.random.default_rng(2)
    up, down = ImpairmentModel(imp, rng), ImpairmentModel(imp, np.random.default_rng(3))
    est = TimesyncEstimator()
    for k in range(120):
        _exchange(est, up, down, 10.0 + k * 0.5, 1234.5)
    assert est.offset_ns is not None
    # the min-round-trip sample's asymmetry error is at most its rtt / 2 and in practice much less
    assert abs(est.offset_ns / NS - 1234.5) < 0.03
    assert est.rtt_percentile_s(50) == pytest.approx(0.300, abs=0.02)
    assert est.rtt_filtered_s == pytest.approx(0.300, abs=0.06)
    assert est.accepted > 100 and est.accepted + est.rejected_rtt + est.rejected_outliers <= 120
    assert est.to_local_s(est.to_remote_s(5.0) or 0.0) == pytest.approx(5.0)


def test_outliers_are_rejected_and_a_clock_jump_restarts() -> None:
    est = TimesyncEstimator(TimesyncConfig(max_consecutive_outliers=3))
    off = 7 * NS
    for k in range(5):
        t = (k + 1) * NS
        assert est.on_response(t + 10_000_000 + off, t, t + 20_000_000)        # 20 ms round trip
    assert est.offset_ns == off
    t = 10 * NS
    assert not est.on_response(t + 10_000_000 + off + NS, t, t + 20_000_000)   # one 1 s jump: outlier
    assert est.offset_ns == off and est.rejected_outliers == 1
    for k in range(2):                                                          # two more: restart
        t = (11 + k) * NS
        assert not est.on_response(t + 10_000_000 + off + NS, t, t + 20_000_000)
    assert est.resets == 1 and est.offset_ns is None
    t = 20 * NS
    assert est.on_response(t + 10_000_000 + off + NS, t, t + 20_000_000)       # the new clock
    assert est.offset_ns == off + NS
    assert not est.on_response(t, t, t + 3 * NS)                               # round trip above 2 s


def test_fields_fit_the_dialect_message() -> None:
    mav = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
    req = mav.timesync_encode(*request_fields(123))
    ans = mav.timesync_encode(*answer_fields(req.ts1, 456))
    parsed = mavlink.MAVLink(None).decode(bytearray(ans.pack(mav)))
    assert (req.tc1, req.ts1) == (0, 123) and (parsed.tc1, parsed.ts1) == (456, 123)
    assert not is_request(parsed.tc1)
