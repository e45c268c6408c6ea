"""The depth sensor models' compiled kernels (vcfusion.fusion.sensors) give, bit for bit, the images
of their whole-image numpy definitions (tests/support/sensor_reference.py) from the same draws, on
random depth images with sky (inf), zeros, holes (nan), near surfaces and flat image patches."""

import numpy as np
import pytest

from support.sensor_reference import stereo_depth_reference
from vcfusion.fusion.sensors import DepthSensorParams, SensorModel, stereo_depth


def _depth(rng: np.random.Generator, shape=(48, 64)) -> np.ndarray:
    H, W = shape
    rows = np.arange(H, dtype=np.float32)[:, None]
    z = np.broadcast_to(2.0 + 300.0 / (rows + 1.0), shape).astype(np.float32).copy()
    for _ in range(5):  # nearer blocks: occlusion bands left of them
        y0, x0 = rng.integers(0, H - 4), rng.integers(0, W - 4)
        z[y0:y0 + rng.integers(2, 20), x0:x0 + rng.integers(2, 30)] = rng.uniform(0.5, 60.0)
    z[: rng.integers(0, H // 4)] = np.inf  # sky
    z[rng.random(shape) < 0.03] = 0.0
    z[rng.random(shape) < 0.03] = np.nan
    z[rng.random(shape) < 0.02] = rng.uniform(1e-3, 0.2)  # very near: large disparities
    return z


def _image(rng: np.random.Generator, shape=(48, 64)) -> np.ndarray:
    img = rng.integers(0, 256, (*shape, 3), dtype=np.uint8)
    img[: shape[0] // 2, : shape[1] // 2] = rng.integers(0, 256, 3, dtype=np.uint8)  # flat: no texture
    img[shape[0] // 2:, shape[1] // 2:] //= 64  # faint texture: std near the threshold
    return img


PARAMS = [DepthSensorParams(), DepthSensorParams(texture_min=0.0),
          # thresholds float32 cannot hold exactly (compared in float32, as the array expressions do)
          DepthSensorParams(baseline_m=0.3, disparity_noise_px=0.7, min_disparity_px=0.7, texture_min=2.3),
          DepthSensorParams(disparity_noise_px=0.0, min_disparity_px=0.0)]


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("k", range(len(PARAMS)))
def test_the_compiled_stereo_model_is_the_array_definition(seed, k):
    rng = np.random.default_rng(seed)
    depth, image = _depth(rng), _image(rng)
    for img in (image, None):
        new = stereo_depth(depth, 457.0073621574767, PARAMS[k], np.random.default_rng([seed, 48]), img)
        ref = stereo_depth_reference(depth, 457.0073621574767, PARAMS[k], np.random.default_rng([seed, 48]), img)
        assert new.dtype == np.float32 and new.tobytes() == ref.tobytes()
    holes = np.isnan(new)
    assert holes.any() and not holes.all()  # the inputs exercise both outcomes


def test_the_stereo_model_leaves_the_generator_where_the_definition_does():
    rng = np.random.default_rng(5)
    depth, image = _depth(rng), _image(rng)
    a, b = np.random.default_rng(7), np.random.default_rng(7)
    stereo_depth(depth, 500.0, DepthSensorParams(), a, image)
    stereo_depth_reference(depth, 500.0, DepthSensorParams(), b, image)
    assert a.random() == b.random()


def test_the_stereo_model_names_a_depth_image_that_is_not_2d_and_an_image_of_another_size():
    model = SensorModel("stereo", rng=np.random.default_rng(0))
    with pytest.raises(ValueError, match="2-D depth image"):
        model.depth(np.zeros((4, 4, 1), np.float32), np.eye(3), np.eye(4))
    with pytest.raises(ValueError, match="depth image's size"):
        model.depth(np.zeros((4, 4), np.float32), np.eye(3), np.eye(4), np.zeros((4, 5, 3), np.uint8))


def test_the_noise_sigma_of_one_depth_is_the_arrays():
    rng = np.random.default_rng(2)
    depths = np.r_[rng.uniform(0.0, 150.0, 300), 0.0, 1.0, 35, np.inf]
    with np.errstate(invalid="ignore"):  # inf x 0 (a term the model lacks at infinite depth): nan both ways
        _compare_sigmas(depths)


def _compare_sigmas(depths):
    from vcfusion.fusion.road import DepthNoise

    for noise in (DepthNoise(c=0.25 / 55.0), DepthNoise(a=0.01, b=0.01), DepthNoise(a=0.02), DepthNoise(0.013, 0.07, 3e-3)):
        array = noise.sigma(depths)
        for z, want in zip(depths, array):
            for scalar in (float(z), np.float64(z), np.float32(z)):
                got = noise.sigma(scalar)
                assert type(got) is np.float32 and got.tobytes() == want.tobytes()
