"""Draws the operator view (section VI-B): the compensated camera image over the exponentially
decaying older images, the obstacle points, the commanded and estimated velocity, the force cue and
the status. Pure apart from the canvas it keeps between frames (time comes with each frame).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from quadlink.camera import CameraIntrinsics
from teleop.view.compensation import R_vc, homography, project, screen_intrinsics

PREDICTION_RIM_M = 0.5   # the velocity inset's rim for the predicted displacement
RED, GREEN, CYAN, YELLOW, WHITE, ORANGE = (0, 0, 255), (0, 220, 0), (255, 220, 0), (0, 230, 255), (255, 255, 255), \
    (0, 140, 255)  # BGR


@dataclass(frozen=True)
class Overlay:
    """What is drawn over the image (H frame NED for velocities, D frame NED for the force)."""

    v_cmd_h_m_s: tuple[float, float, float] = (0.0, 0.0, 0.0)
    v_est_h_m_s: tuple[float, float, float] = (0.0, 0.0, 0.0)
    force_d_n: tuple[float, float, float] = (0.0, 0.0, 0.0)
    force_limit_n: float = 12.0
    obstacle_points_c_m: tuple[tuple[float, float, float], ...] = ()
    obstacle_warning_m: float = 1.0          # nearer points are red, the others orange
    status_lines: tuple[str, ...] = ()
    warnings: tuple[str, ...] = field(default_factory=tuple)
    # where the vehicle is now (teleop.delay): its displacement in H since the image and the obstacle points
    # as seen from there, drawn hollow; None / () without a measured delay
    prediction_h_m: tuple[float, float, float] | None = None
    predicted_points_c_m: tuple[tuple[float, float, float], ...] = ()


class OperatorViewRenderer:
    def __init__(self, width_px: int, height_px: int, decay_time_s: float) -> None:
        self.width_px, self.height_px = width_px, height_px
        self.decay_time_s = decay_time_s
        self._background = np.zeros((height_px, width_px, 3), np.float32)
        self._t_prev: float | None = None
        self.last_shift_px = (0.0, 0.0)

    def render(self, rgb: NDArray[np.uint8] | None, camera: CameraIntrinsics | None, R_qc: NDArray[np.float64],
               roll_rad: float, pitch_rad: float, psi_s_rad: float, stamp_s: float,
               overlay: Overlay) -> NDArray[np.uint8]:
        """One screen image (BGR uint8)."""
        if self._t_prev is not None and stamp_s > self._t_prev:
            self._background *= math.exp(-(stamp_s - self._t_prev) / self.decay_time_s)  # exponential decay
        elif self._t_prev is not None and stamp_s < self._t_prev - 1.0:
            self._background[:] = 0.0   # time went backwards (new flight): start a fresh background
        self._t_prev = stamp_s
        screen = None
        R = np.eye(3)
        if rgb is not None and camera is not None:
            screen = screen_intrinsics(camera, self.width_px, self.height_px)
            R = R_vc(R_qc, roll_rad, pitch_rad, psi_s_rad)
            H = homography(camera, screen, R)
            bgr = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
            warped = cv2.warpPerspective(bgr, H, (self.width_px, self.height_px), flags=cv2.INTER_LINEAR,
                                         borderMode=cv2.BORDER_CONSTANT)
            mask = cv2.warpPerspective(np.full(rgb.shape[:2], 255, np.uint8), H, (self.width_px, self.height_px),
                                       flags=cv2.INTER_NEAREST) > 0
            self._background[mask] = warped[mask]
            c = H @ np.array([camera.cx, camera.cy, 1.0])
            self.last_shift_px = (float(c[0] / c[2] - screen.cx), float(c[1] / c[2] - screen.cy))
        img = np.clip(self._background, 0, 255).astype(np.uint8)
        if screen is not None:
            img = self._draw_current_border(img, camera, screen, R)  # type: ignore[arg-type]
            self._draw_obstacles(img, overlay.obstacle_points_c_m, R, screen, overlay.obstacle_warning_m)
            self._draw_obstacles(img, overlay.predicted_points_c_m, R, screen, overlay.obstacle_warning_m,
                                 hollow=True)
        self._draw_centre(img)
        self._draw_velocity_inset(img, overlay)
        self._draw_force_inset(img, overlay)
        self._draw_text(img, overlay)
        return img

    def _draw_current_border(self, img: NDArray[np.uint8], camera: CameraIntrinsics, screen: CameraIntrinsics,
                             R: NDArray[np.float64]) -> NDArray[np.uint8]:
        H = homography(camera, screen, R)
        corners = np.array([[0, 0], [camera.width - 1, 0], [camera.width - 1, camera.height - 1],
                            [0, camera.height - 1]], np.float64).reshape(-1, 1, 2)
        poly = cv2.perspectiveTransform(corners, H).reshape(-1, 2)
        cv2.polylines(img, [np.round(poly).astype(np.int32)], True, (90, 90, 90), 1, cv2.LINE_AA)
        return img

    def _draw_obstacles(self, img: NDArray[np.uint8], points: tuple[tuple[float, float, float], ...],
                        R: NDArray[np.float64], screen: CameraIntrinsics, warning_m: float = 1.0,
                        hollow: bool = False) -> None:
        if not points:
            return
        p = np.asarray(points, dtype=float).reshape(-1, 3)
        uv = project(p, R, screen)
        dist = np.linalg.norm(p, axis=1)
        for (u, v), d in zip(uv, dist):
            if not (np.isfinite(u) and np.isfinite(v)):
                continue
            radius = int(np.clip(6.0 / max(d, 0.3), 2, 8))      # nearer points are bigger
            colour = RED if d < warning_m else ORANGE
            if hollow:   # predicted: where the point is now relative to the vehicle
                cv2.circle(img, (int(round(u)), int(round(v))), radius + 2, WHITE, 1, cv2.LINE_AA)
                continue
            cv2.circle(img, (int(round(u)), int(round(v))), radius + 1, (0, 0, 0), -1, cv2.LINE_AA)
            cv2.circle(img, (int(round(u)), int(round(v))), radius, colour, -1, cv2.LINE_AA)

    def _draw_centre(self, img: NDArray[np.uint8]) -> None:
        cx, cy = self.width_px // 2, self.height_px // 2
        cv2.line(img, (cx - 10, cy), (cx + 10, cy), YELLOW, 1, cv2.LINE_AA)
        cv2.line(img, (cx, cy - 10), (cx, cy + 10), YELLOW, 1, cv2.LINE_AA)

    def _draw_velocity_inset(self, img: NDArray[np.uint8], ov: Overlay) -> None:
        """Top-down H frame: forward = up, right = right; green = commanded, cyan = estimated."""
        r = 45
        cx, cy = r + 10, self.height_px - r - 10
        cv2.circle(img, (cx, cy), r, (60, 60, 60), -1)
        cv2.circle(img, (cx, cy), r, WHITE, 1, cv2.LINE_AA)
        scale = r / 1.0   # px per m/s, 1 m/s at the rim
        for v, colour in ((ov.v_cmd_h_m_s, GREEN), (ov.v_est_h_m_s, CYAN)):
            end = (int(round(cx + scale * np.clip(v[1], -1.5, 1.5))), int(round(cy - scale * np.clip(v[0], -1.5, 1.5))))
            cv2.arrowedLine(img, (cx, cy), end, colour, 2, cv2.LINE_AA, tipLength=0.25)
        if ov.prediction_h_m is not None:   # ghost: the vehicle now, 0.5 m at the rim
            d = np.clip(np.asarray(ov.prediction_h_m[:2], dtype=float) / PREDICTION_RIM_M, -1.0, 1.0) * r
            ghost = (int(round(cx + d[1])), int(round(cy - d[0])))
            cv2.circle(img, ghost, 5, WHITE, 1, cv2.LINE_AA)
            cv2.line(img, (cx, cy), ghost, WHITE, 1, cv2.LINE_AA)
        cv2.putText(img, "v cmd", (cx - r, cy - r - 14), cv2.FONT_HERSHEY_SIMPLEX, 0.35, GREEN, 1, cv2.LINE_AA)
        cv2.putText(img, "v est", (cx - r, cy - r - 3), cv2.FONT_HERSHEY_SIMPLEX, 0.35, CYAN, 1, cv2.LINE_AA)

    def _draw_force_inset(self, img: NDArray[np.uint8], ov: Overlay) -> None:
        """Force cue in D: x (forward) up, y right; vertical bar = z (down)."""
        r = 45
        cx, cy = self.width_px - r - 30, self.height_px - r - 10
        f = np.asarray(ov.force_d_n, dtype=float)
        mag = float(np.linalg.norm(f))
        colour = ORANGE if mag < 0.5 * ov.force_limit_n else RED
        cv2.circle(img, (cx, cy), r, (60, 60, 60), -1)
        cv2.circle(img, (cx, cy), r, WHITE, 1, cv2.LINE_AA)
        scale = r / (0.5 * ov.force_limit_n)
        end = (int(round(cx + np.clip(scale * f[1], -r, r))), int(round(cy - np.clip(scale * f[0], -r, r))))
        cv2.arrowedLine(img, (cx, cy), end, colour, 3, cv2.LINE_AA, tipLength=0.25)
        bx = self.width_px - 15
        h = int(np.clip(scale * f[2], -r, r))
        cv2.rectangle(img, (bx - 5, cy), (bx + 5, cy + h), colour, -1)
        cv2.putText(img, f"force {mag:4.1f} N", (cx - r, cy - r - 3), cv2.FONT_HERSHEY_SIMPLEX, 0.35, colour, 1,
                    cv2.LINE_AA)

    def _draw_text(self, img: NDArray[np.uint8], ov: Overlay) -> None:
        y = 14
        for line in ov.status_lines:
            cv2.putText(img, line, (6, y), cv2.FONT_HERSHEY_SIMPLEX, 0.42, WHITE, 1, cv2.LINE_AA)
            y += 15
        for line in ov.warnings:
            cv2.putText(img, line, (6, y), cv2.FONT_HERSHEY_SIMPLEX, 0.42, RED, 1, cv2.LINE_AA)
            y += 15
