"""The operator view's step: one operator image + its metadata -> pan-scan compensation -> rendered view.

The image's metadata is the companion's :class:`quadlink.operator_image.OperatorImageMeta`, decoded
strictly (:func:`image_meta`): the pan-scan flag the estimator gets, the attitude the renderer uses and
the overlay's velocities and obstacle points all come from it — never from a fallback.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from quadlink.camera import RgbdFrame
from quadlink.operator_image import OperatorImageMeta
from teleop.config import TeleopConfig
from teleop.delay import predicted_displacement_h_m, predicted_points_c_m
from teleop.view.panscan import PanScanEstimate, PanScanEstimator
from teleop.view.render import OperatorViewRenderer, Overlay


def image_meta(frame: RgbdFrame) -> OperatorImageMeta:
    """The frame's metadata; :class:`quadlink.errors.ProtocolError` if it is not the companion's."""
    return OperatorImageMeta.from_wire(frame.meta)


def make_estimator(cfg: TeleopConfig) -> PanScanEstimator:
    v = cfg.view
    return PanScanEstimator(v.initial_frequency_hz, v.min_frequency_hz, v.max_frequency_hz, v.bandpass_q,
                            v.bias_periods, operator_yaw_time_constant_s=v.operator_yaw_time_constant_s)


def overlay(cfg: TeleopConfig, status: dict[str, Any], meta: OperatorImageMeta | None,
            extra_warnings: tuple[str, ...] = (), R_qc: NDArray[np.float64] | None = None) -> Overlay:
    """The view's overlay from the station's status and the image's metadata (pure). Without an image
    (``meta`` None) the velocity arrows are zero. With a measured round trip (``status['rtt_ms']``) and
    an image, the prediction of :mod:`teleop.delay`: the vehicle now, one way (rtt / 2) after the image."""
    zero = (0.0, 0.0, 0.0)
    bat = f"{status['battery_v']:.1f} V" if status["battery_v"] is not None else "- V"
    obst = f"{status['min_obstacle_m']:.2f} m" if status["min_obstacle_m"] is not None else "none"
    scan = "-" if meta is None else ("on" if meta.pan_scan.enabled else "off")
    rtt_ms = status.get("rtt_ms")
    delay = ("RTT - ms" if rtt_ms is None else
             f"RTT {rtt_ms:.0f} ms (p50 {_ms(status.get('rtt_p50_ms'))} p99 {_ms(status.get('rtt_p99_ms'))})")
    prediction = None
    points_now: tuple[tuple[float, float, float], ...] = ()
    if meta is not None and rtt_ms is not None and R_qc is not None:
        prediction = predicted_displacement_h_m(meta.v_est_h_m_s, 0.5 * rtt_ms * 1e-3)
        if prediction is not None and meta.obstacle_points_c_m:
            moved = predicted_points_c_m(meta.obstacle_points_c_m, prediction, meta.roll_rad, meta.pitch_rad, R_qc)
            points_now = tuple((float(p[0]), float(p[1]), float(p[2])) for p in moved)
    if prediction is not None:
        delay += f"  vehicle now +{math.hypot(prediction[0], prediction[1]):.2f} m"
    lines = (f"link {status['link']}  mode {status['mode']}  {'ARMED' if status['armed'] else 'disarmed'}",
             f"battery {bat}  obstacle {obst}  pan-scan {scan}", delay, _vertical_line(meta))
    f = status["force_n"]
    return Overlay(v_cmd_h_m_s=meta.v_cmd_h_m_s if meta else zero, v_est_h_m_s=meta.v_est_h_m_s if meta else zero,
                   force_d_n=(float(f[0]), float(f[1]), float(f[2])), force_limit_n=cfg.device.force_limit_n,
                   obstacle_points_c_m=meta.obstacle_points_c_m if meta else (),
                   obstacle_warning_m=cfg.view.obstacle_warning_m, status_lines=lines,
                   warnings=tuple(status["warnings"]) + extra_warnings, prediction_h_m=prediction,
                   predicted_points_c_m=points_now)


def _ms(v: float | None) -> str:
    return "-" if v is None else f"{v:.0f}"


def _m(v: float | None) -> str:
    return "-" if v is None else f"{v:.2f}"


def _vertical_line(meta: OperatorImageMeta | None) -> str:
    """The safety layer's vertical limits as the companion applied them (issue 14): height, floor, ceiling."""
    if meta is None:
        return "height - m  floor -  ceiling -"
    v = meta.vertical
    return f"height {_m(v.height_m)} m  floor {_m(v.floor_height_m)}  ceiling {_m(v.ceiling_height_m)}"


@dataclass(frozen=True)
class ViewFrame:
    image_bgr: NDArray[np.uint8]
    estimate: PanScanEstimate


class OperatorView:
    """Renderer + pan-scan estimator of the view loop (no I/O; time and inputs are arguments)."""

    def __init__(self, cfg: TeleopConfig, estimator: PanScanEstimator | None = None) -> None:
        v = cfg.view
        self.cfg = cfg
        self.renderer = OperatorViewRenderer(v.canvas_width_px, v.canvas_height_px, v.background_decay_s)
        self.estimator = estimator if estimator is not None else make_estimator(cfg)

    def on_image(self, frame: RgbdFrame, meta: OperatorImageMeta, operator_yaw_rate_cmd_rad_s: float,
                 status: dict[str, Any]) -> ViewFrame:
        """One operator image: the estimator takes the gyro and the pan-scan flag of the metadata."""
        est = self.estimator.update(meta.gyro_yaw_rate_rad_s, frame.stamp_s, meta.pan_scan.enabled,
                                    operator_yaw_rate_cmd_rad_s)
        img = self.renderer.render(frame.rgb, frame.intrinsics, frame.R_qc, meta.roll_rad, meta.pitch_rad,
                                   est.yaw_rad, frame.stamp_s, overlay(self.cfg, status, meta, R_qc=frame.R_qc))
        return ViewFrame(img, est)

    def waiting(self, t_s: float, status: dict[str, Any], why: str) -> NDArray[np.uint8]:
        """The page without an image (status and force stay alive)."""
        return self.renderer.render(None, None, np.eye(3), 0.0, 0.0, 0.0, t_s, overlay(self.cfg, status, None, (why,)))
