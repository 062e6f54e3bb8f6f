"""The Xtion sensor model (sim_sitl/xtion.py) on synthetic depth maps: disparity steps and noise, IR shadows,
materials, range, frame drops and stamp jitter, motion blur. No renderer (tests/sitl/test_sitl_xtion_render.py
renders)."""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
import pytest

from quadlink.camera import CameraIntrinsics
from quadlink.config import from_dict
from quadlink.errors import ConfigError
from sim_sitl.config import CameraNoiseConfig, ScenarioConfig, SitlConfig, XtionConfig
from sim_sitl.scenario_gen import generate_procedural, generate_scenario, scenario_to_dict
from sim_sitl.scene import MATERIAL_CODE
from sim_sitl.xtion import (
    camera_velocity,
    depth_sigma_m,
    depth_step_m,
    disparity_depth,
    draw_frame_dropped,
    draw_stamp_error_s,
    image_motion_px,
    ir_shadow,
    max_motion_bound_px,
    motion_blur,
    xtion_depth,
)

K = CameraIntrinsics.from_fov(320, 240, 58.0, 45.0)
CFG = XtionConfig()
FB = CFG.ir_focal_px * abs(CFG.projector_x_m)  # 43.5 px m


def test_depth_steps_grow_with_z_squared_as_disparity_steps():
    """Noise-free, the reported depths are f b / (n step_d): their gaps are z^2 step_d / (f b), ~1.15 cm at 2 m."""
    cfg = dataclasses.replace(CFG, disparity_sigma_px=0.0)
    z = np.linspace(0.6, 4.9, 400_000, dtype=np.float32)
    levels = np.unique(disparity_depth(z, cfg))
    for z0 in (0.8, 1.0, 2.0, 3.0, 4.5):
        i = int(np.searchsorted(levels, z0))
        gap = float(levels[i] - levels[i - 1])
        expected = z0 * z0 * 0.125 / (580.0 * 0.075)  # K&OE 2012: step_z = z^2 step_d / (f b)
        assert gap == pytest.approx(expected, rel=0.02), z0
        assert gap == pytest.approx(depth_step_m(z0, cfg), rel=0.02)
    assert depth_step_m(2.0, cfg) == pytest.approx(0.0115, abs=0.0005)  # "about 1 cm at 2 m"
    i = int(np.searchsorted(levels, 3.0))
    assert levels[i] - levels[i - 1] > 0.02  # not the 1 mm steps of the basic model
    # every output is one of the disparity levels: f b / depth is a whole number of steps
    n = FB / levels / 0.125
    np.testing.assert_allclose(n, np.round(n), atol=2e-3)


@pytest.mark.parametrize("z_m", [1.0, 2.0, 3.0, 5.0])
def test_depth_sigma_grows_with_z_squared(z_m):
    """Without the steps, 200k samples give sigma = z^2 sigma_d / (f b) within 2 %: 4 cm at 5 m (K&OE 2012)."""
    cfg = dataclasses.replace(CFG, disparity_step_px=0.0)
    rng = np.random.default_rng(11)
    z = np.full((500, 400), z_m, np.float32)
    out = disparity_depth(z, cfg, rng.standard_normal(z.shape, dtype=np.float32))
    sigma = float(out.std())
    assert sigma == pytest.approx(z_m ** 2 * 0.0696 / (580.0 * 0.075), rel=0.02)
    assert sigma == pytest.approx(depth_sigma_m(z_m, cfg), rel=0.02)
    assert abs(float(out.mean()) - z_m) < 0.01 * sigma + 3 * sigma ** 2 / z_m  # 1/z noise: a small z sigma^2 bias
    if z_m == 5.0:
        assert sigma == pytest.approx(0.04, rel=0.03)


def _edge_scene(z_fore_m: float = 1.0, z_back_m: float = 3.0) -> np.ndarray:
    """A background plane and a foreground block (rows 80-159, columns 140-179) in front of it."""
    z = np.full((240, 320), z_back_m, np.float32)
    z[80:160, 140:180] = z_fore_m
    return z


@pytest.mark.parametrize("z_fore_m,z_back_m", [(1.0, 3.0), (1.5, 2.0), (0.8, 3.4)])
def test_ir_shadow_lies_beside_the_edge_away_from_the_projector(z_fore_m, z_back_m):
    """Projector on the right (+x): a hole left of the block, f_x b (1/z_near - 1/z_far) px wide, none right of it;
    the projector moved to the left moves the hole to the right edge."""
    z = _edge_scene(z_fore_m, z_back_m)
    width = K.fx * 0.075 * (1 / z_fore_m - 1 / z_back_m)
    right = ir_shadow(z, K, +0.075)
    cols = np.flatnonzero(right[120])
    assert len(cols) == pytest.approx(width, abs=1.0)
    assert cols.max() == 139 and cols.min() >= 140 - width - 1  # adjacent to the block's left edge
    assert not right[120, 180:].any()  # the other side of the block: lit
    assert not right[:80].any() and not right[160:].any()  # rows without the block: lit
    left = ir_shadow(z, K, -0.075)
    cols = np.flatnonzero(left[120])
    assert len(cols) == pytest.approx(width, abs=1.0) and cols.min() == 180
    assert not left[120, :140].any()


def test_ir_shadow_width_grows_with_the_depth_jump_and_the_baseline():
    widths = []
    for z_back in (1.2, 2.0, 3.0):
        widths.append(int(ir_shadow(_edge_scene(1.0, z_back), K, 0.075)[120].sum()))
    assert widths[0] < widths[1] < widths[2]
    wide = int(ir_shadow(_edge_scene(1.0, 3.0), K, 0.15)[120].sum())
    assert wide == pytest.approx(2 * widths[2], abs=1)


def test_ir_shadow_spares_smooth_surfaces():
    """Planes (fronto-parallel, slanted either way) and a smooth bump cast no shadow on themselves."""
    u = ((np.arange(320) - K.cx) / K.fx)[None, :]
    for deg in (-60.0, -30.0, 0.0, 30.0, 60.0):
        th = math.radians(deg)
        plane = np.broadcast_to(2.0 / (u * math.sin(th) + math.cos(th)), (240, 320)).astype(np.float32)
        assert not ir_shadow(plane, K, 0.075).any(), deg
    bump = (2.0 - 0.2 * np.exp(-((np.arange(320) - 160) / 30.0) ** 2))[None, :].repeat(240, 0).astype(np.float32)
    assert not ir_shadow(bump, K, 0.075).any()


def test_materials_dark_specular_glass_give_no_return_matte_does():
    z = np.full((240, 320), 2.0, np.float32)
    material = np.zeros((240, 320), np.uint8)
    material[:, 80:160] = MATERIAL_CODE["dark"]
    material[:, 160:240] = MATERIAL_CODE["specular"]
    material[:, 240:] = MATERIAL_CODE["glass"]
    out = xtion_depth(z, material, K, CFG, 0.5, 3.5, noise=np.random.default_rng(2).standard_normal(
        z.shape, dtype=np.float32))
    assert np.all(out[:, :80] > 0)
    assert np.all(out[:, 80:] == 0)
    assert np.abs(out[:, :80] - 2.0).max() < 6 * depth_sigma_m(2.0, CFG) + depth_step_m(2.0, CFG)


def test_valid_range_gives_no_return_outside():
    """0 (the driver's "no return") outside [0.5, 3.5] m of the reported depth, the reading inside."""
    cfg = dataclasses.replace(CFG, disparity_sigma_px=0.0)
    z = np.array([[0.3, 0.45, 0.55, 1.0, 3.4, 3.6, 5.0, 15.0]], np.float32).repeat(4, 0)
    out = xtion_depth(z, None, K, cfg, 0.5, 3.5)
    assert np.all(out[:, [0, 1, 5, 6, 7]] == 0)
    np.testing.assert_allclose(out[:, [2, 3, 4]], z[:, [2, 3, 4]], atol=depth_step_m(3.4, cfg))
    assert np.all(out[:, [2, 3, 4]] > 0)


def test_grazing_pixels_stay_invalid():
    z = np.full((24, 32), 2.0, np.float32)
    ok = np.ones(z.shape, bool)
    ok[:, :5] = False
    out = xtion_depth(z, None, K, CFG, 0.5, 3.5, incidence_ok=ok)
    assert np.all(out[:, :5] == 0) and np.all(out[:, 5:] > 0)


@pytest.mark.parametrize("p_drop", [0.0, 0.02, 0.2])
def test_frame_drop_rate_matches_config(p_drop):
    cfg = dataclasses.replace(CFG, frame_drop_probability=p_drop)
    rng = np.random.default_rng(5)
    n = 40_000
    drops = np.array([draw_frame_dropped(rng, cfg) for _ in range(n)])
    rate = drops.mean()
    assert abs(rate - p_drop) <= 4 * math.sqrt(max(p_drop * (1 - p_drop), 1e-12) / n)
    if p_drop == 0.0:
        assert not drops.any()
    else:  # independent: a drop does not change the next frame's chance (no bursts in this model)
        after = drops[1:][drops[:-1]].mean()
        assert abs(after - p_drop) <= 4 * math.sqrt(p_drop * (1 - p_drop) / drops[:-1].sum())


def test_stamp_jitter_statistics_match_config():
    rng = np.random.default_rng(6)
    err = np.array([draw_stamp_error_s(rng, CFG, 1 / 30) for _ in range(40_000)])
    clip = CFG.stamp_jitter_max_s  # 3 sigma: the clipped normal's sigma is 0.986 of the unclipped one
    assert np.abs(err).max() <= clip + 1e-12
    assert err.std() == pytest.approx(CFG.stamp_jitter_s * 0.9866, rel=0.02)
    assert abs(err.mean()) < 4 * CFG.stamp_jitter_s / math.sqrt(len(err))
    assert np.mean(np.abs(err) > CFG.stamp_jitter_s) == pytest.approx(0.317, abs=0.015)  # Gaussian, not uniform
    # the clip also keeps stamps in order at any frame rate: below half a period
    wide = dataclasses.replace(CFG, stamp_jitter_s=0.05, stamp_jitter_max_s=0.2)
    assert max(abs(draw_stamp_error_s(rng, wide, 1 / 30)) for _ in range(2000)) <= 0.45 / 30 + 1e-12
    assert draw_stamp_error_s(rng, dataclasses.replace(CFG, stamp_jitter_s=0.0), 1 / 30) == 0.0


def test_image_motion_of_a_pure_rotation_and_translation():
    """Centre pixel: yaw rate about the optical y axis moves it by -f_x w_y T; sideways flight by -f_x v_x T / z."""
    z = np.full((240, 320), 2.0, np.float32)
    du, dv = image_motion_px(z, K, np.zeros(3), np.array([0.0, 1.0, 0.0]), 0.015)
    cu, cv = int(round(K.cx)), int(round(K.cy))
    assert du[cv, cu] == pytest.approx(-K.fx * 0.015, rel=0.01)
    assert abs(dv[cv, cu]) < 0.01
    assert abs(du[cv, 0]) > abs(du[cv, cu])  # (1 + x^2): more at the border
    du, dv = image_motion_px(z, K, np.array([1.0, 0.0, 0.0]), np.zeros(3), 0.015)
    assert du[cv, cu] == pytest.approx(-K.fx * 1.0 * 0.015 / 2.0, rel=0.01)
    du2, _ = image_motion_px(z * 2, K, np.array([1.0, 0.0, 0.0]), np.zeros(3), 0.015)
    assert du2[cv, cu] == pytest.approx(du[cv, cu] / 2, rel=0.01)  # parallax: half as much at twice the depth
    # the motion of pixels checks against projecting the moved points (finite difference, small step)
    w, v, T = np.array([0.3, -0.5, 0.8]), np.array([0.4, -0.2, 0.6]), 1e-4
    du, dv = image_motion_px(z, K, v, w, T)
    for (r, c) in ((10, 15), (200, 300), (120, 160)):
        P = 2.0 * np.array([(c - K.cx) / K.fx, (r - K.cy) / K.fy, 1.0])
        P2 = P + T * (-v - np.cross(w, P))
        assert du[r, c] == pytest.approx(K.fx * P2[0] / P2[2] + K.cx - c, rel=1e-3, abs=1e-7)
        assert dv[r, c] == pytest.approx(K.fy * P2[1] / P2[2] + K.cy - r, rel=1e-3, abs=1e-7)
    assert max_motion_bound_px(2.0, K, v, w, T) >= float(np.hypot(du, dv).max())


def test_camera_velocity_from_the_body():
    R_qc = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # optical z = body x
    v_c, w_c = camera_velocity(np.eye(3), np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 2.0]), R_qc,
                               np.array([0.1, 0.0, 0.0]))
    # yaw (body z) is optical y; the lever arm 0.1 m ahead adds 0.2 m/s toward body y = optical x
    np.testing.assert_allclose(w_c, [0.0, 2.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(v_c, [0.2, 0.0, 1.0], atol=1e-12)


def _gradient_energy(rgb: np.ndarray) -> float:
    grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float32)
    return float(np.mean(np.diff(grey, axis=1)[:-1] ** 2 + np.diff(grey, axis=0)[:, :-1] ** 2))


def test_blur_grows_with_angular_rate():
    rng = np.random.default_rng(8)
    rgb = cv2.resize(rng.integers(0, 256, (60, 80, 3), dtype=np.uint8), (320, 240), interpolation=cv2.INTER_NEAREST)
    z = np.full((240, 320), 2.0, np.float32)
    energies = []
    for rate in (0.0, 0.5, 1.5, 4.0):
        du, dv = image_motion_px(z, K, np.zeros(3), np.array([0.0, rate, 0.0]), CFG.exposure_s)
        energies.append(_gradient_energy(motion_blur(rgb, du, dv, CFG)))
    assert energies[0] == _gradient_energy(rgb)  # at rest: untouched
    assert energies[0] > energies[1] > energies[2] > energies[3]
    assert energies[3] < 0.5 * energies[0]
    # along the motion only: near the centre row a pan moves pixels along the rows (|dv| < 0.2 px, the x y term):
    # horizontal stripes keep their contrast, vertical ones are washed out
    stripes = np.zeros((240, 320, 3), np.uint8)
    stripes[::8] = 255
    du, dv = image_motion_px(z, K, np.zeros(3), np.array([0.0, 4.0, 0.0]), CFG.exposure_s)
    smeared = motion_blur(stripes, du, dv, CFG)
    assert np.abs(dv[104:136, 100:220]).max() < 0.2 < 5 < np.abs(du[104:136, 100:220]).min()
    assert np.abs(smeared[104:136, 100:220].astype(int) - stripes[104:136, 100:220]).max() <= 16
    columns = np.zeros((240, 320, 3), np.uint8)
    columns[:, ::8] = 255
    assert motion_blur(columns, du, dv, CFG)[104:136, 100:220].max() < 128


def test_xtion_config_validation_names_the_key():
    with pytest.raises(ConfigError, match="camera_noise.xtion"):
        from_dict(SitlConfig, {"camera_noise": {"xtion": {"frame_drop_probability": 1.5}}})
    with pytest.raises(ConfigError, match="camera_noise.model"):
        from_dict(SitlConfig, {"camera_noise": {"model": "kinect2"}})
    cfg = from_dict(SitlConfig, {"camera_noise": {"model": "xtion", "xtion": {"projector_x_m": -0.075}}})
    assert cfg.camera_noise.xtion.projector_x_m == -0.075 and isinstance(cfg.camera_noise, CameraNoiseConfig)


def test_scene_object_material_is_validated():
    ok = from_dict(ScenarioConfig, {"objects": [{"kind": "box"}, {"kind": "box", "material": "glass"}]})
    assert [o.material for o in ok.objects] == ["matte", "glass"]
    with pytest.raises(ConfigError, match=r"objects\[1\]\.material.*'mirror'"):
        from_dict(ScenarioConfig, {"objects": [{"kind": "box"}, {"kind": "box", "material": "mirror"}]})


def _matte(scenario: ScenarioConfig) -> ScenarioConfig:
    return dataclasses.replace(scenario, objects=tuple(dataclasses.replace(o, material="matte")
                                                      for o in scenario.objects))


def test_procedural_arenas_draw_hazard_materials_reproducibly():
    n_objects = n_hazard = 0
    kinds: set[str] = set()
    for seed in range(150):
        plain, layout = generate_procedural(np.random.default_rng(seed), "t")
        assert all(o.material == "matte" for o in plain.objects)  # the default: arenas as before
        some, layout2 = generate_procedural(np.random.default_rng(seed), "t", hazard_material_p=0.3)
        more, _ = generate_procedural(np.random.default_rng(seed), "t", hazard_material_p=0.6)
        again, _ = generate_procedural(np.random.default_rng(seed), "t", hazard_material_p=0.3)
        assert layout2 == layout and _matte(some) == plain  # the same geometry, textures and colours
        assert again == some  # reproducible from the seed
        hazard = [o.material != "matte" for o in some.objects]
        # monotone in p: what is hazardous at 0.3 is so, with the same material, at 0.6
        assert all(m.material == o.material for o, m, h in zip(some.objects, more.objects, hazard, strict=True) if h)
        n_objects += len(hazard)
        n_hazard += sum(hazard)
        kinds |= {o.material for o in some.objects}
    assert n_objects > 300
    assert abs(n_hazard / n_objects - 0.3) < 4 * math.sqrt(0.3 * 0.7 / n_objects)
    assert kinds == {"matte", "dark", "specular", "glass"}


def test_campaign_arena_records_its_hazards_and_keeps_its_start():
    for seed in range(20):
        plain = generate_scenario(np.random.default_rng(seed), "t")
        hazardous = generate_scenario(np.random.default_rng(seed), "t", hazard_material_p=0.5)
        assert hazardous.scenario.start == plain.scenario.start
        assert "hazard_materials" not in plain.record
        assert hazardous.record["hazard_materials"] == {o.name: o.material for o in hazardous.scenario.objects
                                                        if o.material != "matte"}
        # the YAML form the SITL loads keeps the materials
        again = from_dict(ScenarioConfig, scenario_to_dict(hazardous.scenario))
        assert [o.material for o in again.objects] == [o.material for o in hazardous.scenario.objects]
