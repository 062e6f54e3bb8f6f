"""Late data is unsafe data: the age of what a setpoint is built from, and what the safety law pays for it (pure).

Every setpoint is built from a camera frame; by the time it leaves, the frame is ``age_s`` old (capture, transport,
queueing, perception). The reference law's stopping distance (:mod:`companion.avoidance`, ``stopping_time_s``)
assumes ``nominal_s`` of it — the companion's own latency on an unloaded board. A starved CPU (issue 30: a 0.35-core
share and a busy neighbour took frame-to-setpoint from 8 to 25 ms and perception from 7 to 19 ms, and the vehicle
flew on at the operator's speed into a wall) makes it larger, and the law must know:

* the stopping time grows by the excess, ``stopping_time_s + max(0, age_s - nominal_s)`` (PX4's ``CP_DELAY`` with a
  user-entered delay; here it is measured, frame by frame);
* the speed limit falls linearly from ``max_speed_m_s`` at ``nominal_s`` to nothing at ``hold_s``;
* past ``hold_s`` for ``hold_after_frames`` frames in a row the companion holds (no operator or script motion; the
  repulsion still acts), says so, and resumes once ``resume_after_s`` of frames younger than ``resume_s`` have
  passed (hysteresis: a flickering link does not toggle the vehicle).

* the map's drift margin (``map_drift_m_s``, :func:`companion.obstacle_points.drifted_toward`) grows with the frames
  the companion had to skip: the odometry that carries an unseen wall along (eq. 14) measures the velocity from the
  frames it processes, and with one in ``g`` processed its error runs longer between corrections. The margin is
  scaled by the running mean of the sequence gap between processed frames (1 when none is skipped), up to
  ``max_drift_scale`` (issue 30: on a starved CPU a wall the camera had panned away from read 5 cm far after 2 s
  unseen, 2.5 x the unloaded drift the margin covers, and the vehicle sliding along it came to 0.393 m).

The age is measured on the autopilot's clock (the IMU stream's stamps), so it is the same number in real time, in
lock-step and in a replay.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class LatencyParams:
    nominal_s: float = 0.10          # the age the reference law's stopping_time_s already covers
    hold_s: float = 0.35             # older than this: no commanded motion
    resume_s: float = 0.20           # ... until frames are younger than this again
    hold_after_frames: int = 3       # consecutive late frames before holding (one slow frame is not a trend)
    resume_after_s: float = 1.0      # how long frames must be young before the hold ends
    max_drift_scale: float = 3.0     # the map's drift margin grows with the frames skipped, up to this factor
    gap_mean_frames: int = 10        # ... the sequence gap averaged over about this many processed frames

    def __post_init__(self) -> None:
        if not 0.0 <= self.nominal_s < self.resume_s <= self.hold_s:
            raise ValueError("need 0 <= nominal_s < resume_s <= hold_s")
        if self.hold_after_frames < 1 or not self.resume_after_s >= 0.0:
            raise ValueError("hold_after_frames >= 1 and resume_after_s >= 0 required")
        if not 1.0 <= self.max_drift_scale <= 10.0 or self.gap_mean_frames < 1:
            raise ValueError("need 1 <= max_drift_scale <= 10 and gap_mean_frames >= 1")


@dataclass(frozen=True)
class LatencyVerdict:
    age_s: float                 # this frame's age when its setpoint is built
    stopping_time_s: float       # the reference law's stopping time for it
    max_speed_m_s: float         # and its speed limit
    holding: bool                # no commanded motion
    changed: bool                # the hold started or ended with this frame
    drift_scale: float = 1.0     # the map's drift margin is this many times the configured one


class LatencyGuard:
    """Feed it each frame's age (:meth:`on_frame`); it returns what the safety law flies with."""

    def __init__(self, params: LatencyParams | None = None) -> None:
        self.params = params or LatencyParams()
        self.holding = False
        self._late_frames = 0
        self._young_since_s: float | None = None
        self.holds = 0               # how many times the hold started
        self.gap_mean = 1.0          # running mean of the sequence gap between processed frames

    def on_frame(self, t_s: float, age_s: float, stopping_time_s: float, max_speed_m_s: float,
                 seq_gap: int = 1) -> LatencyVerdict:
        """A frame at time ``t_s`` (any monotonic clock), ``age_s`` old, ``seq_gap`` camera frames after the last one
        processed (1: none skipped); the law's nominal stopping time and speed limit. A non-finite or negative age
        (no clock yet) counts as nominal: nothing is known to be late; a gap below 1 (a restarted camera) as 1."""
        p = self.params
        gap = float(min(max(seq_gap, 1), 100))
        self.gap_mean += (gap - self.gap_mean) / p.gap_mean_frames
        age = age_s if math.isfinite(age_s) and age_s >= 0.0 else p.nominal_s
        was = self.holding
        if age > p.hold_s:
            self._late_frames += 1
            self._young_since_s = None
            if self._late_frames >= p.hold_after_frames:
                self.holding = True
        else:
            self._late_frames = 0
            if self.holding:
                if age <= p.resume_s:
                    if self._young_since_s is None:
                        self._young_since_s = t_s
                    if t_s - self._young_since_s >= p.resume_after_s:
                        self.holding = False
                else:
                    self._young_since_s = None
        if self.holding and not was:
            self.holds += 1
        excess = max(0.0, age - p.nominal_s)
        scale = min(1.0, max(0.0, (p.hold_s - age) / (p.hold_s - p.nominal_s)))
        return LatencyVerdict(age, stopping_time_s + excess, max_speed_m_s * scale, self.holding,
                              self.holding != was, min(self.gap_mean, p.max_drift_scale))
