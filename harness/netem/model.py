"""Network impairment model, pure: packets in (arrival time, size), release times out. No I/O, no clock.

One direction of a link, in the order a packet meets the impairments:

1. **loss**: the packet is dropped with probability ``loss`` (independent, Bernoulli). A lost packet does
   not use the link.
2. **rate**: the link serialises ``size_bytes * 8 / rate_kbit_s`` seconds per packet, one packet at a time
   (a FIFO transmit queue; a packet arriving while ``queue_limit`` packets wait is dropped, like a full
   qdisc). ``rate_kbit_s = 0`` is an unlimited link.
3. **delay and jitter**: propagation delay ``delay_ms + x``, clipped at 0, with ``x`` normal of standard
   deviation ``jitter_ms`` (like ``tc netem delay D J distribution normal``): independent per packet by
   default, or a Gauss-Markov process of correlation time ``jitter_correlation_s`` (a queue that builds
   up and drains: consecutive packets see nearly the same delay).
4. **order**: the link is FIFO: a packet is never released before the one sent just before it, so jitter
   alone never reorders (unlike plain ``tc netem`` with jitter). With probability ``reorder`` a packet
   instead leaves the FIFO and is held ``reorder_gap_ms`` longer, so the packets sent after it overtake
   it: reordering happens only when configured. A FIFO link holds a packet behind an earlier, slower one,
   so when independent jitter is comparable to the packet spacing the delays spread less than
   ``jitter_ms`` and their mean rises (50 Hz: 10 ms jitter gives 9.4 ms spread and +0.5 ms mean; 30 ms
   jitter gives about 24 ms and +10 ms; 500 Hz, 30 ms: 17 ms and +41 ms). Correlated jitter
   (``jitter_correlation_s`` well above the packet spacing) keeps the configured mean and spread.

Times are seconds on the caller's clock; the random generator is injected (``numpy.random.Generator``),
so a seed reproduces every drop, delay and swap. :class:`DelayLine` is the matching pure scheduler:
payloads held until their release time.
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass
from typing import Generic, TypeVar

import numpy as np

from quadlink.errors import ConfigError

T = TypeVar("T")


@dataclass(frozen=True)
class Impairment:
    """Impairments of one direction of a link (SI-ish units in the names)."""

    delay_ms: float = 0.0          # one-way propagation delay (mean)
    jitter_ms: float = 0.0         # standard deviation of the delay (normal)
    loss: float = 0.0              # drop probability per packet, [0, 1)
    reorder: float = 0.0           # probability that a packet is held back and overtaken, [0, 1]
    reorder_gap_ms: float = 25.0   # how much longer a reordered packet is held
    jitter_correlation_s: float = 0.0  # correlation time of the jitter; 0 = independent per packet
    rate_kbit_s: float = 0.0       # link rate in kbit/s (1000 bit/s); 0 = unlimited
    queue_limit: int = 1000        # packets waiting for the rate-limited link before drops

    def __post_init__(self) -> None:
        values = (self.delay_ms, self.jitter_ms, self.loss, self.reorder, self.reorder_gap_ms, self.rate_kbit_s,
                  self.jitter_correlation_s)
        if not all(math.isfinite(v) for v in values):
            raise ConfigError("netem: impairment values must be finite")
        if min(self.delay_ms, self.jitter_ms, self.reorder_gap_ms, self.rate_kbit_s, self.jitter_correlation_s) < 0:
            raise ConfigError("netem: delay, jitter, its correlation time, reorder gap and rate must be >= 0")
        if not 0.0 <= self.loss < 1.0:
            raise ConfigError(f"netem: loss {self.loss} must be in [0, 1)")
        if not 0.0 <= self.reorder <= 1.0:
            raise ConfigError(f"netem: reorder {self.reorder} must be in [0, 1]")
        if self.queue_limit < 1:
            raise ConfigError("netem: queue_limit must be >= 1")

    @property
    def is_identity(self) -> bool:
        return (self.delay_ms == 0 and self.jitter_ms == 0 and self.loss == 0 and self.reorder == 0
                and self.rate_kbit_s == 0)


@dataclass
class ImpairmentStats:
    """Counters of one direction (mutable: the model's running account)."""

    packets_in: int = 0
    bytes_in: int = 0
    dropped_loss: int = 0
    dropped_queue: int = 0
    reordered: int = 0
    delay_sum_s: float = 0.0       # sum of (release - arrival) over released packets

    @property
    def released(self) -> int:
        return self.packets_in - self.dropped_loss - self.dropped_queue

    @property
    def mean_delay_s(self) -> float:
        return self.delay_sum_s / self.released if self.released else math.nan


class ImpairmentModel:
    """One direction of an impaired link. ``submit(t, size)`` -> release time, or None if dropped.

    Arrival times must not decrease (the order the caller received the packets in).
    """

    def __init__(self, impairment: Impairment, rng: np.random.Generator) -> None:
        self.cfg = impairment
        self._rng = rng
        self.stats = ImpairmentStats()
        self._link_free_s = -math.inf          # when the rate-limited link finishes its current packet
        self._tx_done_s: list[float] = []      # heap: transmit-done times of queued packets (queue length)
        self._last_fifo_release_s = -math.inf
        self._last_arrival_s = -math.inf
        self._jitter_s = 0.0                   # the correlated jitter's current value
        self._jitter_t_s: float | None = None

    def submit(self, t_arrival_s: float, size_bytes: int) -> float | None:
        cfg = self.cfg
        if t_arrival_s < self._last_arrival_s:
            raise ValueError(f"netem: arrival time went backwards ({t_arrival_s} < {self._last_arrival_s})")
        self._last_arrival_s = t_arrival_s
        self.stats.packets_in += 1
        self.stats.bytes_in += size_bytes
        if cfg.loss > 0 and self._rng.random() < cfg.loss:
            self.stats.dropped_loss += 1
            return None
        t_sent = t_arrival_s
        if cfg.rate_kbit_s > 0:
            while self._tx_done_s and self._tx_done_s[0] <= t_arrival_s:
                heapq.heappop(self._tx_done_s)
            if len(self._tx_done_s) >= cfg.queue_limit:
                self.stats.dropped_queue += 1
                return None
            t_sent = max(t_arrival_s, self._link_free_s) + size_bytes * 8.0 / (cfg.rate_kbit_s * 1000.0)
            self._link_free_s = t_sent
            heapq.heappush(self._tx_done_s, t_sent)
        delay_s = cfg.delay_ms * 1e-3
        if cfg.jitter_ms > 0:
            delay_s = max(0.0, delay_s + self._jitter(t_arrival_s))
        candidate = t_sent + delay_s
        if cfg.reorder > 0 and self._rng.random() < cfg.reorder:
            self.stats.reordered += 1
            release = candidate + cfg.reorder_gap_ms * 1e-3      # out of the FIFO: later packets pass it
        else:
            release = max(candidate, self._last_fifo_release_s)  # FIFO: jitter never reorders
            self._last_fifo_release_s = release
        self.stats.delay_sum_s += release - t_arrival_s
        return release


    def _jitter(self, t_s: float) -> float:
        sigma_s = self.cfg.jitter_ms * 1e-3
        tau_s = self.cfg.jitter_correlation_s
        if tau_s <= 0.0:
            return float(self._rng.normal(0.0, sigma_s))
        if self._jitter_t_s is None:                       # start in the stationary distribution
            self._jitter_s = float(self._rng.normal(0.0, sigma_s))
        else:                                              # exact Gauss-Markov (OU) step over the gap
            rho = math.exp(-(t_s - self._jitter_t_s) / tau_s)
            self._jitter_s = rho * self._jitter_s + math.sqrt(1.0 - rho * rho) * float(self._rng.normal(0.0, sigma_s))
        self._jitter_t_s = t_s
        return self._jitter_s


class DelayLine(Generic[T]):
    """Payloads held until their release time (pure: the caller says what time it is)."""

    def __init__(self) -> None:
        self._heap: list[tuple[float, int, T]] = []
        self._n = 0

    def push(self, release_s: float, payload: T) -> None:
        heapq.heappush(self._heap, (release_s, self._n, payload))   # n: equal times keep submit order
        self._n += 1

    def pop_due(self, now_s: float) -> list[T]:
        out = []
        while self._heap and self._heap[0][0] <= now_s:
            out.append(heapq.heappop(self._heap)[2])
        return out

    def next_release_s(self) -> float | None:
        return self._heap[0][0] if self._heap else None

    def __len__(self) -> int:
        return len(self._heap)
