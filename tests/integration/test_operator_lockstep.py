"""The two scripted operators as participants of the deterministic lock-step (quadlink.lockstep): the offboard
client (``python -m harness.campaign.offboard_client --lockstep``) and the ground station (``quadlink teleop
--lockstep``), each a real subprocess, against the real :class:`Coordinator` driven from the test thread and a
fake companion on a plain UDP socket that plays the SITL-side part of the protocol: per step it reads exactly the
datagrams the operator's last DONE announced, answers (feedback, acks, TIMESYNC), and announces its own count.

Checked: DONE counts are the datagrams that arrived; a datagram that reached the operator's socket before its
step is not handled before the step that announces it; two flights of the same steps and the same companion
messages but different wall timing (random sleeps, datagrams still in flight when the step is announced,
datagrams that come a step early) send byte-identical datagrams at the same steps; the offboard client's
commands come at the simulated times its plan says.
"""

from __future__ import annotations

import random
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
import yaml

from quadlink.lockstep import Coordinator
from quadlink.mavlink import mavlink
from quadlink.px4_modes import Px4MainMode, encode_custom_mode
from teleop.config import TeleopConfig

REPO = Path(__file__).resolve().parents[2]
STEP_S = 0.01
LINK_IN = "operator>companion"     # the fake companion's input link (the operator's output)
LINK_OUT = "companion>operator"
WALL_LIMIT_S = 120.0               # a whole flight, however loaded the machine

PLAN = {"takeoff_s": 3.2, "landing_s": 0.3, "duration_s": 4.0,
        "segments": [{"frame": "body", "forward_m_s": 0.3, "right_m_s": 0.1, "down_m_s": 0.0,
                      "yawspeed_deg_s": 10.0, "duration_s": 0.3},
                     {"frame": "ned", "north_m_s": 0.2, "east_m_s": 0.0, "down_m_s": 0.0, "yaw_deg": 90.0,
                      "duration_s": 0.2}]}


def _t(k: int) -> float:
    return round(k * STEP_S, 9)


def parse(datagram: bytes) -> list[Any]:
    parser = mavlink.MAVLink(None)
    parser.robust_parsing = True
    return [m for m in (parser.parse_buffer(datagram) or []) if m.get_type() != "BAD_DATA"]


class Companion:
    """The companion's ground-station endpoint on a plain UDP socket; packs with the quadlink dialect."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]
        self.peer: tuple[str, int] | None = None
        self.rx: list[bytes] = []
        self.tx = 0
        self.mav = mavlink.MAVLink(None, 1, 191)        # the companion's identity
        self.autopilot = mavlink.MAVLink(None, 1, 1)    # the autopilot's, routed through the companion

    def read_until(self, n: int, timeout_s: float = 10.0) -> None:
        """Read datagrams until ``n`` have come (the count the operator's DONE announced)."""
        deadline = time.monotonic() + timeout_s
        while len(self.rx) < n:
            remaining = deadline - time.monotonic()
            assert remaining > 0, f"the operator announced {n} datagrams, {len(self.rx)} came"
            self.sock.settimeout(min(remaining, 0.1))
            try:
                data, addr = self.sock.recvfrom(65536)
            except TimeoutError:
                continue
            self.peer = addr
            self.rx.append(data)

    def extra(self, wait_s: float = 0.3) -> int:
        """Datagrams that came beyond what was read (there must be none)."""
        self.sock.settimeout(wait_s)
        n = 0
        try:
            while True:
                self.sock.recvfrom(65536)
                n += 1
                self.sock.settimeout(0.05)
        except TimeoutError:
            return n

    def send(self, buf: bytes) -> None:
        assert self.peer is not None
        self.sock.sendto(buf, self.peer)
        self.tx += 1

    def feedback(self, time_s: float, mode: int = 2) -> bytes:
        msg = mavlink.MAVLink_teleop_feedback_message(
            time_usec=int(round(time_s * 1e6)), vx_h=0.1, vy_h=0.0, vz_h=0.0, vx_cmd=0.1, vy_cmd=0.0, vz_cmd=0.0,
            vx_rep=0.0, vy_rep=0.0, vz_rep=0.0, alpha=0.0, pan_scan_yaw_rate=0.0, yaw_rate_cmd=0.0,
            gyro_yaw_rate=0.0, obstacle_x=0.9, obstacle_y=0.0, obstacle_z=0.0, obstacle_distance=0.9, mode=mode,
            flags=0b0110)
        return bytes(msg.pack(self.mav))

    def replies(self, k: int, received: list[Any]) -> list[bytes]:
        """What a companion answers at step ``k`` to what the operator sent at step ``k - 1``."""
        out = []
        for msg in received:
            mtype = msg.get_type()
            if mtype == "COMMAND_LONG":
                out.append(bytes(self.autopilot.command_ack_encode(msg.command, mavlink.MAV_RESULT_ACCEPTED)
                                 .pack(self.autopilot)))
            elif mtype == "PARAM_SET":
                out.append(bytes(self.mav.param_value_encode(msg.param_id.encode(), msg.param_value,
                                                             msg.param_type, 1, 0).pack(self.mav)))
            elif mtype == "TIMESYNC" and msg.tc1 == 0:
                out.append(bytes(self.mav.timesync_encode(int(_t(k) * 1e9), msg.ts1).pack(self.mav)))
        if k % 50 == 7:   # the companion's own TIMESYNC request (the operator answers it)
            out.append(bytes(self.mav.timesync_encode(0, int(_t(k) * 1e9)).pack(self.mav)))
        if k % 100 == 3:
            out.append(bytes(self.autopilot.heartbeat_encode(
                mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_GENERIC, mavlink.MAV_MODE_FLAG_SAFETY_ARMED, 0,
                mavlink.MAV_STATE_ACTIVE).pack(self.autopilot)))
        return out

    def close(self) -> None:
        self.sock.close()


@dataclass
class Flight:
    steps: list[list[bytes]] = field(default_factory=list)   # steps[k]: the operator's datagrams of DONE k
    done_counts: list[int] = field(default_factory=list)
    left_at: int | None = None                                 # the step after which the operator left
    returncode: int | None = None
    extra: int = 0
    output: str = ""
    early_sent: int = 0        # datagrams sent before the STEP before theirs
    late_sent: int = 0         # datagrams sent after their STEP was announced (still in flight)

    def messages(self) -> list[tuple[int, Any]]:
        return [(k, m) for k, grams in enumerate(self.steps) for d in grams for m in parse(d)]


#: feedback(companion, k) -> the TELEOP_FEEDBACK datagram of step k (None: none this step)
Feedback = Callable[[Companion, int], bytes | None]


def steady_feedback(companion: Companion, k: int) -> bytes | None:
    return companion.feedback(_t(k)) if companion.peer is not None else None


def fly(argv: Callable[[str, int], list[str]], feedback: Feedback = steady_feedback, max_steps: int = 1000,
        jitter: random.Random | None = None, early: frozenset[int] = frozenset(),
        stop_after: int | None = None) -> Flight:
    """One flight: the coordinator and the companion here, the operator ``argv(url, port)`` a subprocess.

    ``jitter``: random wall timing (sleeps, datagrams still in flight when the step is announced, feedback
    sent a step early). ``early``: steps whose feedback is sent before the previous STEP (and held 50 ms so it
    surely reached the operator's socket), announced only with its own step.
    """
    coord = Coordinator("127.0.0.1", 0, ("operator",))
    companion = Companion()
    proc = subprocess.Popen(argv(coord.url, companion.port), cwd=REPO, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    flight = Flight()
    wall_deadline = time.monotonic() + WALL_LIMIT_S
    try:
        while not coord.all_registered():
            assert time.monotonic() < wall_deadline and proc.poll() is None, "the operator did not register"
            coord.poll(0.05)
        assert coord.sent.get(LINK_IN) == 0, "the operator sent before the first step"
        pre_sent: dict[int, bytes] = {}   # step -> its feedback, already on the wire
        announced = 0
        last_done = 0
        for k in range(1, max_steps + 1):
            n = coord.sent.get(LINK_IN, 0)
            if jitter is not None and jitter.random() < 0.2:
                time.sleep(jitter.uniform(0.0, 0.003))
            companion.read_until(n)
            flight.done_counts.append(n)
            got = companion.rx[sum(len(s) for s in flight.steps):n]
            flight.steps.append(got)
            if "operator" in coord.left:
                flight.left_at = last_done
                break
            if stop_after is not None and k > stop_after:
                break
            received = [m for d in got for m in parse(d)]
            if k in pre_sent:
                announced += 1
                out = []
            else:
                fb = feedback(companion, k)
                out = [fb] if fb is not None else []
            out += companion.replies(k, received)
            in_flight = 0
            if jitter is not None and jitter.random() < 0.3:
                in_flight = jitter.randint(1, len(out)) if out else 0
            for buf in out[:len(out) - in_flight]:
                companion.send(buf)
                if jitter is not None and jitter.random() < 0.1:
                    time.sleep(jitter.uniform(0.0, 0.002))
            announced += len(out)
            coord.sent[LINK_OUT] = announced
            nxt = k + 1
            send_early = nxt in early or (jitter is not None and companion.peer is not None
                                          and jitter.random() < 0.3)
            if send_early and companion.peer is not None and in_flight == 0:
                fb = feedback(companion, nxt)   # sent now, announced with step k + 1
                if fb is not None:
                    pre_sent[nxt] = fb
                    companion.send(fb)
                    flight.early_sent += 1
                    if nxt in early:
                        time.sleep(0.05)
            coord.send_step(k, _t(k))
            for buf in out[len(out) - in_flight:]:
                if jitter is not None:
                    time.sleep(jitter.uniform(0.0, 0.002))
                companion.send(buf)
                flight.late_sent += 1
            while not coord.all_done(k):
                assert time.monotonic() < wall_deadline, f"no DONE {k}"
                assert proc.poll() is None or coord.all_done(k) or "operator" in coord.left, \
                    f"the operator died at step {k}"
                coord.poll(0.05)
            last_done = k   # answered (its last DONE, if the operator left with it)
        flight.extra = companion.extra()
    finally:
        coord.close()   # the coordinator is gone: a participant still running exits
        try:
            out_text, _ = proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            out_text, _ = proc.communicate()
        companion.close()
    flight.returncode = proc.returncode
    flight.output = out_text
    return flight


# ------------------------------------------------------------------------------------------------ offboard (A)
def offboard_argv(plan_path: Path) -> Callable[[str, int], list[str]]:
    def argv(url: str, port: int) -> list[str]:
        return [sys.executable, "-m", "harness.campaign.offboard_client", "--vehicle", f"udpout:127.0.0.1:{port}",
                "--plan", str(plan_path), "--lockstep", url]
    return argv


@pytest.fixture
def plan_path(tmp_path: Path) -> Path:
    path = tmp_path / "plan.yaml"
    path.write_text(yaml.safe_dump(PLAN))
    return path


def _commands(flight: Flight) -> dict[int, list[int]]:
    out: dict[int, list[int]] = {}
    for k, m in flight.messages():
        if m.get_type() == "COMMAND_LONG":
            out.setdefault(m.command, []).append(k)
    return out


def test_offboard_counts_timeline_and_exit(plan_path: Path) -> None:
    flight = fly(offboard_argv(plan_path))
    assert flight.returncode == 0, flight.output
    # (a) every DONE count is what arrived, and nothing came beyond the last one
    assert flight.done_counts[-1] == sum(len(s) for s in flight.steps) and flight.extra == 0
    assert flight.steps[0] == [] and flight.steps[1], "nothing before the first step, a heartbeat in it"
    # (d) the plan's times, on the vehicle clock from the first feedback: the companion learns the client's
    # address from its step-1 heartbeat and sends feedback from step 2 on (vehicle time = the step's time)
    # (in the client's arithmetic: TELEOP_FEEDBACK time_usec * 1e-6)
    origin = round(_t(2) * 1e6) * 1e-6
    vehicle = {k: round(_t(k) * 1e6) * 1e-6 for k in range(2, len(flight.steps))}

    def plan_time(k: int) -> float:
        return vehicle[k] - origin

    cmds = _commands(flight)
    expected = {mavlink.MAV_CMD_COMPONENT_ARM_DISARM: 2.0, mavlink.MAV_CMD_NAV_TAKEOFF: 3.0,
                mavlink.MAV_CMD_DO_SET_MODE: PLAN["takeoff_s"],
                mavlink.MAV_CMD_NAV_LAND: PLAN["takeoff_s"] + 0.5}
    for command, due_s in expected.items():
        assert len(cmds.get(command, [])) == 1, (command, cmds)
        k = cmds[command][0]
        # the first step whose plan time reaches the due time
        assert plan_time(k) >= due_s > plan_time(k - 1), (command, k, plan_time(k))
    mode = next(m for _, m in flight.messages() if m.get_type() == "COMMAND_LONG"
                and m.command == mavlink.MAV_CMD_DO_SET_MODE)
    assert mode.param2 == float(encode_custom_mode(Px4MainMode.OFFBOARD))
    setpoints = [(k, m) for k, m in flight.messages() if m.get_type() == "SET_POSITION_TARGET_LOCAL_NED"]
    assert setpoints and all(PLAN["takeoff_s"] <= plan_time(k) < PLAN["takeoff_s"] + 0.5 for k, _ in setpoints)
    gaps = [plan_time(b) - plan_time(a) for (a, _), (b, _) in zip(setpoints, setpoints[1:])]
    assert all(0.05 - 1e-6 <= g <= 0.06 + 1e-6 for g in gaps), gaps   # 20 Hz on the vehicle clock
    assert all(abs(m.time_boot_ms - vehicle[k] * 1000) <= 1 for k, m in setpoints)
    # heartbeats at 1 Hz of simulated time from the first step (a step of float slack)
    beats = [k for k, m in flight.messages() if m.get_type() == "HEARTBEAT"]
    assert beats[0] == 1 and len(beats) >= 3 and all(b - a in (100, 101) for a, b in zip(beats, beats[1:])), beats
    # the plan's end: the client answered the step in which plan time reached duration_s, then left
    assert flight.left_at is not None
    assert plan_time(flight.left_at) >= PLAN["duration_s"] > plan_time(flight.left_at - 1)


def test_offboard_does_not_handle_a_datagram_before_its_step(plan_path: Path) -> None:
    """(b) The feedback of step 40 (vehicle time 3.1 s after the origin: arm and takeoff are due) reaches the
    client's socket before STEP 39; the client must command them at step 40, the step that announces it."""
    def feedback(companion: Companion, k: int) -> bytes | None:
        if companion.peer is None:
            return None
        return companion.feedback(_t(2) + 3.1) if k == 40 else companion.feedback(_t(2)) if k <= 20 else None

    flight = fly(offboard_argv(plan_path), feedback=feedback, early=frozenset({40}), max_steps=45)
    cmds = _commands(flight)
    assert cmds[mavlink.MAV_CMD_COMPONENT_ARM_DISARM] == [40], cmds
    assert cmds[mavlink.MAV_CMD_NAV_TAKEOFF] == [40]
    assert flight.done_counts[-1] == sum(len(s) for s in flight.steps) and flight.extra == 0


def test_offboard_same_steps_same_datagrams_whatever_the_wall_timing(plan_path: Path) -> None:
    """(c) Byte-identical datagrams at identical steps: a calm flight and one with random wall timing."""
    calm = fly(offboard_argv(plan_path))
    shaken = fly(offboard_argv(plan_path), jitter=random.Random(15))
    assert calm.returncode == shaken.returncode == 0, shaken.output
    assert calm.done_counts == shaken.done_counts
    assert calm.steps == shaken.steps
    assert calm.left_at == shaken.left_at
    assert sum(len(s) for s in calm.steps) > 15
    assert shaken.early_sent > 50 and shaken.late_sent > 50 and calm.early_sent == calm.late_sent == 0


def test_offboard_exits_1_when_the_coordinator_goes(plan_path: Path) -> None:
    flight = fly(offboard_argv(plan_path), max_steps=30, stop_after=20)
    assert flight.returncode == 1
    errors = [line for line in flight.output.splitlines() if line.startswith("offboard_client: error:")]
    assert len(errors) == 1 and "lock-step" in errors[0], flight.output


def test_offboard_without_lockstep_is_unchanged(plan_path: Path) -> None:
    """No --lockstep: today's client (heartbeat at once, plan on the first feedback's clock)."""
    companion = Companion()
    proc = subprocess.Popen([sys.executable, "-m", "harness.campaign.offboard_client", "--vehicle",
                             f"udpout:127.0.0.1:{companion.port}", "--plan", str(plan_path)], cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        companion.read_until(1, timeout_s=30.0)
        assert parse(companion.rx[0])[0].get_type() == "HEARTBEAT"
        t_s = 0.0
        while proc.poll() is None and t_s < 10.0:   # vehicle time runs 10x wall time
            companion.send(companion.feedback(t_s))
            t_s += 0.1
            time.sleep(0.01)
        out, _ = proc.communicate(timeout=30)
        assert proc.returncode == 0, out
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
        companion.close()


# ------------------------------------------------------------------------------------------- ground station (B)
SCRIPT = """steps:
  - wait_s: 0.3
  - button: arm
  - wait_s: 0.2
  - button: takeoff
  - push: forward
    force_n: 2.0
    duration_s: 0.5
  - button: pan_scan_toggle
  - release: true
    duration_s: 0.3
  - button: land
"""
SCRIPT_END_S = 1.3


def teleop_argv(script_path: Path, clock: str = "vehicle") -> Callable[[str, int], list[str]]:
    def argv(url: str, port: int) -> list[str]:
        return [sys.executable, "-m", "quadlink.cli", "teleop", "--device", "virtual", "--script", str(script_path),
                "--vehicle", f"udpout:127.0.0.1:{port}", "--image-stream", "none", "--http-port", "-1",
                "--exit-at-script-end", "--script-clock", clock, "--lockstep", url]
    return argv


@pytest.fixture
def script_path(tmp_path: Path) -> Path:
    path = tmp_path / "script.yaml"
    path.write_text(SCRIPT)
    return path


def test_teleop_counts_script_and_exit(script_path: Path) -> None:
    flight = fly(teleop_argv(script_path), max_steps=400)
    assert flight.returncode == 0, flight.output
    # (a) DONE counts are the datagrams that arrived, nothing beyond
    assert flight.done_counts[-1] == sum(len(s) for s in flight.steps) and flight.extra == 0
    msgs = flight.messages()
    first = [m.get_type() for k, m in msgs if k == 1]
    assert flight.steps[0] == [] and first == ["COMMAND_STAMP", "MANUAL_CONTROL", "HEARTBEAT", "TIMESYNC"], first
    # MANUAL_CONTROL at 50 Hz of simulated time (every other step), each after its COMMAND_STAMP of the step's time
    manual = [k for k, m in msgs if m.get_type() == "MANUAL_CONTROL"]
    assert manual == list(range(1, manual[-1] + 1, 2))
    stamps = [(k, m) for k, m in msgs if m.get_type() == "COMMAND_STAMP"]
    assert all(m.time_usec == round(_t(k) * 1e6) for k, m in stamps)
    # TIMESYNC: requests stamped with the step's time, the companion's requests answered with it
    requests = [(k, m) for k, m in msgs if m.get_type() == "TIMESYNC" and m.tc1 == 0]
    answers = [(k, m) for k, m in msgs if m.get_type() == "TIMESYNC" and m.tc1 != 0]
    assert [k for k, _ in requests][:3] == [1, 51, 101] and all(m.ts1 == round(_t(k) * 1e9) for k, m in requests)
    assert answers and all(m.tc1 == round(_t(k) * 1e9) and k % 50 == 7 for k, m in answers)
    # the script on the vehicle clock: feedback from step 2 (vehicle time = step time), presses turn into commands
    # at the next link tick after the force tick that crossed them
    cmds = _commands(flight)
    script_s = {k: _t(k) - _t(2) for k in range(len(flight.steps))}
    for command, due_s in ((mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0.3), (mavlink.MAV_CMD_NAV_TAKEOFF, 0.5),
                           (mavlink.MAV_CMD_NAV_LAND, SCRIPT_END_S)):
        assert len(cmds.get(command, [])) == 1, (command, cmds)   # acked: never re-sent
        assert due_s - 1e-6 <= script_s[cmds[command][0]] <= due_s + 0.03 + 1e-6, (command, cmds[command])
    params = [(k, m) for k, m in msgs if m.get_type() == "PARAM_SET"]
    assert len(params) == 1 and params[0][1].param_value == 1.0
    # the push commanded forward motion; after the release the handle came back (to the cue of the feedback's
    # 0.1 m/s)
    xs = {k: m.x for k, m in msgs if m.get_type() == "MANUAL_CONTROL"}
    assert max(xs.values()) > 500 and xs[max(xs)] < 200
    # the station left right after the script's end (--exit-at-script-end), its last step answered
    assert flight.left_at is not None and SCRIPT_END_S <= script_s[flight.left_at] <= SCRIPT_END_S + 0.03
    assert cmds[mavlink.MAV_CMD_NAV_LAND][0] <= flight.left_at


def test_teleop_does_not_handle_a_datagram_before_its_step(script_path: Path) -> None:
    """(b) The feedback of step 41 (0.35 s of script: arm due) reaches the station's socket before STEP 40.
    Handled at 41, the force ticks of step 42 play the press and the link tick of step 43 sends it; handled a
    step early, the command would go at step 41."""
    def feedback(companion: Companion, k: int) -> bytes | None:
        if companion.peer is None:
            return None
        return companion.feedback(_t(2) + 0.35) if k == 41 else companion.feedback(_t(2)) if k <= 20 else None

    flight = fly(teleop_argv(script_path), feedback=feedback, early=frozenset({41}), max_steps=50)
    cmds = _commands(flight)
    assert cmds[mavlink.MAV_CMD_COMPONENT_ARM_DISARM] == [43], cmds
    assert flight.done_counts[-1] == sum(len(s) for s in flight.steps) and flight.extra == 0


@pytest.mark.parametrize("clock", ["vehicle", "wall"])
def test_teleop_same_steps_same_datagrams_whatever_the_wall_timing(script_path: Path, clock: str) -> None:
    """(c) Byte-identical datagrams at identical steps (MANUAL_CONTROL from the simulated device, its stamps,
    commands, heartbeats, TIMESYNC): a calm flight and one with random wall timing."""
    calm = fly(teleop_argv(script_path, clock), max_steps=400)
    shaken = fly(teleop_argv(script_path, clock), max_steps=400, jitter=random.Random(18))
    assert calm.returncode == shaken.returncode == 0, shaken.output
    assert calm.done_counts == shaken.done_counts
    assert calm.steps == shaken.steps
    assert calm.left_at == shaken.left_at
    assert shaken.early_sent > 20 and shaken.late_sent > 20
    xs = [m.x for _, m in calm.messages() if m.get_type() == "MANUAL_CONTROL"]
    assert len(set(xs)) > 10   # the handle moved: the device's dynamics are in the comparison


def test_teleop_exits_1_when_the_coordinator_goes(script_path: Path) -> None:
    flight = fly(teleop_argv(script_path), max_steps=30, stop_after=20)
    assert flight.returncode == 1, flight.output
    errors = [line for line in flight.output.splitlines() if line.startswith("quadlink: error:")]
    assert len(errors) == 1 and "lock-step" in errors[0], flight.output


def test_teleop_lockstep_refuses_a_real_device() -> None:
    from click.testing import CliRunner

    from quadlink.cli import main

    result = CliRunner().invoke(main, ["teleop", "--device", "gamepad", "--lockstep", "tcp://127.0.0.1:9"])
    assert result.exit_code == 2 and "--lockstep drives the virtual device only" in result.output
    assert TeleopConfig().mapping.rate_hz == 50.0   # the rates the assertions above are written for
    assert TeleopConfig().device.force_rate_hz == 1000.0
