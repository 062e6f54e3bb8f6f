"""Commands have an age (issue 18): companion.command_age with the mode machine, driven with time.

The link is simulated here on a shared time axis: the station's clock runs ``CLOCK_OFFSET_S`` ahead of the
companion's, the TIMESYNC offset comes from the real estimator fed with the exchanges of the same link, and
every packet arrives ``delay`` after it was sent (or never, in an outage).
"""

from __future__ import annotations

import math

import pytest

from companion.command_age import CommandAgeFilter, CommandAgeParams, Verdict
from companion.modes import Mode, ModeMachine, ModeParams, VehicleStatus
from quadlink.mavlink import mavlink
from quadlink.mavlink.timesync import NS, TimesyncConfig, TimesyncEstimator

CLOCK_OFFSET_S = 1234.5           # station clock minus companion clock
STATION = (255, 190)
MC = mavlink.MAVLINK_MSG_ID_MANUAL_CONTROL
IN_AIR = VehicleStatus(armed=True, in_air=True, reports_landed_state=True)


def teleop_machine(params: ModeParams, t_s: float) -> ModeMachine:
    m = ModeMachine(params)
    ok, _ = m.request("takeoff", t_s, VehicleStatus(armed=True))
    assert ok
    m.on_manual_control(t_s)
    m.update(t_s + params.takeoff_min_s + 0.01, IN_AIR, True)
    assert m.mode == Mode.TELEOP
    return m


class Link:
    """Station -> companion packets with a one-way delay; ``up(t)`` False drops everything sent at t."""

    def __init__(self, delay_s: float, up=lambda t: True) -> None:  # noqa: ANN001 - a small predicate
        self.delay_s, self.up = delay_s, up
        self.queue: list[tuple[float, tuple]] = []

    def send(self, t_s: float, packet: tuple) -> None:
        if self.up(t_s):
            self.queue.append((t_s + self.delay_s, packet))

    def due(self, t_s: float) -> list[tuple]:
        out = [p for a, p in self.queue if a <= t_s + 1e-12]
        self.queue = [(a, p) for a, p in self.queue if a > t_s + 1e-12]
        return out


def fly(duration_s: float, delay_s: float, max_age_s: float, params: ModeParams, up=lambda t: True,  # noqa: ANN001
        dt_s: float = 0.01) -> tuple[list[tuple[float, Mode, bool]], CommandAgeFilter, list[float], list[float]]:
    """Station at 50 Hz (COMMAND_STAMP + MANUAL_CONTROL, TIMESYNC every 0.5 s) -> companion, stepped by dt_s."""
    age = CommandAgeFilter(CommandAgeParams(max_command_age_s=max_age_s))
    sync = TimesyncEstimator(TimesyncConfig())
    modes = teleop_machine(params, 0.0)
    uplink, downlink = Link(delay_s, up), Link(delay_s, up)
    trace: list[tuple[float, Mode, bool]] = []
    accepted_sent: list[float] = []
    accepted_arrival: list[float] = []
    seq = 0
    n = int(round(duration_s / dt_s))
    for k in range(1, n + 1):
        t = k * dt_s
        if k % 2 == 0:                                  # the station, 50 Hz, its own clock
            uplink.send(t, ("stamp", seq, int((t + CLOCK_OFFSET_S) * 1e6)))
            uplink.send(t, ("manual", (seq + 1) % 256))
            seq = (seq + 2) % 256
        if k % 50 == 0:                                 # companion's TIMESYNC request, station answers
            uplink_t = t
            downlink.send(uplink_t, ("ts_req", int(t * NS)))
        for p in downlink.due(t):                       # at the station: answer with its clock
            uplink.send(t, ("ts_ans", int((t + CLOCK_OFFSET_S) * NS), p[1]))
        for p in uplink.due(t):
            if p[0] == "stamp":
                age.on_stamp(STATION, p[1], p[2], MC, t)
            elif p[0] == "manual":
                offset = None if sync.offset_ns is None else sync.offset_ns / NS
                verdict = age.on_command(STATION, p[1], MC, t, offset)
                if verdict.accepted:
                    accepted_sent.append(verdict.sent_s)
                    modes.on_manual_control(t)          # liveness from the accepted arrival (the daemon's)
                    accepted_arrival.append(t)
            elif p[0] == "ts_ans":
                sync.on_response(p[1], p[2], int(t * NS))
        modes.update(t, IN_AIR, True)
        trace.append((t, modes.mode, age.fresh(t)))
    return trace, age, accepted_sent, accepted_arrival


def first(trace: list[tuple[float, Mode, bool]], pred, after_s: float = 0.0) -> float:  # noqa: ANN001
    return next(t for t, m, f in trace if t > after_s and pred(m, f))


def test_a_2s_outage_holds_within_the_age_and_resumes_cleanly() -> None:
    max_age = 0.3
    params = ModeParams(gcs_timeout_s=max_age, gcs_land_timeout_s=5.0, odometry_recover_s=0.5, takeoff_min_s=0.3)
    outage = (6.0, 8.0)
    trace, age, sent, arrivals = fly(12.0, 0.05, max_age, params, up=lambda t: not outage[0] <= t < outage[1])
    last_sent = max(s for s in sent if s < outage[0] + 0.5)
    # the last command before the outage was sent just before it began (station clock converted back)
    assert last_sent == pytest.approx(outage[0] - 0.02, abs=0.015)
    t_stale = first(trace, lambda m, f: not f, after_s=outage[0] - 0.1)
    t_hold = first(trace, lambda m, f: m == Mode.HOLD)
    last_arrival = max(a for a in arrivals if a < outage[0] + 0.5)
    assert t_stale - last_sent <= max_age + 0.011          # operator input zeroed within the age ...
    assert t_hold - last_arrival <= params.gcs_timeout_s + 0.011   # ... HOLD gcs_timeout after the last arrival
    assert t_hold > outage[0]
    # no LAND (the outage is shorter than the land timeout); TELEOP again once fresh commands arrive
    modes_after = [m for t, m, _ in trace if t > t_hold]
    assert Mode.LAND not in modes_after
    t_back = first(trace, lambda m, f: m == Mode.TELEOP, after_s=t_hold)
    assert outage[1] + 0.05 <= t_back <= outage[1] + 0.1
    assert all(m == Mode.TELEOP and f for t, m, f in trace if t > t_back + 0.05)
    # with a 50 ms one-way delay every stamped command was accepted, aged ~50 ms with the estimated offset
    assert age.counts.dropped == 0 and age.counts.stamped > 400
    assert age.age_percentile_s(50) == pytest.approx(0.05, abs=0.002)


def test_a_sustained_delay_above_the_age_drops_everything_then_holds_then_lands() -> None:
    params = ModeParams(gcs_timeout_s=0.2, gcs_land_timeout_s=2.0, takeoff_min_s=0.3)
    trace, age, sent, _ = fly(4.0, 0.3, 0.2, params)
    # the first commands arrive unsynced (arrival time) until the first TIMESYNC round trip, then all are stale
    assert age.counts.unsynced > 0 and age.counts.stale > 0.9 * (age.counts.stale + age.counts.stamped)
    assert age.counts.stamped == 0
    last_accepted = max(sent)          # the last arrival-time command, just before the offset was known
    assert 0.6 < last_accepted < 1.3
    t_hold = first(trace, lambda m, f: m == Mode.HOLD, after_s=last_accepted)
    t_land = first(trace, lambda m, f: m == Mode.LAND)
    assert t_hold - last_accepted == pytest.approx(0.2, abs=0.011)
    assert t_land - last_accepted == pytest.approx(2.0, abs=0.011)
    assert age.age_percentile_s(50) == pytest.approx(0.3, abs=0.003)


def test_a_lost_stamp_makes_the_command_unpaired_and_it_is_dropped() -> None:
    f = CommandAgeFilter(CommandAgeParams(max_command_age_s=0.5))
    f.on_stamp(STATION, 10, int(100.0e6), MC, 100.0)
    assert f.on_command(STATION, 11, MC, 100.01, 0.0).accepted
    # stamp 12 lost: command 13 has no stamp of its own
    res = f.on_command(STATION, 13, MC, 100.03, 0.0)
    assert res.verdict == Verdict.UNPAIRED and math.isnan(res.age_s)
    # a stamp for another message id does not pair either
    f.on_stamp(STATION, 14, int(100.04e6), 84, 100.04)
    assert f.on_command(STATION, 15, MC, 100.05, 0.0).verdict == Verdict.UNPAIRED
    assert f.counts.unpaired == 2


def test_unstamped_senders_use_the_arrival_time_and_reordered_commands_are_superseded() -> None:
    f = CommandAgeFilter(CommandAgeParams(max_command_age_s=0.2))
    qgc = (255, 0)
    res = f.on_command(qgc, 3, MC, 50.0, None)
    assert res.accepted and not res.stamped and res.sent_s == 50.0 and res.age_s == 0.0
    assert f.fresh(50.19) and not f.fresh(50.21)
    # a stamping sender whose later command overtook an earlier one on the link
    f.on_stamp(STATION, 20, int(60.10e6), MC, 60.15)
    assert f.on_command(STATION, 21, MC, 60.15, 0.0).accepted
    f.on_stamp(STATION, 18, int(60.08e6), MC, 60.16)
    assert f.on_command(STATION, 19, MC, 60.16, 0.0).verdict == Verdict.SUPERSEDED
    # a stamp far in our future is a broken clock estimate
    f.on_stamp(STATION, 22, int(61.0e6), MC, 60.2)
    assert f.on_command(STATION, 23, MC, 60.2, 0.0).verdict == Verdict.FUTURE
    assert f.counts.arrival_time == 1 and f.counts.stamped == 1 and f.counts.dropped == 2
