"""The depth sensor and pose error models (vcfusion.fusion.sensors) against their closed forms."""

import numpy as np
import pytest

from vcfusion.fusion.sensors import (DepthSensorParams, PoseNoiseParams, SensorModel, lidar_scan_mask,
                                     stereo_sigma_z)

F = 1000.0
K = np.array([[F, 0.0, 320.0], [0.0, F, 240.0], [0.0, 0.0, 1.0]])
T = np.eye(4)
T[:3, :3] = [[0, -1, 0], [0, 0, -1], [1, 0, 0]]  # at the origin, looking along +x, level
T[:3, 3] = -T[:3, :3] @ np.array([0.0, 0.0, 1.4])
FLAT = DepthSensorParams(texture_min=0.0)  # no image: no low-texture holes


def test_stereo_depth_error_grows_as_z_squared_with_the_closed_form_coefficient():
    sigmas = {}
    for z in (5.0, 10.0, 20.0):
        model = SensorModel("stereo", FLAT, rng=np.random.default_rng(1))
        out = model.depth(np.full((200, 300), z, np.float32), K, T)
        err = out[np.isfinite(out)] - z
        sigmas[z] = float(np.std(err))
        want = float(stereo_sigma_z(z, F, FLAT.baseline_m, FLAT.disparity_noise_px))  # z^2 sigma_d / (f B)
        assert sigmas[z] == pytest.approx(want, rel=0.05)
        assert abs(float(np.mean(err))) < 0.1 * want + 1e-3
    assert sigmas[20.0] / sigmas[5.0] == pytest.approx(16.0, rel=0.08)


def test_stereo_has_an_occlusion_band_left_of_a_nearer_surface_and_no_depth_beyond_its_range():
    depth = np.full((50, 200), 40.0, np.float32)
    depth[:, 100:150] = 5.0  # disparities 3 px (background) and 24 px (the near surface)
    model = SensorModel("stereo", DepthSensorParams(texture_min=0.0, disparity_noise_px=0.0),
                        rng=np.random.default_rng(0))
    out = model.depth(depth, K, T)
    band = np.isnan(out[0])
    # the right camera sees the background left of the surface shifted by 24 - 3 = 21 px less
    assert band[80:100].all() and not band[:79].any() and not band[100:].any()
    far = model.depth(np.full((10, 10), F * 0.12 / 0.3, np.float32), K, T)  # 0.3 px: beyond the matcher
    assert np.isnan(far).all()


def test_lidar_depth_lies_only_on_its_scan_and_reads_the_range_there():
    depth = np.full((480, 640), 30.0, np.float32)
    model = SensorModel("lidar", rng=np.random.default_rng(3))
    out = model.depth(depth, K, T)
    scan = lidar_scan_mask(K, T, (640, 480), DepthSensorParams())
    valid = np.isfinite(out)
    assert valid.any() and not (valid & ~scan).any()
    assert scan.mean() < 0.1  # sparse: a few percent of the pixels
    # a 64-beam pattern: at most 64 returns down any image column
    assert valid.sum(axis=0).max() <= 64
    assert np.abs(out[valid] - 30.0).max() < 0.15


def test_tof_noise_grows_with_range_and_flying_pixels_only_at_depth_steps():
    depth = np.full((100, 100), 40.0, np.float32)
    depth[:, :50] = 10.0
    out = SensorModel("tof", rng=np.random.default_rng(2)).depth(depth, K, T)
    p = DepthSensorParams()
    for z, cols in ((10.0, slice(0, 45)), (40.0, slice(55, 100))):
        assert np.std(out[:, cols] - z) == pytest.approx(p.tof_sigma0_m + p.tof_sigma_rel * z, rel=0.1)
    mixed = (out > 12.0) & (out < 37.0)
    assert mixed[:, 49:51].mean() > 0.5 and not mixed[:, :48].any() and not mixed[:, 52:].any()


@pytest.mark.parametrize("kind", ["stereo", "tof", "lidar"])
def test_the_same_seed_gives_the_same_depth(kind):
    rng = np.random.default_rng(7)
    depth = rng.uniform(3.0, 60.0, (480, 640)).astype(np.float32)
    image = rng.integers(0, 255, (480, 640, 3), dtype=np.uint8)
    a, b, c = (SensorModel(kind, rng=np.random.default_rng(s)).depth(depth, K, T, image) for s in (5, 5, 6))
    assert np.array_equal(a, b, equal_nan=True) and not np.array_equal(a, c, equal_nan=True)


def test_braking_pitches_the_camera_down_after_the_suspension_lag():
    pose = PoseNoiseParams(body_motion=True)
    model = SensorModel("exact", pose=pose, rng=np.random.default_rng(0))
    for k in range(40):  # 2 s of -5 m/s^2 at 20 frames/s: settled
        believed = model.believed_pose(T, 0.05 * k, accel=-5.0, speed=20.0, heading=0.0)
    # the fusion believes a level camera while the image was taken pitched down: the camera it is
    # handed looks up by the pitch (the same relative error)
    fwd_nominal, fwd_believed = T[2, :3], believed[2, :3]
    angle = np.degrees(np.arcsin(fwd_believed[2] - fwd_nominal[2]))
    assert angle == pytest.approx(5.0 * pose.pitch_gain_deg_per_mps2, rel=0.02)
    one_step = SensorModel("exact", pose=pose, rng=np.random.default_rng(0))
    one_step.believed_pose(T, 0.0, accel=-5.0, speed=20.0, heading=0.0)
    first = one_step.believed_pose(T, 0.05, accel=-5.0, speed=20.0, heading=0.0)
    lag = 1.0 - np.exp(-0.05 / pose.suspension_tau_s)
    assert np.degrees(np.arcsin(first[2, 2])) == pytest.approx(0.75 * lag, rel=0.02)
    mount = [SensorModel("exact", pose=PoseNoiseParams(mount_std_deg=0.3), rng=np.random.default_rng(s)).mount
             for s in (1, 1, 2)]
    assert np.array_equal(mount[0], mount[1]) and not np.array_equal(mount[0], mount[2])


def test_the_sensors_change_what_the_fusion_sees_never_the_ground_truth():
    from vcfusion.fusion.sensors import SensorModel
    from vcfusion.fusion.stage import frame_from_render
    from vcfusion.records import VehicleStates
    from vcfusion.render.renderer import Frame

    n = 2
    truth = VehicleStates(time=1.0, ids=("ego", "car"), vtype=("ego", "car"), vclass=("passenger",) * n,
                          x=np.array([0.0, 20.0]), y=np.zeros(n), z=np.zeros(n), heading=np.zeros(n),
                          speed=np.full(n, 20.0), accel=np.array([-4.0, 0.0]), lane=np.zeros(n, np.int16),
                          lateral_offset=np.zeros(n), length=np.full(n, 4.5), width=np.full(n, 1.8),
                          height=np.full(n, 1.5))
    depth = np.full((480, 640), 60.0, np.float32)
    instances = np.full((480, 640), -1, np.int32)
    depth[200:260, 280:360], instances[200:260, 280:360] = 17.75, 0
    frame = Frame(1.0, np.zeros((480, 640, 3), np.uint8), depth, instances, ("car",), K, T)
    exact = frame_from_render(frame, truth)
    sensed = frame_from_render(frame, truth, SensorModel("stereo", FLAT, PoseNoiseParams(mount_std_deg=0.3),
                                                         rng=np.random.default_rng(4)))
    assert np.array_equal(sensed.gt_boxes, exact.gt_boxes) and sensed.gt_ids == exact.gt_ids == ("car",)
    assert np.array_equal(sensed.instances, exact.instances)
    assert not np.array_equal(sensed.depth, exact.depth, equal_nan=True)
    assert not np.allclose(sensed.camera.T_world_to_camera, exact.camera.T_world_to_camera)
    assert np.array_equal(frame.depth, depth)  # the render itself is left as it was
    assert sensed.depth_noise.c > 0 and exact.depth_noise.exact


def test_a_stereo_pairs_median_reading_near_its_smallest_disparity_is_the_models_own():
    """DepthNoise.reading: the median of what the stereo model measures on a flat wall, its holes
    left out, against the closed form; nearer than the wall near the disparity floor, the wall
    itself well inside the range, and the exact depth (no stereo model) is read as it is."""
    model = SensorModel("stereo", FLAT, rng=np.random.default_rng(2))
    noise = model.noise(K)
    fb = F * FLAT.baseline_m
    for z in (20.0, 200.0, 230.0):  # disparities 6, 0.6 and 0.52 px; the floor is 0.5 px
        out = model.depth(np.full((200, 300), z, np.float32), K, T)
        measured = float(np.median(out[np.isfinite(out)]))
        assert float(noise.reading(z)) == pytest.approx(measured, rel=0.02)
        assert float(noise.scaled(0.3).reading(z)) == float(noise.reading(z))  # a filter keeps what is matched
    assert float(noise.reading(20.0)) == pytest.approx(20.0, rel=1e-3)
    assert float(noise.reading(200.0)) < 0.85 * 200.0
    # beyond the range (0.48 px) the model gives no depth and nothing is read
    assert np.isnan(model.depth(np.full((50, 50), 250.0, np.float32), K, T)).all() and np.isnan(noise.reading(250.0))
    assert fb / 250.0 < FLAT.min_disparity_px
    assert SensorModel("lidar", FLAT).noise(K).reading(200.0) == 200.0
