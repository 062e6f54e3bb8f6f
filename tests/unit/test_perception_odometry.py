"""RGB-D odometry on synthetic pairs with known motion and on real TUM frames; metrics, sources, vo-eval."""

from __future__ import annotations

import dataclasses
import importlib.util
import math
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from perception import cli, metrics
from perception.cli import command as vo_eval
from perception.odometry import (
    OdometryConfig,
    RgbdOdometry,
    _adjoint,
    _se3_log,
    fuse_poses,
    prepare_frame,
    rotate_depth,
    se3_exp,
)
from perception.odometry_frame import _reference
from perception.synthetic import pose, qvga_intrinsics, render
from quadlink.datasets.tum import (
    DatasetUnavailable,
    TumSequence,
    associate,
    read_tum_trajectory,
    write_tum_trajectory,
)
from quadlink.errors import ConfigError
from quadlink.frames import R_from_euler
from quadlink.lie import inv_T, so3_log

K = qvga_intrinsics()


def _pair_error(T_w_c0: np.ndarray, T_w_c1: np.ndarray, R_prior: np.ndarray | None = None,
                config: OdometryConfig | None = None) -> tuple[float, float, bool]:
    cfg = config or OdometryConfig()
    f0, f1 = render(T_w_c0, K), render(T_w_c1, K)
    odo = RgbdOdometry(cfg)
    res = odo.align(prepare_frame(*f0, K, cfg), prepare_frame(*f1, K, cfg), R_prior)
    truth = inv_T(T_w_c1) @ T_w_c0      # T_c1_c0
    E = inv_T(truth) @ res.T_ck_ckm1
    return float(np.linalg.norm(E[:3, 3])), math.degrees(np.linalg.norm(so3_log(E[:3, :3]))), res.ok


@pytest.mark.parametrize("name,R,t", [
    ("pure translation", np.eye(3), [0.02, -0.01, 0.015]),
    ("pure rotation", R_from_euler(0.01, -0.015, 0.02), [0.0, 0.0, 0.0]),
    ("combined", R_from_euler(-0.01, 0.012, -0.02), [-0.015, 0.01, 0.02]),
])
def test_synthetic_pair_known_motion(name: str, R: np.ndarray, t: list[float]) -> None:
    T0 = pose(R_from_euler(0.05, -0.1, 0.2), [0.1, 0.2, -0.1])
    T1 = T0 @ pose(R, t)
    err_t, err_r, ok = _pair_error(T0, T1)
    motion = float(np.linalg.norm(t))
    assert ok
    assert err_t < 2e-4 and err_t < 0.01 * motion + 1e-4, name   # a fraction of a millimetre on exact data
    assert err_r < 0.005, name


def test_imu_rotation_prior_rescues_a_fast_rotation() -> None:
    """A 12° rotation between frames: beyond the pyramid's basin without help, fine with the gyro prior."""
    T0 = pose(np.eye(3), [0.0, 0.0, 0.0])
    R_rel = R_from_euler(0.05, 0.12, 0.17)
    T1 = T0 @ pose(R_rel, [0.01, 0.0, 0.0])
    err_no, _, _ = _pair_error(T0, T1)
    # the prior is the camera rotation k-1 -> k (as integrated from the gyro), slightly wrong (0.3°)
    noisy_prior = R_rel @ se3_exp(np.array([0, 0, 0, 0.003, -0.003, 0.002]))[:3, :3]
    err_prior, err_r, ok = _pair_error(T0, T1, noisy_prior)
    assert ok
    assert err_prior < 2e-3
    assert err_r < 0.1
    assert err_no > 10 * err_prior


def test_constant_velocity_prior_term_pulls_the_translation_by_its_weight() -> None:
    """DVO's motion prior on the translation: a prediction 5 mm off the true motion. Without the term the
    alignment finds the truth; with a tiny sigma it returns the prediction's translation (the term's Jacobian has
    the right sign and frame, or it would diverge); in between, the smaller the sigma the nearer the prediction."""
    T0 = pose(R_from_euler(0.05, -0.1, 0.2), [0.1, 0.2, -0.1])
    T1 = T0 @ pose(R_from_euler(-0.01, 0.012, -0.02), [-0.015, 0.01, 0.02])
    truth = inv_T(T1) @ T0                       # T_c1_c0
    off = truth.copy()
    off[:3, 3] += [0.004, -0.003, 0.0]           # the prediction: 5 mm off
    f0, f1 = render(T0, K), render(T1, K)
    errors = {}
    for sigma in (0.0, 2e-4, 3e-5, 1e-7):
        cfg = OdometryConfig(motion_prior_sigma_m=sigma)
        res = RgbdOdometry(cfg).align(prepare_frame(*f0, K, cfg), prepare_frame(*f1, K, cfg), T_init=truth,
                                      T_motion_prior=off)
        assert res.ok
        errors[sigma] = (float(np.linalg.norm(res.T_ck_ckm1[:3, 3] - truth[:3, 3])),
                         float(np.linalg.norm(res.T_ck_ckm1[:3, 3] - off[:3, 3])))
    assert errors[0.0][0] < 2e-4
    assert errors[1e-7][1] < 1e-4
    to_truth = [errors[s][0] for s in (0.0, 2e-4, 3e-5, 1e-7)]
    assert to_truth == sorted(to_truth) and to_truth[1] > 1.5 * to_truth[0] and to_truth[2] > 10 * to_truth[1]


def test_brightness_change_recovered_by_the_affine_model() -> None:
    """Exposure change between frames (gain 0.8, bias +0.06): photometric-only alignment is biased by
    millimetres without the brightness model; with it the motion and the gain/bias are recovered."""
    T0 = pose(R_from_euler(0.05, -0.1, 0.2), [0.1, 0.2, -0.1])
    T1 = T0 @ pose(R_from_euler(-0.01, 0.012, -0.02), [-0.015, 0.01, 0.02])
    (rgb0, d0), (rgb1, d1) = render(T0, K), render(T1, K)
    rgb1 = np.clip(rgb1.astype(np.float32) * 0.8 + 0.06 * 255, 0, 255).astype(np.uint8)
    truth = inv_T(T1) @ T0
    errors = {}
    for affine in (False, True):
        cfg = OdometryConfig(affine_brightness=affine, depth_weight=0.0)
        res = RgbdOdometry(cfg).align(prepare_frame(rgb0, d0, K, cfg), prepare_frame(rgb1, d1, K, cfg))
        E = inv_T(truth) @ res.T_ck_ckm1
        errors[affine] = float(np.linalg.norm(E[:3, 3]))
        if affine:
            assert res.ok
            assert res.gain == pytest.approx(0.8, abs=0.01) and res.bias == pytest.approx(0.06, abs=0.005)
            assert math.degrees(np.linalg.norm(so3_log(E[:3, :3]))) < 0.01
    assert errors[True] < 3e-4
    assert errors[False] > 5 * errors[True]


def test_constant_velocity_start_tracks_an_accelerating_rotation() -> None:
    """Yaw steps of 3, 6 and 9 degrees between frames: from identity a step beyond ~4 degrees leaves the
    pyramid's basin (no gyro here), started from the previous pair's motion each pair is a 3-degree problem."""
    T_w = [pose(R_from_euler(0.05, -0.1, 0.2), [0.1, 0.2, -0.1])]
    for deg in (3.0, 6.0, 9.0):
        T_w.append(T_w[-1] @ pose(R_from_euler(0.0, math.radians(deg), 0.0), [0.004, 0.0, 0.0]))
    frames = [render(T, K) for T in T_w]
    odo = RgbdOdometry()
    for k, (rgb, depth) in enumerate(frames):
        res = odo.process(k / 30, rgb, depth, K)
        assert res.ok, k
        E = inv_T(inv_T(T_w[0]) @ T_w[k]) @ res.T_c0_ck
        assert np.linalg.norm(E[:3, 3]) < 1e-3 and math.degrees(np.linalg.norm(so3_log(E[:3, :3]))) < 0.02, k
    cfg = odo.config
    alone = odo.align(prepare_frame(*frames[2], K, cfg), prepare_frame(*frames[3], K, cfg))
    E = inv_T(inv_T(T_w[3]) @ T_w[2]) @ alone.T_ck_ckm1
    assert math.degrees(np.linalg.norm(so3_log(E[:3, :3]))) > 0.5   # the 9-degree pair from identity fails


def test_reference_jacobian_matches_finite_differences() -> None:
    """Inverse-compositional Jacobian rows of the reference points against central differences of the
    residuals under a small left increment exp(xi) of the reference points."""
    cfg = OdometryConfig()
    rgb, depth = render(pose(R_from_euler(0.05, -0.1, 0.2), [0.1, 0.2, -0.1]), K)
    level = prepare_frame(rgb, depth, K, cfg).levels[0]
    gray_tex = cv2.GaussianBlur(level.gray, (0, 0), 0.7)   # smooth enough for a finite difference
    level_smooth = dataclasses.replace(level, gray=gray_tex, grad=None)   # gradients of the smoothed image
    rp = _reference(level_smooth, 2000, 0.75, affine=False)
    n = rp.I.shape[0]
    P = rp.P[:3].astype(np.float64)

    def residuals(xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        T = se3_exp(xi)
        Q = T[:3, :3] @ P + T[:3, 3:4]
        u = (K.fx * Q[0] / Q[2] + K.cx).astype(np.float32).reshape(1, -1)
        v = (K.fy * Q[1] / Q[2] + K.cy).astype(np.float32).reshape(1, -1)
        i = cv2.remap(gray_tex, u, v, cv2.INTER_LINEAR)[0]
        z = cv2.remap(level.depth, u, v, cv2.INTER_LINEAR)[0]
        return i.astype(np.float64), (z - Q[2]) * rp.z_norm
    h = 1e-4
    for k in range(6):
        xi = np.zeros(6)
        xi[k] = h
        (ip, zp), (im, zm) = residuals(xi), residuals(-xi)
        for numeric, analytic, mask in ((ip - im, rp.J[k, :n], np.ones(n, bool)),
                                        (zp - zm, rp.J[k, n:], rp.z_ok)):
            numeric = numeric[mask] / (2 * h)
            analytic = analytic[mask].astype(np.float64)
            # Sobel gradients vs bilinear slopes differ point by point; the rows must agree as a whole
            assert np.corrcoef(numeric, analytic)[0, 1] > 0.95, k
            assert float(analytic @ numeric / (analytic @ analytic)) == pytest.approx(1.0, abs=0.1), k


def test_depth_term_skips_depth_discontinuities() -> None:
    """A box 0.5 m in front of a wall: reference points on the box's outline have no depth term, points on
    the flat faces keep it."""
    depth = np.full((240, 320), 2.0, np.float32)
    depth[80:160, 100:220] = 1.5
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 255, (240, 320, 3), dtype=np.uint8)
    cfg = OdometryConfig()
    level = prepare_frame(rgb, depth, K, cfg).levels[0]
    rp = _reference(level, 20000, 0.75, affine=False)
    u = np.rint(K.fx * rp.P[0] / rp.P[2] + K.cx).astype(int)
    v = np.rint(K.fy * rp.P[1] / rp.P[2] + K.cy).astype(int)
    # the pixels whose 3x3 neighbourhood straddles the step
    on_edge = (np.isin(u, (99, 100, 219, 220)) & (v >= 79) & (v <= 160)) \
        | (np.isin(v, (79, 80, 159, 160)) & (u >= 99) & (u <= 220))
    assert on_edge.sum() > 50
    assert not rp.z_ok[on_edge].any()
    assert rp.z_ok[~on_edge].mean() > 0.99


def test_invalid_depth_and_textureless_frames_do_not_crash() -> None:
    odo = RgbdOdometry()
    rgb = np.full((240, 320, 3), 128, np.uint8)
    depth = np.zeros((240, 320), np.float32)
    r0 = odo.process(0.0, rgb, depth, K)
    r1 = odo.process(0.033, rgb, depth, K)
    assert r0.ok and not r1.ok
    assert np.allclose(r1.T_c0_ck, np.eye(4))
    depth_nan = np.full((240, 320), np.nan, np.float32)
    r2 = odo.process(0.066, rgb, depth_nan, K)
    assert not r2.ok and np.all(np.isfinite(r2.T_c0_ck))


def test_chained_poses_on_a_synthetic_sequence() -> None:
    odo = RgbdOdometry()
    poses_true, poses_est, stamps = [], [], []
    for k in range(8):
        t = k / 30
        T = pose(R_from_euler(0.05 * math.sin(3 * t), 0.1 * t, 0.2 * t), [0.3 * t, -0.1 * t, 0.05 * math.sin(4 * t)])
        rgb, depth = render(T, K)
        res = odo.process(t, rgb, depth, K)
        assert res.ok
        poses_true.append(T)
        poses_est.append(res.T_c0_ck)
        stamps.append(t)
    gt = np.array([inv_T(poses_true[0]) @ T for T in poses_true])
    est = np.array(poses_est)
    rpe = metrics.rpe(np.array(stamps), est, gt)
    assert rpe.trans_rmse_m_s < 0.02            # < 0.7 mm per frame at 30 Hz
    assert rpe.rot_rmse_deg_s < 0.5
    assert metrics.ate(est, gt).rmse_m < 2e-3


def test_a_jump_no_multirotor_can_make_is_refused_and_tracking_resumes() -> None:
    """Hovering, then one frame rendered 9 cm away (a wrong alignment as seen in the SITL looks like this to
    the velocity estimate): refused as not ok, the pose keeps its place, and tracking resumes after it."""
    odo = RgbdOdometry()
    base = pose(np.eye(3), [0.0, 0.0, 0.0])
    results = [odo.process(k / 30, *render(base, K), K) for k in range(4)]
    assert all(r.ok for r in results)
    jumped = pose(np.eye(3), [0.09, 0.0, 0.0])
    r = odo.process(4 / 30, *render(jumped, K), K)
    assert not r.ok and odo.rejected_jumps == 1
    assert np.linalg.norm(r.T_c0_ck[:3, 3]) < 1e-3          # held, not moved by the suspicious alignment
    # from there on (no velocity prediction after a refusal) the new place is tracked again
    r = odo.process(5 / 30, *render(jumped, K), K)
    assert r.ok and np.linalg.norm(r.T_ckm1_ck[:3, 3]) < 1e-3
    # a real, smooth acceleration is not refused: 0.3 m/s gained over 5 frames
    odo2 = RgbdOdometry()
    x = 0.0
    for k in range(8):
        x += 0.06 * max(0, k - 2) / 30
        assert odo2.process(k / 30, *render(pose(np.eye(3), [x, 0.0, 0.0]), K), K).ok
    assert odo2.rejected_jumps == 0


def _striped_floor(T_w_c: np.ndarray, supersample: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Colour and depth of a floor (world z = 0, z up) with wavy stripes 6 cm apart (the SITL's wood) and a weaker
    texture that does not repeat; colour averaged over supersample^2 samples a pixel."""
    offs = (np.arange(supersample) + 0.5) / supersample - 0.5
    u, v = np.meshgrid(np.arange(K.width, dtype=float), np.arange(K.height, dtype=float))
    R, o = T_w_c[:3, :3], T_w_c[:3, 3]

    def cast(uu: np.ndarray, vv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        d = np.stack([(uu - K.cx) / K.fx, (vv - K.cy) / K.fy, np.ones_like(uu)], -1) @ R.T
        t = -o[2] / d[..., 2]
        x, y = o[0] + d[..., 0] * t, o[1] + d[..., 1] * t
        i = 0.5 + 0.25 * np.sin(2 * np.pi * (x / 0.06 + 0.4 * np.sin(2 * np.pi * y / 0.7)))
        i += 0.08 * np.sin(9.1 * x + 13.7 * y + 0.4) + 0.07 * np.sin(-17.3 * x + 7.9 * y + 1.3) \
            + 0.06 * np.sin(5.3 * x - 21.1 * y)
        return np.clip(i, 0.0, 1.0), t
    inten = sum(cast(u + a, v + b)[0] for a in offs for b in offs) / supersample**2
    rgb = np.repeat((inten * 255.0 + 0.5).astype(np.uint8)[..., None], 3, axis=2)
    return rgb, cast(u, v)[1].astype(np.float32)


def _over_the_floor(t: float) -> np.ndarray:
    """1 m above the striped floor, looking 50 degrees down across the stripes, at 0.45 m/s."""
    zc = np.array([math.cos(math.radians(50)), 0.0, -math.sin(math.radians(50))])
    xc = np.array([0.0, -1.0, 0.0])
    return pose(np.stack([xc, np.cross(zc, xc), zc], axis=1), [0.45 * t, 0.0, 1.0])


@pytest.mark.parametrize("restart", [True, False])
def test_a_wrong_constant_velocity_on_a_striped_floor_is_overturned_by_a_restart_from_rest(restart: bool) -> None:
    """The SITL's wood-floor take-offs (campaigns 26 and 20261215: 4 of 4 landed themselves): a few poorly
    constrained frames left the constant velocity wrong, and from that start every frame locked onto the next
    stripe, a period a frame (2 m/s), fit after fit (0.55) and ok. Here the constant velocity is made one period
    (6 cm a frame) wrong: restarted from rest, the motion is exact again at once; without, it stays locked."""
    odo = RgbdOdometry(OdometryConfig(restart_from_rest=restart))

    def step(k: int) -> float:
        t, t_prev = k / 30, (k - 1) / 30
        prior = None if k == 0 else (inv_T(_over_the_floor(t_prev)) @ _over_the_floor(t))[:3, :3]
        res = odo.process(t, *_striped_floor(_over_the_floor(t)), K, prior)
        if k == 0:
            return 0.0
        E = inv_T(inv_T(_over_the_floor(t_prev)) @ _over_the_floor(t)) @ res.T_ckm1_ck
        return float(np.linalg.norm(E[:3, 3])) if res.ok else math.inf

    assert max(step(k) for k in range(4)) < 1e-3
    assert odo._last_motion is not None
    T_last, dt = odo._last_motion
    wrong = T_last.copy()
    wrong[:3, 3] -= _over_the_floor(0.0)[:3, :3].T @ np.array([0.06, 0.0, 0.0])   # one stripe more a frame
    odo._last_motion = (wrong, dt)
    errors = [step(k) for k in range(4, 8)]
    if restart:
        assert max(errors) < 1e-3 and odo.restarts == 1, errors
    else:
        assert min(errors) > 0.03 and odo.restarts == 0, errors   # locked: a period a frame, every frame


def _fast_yaw(t: float) -> np.ndarray:
    """A fast pan: yaw rate rising to 3 rad/s in 0.1 s, then steady (5.7 degrees a frame at 30 Hz), while moving
    at 0.3 m/s."""
    yaw = 15.0 * t * t if t < 0.1 else 0.15 + 3.0 * (t - 0.1)
    return pose(R_from_euler(0.02, yaw, 0.0), [0.3 * t, 0.0, 0.05 * t])


@pytest.mark.parametrize("gyro", [False, True])
def test_a_frame_that_cannot_be_aligned_is_bridged_by_the_motion_prior(gyro: bool) -> None:
    """Fast yaw; frame 6 is blurred beyond use and frame 7 blank (over-exposed), both without depth: neither can
    be aligned. Each moves by the motion prior (the gyro's rotation, else the constant-velocity rotation, and the
    constant-velocity translation), is counted, and is not ok; the motion per frame (what the velocity estimate
    differentiates) stays that of the truth, and tracking resumes at frame 8 against the last keyframe (a frame
    without depth never becomes one)."""
    odo = RgbdOdometry()
    dt = 1 / 30
    for k in range(12):
        t = k * dt
        rgb, depth = render(_fast_yaw(t), K)
        if k in (6, 7):
            depth = np.zeros_like(depth)
            rgb = cv2.GaussianBlur(rgb, (0, 0), 8.0) if k == 6 else np.full_like(rgb, 250)
        prior = (inv_T(_fast_yaw(t - dt)) @ _fast_yaw(t))[:3, :3] if gyro and k > 0 else None
        res = odo.process(t, rgb, depth, K, prior)
        assert res.ok == (k not in (6, 7)), k
        assert res.fallback == (k in (6, 7)), k
        step = inv_T(_fast_yaw(t - dt)) @ _fast_yaw(t)
        if k > 0:
            E = inv_T(step) @ res.T_ckm1_ck
            # an aligned step is accurate to a millimetre; a bridged one to the constant velocity's accuracy: the
            # rotation rate is steady, but the camera-frame direction of the 10 mm step turns with the camera
            # (5.7 degrees a frame: 1 mm more for each frame since the last aligned one); the first aligned step
            # after the bridge takes back the bridge's error (at most 1 + 2 mm here)
            bridge_m = 0.12 * float(np.linalg.norm(step[:3, 3]))
            bound_m = {6: bridge_m, 7: 2 * bridge_m, 8: 3 * bridge_m}.get(k, 1e-3)
            assert np.linalg.norm(E[:3, 3]) < bound_m, k
            assert math.degrees(np.linalg.norm(so3_log(E[:3, :3]))) < 0.05, k
        # the chained pose: exact while aligned, off by the bridge's error while bridged, exact again after it
        E = inv_T(inv_T(_fast_yaw(0.0)) @ _fast_yaw(t)) @ res.T_c0_ck
        bound_m = 4e-3 if k in (6, 7) else 1e-3
        assert np.linalg.norm(E[:3, 3]) < bound_m and math.degrees(np.linalg.norm(so3_log(E[:3, :3]))) < 0.1, k
    assert odo.fallbacks == 2 and odo.lost == 0


def test_the_bridge_ends_after_max_bridged_frames_and_the_pose_then_holds() -> None:
    """The constant velocity is not carried on for ever: past max_bridged_frames failed frames in a row the
    pose holds (counted as lost). The next frame, 23 degrees from the keyframe with no motion to start from, is
    lost too and becomes the keyframe: tracking re-initialises from it."""
    odo = RgbdOdometry(OdometryConfig(max_bridged_frames=2))
    dt = 1 / 30
    flags = []
    for k in range(8):
        rgb, depth = render(_fast_yaw(k * dt), K)
        if 3 <= k <= 5:   # the lens covered
            rgb, depth = np.zeros_like(rgb), np.zeros_like(depth)
        res = odo.process(k * dt, rgb, depth, K)
        flags.append((res.ok, res.fallback))
        if k == 5:
            assert np.allclose(res.T_ckm1_ck, np.eye(4))
    assert flags == [(True, False)] * 3 + [(False, True)] * 2 + [(False, False)] * 2 + [(True, False)]
    assert odo.fallbacks == 2 and odo.lost == 2


def _glide(t: float) -> np.ndarray:
    """A slow pan (0.3 rad/s) while moving at 0.4 m/s across and 0.1 m/s up: a steady velocity."""
    return pose(R_from_euler(0.02, 0.3 * t, 0.0), [0.4 * t, -0.1 * t, 0.05 * t])


def test_a_bridged_frame_after_a_long_interval_moves_by_the_velocity_not_by_three_intervals() -> None:
    """A starved reader's irregular intervals: three frames 33 ms apart, then a frame 0.2 s later (six intervals)
    that cannot be aligned (lens covered). It is bridged by the last velocity over its whole interval (83 mm of
    motion, to a tenth of it: the camera-frame direction of the velocity turns 3.4 degrees with the pan in 0.2 s),
    not by three of the last intervals (a velocity halved, 42 mm off, that the bridge would carry on); the next
    frame, aligned, takes that error back: its pose is accurate to a millimetre."""
    odo = RgbdOdometry()
    stamps = [0.0, 1 / 30, 2 / 30, 2 / 30 + 0.2, 2 / 30 + 0.2 + 1 / 30]
    for k, t in enumerate(stamps):
        rgb, depth = render(_glide(t), K)
        if k == 3:
            rgb, depth = np.zeros_like(rgb), np.zeros_like(depth)
        prior = (inv_T(_glide(stamps[k - 1])) @ _glide(t))[:3, :3] if k else None
        res = odo.process(t, rgb, depth, K, prior)
        assert (res.ok, res.fallback) == ((False, True) if k == 3 else (True, False)), k
        if k:
            step = inv_T(_glide(stamps[k - 1])) @ _glide(t)
            err_m = float(np.linalg.norm((inv_T(step) @ res.T_ckm1_ck)[:3, 3]))
            assert err_m < (8e-3 if k in (3, 4) else 1e-3), (k, err_m)
    E = inv_T(inv_T(_glide(0.0)) @ _glide(stamps[-1])) @ res.T_c0_ck
    assert np.linalg.norm(E[:3, 3]) < 1e-3


def test_a_jump_after_a_bridged_frame_is_refused_unless_the_next_frame_seconds_it() -> None:
    """The jump gate holds after bridged frames too (it measured nothing there, and a wrong basin's 3.6 m/s read
    after a bridged frame flew the dark partition push to 0.267 m). At 30 Hz frame 4 is blank (bridged); frame 5
    is rendered 8 cm off the path (2.4 m/s in one frame, no multirotor's motion): its alignment, however good, is
    refused. The camera then stays on the displaced path: frame 6's alignment agrees with frame 5's and not with
    the carried velocity, so the carried velocity is the one that is wrong: it is accepted (two in a row)."""
    odo = RgbdOdometry()
    dt = 1 / 30
    offset = pose(np.eye(3), [0.08, 0.0, 0.0])

    def truth(k: int) -> np.ndarray:
        return _glide(k * dt) @ offset if k >= 5 else _glide(k * dt)

    flags = []
    for k in range(8):
        rgb, depth = render(truth(k), K)
        if k == 4:
            rgb, depth = np.zeros_like(rgb), np.zeros_like(depth)
        prior = (inv_T(truth(k - 1)) @ truth(k))[:3, :3] if k else None
        res = odo.process(k * dt, rgb, depth, K, prior)
        flags.append((res.ok, res.fallback))
        if k >= 6:
            E = inv_T(inv_T(truth(k - 1)) @ truth(k)) @ res.T_ckm1_ck
            assert np.linalg.norm(E[:3, 3]) < 1e-3, k
    assert flags == [(True, False)] * 4 + [(False, True)] * 2 + [(True, False)] * 2
    assert odo.rejected_jumps == 1 and odo.fallbacks == 2


def test_a_real_frame_without_depth_is_bridged_on_fast_rotation() -> None:
    """The fr1_rpy clip (up to 7 degrees a frame, hand-held) with its fifth frame blanked (colour and depth: the
    lens covered): that frame is bridged by the constant velocity (no gyro in TUM), no frame is lost, the bridged
    frame's rotation is within a third of its true rotation, and the clip's per-frame error stays within twice the
    undisturbed run's. A frame with colour but without depth is still aligned (photometrically)."""
    from conftest import tum_clip_path

    folder = tum_clip_path("fr1_rpy")
    frames = cli.load_frames(folder)
    gs, gp = read_tum_trajectory(folder / "groundtruth.txt")
    stamps = np.array([f.stamp_s for f in frames])
    ok, gt = metrics.interpolate_poses(gs, gp, stamps)
    assert ok.all()
    errors = {}
    for drop in (None, 4):
        odo = RgbdOdometry()
        poses = []
        for k, f in enumerate(frames):
            rgb, depth = (np.zeros_like(f.rgb), np.zeros_like(f.depth_m)) if k == drop else (f.rgb, f.depth_m)
            res = odo.process(f.stamp_s, rgb, depth, f.intrinsics, depth_offset_s=f.meta["depth_offset_s"])
            assert res.ok == (k != drop) and res.fallback == (k == drop), k
            poses.append(res.T_c0_ck)
            if k == drop:
                true_step = inv_T(gt[k - 1]) @ gt[k]
                E = inv_T(true_step) @ res.T_ckm1_ck
                assert np.linalg.norm(so3_log(E[:3, :3])) < np.linalg.norm(so3_log(true_step[:3, :3])) / 3
        assert odo.lost == 0 and odo.fallbacks == (drop is not None)
        errors[drop] = metrics.rpe_window(stamps, np.array(poses), gt, float(np.median(np.diff(stamps))))
    assert errors[4].rot_rmse_deg < 2 * errors[None].rot_rmse_deg
    assert errors[4].trans_rmse_m < 2 * errors[None].trans_rmse_m


def _flight_frames(n: int) -> list[np.ndarray]:
    """Camera poses T_w_ck of a smooth synthetic flight at 30 Hz: ~1.2 deg and ~9 mm per frame."""
    return [pose(R_from_euler(0.05 * math.sin(3 * k / 30), 0.2 * k / 30, 0.6 * k / 30),
                 [0.25 * k / 30, -0.1 * k / 30, 0.05 * math.sin(4 * k / 30)]) for k in range(n)]


def test_keyframe_pose_chain_over_several_keyframes_against_ground_truth() -> None:
    """Frames aligned against keyframes (a new one every 4 frames or 2.9 degrees): the chained pose T_c0_ck
    and the per-frame motion T_ckm1_ck both match the ground truth, and T_ckm1_ck is exactly the chained
    poses' difference (velocity is differentiated from it)."""
    cfg = OdometryConfig(keyframe_max_frames=4, keyframe_max_rotation_rad=0.05)
    odo = RgbdOdometry(cfg)
    T_w = _flight_frames(16)
    results = []
    for k, T in enumerate(T_w):
        results.append(odo.process(k / 30, *render(T, K), K))
        assert results[-1].ok, k
    assert 5 <= odo.keyframes <= 8   # the first frame, then a switch every 2-4 frames (rotation ~2.4 deg/frame)
    for k in range(1, len(T_w)):
        E = inv_T(inv_T(T_w[0]) @ T_w[k]) @ results[k].T_c0_ck
        assert np.linalg.norm(E[:3, 3]) < 1e-3 and math.degrees(np.linalg.norm(so3_log(E[:3, :3]))) < 0.02, k
        step_true = inv_T(T_w[k - 1]) @ T_w[k]
        E = inv_T(step_true) @ results[k].T_ckm1_ck
        assert np.linalg.norm(E[:3, 3]) < 3e-4 and math.degrees(np.linalg.norm(so3_log(E[:3, :3]))) < 0.01, k
        chained = inv_T(results[k - 1].T_c0_ck) @ results[k].T_c0_ck
        assert np.allclose(chained, results[k].T_ckm1_ck, atol=1e-9), k
    # frame-to-frame (keyframe_max_frames 1) agrees with the keyframe chain to the errors above
    f2f = RgbdOdometry(dataclasses.replace(cfg, keyframe_max_frames=1))
    for k, T in enumerate(T_w):
        last = f2f.process(k / 30, *render(T, K), K)
    assert f2f.keyframes == len(T_w)
    assert np.linalg.norm(last.T_c0_ck[:3, 3] - results[-1].T_c0_ck[:3, 3]) < 2e-3


def test_per_frame_fusion_keeps_every_pose_and_step_on_the_truth() -> None:
    """frame_fusion (a variant, off by default): every frame not right after a keyframe switch is fused with its
    alignment against the previous frame, and the fused poses and steps stay on the truth."""
    odo = RgbdOdometry(OdometryConfig(frame_fusion=True))
    T_w = _flight_frames(16)
    results = [odo.process(k / 30, *render(T, K), K) for k, T in enumerate(T_w)]
    assert all(r.ok for r in results)
    assert odo.fused_frames >= len(T_w) - 2 * odo.keyframes
    for k in range(1, len(T_w)):
        E = inv_T(inv_T(T_w[0]) @ T_w[k]) @ results[k].T_c0_ck
        assert np.linalg.norm(E[:3, 3]) < 1e-3 and math.degrees(np.linalg.norm(so3_log(E[:3, :3]))) < 0.02, k
        E = inv_T(inv_T(T_w[k - 1]) @ T_w[k]) @ results[k].T_ckm1_ck
        assert np.linalg.norm(E[:3, 3]) < 3e-4 and math.degrees(np.linalg.norm(so3_log(E[:3, :3]))) < 0.01, k
        assert np.allclose(inv_T(results[k - 1].T_c0_ck) @ results[k].T_c0_ck, results[k].T_ckm1_ck, atol=1e-9), k


def test_fuse_poses_is_the_information_weighted_mean_and_refuses_a_step_outside_the_two() -> None:
    T_a = pose(R_from_euler(0.0, 0.1, 0.0), [1.0, 0.0, 0.0])
    T_b = se3_exp(np.array([0.02, 0.0, 0.0, 0.0, 0.0, 0.004])) @ T_a   # 2 cm and 0.23 deg off, in the reference
    cov = np.eye(6) * 1e-6
    fused = fuse_poses(T_a, cov, T_b, cov, 0.03)
    assert fused is not None
    T, cov_f = fused
    assert np.allclose(_se3_log(T @ inv_T(T_a)), [0.01, 0.0, 0.0, 0.0, 0.0, 0.002], atol=1e-6)   # the midpoint
    assert np.allclose(cov_f, cov / 2)
    fused = fuse_poses(T_a, cov, T_b, 4 * cov, 0.03)   # b four times as uncertain: a fifth of the way
    assert fused is not None and np.allclose(_se3_log(fused[0] @ inv_T(T_a))[:3], [0.004, 0.0, 0.0], atol=1e-6)
    assert fuse_poses(T_a, cov, T_b, cov, 0.005) is None   # a 1 cm step beyond the gate's 5 mm


def test_se3_log_inverts_se3_exp_and_the_adjoint_moves_a_twist() -> None:
    xi = np.array([0.03, -0.02, 0.05, 0.4, -0.3, 0.2])
    assert np.allclose(_se3_log(se3_exp(xi)), xi, atol=1e-12)
    assert np.allclose(_se3_log(se3_exp(xi * 1e-7)), xi * 1e-7, atol=1e-18)
    T = se3_exp(np.array([0.3, 0.1, -0.2, 0.4, 0.1, -0.3]))
    x = np.array([1e-3, 2e-3, 0.0, 1e-2, 0.0, 2e-2])
    assert np.allclose(_se3_log(T @ se3_exp(x) @ inv_T(T)), _adjoint(T) @ x, atol=1e-12)


def test_keyframe_refinement_cuts_the_drift_of_noisy_frames() -> None:
    """Noisy frames (intensity sigma 6 grey levels, depth 1 %) of the smooth flight, a keyframe every ~2.4
    degrees: fusing each new keyframe's alignment against the keyframe before with the chain (DVO-SLAM's local
    window) halves part of the error each keyframe hands on, so the chained pose drifts less."""
    T_w = _flight_frames(24)
    rng = np.random.default_rng(0)
    frames = []
    for T in T_w:
        rgb, depth = render(T, K)
        rgb = np.clip(rgb + rng.normal(0.0, 6.0, rgb.shape), 0, 255).astype(np.uint8)
        frames.append((rgb, (depth * (1.0 + rng.normal(0.0, 0.01, depth.shape))).astype(np.float32)))
    final_error_m = {}
    for refine in (False, True):
        # eight frames a keyframe at most: the keyframes follow the rotation (the case the window is for)
        odo = RgbdOdometry(OdometryConfig(keyframe_refinement=refine, keyframe_max_frames=8))
        results = [odo.process(k / 30, rgb, depth, K) for k, (rgb, depth) in enumerate(frames)]
        assert all(r.ok for r in results)
        assert (odo.refined_keyframes > 0) == refine
        for a, b in zip(results, results[1:]):   # the per-frame motion stays the chained poses' difference
            assert np.allclose(inv_T(a.T_c0_ck) @ b.T_c0_ck, b.T_ckm1_ck, atol=1e-9)
        E = inv_T(inv_T(T_w[0]) @ T_w[-1]) @ results[-1].T_c0_ck
        final_error_m[refine] = float(np.linalg.norm(E[:3, 3]))
    assert final_error_m[True] < 0.9 * final_error_m[False] and final_error_m[True] < 6e-3


def test_refined_keyframes_keep_the_chained_pose_rigid() -> None:
    """A keyframe every frame, each refined: the chained pose stays a rigid transform. The fused pose used to be
    inv(T_p_kf) exp(step) T_p_kf T_kf_ck with inv_T (R^T) of a rotation that is orthonormal only to rounding, and
    became the next T_p_kf: the departure from SO(3) doubled at every refined keyframe (1e-16 to 0.06 in 47 of
    them, a 40 m divergence of the SITL's odometry); here it passed 1e-13 by the tenth frame (now ~2e-15)."""
    odo = RgbdOdometry(OdometryConfig(keyframe_max_frames=1, keyframe_refinement=True))
    T_w = _flight_frames(32)
    for k, T in enumerate(T_w):
        result = odo.process(k / 30, *render(T, K), K)
        assert result.ok
        R = result.T_c0_ck[:3, :3]
        assert np.abs(R.T @ R - np.eye(3)).max() < 1e-13, k
    assert odo.refined_keyframes >= 28 and odo.rejected_refinements == 0
    E = inv_T(inv_T(T_w[0]) @ T_w[-1]) @ odo.T_c0_ck
    assert np.linalg.norm(E[:3, 3]) < 1e-3


@pytest.mark.parametrize("change,expected", [
    ({"keyframe_max_frames": 3}, [0, 3, 6, 9]),                                # every 3 frames
    ({"keyframe_max_rotation_rad": 0.035}, [0, 2, 4, 6, 8]),                   # 2.0 deg: every 2nd frame
    ({"keyframe_max_translation_m": 0.015}, [0, 2, 4, 6, 8]),                  # 9.3 mm a frame
    ({"keyframe_max_frames": 1}, list(range(10))),                             # frame-to-frame
])
def test_keyframe_switching(change: dict[str, float], expected: list[int]) -> None:
    """Each criterion alone (the others out of reach) makes the frame that crosses it the next keyframe."""
    base = dict(keyframe_max_frames=100, keyframe_max_rotation_rad=1.0, keyframe_max_translation_m=1.0)
    odo = RgbdOdometry(OdometryConfig(**{**base, **change}))
    taken = []
    for k, T in enumerate(_flight_frames(10)):
        before = odo.keyframes
        assert odo.process(k / 30, *render(T, K), K).ok
        if odo.keyframes > before:
            taken.append(k)
    assert taken[:-1] == expected[:len(taken) - 1] and taken == expected[:len(taken)]
    assert len(taken) == len(expected) or taken[-1] == 9


def test_keyframe_fitness_drop_switches_keyframe() -> None:
    """A frame whose fitness against the keyframe drops below keyframe_min_fitness (a fifth of the image newly
    occluded, and staying so) but is still a good alignment becomes the keyframe; the frames around it do not."""
    T_w = _flight_frames(4)
    odo = RgbdOdometry(OdometryConfig(keyframe_min_fitness=0.9))
    fitness = []
    for k, T in enumerate(T_w):
        rgb, depth = render(T, K)
        if k >= 2:
            rgb[:, :60] = 128   # the occluder, a flat grey card (the depth still sees the room)
        res = odo.process(k / 30, rgb, depth, K)
        assert res.ok, k
        fitness.append(res.fitness)
        E = inv_T(inv_T(T_w[0]) @ T) @ res.T_c0_ck
        assert np.linalg.norm(E[:3, 3]) < 1e-3, k
        assert odo.keyframes == (1 if k < 2 else 2), k
    assert fitness[2] < odo.config.keyframe_min_fitness <= min(fitness[1], fitness[3])


def test_keyframe_failure_falls_back_to_the_previous_frame() -> None:
    """Yaw 11.5 degrees a frame with the gyro prior, keyframe thresholds out of reach: the fifth frame has too
    little overlap with the keyframe (46 degrees away) and is aligned to the previous frame instead; it then
    becomes the keyframe. The chained pose stays right."""
    T_w = [pose(R_from_euler(0.0, 0.2 * k, 0.0), [0.01 * k, 0.0, 0.0]) for k in range(6)]
    odo = RgbdOdometry(OdometryConfig(keyframe_min_fitness=0.0, keyframe_max_rotation_rad=3.0))
    for k, T in enumerate(T_w):
        prior = None if k == 0 else (inv_T(T_w[k - 1]) @ T)[:3, :3]
        res = odo.process(k / 30, *render(T, K), K, prior)
        assert res.ok, k
        assert odo.keyframes == (1 if k < 4 else 2), k
        E = inv_T(inv_T(T_w[0]) @ T) @ res.T_c0_ck
        assert np.linalg.norm(E[:3, 3]) < 1e-3 and math.degrees(np.linalg.norm(so3_log(E[:3, :3]))) < 0.02, k


def test_rotate_depth_matches_the_depth_rendered_at_the_turned_pose() -> None:
    """A depth image taken 1.5 degrees of rotation before the colour one, turned by rotate_depth, matches the
    depth rendered at the colour pose (to the nearest-neighbour resampling), far better than unturned."""
    T_c = pose(R_from_euler(0.05, -0.1, 0.2), [0.1, 0.2, -0.1])
    T_d = T_c @ pose(R_from_euler(0.01, -0.02, 0.012), [0.0, 0.0, 0.0])
    depth_c, depth_d = render(T_c, K)[1], render(T_d, K)[1]
    R_c_d = (inv_T(T_c) @ T_d)[:3, :3]
    turned = rotate_depth(depth_d, K, R_c_d)
    both = (turned > 0) & (depth_c > 0)
    assert both.mean() > 0.9
    err_turned = np.abs(turned - depth_c)[both]
    err_raw = np.abs(depth_d - depth_c)[(depth_d > 0) & (depth_c > 0)]
    assert np.median(err_turned) < 2e-3 < np.median(err_raw) / 3
    assert rotate_depth(depth_d, K, np.eye(3)) == pytest.approx(depth_d)


def _unsynchronised_step_errors(T_w: Callable[[float], np.ndarray], offsets_s: list[float],
                                config: OdometryConfig) -> list[float]:
    """Frames at 30 Hz along ``T_w``, each depth image rendered ``offsets_s[k]`` from its colour image (the gyro's
    rotation as the prior): the translation error of each frame's motion since the one before (m; inf when the
    alignment failed), from the second frame on."""
    odo = RgbdOdometry(config)
    errors = []
    for k, offset in enumerate(offsets_s):
        t = k / 30
        prior = None if k == 0 else (inv_T(T_w((k - 1) / 30)) @ T_w(t))[:3, :3]
        res = odo.process(t, render(T_w(t), K)[0], render(T_w(t + offset), K)[1], K, prior, offset)
        if k >= 1:
            E = inv_T(inv_T(T_w((k - 1) / 30)) @ T_w(t)) @ res.T_ckm1_ck
            errors.append(float(np.linalg.norm(E[:3, 3])) if res.ok else math.inf)
    return errors


def test_unsynchronised_depth_is_registered_to_the_colour_instant() -> None:
    """Yaw at 1.5 rad/s (with the gyro's rotation as the prior), each depth image taken 12-19 ms before its
    colour image as a Kinect v1 does: once the rate is known (from the second pair on) every registered pair is
    accurate to under a millimetre; unregistered, the photometric and depth terms measure motions between
    different instants and the translation leaks (centimetres, or a refused alignment)."""
    rate = 1.5
    offsets = [-0.012, -0.019, -0.013, -0.018, -0.014, -0.019, -0.012, -0.017]

    def T_w(t: float) -> np.ndarray:
        return pose(R_from_euler(0.02, rate * t, 0.0), [0.1 * t, 0.0, 0.02 * t])

    step_errors = {register: _unsynchronised_step_errors(T_w, offsets,
                                                         OdometryConfig(register_depth_in_time=register))[2:]
                   for register in (True, False)}   # from the third pair (the rate known)
    assert max(step_errors[True]) < 1.5e-3
    assert max(step_errors[False]) > 5 * max(step_errors[True])
    # synchronised frames are left alone
    odo = RgbdOdometry()
    odo.process(0.0, *render(T_w(0.0), K), K, depth_offset_s=2e-4)
    assert odo._kf is not None and odo._kf.depth_at_colour_instant


@pytest.mark.parametrize("offsets_s", [
    [-0.012, -0.019, -0.013, -0.018, -0.014, -0.019, -0.012, -0.017],   # Kinect v1: 12-19 ms early
    [-0.015, 0.015, -0.013, 0.016, -0.015, 0.013, -0.016, 0.015],       # pairs on either side (TUM fr1_rpy)
])
def test_unsynchronised_depth_of_a_translating_camera_is_compared_at_its_own_instant(offsets_s: list[float]) -> None:
    """A camera sliding at 0.4 m/s, each depth image taken a few ms from its colour image: the depth term
    measures the motion between the depth instants, which differs from the colour instants' by the speed times
    the change of offset (1.4-13 mm here). Comparing the depth instants (their translation at constant
    velocity) keeps every step, from the first, to a fifth of a millimetre; without it the steps
    are off by millimetres."""
    v = np.array([0.4, -0.1, 0.15])

    def T_w(t: float) -> np.ndarray:
        return pose(R_from_euler(0.02, 0.3, 0.0), v * t)

    step_errors = {register: _unsynchronised_step_errors(T_w, offsets_s,
                                                         OdometryConfig(register_depth_translation=register))
                   for register in (True, False)}
    assert max(step_errors[True]) < 2e-4, step_errors
    assert min(step_errors[False]) > 1e-3, step_errors


def _clip_runs(folder: Path, methods: tuple[str, ...], passes: int = 1
               ) -> dict[str, tuple[cli.SequenceRun, cli.SequenceMetrics]]:
    """Each method on a committed TUM clip, one thread, in this process (as ``quadlink vo-eval``): the run of the
    pass with the lowest median CPU time (the machine is shared; the trajectories are deterministic) and its TUM
    metrics against the truth interpolated at the colour stamps."""
    frames = cli.load_frames(folder)
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        out = {}
        for method in methods:
            runs = [cli.run_sequence(frames, method, folder.name) for _ in range(passes)]
            run = min(runs, key=lambda r: float(np.median(r.cpu_ms)))
            gt = cli.ground_truth_at(folder, run.stamps_s)
            assert gt is not None
            assert gt[0].all(), "every frame of a clip has ground truth"
            out[method] = (run, cli.evaluate(run, *gt))
        return out
    finally:
        cv2.setNumThreads(threads)


def test_tum_clip_accuracy_against_ground_truth_and_the_peers(any_tum_clip: Path) -> None:
    """Issue 33's accuracy targets on real frames, against OpenCV and Open3D run on the same frames here:
    per-frame translational RPE <= 0.8x the better peer's, rotational no worse than the better peer's, ATE no
    worse, no failed frame. And against the truth alone: the error of the clip's dominant motion (fr3_teddy:
    15 mm a frame; fr1_rpy: 2.9 degrees a frame) is under a fifth of that motion."""
    methods = ("ours", "opencv") + (("open3d",) if importlib.util.find_spec("open3d") else ())
    runs = _clip_runs(any_tum_clip, methods)
    run, ours = runs["ours"]
    assert run.failures == 0 and ours.frames_evaluated == len(run.stamps_s) == 10
    peers = [m for name, (_, m) in runs.items() if name != "ours"]
    best_t = min(m.rpe_frame.trans_rmse_m for m in peers)
    best_r = min(m.rpe_frame.rot_rmse_deg for m in peers)
    assert ours.rpe_frame.trans_rmse_m <= 0.8 * best_t, (ours.rpe_frame, best_t)
    assert ours.rpe_frame.rot_rmse_deg <= best_r, (ours.rpe_frame, best_r)
    assert ours.ate.rmse_m <= min(m.ate.rmse_m for m in peers)
    # a motionless estimate's error is the truth's own motion between frames
    ok, gt = cli.ground_truth_at(any_tum_clip, run.stamps_s)  # type: ignore[misc]
    still = metrics.rpe_window(run.stamps_s, np.repeat(np.eye(4)[None], len(gt), 0), gt,
                               ours.rpe_frame.delta_s)
    checked = 0
    if still.trans_rmse_m > 0.005:
        assert ours.rpe_frame.trans_rmse_m < 0.2 * still.trans_rmse_m
        checked += 1
    if still.rot_rmse_deg > 1.5:
        assert ours.rpe_frame.rot_rmse_deg < 0.2 * still.rot_rmse_deg
        checked += 1
    assert checked >= 1, "the clip moves"


def test_tum_clip_time_per_frame_is_under_half_of_opencvs(tum_clip: Path) -> None:
    """Issue 33's speed target as a ratio measured here, both on one thread: median CPU time per frame of ours at
    most half of OpenCV's RGBD odometry's on the same real frames (best of three passes each)."""
    runs = _clip_runs(tum_clip, ("ours", "opencv"), passes=3)
    ratio = float(np.median(runs["ours"][0].cpu_ms)) / float(np.median(runs["opencv"][0].cpu_ms))
    assert ratio <= 0.5, ratio


def test_metrics_horn_alignment_and_rpe() -> None:
    rng = np.random.default_rng(3)
    n = 20
    gt = np.array([pose(R_from_euler(*rng.normal(0, 0.3, 3)), rng.normal(0, 1, 3)) for _ in range(n)])
    G = pose(R_from_euler(0.3, -0.2, 1.0), [1.0, 2.0, 3.0])
    est = np.array([G @ T for T in gt])         # same trajectory in another world frame
    assert metrics.ate(est, gt).rmse_m < 1e-9
    stamps = np.arange(n) * 0.1
    r = metrics.rpe(stamps, est, gt)
    assert r.trans_rmse_m_s < 1e-9 and r.rot_rmse_deg_s < 1e-9
    # a 1 cm offset on every other pose: consecutive RPE 1 cm per 0.1 s
    est2 = est.copy()
    est2[1::2, :3, 3] += np.array([0.01, 0.0, 0.0])
    r2 = metrics.rpe(stamps, est2, gt)
    assert r2.trans_median_m_s == pytest.approx(0.1, rel=1e-6)
    assert metrics.rpe(stamps, est, gt, delta_s=1.0).pairs == n - 10


def test_tum_association_and_trajectory_round_trip(tmp_path: Path) -> None:
    pairs = associate([0.0, 0.033, 0.066, 0.1], [0.001, 0.035, 0.2])
    assert pairs == [(0, 0), (1, 1)]
    stamps = np.array([1.0, 2.0])
    poses = np.array([pose(R_from_euler(0.1, 0.2, 0.3), [1, 2, 3]), np.eye(4)])
    write_tum_trajectory(tmp_path / "t.txt", stamps, poses)
    s2, p2 = read_tum_trajectory(tmp_path / "t.txt")
    assert np.allclose(s2, stamps) and np.allclose(p2, poses, atol=1e-5)


def _write_sequence(folder: Path, jpeg: bool, camera_yaml: str | None) -> None:
    (folder / "rgb").mkdir(parents=True)
    (folder / "depth").mkdir()
    rgb_lines, depth_lines = [], []
    for k in range(3):
        T = pose(np.eye(3), [0.01 * k, 0.0, 0.0])
        rgb, depth = render(T, K)
        name = f"{k:03d}.{'jpg' if jpeg else 'png'}"
        cv2.imwrite(str(folder / "rgb" / name), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        cv2.imwrite(str(folder / "depth" / f"{k:03d}.png"), (depth * 1000).astype(np.uint16))
        rgb_lines.append(f"{k / 30:.6f} rgb/{name}")
        depth_lines.append(f"{k / 30 + 0.002:.6f} depth/{k:03d}.png")
    (folder / "rgb.txt").write_text("# rgb\n" + "\n".join(rgb_lines) + "\n")
    (folder / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    if camera_yaml is not None:
        (folder / "camera.yaml").write_text(camera_yaml)


def test_tum_folder_source_camera_yaml_jpeg_and_overrides(tmp_path: Path) -> None:
    yaml_text = f"fx: {K.fx}\nfy: {K.fy}\ncx: {K.cx}\ncy: {K.cy}\ndepth_scale: 1000\n"
    _write_sequence(tmp_path / "seq", jpeg=True, camera_yaml=yaml_text)
    src = TumSequence(tmp_path / "seq")
    frames = list(src.frames())
    assert len(frames) == 3
    assert frames[0].intrinsics.fx == pytest.approx(K.fx) and frames[0].rgb.shape == (240, 320, 3)
    assert float(np.median(frames[0].depth_m[frames[0].depth_m > 0])) > 1.0       # metres, scale 1000
    src2 = TumSequence(tmp_path / "seq", {"fx": 100.0, "depth_scale": 5000.0})
    assert src2.params.fx == 100.0 and src2.params.fy == pytest.approx(K.fy) and src2.params.depth_scale == 5000.0
    (tmp_path / "seq" / "camera.yaml").write_text("fx: 1\nfocal: 2\n")
    with pytest.raises(ConfigError, match="focal"):
        TumSequence(tmp_path / "seq")
    with pytest.raises(DatasetUnavailable):
        TumSequence(tmp_path / "missing")


def test_tum_folder_pairs_from_associations_txt_win_over_the_nearest_stamp_rule(tmp_path: Path) -> None:
    _write_sequence(tmp_path / "seq", jpeg=False, camera_yaml=None)
    # the nearest-stamp rule pairs colour k with depth k; the maker's file pairs 0 with 1 and 1 with 0 (to tell them
    # apart), and leaves frame 2 out
    (tmp_path / "seq" / "associations.txt").write_text(
        "# rgb_timestamp rgb_filename depth_timestamp depth_filename\n"
        f"{1 / 30:.6f} rgb/001.png 0.002000 depth/000.png\n0.000000 rgb/000.png {1 / 30 + 0.002:.6f} depth/001.png\n")
    frames = list(TumSequence(tmp_path / "seq").frames())
    assert [f.meta["rgb"] for f in frames] == ["rgb/000.png", "rgb/001.png"]          # colour-stamp order
    assert [f.meta["depth"] for f in frames] == ["depth/001.png", "depth/000.png"]
    assert frames[0].meta["depth_stamp_s"] == pytest.approx(1 / 30 + 0.002, abs=1e-6)
    (tmp_path / "seq" / "associations.txt").write_text("0.0 rgb/000.png depth/000.png\n")
    with pytest.raises(DatasetUnavailable, match="depth_stamp"):
        TumSequence(tmp_path / "seq")


def test_truth_gap_is_twice_the_truths_own_interval_and_never_under_tum_s_20_ms() -> None:
    assert cli.truth_gap_s(np.arange(0.0, 1.0, 0.01)) == pytest.approx(cli.GT_MAX_GAP_S)   # 100 Hz
    dropout = np.r_[np.arange(0.0, 0.5, 0.01), np.arange(0.6, 1.0, 0.01)]
    assert cli.truth_gap_s(dropout) == pytest.approx(cli.GT_MAX_GAP_S)   # a dropout stays out
    assert cli.truth_gap_s(np.array([0.0, 0.04, 0.07, 0.10, 0.14])) == pytest.approx(0.07)     # one row per frame


def test_the_retimed_fr1_xyz_clip_meets_benchmark_rows_it_does_not_hold() -> None:
    """tests/data/tum/fr1_xyz holds ten motion-capture rows at the benchmark's stamps. Four other rows of the
    benchmark's freiburg1_xyz ground truth (quoted from its groundtruth.txt) fall between them: interpolated at
    their stamps, the clip's truth must meet them to the file's 0.1 mm rounding and the clip's curvature. With the
    rows at the shared folder's approximate stamps (first colour stamp + i/30 s) it is 3 mm off."""
    from conftest import tum_clip_path

    other_rows = np.array([[1305031102.1758, 1.3405, 0.6266, 1.6575], [1305031102.2159, 1.3303, 0.6256, 1.6464],
                           [1305031102.2758, 1.3160, 0.6254, 1.6302], [1305031102.4159, 1.2830, 0.6257, 1.5933]])
    gs, gp = read_tum_trajectory(tum_clip_path("fr1_xyz") / "groundtruth.txt")
    approx = gs[0] + 1.0 / 30.0 * np.arange(gs.size) + (1305031102.175304 - 1305031102.1658)
    for stamps, within_mm in ((gs, (0.0, 0.5)), (approx, (2.0, 5.0))):
        ok, T = metrics.interpolate_poses(stamps, gp, other_rows[:, 0], cli.truth_gap_s(stamps))
        assert ok.all()
        err_mm = np.linalg.norm(T[:, :3, 3] - other_rows[:, 1:], axis=1) * 1e3
        assert within_mm[0] <= err_mm.max() <= within_mm[1], err_mm


def test_vo_eval_cli_prints_metrics_and_writes_trajectory(tum_clip: Path, tmp_path: Path) -> None:
    out = tmp_path / "traj.txt"
    res = CliRunner().invoke(vo_eval, [str(tum_clip), "--out", str(out), "--max-frames", "5"])
    assert res.exit_code == 0, res.output
    assert "RPE1s" in res.output and "ATE" in res.output and "CPU ms" in res.output
    row = [line for line in res.output.splitlines() if line.startswith("fr3_teddy")]
    assert len(row) == 1
    fields = row[0].split()
    assert fields[1] == "ours" and fields[2] == "5/5" and fields[3] == "-"   # 0.13 s: no pair 1 s apart
    assert 0.0 < float(fields[6]) < 0.01                                     # ATE, m
    s, p = read_tum_trajectory(out)
    assert len(s) == 5 and np.allclose(p[0], np.eye(4))


def test_vo_eval_cli_several_sequences_and_methods(tum_clip: Path, tmp_path: Path) -> None:
    """Two sequences (the shared head and a synthetic one with truth) and two methods in one call: one table
    row each, one trajectory file each; the synthetic sequence's metrics come from its interpolated truth."""
    seq = tmp_path / "synth"
    _write_sequence(seq, jpeg=False, camera_yaml=f"fx: {K.fx}\nfy: {K.fy}\ncx: {K.cx}\ncy: {K.cy}\n"
                    "depth_scale: 1000\n")
    # truth at 100 Hz around the frames: the camera moves 1 cm along x per frame (0.3 m/s)
    gt = [f"{t:.6f} {0.3 * t:.6f} 0 0 0 0 0 1" for t in np.arange(-0.02, 0.1, 0.01)]
    (seq / "groundtruth.txt").write_text("\n".join(gt) + "\n")
    out = tmp_path / "trajs"
    res = CliRunner().invoke(vo_eval, [str(tum_clip), str(seq), "--method", "ours", "--method", "opencv",
                                       "--max-frames", "3", "--out", str(out)])
    assert res.exit_code == 0, res.output
    rows = [line.split() for line in res.output.splitlines() if line.startswith(("fr3_teddy", "synth"))]
    assert [(r[0], r[1]) for r in rows] == [("fr3_teddy", "ours"), ("fr3_teddy", "opencv"),
                                            ("synth", "ours"), ("synth", "opencv")]
    ours_synth = rows[2]
    assert ours_synth[2] == "3/3"
    assert float(ours_synth[6]) < 1e-3 and float(ours_synth[7]) < 1.0   # ATE m, per-frame RPE mm
    assert sorted(p.name for p in out.iterdir()) == ["fr3_teddy_opencv.txt", "fr3_teddy_ours.txt",
                                                     "synth_opencv.txt", "synth_ours.txt"]


def test_vo_eval_cli_without_groundtruth_and_bad_path(tmp_path: Path) -> None:
    _write_sequence(tmp_path / "seq", jpeg=False, camera_yaml=f"fx: {K.fx}\nfy: {K.fy}\ncx: {K.cx}\ncy: {K.cy}\n"
                    "depth_scale: 1000\n")
    res = CliRunner().invoke(vo_eval, [str(tmp_path / "seq")])
    assert res.exit_code == 0, res.output
    assert "metrics skipped" in res.output
    res = CliRunner().invoke(vo_eval, [str(tmp_path / "nope")])
    assert res.exit_code != 0
