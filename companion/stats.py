"""The daemon's counters and its progress line (:class:`ProgressLine`, logged every :data:`PROGRESS_EVERY_S`)."""

from __future__ import annotations

from dataclasses import dataclass, field

from perception.odometry import OdometryCounts

PROGRESS_EVERY_S = 5.0


def _recent_median_ms(values_s: list[float], n: int = 300) -> str:
    """Median of the last ``n`` durations, for the status line."""
    recent = sorted(values_s[-n:])
    return f"{recent[len(recent) // 2] * 1e3:.1f} ms" if recent else "-"


def _recent_max_ms(values_s: list[float], n: int = 300) -> str:
    """Largest of the last ``n`` durations, for the status line."""
    recent = values_s[-n:]
    return f"{max(recent) * 1e3:.1f} ms" if recent else "-"


@dataclass
class Stats:
    frames: int = 0
    setpoints: int = 0
    feedback: int = 0
    routed_to_gcs: int = 0
    routed_to_autopilot: int = 0
    manual_controls: int = 0
    pipeline_errors: int = 0
    handler_errors: int = 0         # unexpected exceptions caught in one message's handling (companion.guard)
    non_finite_dropped: int = 0     # messages for the autopilot refused for a non-finite field
    forward_refused: int = 0        # ground-station messages for the autopilot refused for a non-finite value
    gcs_bad_data: int = 0           # undecodable or refused by signing (unsigned, wrong key, replayed)
    refused_senders: int = 0        # state-changing messages from system ids not on the allowlist
    latencies_s: list[float] = field(default_factory=list)
    perception_s: list[float] = field(default_factory=list)
    data_ages_s: list[float] = field(default_factory=list)   # camera stamp -> setpoint (companion.latency)
    frames_skipped: int = 0         # frames read past to process the newest (a backlog is never processed)

    def summary(self, odometry_ok: bool, gcs_ok: bool, odometry_counts: str = "") -> str:
        counts = f" ({odometry_counts})" if odometry_counts else ""
        return (f"frame->setpoint p50 {_recent_median_ms(self.latencies_s)} "
                f"(perception {_recent_median_ms(self.perception_s)}, data age p50 "
                f"{_recent_median_ms(self.data_ages_s)} max {_recent_max_ms(self.data_ages_s)}, skipped "
                f"{self.frames_skipped})  odometry {'ok' if odometry_ok else 'FAIL'}{counts}  "
                f"gcs link {'ok' if gcs_ok else 'lost'}  manual {self.manual_controls}  "
                f"routed {self.routed_to_gcs} to GCS / {self.routed_to_autopilot} to autopilot")

    def trim(self, keep: int = 2000, limit: int = 20000) -> None:
        """Bound the duration lists of a long run."""
        if len(self.latencies_s) > limit:
            del self.latencies_s[:-keep]
            del self.perception_s[:-keep]
        if len(self.data_ages_s) > limit:
            del self.data_ages_s[:-keep]


class ProgressLine:
    """The status line logged every ``period_s``: the mode, the camera's rate since the last line, the counters
    (:meth:`Stats.summary`), the height and the ground stations' command figures."""

    def __init__(self, period_s: float = PROGRESS_EVERY_S) -> None:
        self.period_s = period_s
        self._frames = 0

    def line(self, stats: Stats, mode_name: str, odometry_ok: bool, gcs_ok: bool, height: str, commands: str,
             odometry_counts: str = "") -> str:
        fps = (stats.frames - self._frames) / self.period_s
        self._frames = stats.frames
        return (f"mode {mode_name}  camera {fps:.1f} fps  {stats.summary(odometry_ok, gcs_ok, odometry_counts)}  "
                f"{height}  {commands}")


class AirborneCounts:
    """The odometry's counts (:class:`perception.odometry.OdometryCounts`) of the frames taken while the vehicle is
    off the ground: the odometry's own totals include the frames on the ground before a take-off (a camera close to
    the floor: 100-300 bridged frames a flight in the SITL), which hide what it did in the air."""

    def __init__(self) -> None:
        self.counts = OdometryCounts()
        self._last: OdometryCounts | None = None

    def on_output(self, counts: OdometryCounts, airborne: bool) -> None:
        """A frame's output with the odometry's totals as they stood at it; ``airborne``: the vehicle was off the
        ground for it (its counts since the last output are the air's)."""
        if airborne and self._last is not None:
            self.counts = self.counts.plus(counts.since(self._last))
        self._last = counts
