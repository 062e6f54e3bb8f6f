"""What the ground station records: the CSV log of the network loop (force, handle, command, feedback)
and the operator view as a video file."""

from __future__ import annotations

import csv
import logging
import math
from pathlib import Path
from typing import Any, TextIO

import cv2

from quadlink.errors import LinkError
from teleop.delay import LinkDelay
from teleop.force_loop import ForceSnapshot, MotionInput
from teleop.mapping import ManualControl
from teleop.telemetry import Telemetry

log = logging.getLogger(__name__)

CSV_FIELDS = ["t_s", "qx_m", "qy_m", "qz_m", "qdx_m_s", "qdy_m_s", "qdz_m_s", "fop_x_n", "fop_y_n", "fop_z_n",
              "tau_x_n", "tau_y_n", "tau_z_n", "qtx_m", "qty_m", "qtz_m", "link_gain", "cmd_x", "cmd_z", "cmd_r",
              "vx_h", "vy_h", "vz_h", "vx_cmd", "vy_cmd", "vz_cmd", "vx_rep", "vy_rep", "vz_rep", "alpha_rad",
              "yaw_rate", "pan_scan_rate_used", "obstacle_m", "mode", "flags", "armed",
              # issue 18: the measured round trip to the companion (TIMESYNC) and the port's energy account
              "rtt_ms", "rtt_p50_ms", "rtt_p99_ms", "clock_offset_ms",
              "pass_observed_j", "pass_min_observed_j", "pass_input_j", "pass_output_j", "pass_dissipated_j",
              "pass_damping_n_s_m"]


def csv_row(t_s: float, force: ForceSnapshot | None, cmd: ManualControl, tel: Telemetry,
            motion: MotionInput | None, delay: LinkDelay | None = None) -> list[Any]:
    """One row of :data:`CSV_FIELDS` (pure)."""
    z3 = (0.0, 0.0, 0.0)
    dev = force.device if force else None
    q = dev.q_m if dev is not None else z3
    qd = dev.qdot_m_s if dev is not None else z3
    fop = dev.operator_force_n if dev is not None and dev.operator_force_n is not None else z3
    tau = force.tau_d_n if force else z3
    qt = force.q_tilde_m if force and force.q_tilde_m is not None else (math.nan,) * 3
    fb = tel.feedback
    row: list[Any] = [f"{t_s:.4f}", *(f"{v:.5f}" for v in q), *(f"{v:.5f}" for v in qd),
                      *(f"{v:.4f}" for v in fop), *(f"{v:.4f}" for v in tau), *(f"{v:.5f}" for v in qt),
                      f"{force.link_gain if force else 0.0:.3f}", cmd.x, cmd.z, cmd.r]
    if fb is not None:
        row += [*(f"{v:.4f}" for v in fb.v_h_m_s), *(f"{v:.4f}" for v in fb.v_cmd_h_m_s),
                *(f"{v:.4f}" for v in fb.v_rep_h_m_s), f"{fb.alpha_rad:.4f}", f"{fb.gyro_yaw_rate_rad_s:.4f}",
                f"{motion.motion.pan_scan_yaw_rate_rad_s if motion else 0.0:.4f}",
                "" if fb.obstacle_distance_m is None else f"{fb.obstacle_distance_m:.3f}", fb.mode, fb.flags]
    else:
        row += [""] * 15
    row.append(int(tel.armed))
    d = delay if delay is not None else LinkDelay()
    row += [_num(d.rtt_s * 1e3, 2), _num(d.rtt_p50_s * 1e3, 2), _num(d.rtt_p99_s * 1e3, 2), _num(d.offset_s * 1e3, 3)]
    p = force.passivity if force is not None else None
    row += ([f"{v:.6f}" for v in (p.observed_j, p.min_observed_j, p.input_j, p.output_j, p.dissipated_j)]
            + [f"{p.damping_n_s_m:.3f}"] if p is not None else [""] * 6)
    return row


def _num(v: float, decimals: int) -> str:
    return f"{v:.{decimals}f}" if math.isfinite(v) else ""


class CsvLog:
    """The network loop's CSV log (header first); ``close`` is idempotent."""

    def __init__(self, path: str) -> None:
        self.path = path
        self._file: TextIO | None = open(path, "w", newline="", encoding="utf-8")  # noqa: SIM115 - closed in close()
        self._writer = csv.writer(self._file)
        self._writer.writerow(CSV_FIELDS)
        log.info("logging force/q/command to %s", path)

    def write(self, row: list[Any]) -> None:
        self._writer.writerow(row)

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None


def open_video(path: str, width: int, height: int, fps: float = 30.0) -> cv2.VideoWriter:
    fourcc = cv2.VideoWriter.fourcc(*("MJPG" if Path(path).suffix.lower() == ".avi" else "mp4v"))
    writer = cv2.VideoWriter(path, fourcc, fps, (width, height))
    if not writer.isOpened():
        raise LinkError(f"--record {path}: OpenCV cannot open a video writer (use .avi or .mp4)")
    log.info("recording the operator view to %s", path)
    return writer
