"""The 1 kHz force loop (eq. (15) on the device), and the process that can host it.

:func:`run_force_loop` is the loop: poll the device, compute eq. (15) from the latest vehicle motion,
command the force, publish a snapshot, pass button presses on; precise sleep to the next tick. It talks
to the rest of the station through a small :class:`ForceLoopIO`.

It runs either in a thread of the station (``ThreadForceLoop``, used for the keyboard device and in
tests) or in its own process (:class:`ForceProcess`, the default of ``quadlink teleop``). The process
matters on a loaded machine: a real-time (SCHED_FIFO) thread still has to take Python's GIL, and a
normal-priority thread of the same interpreter that holds it and is preempted by other programs stalls
the force loop for milliseconds (priority inversion; measured p99 jitter > 1 ms). In its own process
the loop shares no lock with the view and the network: state crosses through shared memory under a
sequence lock, button presses through a pipe.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from quadlink import errors
from quadlink.errors import QuadlinkError
from teleop.config import TeleopConfig
from teleop.devices.base import DeviceState, HapticDevice
from teleop.force import LinkFade, VehicleMotion, force_law, link_ok, q_tilde, saturate
from teleop.mapping import mapping_gains
from teleop.passivity import PassivityController, PassivityReport

log = logging.getLogger(__name__)

PERIOD_BUFFER = 120_000


@dataclass(frozen=True)
class ForceSnapshot:
    device: DeviceState
    tau_d_n: NDArray[np.float64]
    q_tilde_m: NDArray[np.float64] | None
    link_gain: float
    cue_gain: float = 1.0
    passivity: PassivityReport | None = None   # the port's energy account (teleop/passivity.py)


@dataclass(frozen=True)
class MotionInput:
    """The force loop's view of the vehicle (from TELEOP_FEEDBACK), stamped with the shared monotonic clock."""

    t_recv_s: float
    motion: VehicleMotion
    cue_wanted: bool          # the companion's mode is one of force.cue_modes


@dataclass(frozen=True)
class DeviceSpec:
    """How to open a device in the force process (picklable)."""

    name: str
    script: str | None = None
    script_clock: str = "wall"     # 'wall' or 'vehicle'


class ForceLoopIO(Protocol):
    def motion(self) -> MotionInput | None: ...
    def publish(self, snapshot: ForceSnapshot) -> None: ...
    def button(self, name: str) -> None: ...
    def record_period(self, t_s: float) -> None: ...
    def stop_requested(self) -> bool: ...


def precise_sleep_until(deadline_s: float, clock: Callable[[], float], spin_s: float) -> None:
    remaining = deadline_s - clock()
    if remaining > spin_s:
        time.sleep(remaining - spin_s)
    while clock() < deadline_s:
        pass


def try_realtime(priority: int) -> None:
    """SCHED_FIFO for the calling thread: on a loaded machine the normal scheduler lets the loop miss
    ticks by several ms. The loop sleeps most of each period, so it cannot starve the machine."""
    if priority <= 0:
        return
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        log.info("force loop: real-time priority SCHED_FIFO %d", priority)
    except (AttributeError, OSError) as exc:
        log.warning("force loop: no real-time priority (%s); expect ms jitter under load "
                    "(allow it with 'ulimit -r %d' or CAP_SYS_NICE)", exc, priority)


class ForceLoop:
    """One tick of the force loop at a given time (eq. (15), link and cue fades, passivity), whatever drives it:
    :func:`run_force_loop` on the wall clock, or the ground station's lock-step loop on simulated time
    (``force_rate_hz`` ticks per simulated second, :mod:`teleop.station`)."""

    def __init__(self, device: HapticDevice, cfg: TeleopConfig, io: ForceLoopIO) -> None:
        self.device, self.cfg, self.io = device, cfg, io
        self.gains = mapping_gains(cfg.mapping, cfg.device)
        self.period = 1.0 / cfg.device.force_rate_hz
        self.fade = LinkFade(cfg.force.fade_time_s)
        self.cue_fade = LinkFade(cfg.force.fade_time_s)
        self.pc = PassivityController(cfg.passivity, cfg.device.mass_kg)
        self.next_energy_log: float | None = None   # None: a log period after the first tick

    def tick(self, t: float) -> None:
        cfg, io, device = self.cfg, self.io, self.device
        if self.next_energy_log is None:
            self.next_energy_log = t + cfg.passivity.log_period_s
        io.record_period(t)
        state = device.poll(t)
        m = io.motion()
        ok = m is not None and link_ok(m.t_recv_s, t, cfg.force.link_timeout_s)
        gain = self.fade.update(ok, t)
        cue = self.cue_fade.update(ok and m is not None and m.cue_wanted, t)
        qt = q_tilde(m.motion, self.gains, state.q_m) if m is not None else None
        tau_law = force_law(state.q_m, state.qdot_m_s, qt, cfg.force, cfg.device.force_limit_n, gain, cue)
        tau = tau_passive(self.pc, t, state, tau_law, self.period, cfg.device.force_limit_n)
        device.set_force(tau)
        report = self.pc.report()
        io.publish(ForceSnapshot(state, tau, qt, gain, cue, report))
        if t >= self.next_energy_log:
            self.next_energy_log = t + cfg.passivity.log_period_s
            log_energy(report, cfg.passivity.enabled)
        for button in state.buttons:
            io.button(button)


def run_force_loop(device: HapticDevice, cfg: TeleopConfig, io: ForceLoopIO,
                   clock: Callable[[], float] = time.perf_counter) -> None:
    """Until ``io.stop_requested()``: one tick per 1/force_rate_hz (eq. (15), link and cue fades).

    The passivity observer accounts every tick's work on the handle; with ``passivity.enabled`` its
    controller adds the damping that keeps the observed energy >= 0 (teleop/passivity.py), on top of
    eq. (15), before the device's force limit.
    """
    try_realtime(cfg.device.realtime_priority)
    loop = ForceLoop(device, cfg, io)
    period = loop.period
    spin = cfg.device.spin_s
    next_t = clock()
    loop.next_energy_log = next_t + cfg.passivity.log_period_s
    while not io.stop_requested():
        loop.tick(clock())
        next_t += period
        if clock() - next_t > 50 * period:   # fell far behind (suspended?): resynchronise
            next_t = clock()
        precise_sleep_until(next_t, clock, spin)


def tau_passive(pc: PassivityController, t_s: float, state: DeviceState, tau_law_n: NDArray[np.float64],
                period_s: float, force_limit_n: float) -> NDArray[np.float64]:
    """One tick of the passivity observer/controller around eq. (15)'s force; returns the force to apply."""
    pc.observe(t_s, state.q_m.tolist())          # tolist: plain floats, the cheapest way at 1 kHz
    law = tau_law_n.tolist()
    cmd = pc.control(state.qdot_m_s.tolist(), law, period_s)
    if cmd == law:                                 # the controller did not act (the usual case)
        pc.applied(law, law)
        return tau_law_n
    tau = saturate(np.array(cmd), force_limit_n)
    pc.applied(tau.tolist(), law)
    return tau


def log_energy(r: PassivityReport, enabled: bool) -> None:
    log.info("passivity %s: observed energy %.4f J (min axis %.4f J), hand -> network %.4f J, "
             "network -> hand (injected) %.4f J, dissipated by the controller %.4f J",
             "on" if enabled else "observer only", r.observed_j, r.min_observed_j, r.input_j, r.output_j,
             r.dissipated_j)


class PeriodRecorder:
    """Ring buffer of loop periods (for the jitter figure), over any float buffer."""

    def __init__(self, buf: Any = None, count: Any = None) -> None:
        self._buf = buf if buf is not None else np.zeros(PERIOD_BUFFER)
        self._count = count        # a shared multiprocessing Value, or None (local counter)
        self._n = 0
        self._t_prev: float | None = None

    def record(self, t_s: float) -> None:
        if self._t_prev is not None:
            n = self._count.value if self._count is not None else self._n
            self._buf[n % len(self._buf)] = t_s - self._t_prev
            if self._count is not None:
                self._count.value = n + 1
            else:
                self._n = n + 1
        self._t_prev = t_s

    def periods_s(self) -> NDArray[np.float64]:
        n = self._count.value if self._count is not None else self._n
        return np.array(self._buf[:min(n, len(self._buf))], dtype=float)


# ---- shared memory with a sequence lock (one writer per array) -----------------------------------
def _seq_write(arr: Any, values: Sequence[float]) -> None:
    arr[0] += 1.0                       # odd: being written
    arr[1:1 + len(values)] = values
    arr[0] += 1.0


def _seq_read(arr: Any, n: int) -> list[float] | None:
    for _ in range(1000):
        s1 = arr[0]
        if int(s1) % 2:
            continue
        values = arr[1:1 + n]
        if arr[0] == s1:
            return values if s1 > 0 else None
    return None


_MOTION_N = 11   # t_recv, v(3), alpha, yaw_rate, pan_scan_rate, cue_wanted, valid, vehicle_t, has_vehicle_t
_STATE_N = 27    # t, q(3), qd(3), fop(3), tau(3), qt(3), has_qt, gain, cue, finished, has_fop, passivity(6)


def _motion_values(m: MotionInput | None, vehicle_time_s: float | None) -> list[float]:
    if m is None:
        head = [0.0] * 9
    else:
        head = [m.t_recv_s, *m.motion.v_h_m_s, m.motion.alpha_rad, m.motion.yaw_rate_rad_s,
                m.motion.pan_scan_yaw_rate_rad_s, float(m.cue_wanted), 1.0]
    return head + ([vehicle_time_s, 1.0] if vehicle_time_s is not None else [0.0, 0.0])


def _motion_from(values: list[float] | None) -> tuple[MotionInput | None, float | None]:
    if values is None:
        return None, None
    vt = values[9] if values[10] > 0.5 else None
    if values[8] < 0.5:
        return None, vt
    motion = VehicleMotion((values[1], values[2], values[3]), values[4], values[5], values[6])
    return MotionInput(values[0], motion, values[7] > 0.5), vt


def _passivity_values(r: PassivityReport | None) -> list[float]:
    if r is None:
        return [0.0] * 6
    return [r.observed_j, r.min_observed_j, r.input_j, r.output_j, r.dissipated_j, r.damping_n_s_m]


class _SharedIO:
    """The force process's side of the shared memory."""

    def __init__(self, motion_arr: Any, state_arr: Any, periods: Any, count: Any, stop: Any,
                 buttons_tx: Connection, device: HapticDevice) -> None:
        self._motion_arr, self._state_arr, self._stop, self._tx = motion_arr, state_arr, stop, buttons_tx
        self._periods = PeriodRecorder(periods, count)
        self.device = device
        self._k = 0

    def motion(self) -> MotionInput | None:
        return _motion_from(_seq_read(self._motion_arr, _MOTION_N))[0]

    def vehicle_time_s(self) -> float | None:
        return _motion_from(_seq_read(self._motion_arr, _MOTION_N))[1]

    def publish(self, s: ForceSnapshot) -> None:
        d = s.device
        fop = d.operator_force_n if d.operator_force_n is not None else np.zeros(3)
        qt = s.q_tilde_m if s.q_tilde_m is not None else np.zeros(3)
        _seq_write(self._state_arr, [d.t_s, *d.q_m, *d.qdot_m_s, *fop, *s.tau_d_n, *qt,
                                     float(s.q_tilde_m is not None), s.link_gain, s.cue_gain,
                                     float(self.device.finished), float(d.operator_force_n is not None),
                                     *_passivity_values(s.passivity)])

    def button(self, name: str) -> None:
        self._tx.send(name)

    def record_period(self, t_s: float) -> None:
        self._periods.record(t_s)

    def stop_requested(self) -> bool:
        self._k += 1
        return self._k % 10 == 0 and self._stop.is_set()   # an Event check is a lock: every 10 ms is enough


def _child_main(spec: DeviceSpec, cfg: TeleopConfig, log_level: int, motion_arr: Any, state_arr: Any,
                periods: Any, count: Any, stop: Any, buttons_tx: Connection, ready_tx: Connection) -> None:
    logging.basicConfig(level=log_level, format="%(asctime)s %(levelname).1s %(name)s: %(message)s",
                        datefmt="%H:%M:%S")
    from teleop.devices import open_device

    holder: list[_SharedIO] = []
    clock_fn = (lambda: holder[0].vehicle_time_s() if holder else None) if spec.script_clock == "vehicle" else None
    try:
        device = open_device(spec.name, cfg.device, spec.script, clock_fn)
    except QuadlinkError as exc:
        ready_tx.send(("error", type(exc).__name__, str(exc)))
        return
    io = _SharedIO(motion_arr, state_arr, periods, count, stop, buttons_tx, device)
    holder.append(io)
    ready_tx.send(("ok", device.name, device.has_force_output))
    try:
        run_force_loop(device, cfg, io)
    except KeyboardInterrupt:
        pass
    finally:
        try:
            device.set_force(np.zeros(3))
        finally:
            device.close()


class ForceProcess:
    """The force loop in its own process; the station's handle on it."""

    def __init__(self, spec: DeviceSpec, cfg: TeleopConfig, start_timeout_s: float = 60.0) -> None:
        ctx = multiprocessing.get_context("spawn")
        self._motion_arr = ctx.RawArray("d", 1 + _MOTION_N)
        self._state_arr = ctx.RawArray("d", 1 + _STATE_N)
        self._periods_buf = ctx.RawArray("d", PERIOD_BUFFER)
        self._count = ctx.RawValue("q", 0)
        self._stop = ctx.Event()
        self._buttons_rx, buttons_tx = ctx.Pipe(duplex=False)
        ready_rx, ready_tx = ctx.Pipe(duplex=False)
        self._proc = ctx.Process(target=_child_main, name="teleop-force",
                                 args=(spec, cfg, logging.getLogger().getEffectiveLevel(), self._motion_arr,
                                       self._state_arr, self._periods_buf, self._count, self._stop, buttons_tx,
                                       ready_tx), daemon=True)
        self._proc.start()
        if not ready_rx.poll(start_timeout_s):
            self.close()
            raise QuadlinkError(f"force process did not start within {start_timeout_s:.0f} s")
        status = ready_rx.recv()
        if status[0] == "error":
            self._proc.join(timeout=5.0)
            exc_type = getattr(errors, status[1], QuadlinkError)
            raise exc_type(status[2]) if isinstance(exc_type, type) and issubclass(exc_type, QuadlinkError) \
                else QuadlinkError(status[2])
        self.name, self.has_force_output = status[1], status[2]
        log.info("force loop in process %d (device %s)", self._proc.pid, self.name)

    @property
    def alive(self) -> bool:
        return self._proc.is_alive()

    def set_motion(self, m: MotionInput | None, vehicle_time_s: float | None) -> None:
        _seq_write(self._motion_arr, _motion_values(m, vehicle_time_s))

    def snapshot(self) -> ForceSnapshot | None:
        v = _seq_read(self._state_arr, _STATE_N)
        if v is None:
            return None
        fop = np.array(v[7:10]) if v[20] > 0.5 else None
        state = DeviceState(v[0], np.array(v[1:4]), np.array(v[4:7]), (), fop)
        return ForceSnapshot(state, np.array(v[10:13]), np.array(v[13:16]) if v[16] > 0.5 else None, v[17], v[18],
                             PassivityReport(*v[21:27]))

    @property
    def finished(self) -> bool:
        v = _seq_read(self._state_arr, _STATE_N)
        return v is not None and v[19] > 0.5

    def buttons(self) -> list[str]:
        out = []
        while self._buttons_rx.poll(0):
            try:
                out.append(str(self._buttons_rx.recv()))
            except EOFError:
                break
        return out

    def periods_s(self) -> NDArray[np.float64]:
        n = self._count.value
        return np.array(self._periods_buf[:min(n, PERIOD_BUFFER)], dtype=float)

    def close(self) -> None:
        self._stop.set()
        self._proc.join(timeout=3.0)
        if self._proc.is_alive():
            log.warning("force process did not stop; terminating it")
            self._proc.terminate()
            self._proc.join(timeout=2.0)
