"""Parameters of the direct RGB-D odometry (:mod:`perception.odometry`): one frozen dataclass read by the frame
preparation (:mod:`perception.odometry_frame`), the pair alignment (:mod:`perception.odometry_align`) and the
keyframe tracker."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class OdometryConfig:
    """Parameters of the direct RGB-D odometry (QVGA). docs/reference/odometry.md chooses ``keyframe_max_frames``,
    ``gradient_fraction`` and ``motion_prior_sigma_m`` on two TUM sequences and scores them on the third
    (perception/odometry_loo.py): ``gradient_fraction`` 0.2 is every split's choice; the splits' majority for
    ``keyframe_max_frames`` (4) quadrupled the SITL flight's largest velocity error and the prior term biases
    accelerating flight, so those stay at 8 and 0 (see there). ``depth_weight`` is the maximum-likelihood 1. The
    others were set in earlier rounds on TUM fr1, fr3 and the SITL: not held out."""

    levels: int = 3                                  # pyramid levels (finest = input resolution)
    iterations: tuple[int, ...] = (10, 6, 2)         # Gauss-Newton iterations per level, coarse -> fine (the
                                                     # finest starts close: from the keyframe pose and the gyro)
    max_points: tuple[int, ...] = (600, 1200, 4000)  # selected reference pixels per level, coarse -> fine
    working_width_px: int = 320                      # frames wider than this are downscaled first (QVGA)
    min_depth_m: float = 0.2
    max_depth_m: float = 6.0
    depth_weight: float = 1.0                        # lambda_Z: weight of the depth term, each term being
                                                     # normalised by its robust scale (1: maximum likelihood)
    t_dof: float = 5.0                               # nu of the t-distribution weights (DVO)
    min_intensity_sigma: float = 0.004               # floors of the robust scales (about one grey level and
    min_depth_sigma_m: float = 0.0002                # a structured-light sensor's noise at 1 m) so exact
                                                     # data cannot make one term drown the other
    gradient_fraction: float = 0.2                   # share of the points picked by intensity gradient; the
                                                     # rest spread evenly: the depth term needs no texture and
                                                     # pins the translation (TUM fr1: translational RPE falls
                                                     # steadily from 0.75 to 0.1, rotational rises below ~0.2)
    imu_prior_sigma_rad: float = 0.01                # std of the gyro rotation prior between frames
    motion_prior_sigma_m: float = 0.0                # std of DVO's constant-velocity motion prior on the
                                                     # translation per frame (0: none; the prediction is then only
                                                     # the starting point)
    min_fitness: float = 0.3                         # inlier share below which the result is not ok
    min_points: int = 100
    min_reference_points: int = 2000                 # an alignment is ok only if its reference (keyframe) has this
                                                     # many valid-depth points at the finest level (half its budget,
                                                     # 2.6 % of QVGA): a smaller patch, such as the sliver of floor
                                                     # a take-off first sees at a grazing angle, leaves the motion
                                                     # ill-posed (SITL: 742 points tilted the world by 2-5 deg)
    max_translation_m: float = 0.5                   # per-frame sanity bounds
    max_rotation_rad: float = 0.6
    max_translation_jump_m: float = 0.03             # per-frame translation this far from the constant-velocity
                                                     # prediction is a wrong alignment (0.9 m/s gained in 33 ms
                                                     # at 30 Hz, ~3 g; SITL: a hovering vehicle "jumped" 9 cm)
    max_acceleration_m_s2: float = 10.0              # the most a multirotor's velocity changes per second (1 g;
                                                     # its tracker: 25 deg of tilt, 4.6 m/s^2 level, 0.6 g down):
                                                     # at intervals past 55 ms (a starved reader) or over bridged
                                                     # frames the jump bound grows with it (RgbdOdometry._jump_bound_m)
    convergence_eps: float = 2e-5                    # |delta| (m, rad) below which a level stops
    coarse_convergence_px: float = 0.1               # update (in the level's pixels) below which a coarse level stops
    affine_brightness: bool = False                  # estimate a brightness gain and bias per pair (exposure)
    brightness_prior_sigma: float = 0.1              # std of the gain (about 1) and bias (about 0, intensity 0..1)
    # keyframes: frames are aligned against the last keyframe, whose gradients, points and Jacobians are computed
    # once; the current frame becomes the next keyframe after this many frames (1: frame-to-frame alignment),
    # once it has moved this far from the keyframe, or when its fitness drops below keyframe_min_fitness
    keyframe_max_frames: int = 8
    keyframe_max_translation_m: float = 0.1
    keyframe_max_rotation_rad: float = 0.087         # 5 degrees
    keyframe_min_fitness: float = 0.7
    keyframe_refinement: bool = True                 # a new keyframe is also aligned against the keyframe before
                                                     # the current one and the two estimates are fused by their
                                                     # information (DVO-SLAM's local window of keyframes)
    frame_fusion: bool = False                       # each frame also aligned (finest level) against the previous
                                                     # frame, its two poses fused by their information (held out on
                                                     # TUM it meets every target; the SITL's velocity gains nothing
                                                     # for 50 % more CPU: off, docs/reference/odometry.md)
    register_depth_in_time: bool = True              # turn an unsynchronised depth image to the colour instant
    register_depth_translation: bool = True          # and have the depth term compare the depth instants (their
                                                     # translation at constant velocity, see align_pair)
    restart_from_rest: bool = True                   # a fit below keyframe_min_fitness from the constant-velocity
                                                     # start is aligned again from rest; that fit wins if it is at
                                                     # least keyframe_min_fitness and its step from rest within
                                                     # max_translation_jump_m
    max_bridged_frames: int = 5                      # frames in a row that the constant-velocity prior may bridge
                                                     # when alignments fail (0.17 s at 30 Hz: a multirotor's
                                                     # velocity changes little in that time); a safety bound,
                                                     # not tuned
