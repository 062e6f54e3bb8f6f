"""Bridge figures (issue 4): IMU frame -> HIGHRES_IMU latency, and CPU per second of flight.

Runs ``quadlink bridge`` as its own process against an in-process fake board (two TCP ports on
loopback) and a fake companion (UDP):

* the board writes one 22-byte IMU frame every 2 ms (500 Hz, the real port-2 pacing) and a
  BoardStatus at 10 Hz, and drains the bridge's 100 Hz AttitudeSetpoints;
* the companion sends ODOMETRY at 30 Hz and velocity setpoints (SET_POSITION_TARGET_LOCAL_NED,
  type_mask 1479) at 20 Hz, and receives everything the bridge sends;
* latency = arrival of the HIGHRES_IMU datagram (timestamped on receipt, decoded afterwards)
  minus the moment the IMU frame's last byte was handed to the socket. It includes loopback TCP
  and UDP and this process's own wake-up, so it is an upper bound on the bridge's share.

CPU: user + system seconds of the bridge process (psutil) per second of wall time. The fake board
does not fly, so the bridge runs its 100 Hz control path with the vehicle on the ground (armed by the
companion after 1 s; the bridge auto-disarms after COM_DISARM_PRFLT = 10 s without take-off, as PX4
does) and all telemetry at full rate.

``--busy`` keeps every core busy with a CPU burner per core (a loaded companion board) and runs this process,
which plays the board and the companion, under ``SCHED_FIFO`` (the hardware does not wait for a CPU), so that
the figure is the bridge's own tail; ``--rt-priority N`` starts the bridge with ``--rt-priority N``.

``--cpu-share CORES`` holds the bridge to that much CPU (a CFS share, ``harness.cpu_share``; needs root): a starved
board, where the bridge merges the IMU samples it is late for instead of queueing them.

    python benchmarks/bench_bridge.py [--seconds 20] [--busy] [--rt-priority 20] [--cpu-share 0.15]
"""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import re
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import psutil

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from harness.cpu_share import CpuShare  # noqa: E402
from quadlink.frames import GRAVITY_M_S2  # noqa: E402
from quadlink.mavlink import mavlink  # noqa: E402
from quadlink.mk import messages as mk  # noqa: E402
from quadlink.mk.protocol import ADDR_FC, FrameDecoder, encode_frame  # noqa: E402
from quadlink.realtime import set_realtime_priority  # noqa: E402
from quadlink.vehicle import VehicleConfig  # noqa: E402

TARGET_P99_MS = 2.0
BOARD_PRIORITY = 50   # --busy: the fake board and companion, above the bridge's real-time priority


def free_port(kind: int) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--busy", action="store_true", help="a CPU burner per core during the run (loaded board)")
    parser.add_argument("--rt-priority", type=int, default=0, help="the bridge's --rt-priority (0: normal)")
    parser.add_argument("--cpu-share", type=float, default=0.0,
                        help="hold the bridge to this many cores (CFS, harness.cpu_share; needs root); 0: none")
    args = parser.parse_args()
    with contextlib.ExitStack() as held:
        share = held.enter_context(CpuShare(args.cpu_share)) if args.cpu_share > 0 else None
        _run(args, share)


def _run(args: argparse.Namespace, share: CpuShare | None) -> None:

    cmd_srv = socket.create_server(("127.0.0.1", 0))
    imu_srv = socket.create_server(("127.0.0.1", 0))
    udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    udp.bind(("127.0.0.1", 0))
    udp.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
    udp.settimeout(0.2)
    tmp = Path(tempfile.mkdtemp(prefix="bench_bridge_"))
    (tmp / "bridge.yaml").write_text("status_log_interval_s: 5.0\n")
    log_path = tmp / "bridge.log"
    with open(log_path, "w") as log_file:
        bridge = subprocess.Popen(
            [sys.executable, "-m", "quadlink.cli", "bridge", "--mk-cmd",
             f"socket://127.0.0.1:{cmd_srv.getsockname()[1]}", "--mk-imu",
             f"socket://127.0.0.1:{imu_srv.getsockname()[1]}", "--mavlink", f"udpout:127.0.0.1:{udp.getsockname()[1]}",
             "--params", str(tmp / "params.yaml"), "--config", str(tmp / "bridge.yaml"),
             "--rt-priority", str(args.rt_priority)],
            cwd=REPO, start_new_session=True, stdout=log_file, stderr=subprocess.STDOUT)
    if share is not None:
        share.add(bridge.pid)
    cmd_srv.settimeout(20.0)
    imu_srv.settimeout(20.0)
    cmd, _ = cmd_srv.accept()
    imu, _ = imu_srv.accept()
    imu.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    cmd.settimeout(0.05)

    stop = threading.Event()
    sent_at: dict[int, float] = {}
    datagrams: list[tuple[float, bytes]] = []
    bridge_addr: list[tuple[str, int]] = []
    armed = [False]

    def receive() -> None:
        while not stop.is_set():
            try:
                data, addr = udp.recvfrom(65535)
            except TimeoutError:
                continue
            datagrams.append((time.perf_counter(), data))
            if not bridge_addr:
                bridge_addr.append(addr)

    def board_cmd() -> None:
        decoder = FrameDecoder()
        while not stop.is_set():
            try:
                raw = cmd.recv(4096)
            except TimeoutError:
                continue
            except OSError:
                return
            for frame in decoder.feed(raw):
                if frame.command == "s":
                    armed[0] = mk.AttitudeSetpoint.unpack(frame.payload).armed
                elif frame.command == "v":
                    cmd.sendall(encode_frame(ADDR_FC, "V", mk.Version(2, 10, 11, 0, 0).pack()))

    def companion() -> None:
        enc = mavlink.MAVLink(None, 255, 190)
        k = 0
        while not stop.wait(1.0 / 60.0):
            if not bridge_addr:
                continue
            k += 1
            msgs = [enc.odometry_encode(k, mavlink.MAV_FRAME_LOCAL_FRD, mavlink.MAV_FRAME_BODY_FRD, 0, 0, 0,
                                        [1, 0, 0, 0], 0, 0, 0, 0, 0, 0, [math.nan] * 21, [math.nan] * 21,
                                        0, 0, 100)] \
                if k % 2 == 0 else []
            if k % 3 == 0:
                msgs.append(enc.set_position_target_local_ned_encode(0, 1, 1, mavlink.MAV_FRAME_BODY_NED, 1479, 0, 0, 0,
                                                                     0, 0, 0, 0, 0, 0, 0, 0))
            if k == 60:
                msgs.append(enc.command_long_encode(1, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0))
            for m in msgs:
                udp.sendto(m.pack(enc), bridge_addr[0])

    # --busy: the burners first, then this process (the board) under SCHED_FIFO — after every child is started,
    # since children inherit the policy (real-time burners would starve the machine)
    # (each burner also ends by itself shortly after the run, should this process die without its cleanup)
    burn = f"import time\nend = time.monotonic() + {args.seconds + 60.0}\nwhile time.monotonic() < end: pass"
    burners = [subprocess.Popen([sys.executable, "-c", burn]) for _ in range(os.cpu_count() or 1)] if args.busy else []
    if args.busy and not set_realtime_priority(BOARD_PRIORITY):
        print("  (could not run the fake board under SCHED_FIFO: its own waits count in the figure)")
    threads = [threading.Thread(target=f, daemon=True) for f in (receive, board_cmd, companion)]
    for t in threads:
        t.start()
    imu_cfg = VehicleConfig().imu
    frame_bytes = [encode_frame(ADDR_FC, "I", mk.ImuSample.from_si([0.01, -0.02, -GRAVITY_M_S2], [0.001, 0.0, 0.02],
                                                                   imu_cfg, k).pack()) for k in range(4096)]
    proc = psutil.Process(bridge.pid)
    warmup_s = 3.0
    t_start = time.perf_counter()
    cpu0 = None
    wall0 = 0.0
    k = 0
    try:
        while True:
            due = t_start + k * 0.002
            now = time.perf_counter()
            if due > now:
                time.sleep(due - now)
            if k % 50 == 0:
                status = mk.BoardStatus(armed[0], 0, False, 12000, 0, k * 2, k, 0)
                cmd.sendall(encode_frame(ADDR_FC, "S", status.pack()))
            imu.sendall(frame_bytes[k % 4096])
            sent_at[k] = time.perf_counter()
            k += 1
            elapsed = time.perf_counter() - t_start
            if cpu0 is None and elapsed >= warmup_s:
                t = proc.cpu_times()
                cpu0, wall0 = t.user + t.system, time.perf_counter()
            if elapsed >= warmup_s + args.seconds:
                break
        t = proc.cpu_times()
        cpu_s = t.user + t.system - (cpu0 or 0.0)
        wall_s = time.perf_counter() - wall0
    finally:
        for b in burners:
            b.kill()
            b.wait()
        stop.set()
        for t in threads:
            t.join(timeout=2.0)
        if bridge.poll() is None:
            os.killpg(bridge.pid, signal.SIGINT)
            try:
                bridge.wait(timeout=10.0)
            except subprocess.TimeoutExpired:
                os.killpg(bridge.pid, signal.SIGKILL)
        for s in (cmd, imu, cmd_srv, imu_srv, udp):
            s.close()

    parser_ = mavlink.MAVLink(None, 255, 190)
    parser_.robust_parsing = True
    latencies = []
    counts: dict[str, int] = {}
    for t_rx, data in datagrams:
        for m in parser_.parse_buffer(data) or []:
            counts[m.get_type()] = counts.get(m.get_type(), 0) + 1
            if m.get_type() == "HIGHRES_IMU":
                k_rx = m.time_usec // 2000
                t_tx = sent_at.get(k_rx)
                if t_tx is not None and (t_tx - t_start) >= warmup_s:
                    latencies.append(t_rx - t_tx)
    lat_ms = np.array(latencies) * 1e3
    print(f"bench_bridge: {k} IMU frames sent at 500 Hz, {len(lat_ms)} HIGHRES_IMU measured after "
          f"{warmup_s:.0f} s warm-up")
    print("  messages received: " + ", ".join(f"{n} {c}" for n, c in sorted(counts.items())))
    if len(lat_ms):
        p50, p99, mx = np.percentile(lat_ms, 50), np.percentile(lat_ms, 99), lat_ms.max()
        print(f"  IMU frame last byte -> HIGHRES_IMU on UDP: p50 {p50:.3f} ms  p99 {p99:.3f} ms  max {mx:.2f} ms "
              f"(target p99 <= {TARGET_P99_MS} ms: {'met' if p99 <= TARGET_P99_MS else 'NOT met'}; "
              f"p99/target = {p99 / TARGET_P99_MS:.2f})")
    inside = re.findall(r"in-process p50 ([0-9.]+) p99 ([0-9.]+) ms", log_path.read_text())
    if inside:
        print(f"  of which inside the bridge (bytes read -> HIGHRES_IMU handed to the socket, last 5000): "
              f"p50 {float(inside[-1][0]):.3f} ms  p99 {float(inside[-1][1]):.3f} ms")
    print(f"  bridge CPU: {cpu_s:.2f} s over {wall_s:.1f} s of flight = {100 * cpu_s / wall_s:.1f} % of one core "
          f"(500 Hz IMU in, 500 Hz HIGHRES_IMU + 50 Hz ATTITUDE out, 100 Hz board setpoints, "
          f"30 Hz ODOMETRY + 20 Hz setpoints in)")
    print(f"  machine: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f} (other processes share them); "
          f"{'a CPU burner per core, ' if args.busy else ''}bridge "
          f"{'SCHED_FIFO ' + str(args.rt_priority) if args.rt_priority else 'at normal priority'}"
          + (f", held to {share.cores} core (throttled {share.throttled_s():.1f} s)" if share is not None else ""))


if __name__ == "__main__":
    main()
