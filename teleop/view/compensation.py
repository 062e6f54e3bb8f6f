"""Image compensation geometry for the operator view (section VI-B). Pure.

The screen is a *virtual camera* V: it looks along the real camera's optical axis as it would be
at the centre of the pan-scan oscillation with the body level, and it is upright (x horizontal to
the right, y down), so a portrait-mounted camera is shown upright. The real camera C at the current
attitude is related to V by

    R_VC = R_HV^T Rz(psi_s) R_HQ(roll, pitch) R_QC

(psi_s: yaw displacement from the centre of oscillation, from the pan-scan estimator; roll and
pitch from the vehicle's attitude), and the image is drawn on the screen through the rotation
homography ``H = K_V R_VC K_C^-1``. For a forward-looking camera this is the paper's horizontal
shift p_x = k_px psi_s with k_px = f_x (pixels per radian, from the image size and the FOV), plus
the roll/pitch compensation; for the tilted, portrait camera of the MK-Quadro it is the exact
generalisation.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from quadlink.camera import CameraIntrinsics
from quadlink.frames import R_hq, Rz

Mat3 = NDArray[np.float64]


def virtual_camera_R_hv(R_qc: Mat3) -> Mat3:
    """Upright virtual camera looking along the real camera's axis (level body), columns = its axes in H."""
    z_v = np.asarray(R_qc, dtype=float)[:, 2]
    z_v = z_v / np.linalg.norm(z_v)
    x_v = np.cross(np.array([0.0, 0.0, 1.0]), z_v)   # horizontal, to the right of the view direction
    n = np.linalg.norm(x_v)
    x_v = x_v / n if n > 1e-6 else np.asarray(R_qc, dtype=float)[:, 0]  # camera looking straight down
    y_v = np.cross(z_v, x_v)
    return np.column_stack([x_v, y_v, z_v])


def R_vc(R_qc: Mat3, roll_rad: float, pitch_rad: float, psi_s_rad: float) -> Mat3:
    """Real camera -> virtual (screen) camera rotation (module doc)."""
    return virtual_camera_R_hv(R_qc).T @ Rz(psi_s_rad) @ R_hq(roll_rad, pitch_rad) @ np.asarray(R_qc, dtype=float)


def screen_intrinsics(camera: CameraIntrinsics, width_px: int, height_px: int) -> CameraIntrinsics:
    """Screen camera: the real focal lengths, principal point at the screen centre."""
    return CameraIntrinsics(camera.fx, camera.fy, (width_px - 1) / 2.0, (height_px - 1) / 2.0, width_px, height_px)


def homography(camera: CameraIntrinsics, screen: CameraIntrinsics, R_vc_: Mat3) -> Mat3:
    """Pixel map real image -> screen for a pure rotation (the camera-to-scene distance does not matter)."""
    return screen.matrix() @ R_vc_ @ np.linalg.inv(camera.matrix())


def project(points_c_m: NDArray[np.float64], R_vc_: Mat3, screen: CameraIntrinsics) -> NDArray[np.float64]:
    """Camera-frame points -> screen pixels (N x 2); NaN rows for points behind the screen camera."""
    p = np.asarray(points_c_m, dtype=float).reshape(-1, 3)
    p_v = p @ R_vc_.T
    out = np.full((len(p), 2), np.nan)
    ok = p_v[:, 2] > 1e-3
    uv = p_v[ok] @ screen.matrix().T
    out[ok] = uv[:, :2] / uv[:, 2:3]
    return out


def image_centre_on_screen(camera: CameraIntrinsics, screen: CameraIntrinsics, R_vc_: Mat3) -> NDArray[np.float64]:
    """Where the real image's centre lands on the screen (pixels)."""
    H = homography(camera, screen, R_vc_)
    c = H @ np.array([camera.cx, camera.cy, 1.0])
    return c[:2] / c[2]
