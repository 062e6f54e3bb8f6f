"""The pure impairment model: statistics over many packets, FIFO order, reordering, rate limit."""

from __future__ import annotations

import numpy as np
import pytest

from harness.netem import DelayLine, Impairment, ImpairmentModel, parse_endpoint
from quadlink.errors import ConfigError

N = 10_000


def _run(imp: Impairment, seed: int = 7, period_s: float = 0.02, size: int = 40) -> tuple[np.ndarray, np.ndarray]:
    """Send N packets every period_s; returns (arrival times, release times with NaN for drops)."""
    model = ImpairmentModel(imp, np.random.default_rng(seed))
    t = np.arange(N) * period_s
    rel = np.array([np.nan if (r := model.submit(float(ti), size)) is None else r for ti in t])
    return t, rel


def test_delay_mean_and_jitter_match_the_configuration() -> None:
    # 10 Hz with a 10 ms jitter: FIFO order never binds, so the delays are the configured normal
    t, rel = _run(Impairment(delay_ms=150.0, jitter_ms=10.0), period_s=0.1)
    d_ms = (rel - t) * 1e3
    assert np.mean(d_ms) == pytest.approx(150.0, abs=0.5)
    assert np.std(d_ms) == pytest.approx(10.0, rel=0.05)
    assert np.all(d_ms >= 0)
    # at 50 Hz the FIFO holds a packet behind an earlier, slower one: same mean to within a ms, less spread
    t, rel = _run(Impairment(delay_ms=150.0, jitter_ms=10.0), period_s=0.02)
    d_ms = (rel - t) * 1e3
    assert 150.0 <= np.mean(d_ms) < 151.0 and 8.5 < np.std(d_ms) < 10.0


def test_correlated_jitter_keeps_mean_and_spread_on_a_fifo_link() -> None:
    # 50 Hz, 30 ms jitter: independent draws are clamped by the FIFO (mean up ~10 ms); with a 1 s
    # correlation time consecutive packets see nearly the same delay and the clamp almost never binds
    imp = Impairment(delay_ms=150.0, jitter_ms=30.0)
    t, rel = _run(imp, period_s=0.02)
    assert np.mean((rel - t) * 1e3) > 157.0
    t, rel = _run(Impairment(delay_ms=150.0, jitter_ms=30.0, jitter_correlation_s=1.0), period_s=0.02)
    d_ms = (rel - t) * 1e3
    assert np.mean(d_ms) == pytest.approx(150.0, abs=5.0)       # 200 s of 1 s-correlated samples
    assert np.std(d_ms) == pytest.approx(30.0, rel=0.15)
    assert np.all(np.diff(rel) >= 0)
    # and the correlation is there: neighbours' delays nearly equal
    assert np.corrcoef(d_ms[:-1], d_ms[1:])[0, 1] > 0.95


def test_jitter_alone_never_reorders_but_reorder_does() -> None:
    # jitter (30 ms) larger than the packet spacing (2 ms): an unordered link would swap most packets
    _, rel = _run(Impairment(delay_ms=100.0, jitter_ms=30.0), period_s=0.002)
    assert np.all(np.diff(rel) >= 0)
    model = ImpairmentModel(Impairment(delay_ms=100.0, jitter_ms=5.0, reorder=0.02, reorder_gap_ms=25.0),
                            np.random.default_rng(3))
    rel2 = np.array([model.submit(i * 0.002, 40) for i in range(N)], dtype=float)
    order = np.argsort(rel2, kind="stable")
    overtaken = int(np.sum(order != np.arange(N)))
    assert model.stats.reordered == pytest.approx(0.02 * N, rel=0.15)
    assert overtaken > model.stats.reordered       # each held packet is passed by several later ones


def test_loss_fraction_and_seed_reproducibility() -> None:
    _, rel = _run(Impairment(delay_ms=20.0, loss=0.05), seed=11)
    lost = np.isnan(rel)
    assert lost.mean() == pytest.approx(0.05, abs=0.006)
    _, again = _run(Impairment(delay_ms=20.0, loss=0.05), seed=11)
    np.testing.assert_array_equal(np.isnan(again), lost)
    _, other = _run(Impairment(delay_ms=20.0, loss=0.05), seed=12)
    assert not np.array_equal(np.isnan(other), lost)


def test_rate_limit_is_honoured() -> None:
    # 1000-byte packets offered at 400 kbit/s to a 100 kbit/s link: the output is paced at the rate
    imp = Impairment(delay_ms=10.0, rate_kbit_s=100.0, queue_limit=10_000)
    model = ImpairmentModel(imp, np.random.default_rng(0))
    n, size = 2000, 1000
    rel = np.array([model.submit(i * 0.02, size) for i in range(n)], dtype=float)
    throughput_kbit_s = (n - 1) * size * 8 / (rel[-1] - rel[0]) / 1000.0
    assert throughput_kbit_s == pytest.approx(100.0, rel=1e-6)
    np.testing.assert_allclose(np.diff(rel), size * 8 / 100e3)        # serialisation time, back to back
    # below the rate the link only adds the serialisation time of each packet
    slow = ImpairmentModel(imp, np.random.default_rng(0))
    assert slow.submit(0.0, 100) == pytest.approx(0.010 + 100 * 8 / 100e3)
    assert slow.submit(1.0, 100) == pytest.approx(1.010 + 100 * 8 / 100e3)


def test_full_queue_drops() -> None:
    model = ImpairmentModel(Impairment(rate_kbit_s=8.0, queue_limit=5), np.random.default_rng(0))
    out = [model.submit(0.0, 1000) for _ in range(10)]                # 1 s per packet on the wire
    assert sum(r is None for r in out) == 5 and model.stats.dropped_queue == 5
    assert model.submit(10.0, 1000) is not None                         # the queue drained meanwhile


def test_identity_and_validation() -> None:
    model = ImpairmentModel(Impairment(), np.random.default_rng(0))
    assert Impairment().is_identity and model.submit(1.5, 10) == 1.5
    with pytest.raises(ValueError):
        model.submit(1.0, 10)                                           # time went backwards
    for bad in (dict(loss=1.0), dict(delay_ms=-1.0), dict(reorder=1.5), dict(jitter_ms=float("nan"))):
        with pytest.raises(ConfigError):
            Impairment(**bad)  # type: ignore[arg-type]
    assert parse_endpoint("udp:127.0.0.1:14550") == ("udp", "127.0.0.1", 14550)
    for bad_url in ("udp:127.0.0.1", "http:1.2.3.4:5", "tcp:host:99999"):
        with pytest.raises(ConfigError):
            parse_endpoint(bad_url)


def test_delay_line_releases_in_time_order() -> None:
    line: DelayLine[str] = DelayLine()
    line.push(2.0, "b")
    line.push(1.0, "a")
    line.push(2.0, "c")
    assert line.next_release_s() == 1.0 and line.pop_due(0.5) == []
    assert line.pop_due(2.0) == ["a", "b", "c"] and len(line) == 0
