import numpy as np
import pytest

from vcfusion.fusion.depth_eval import DepthEvalParams, evaluate_box_depths, sampling_areas


def test_sampling_area_is_lower_quarter_of_shrunk_box():
    area = sampling_areas(np.array([[100.0, 100.0, 200.0, 300.0]]), th=0.8)
    # 0.8 * (100 x 200) = 80 x 160 about the centre (150, 200): x 110..190, y 120..280; lower quarter 240..280
    np.testing.assert_allclose(area, [[110.0, 240.0, 190.0, 280.0]])


def test_only_the_lower_quarter_of_the_shrunk_box_is_sampled():
    depth = np.full((480, 640), 99.0, np.float32)
    depth[100:301, 100:201] = 5.0  # the whole box: the sampled area must see only 18.69 below
    # pixel-centre convention: the area x 110..190, y 240..280 touches pixels 110..190, 240..280
    depth[240:281, 110:191] = 18.69
    rng = np.random.default_rng(0)
    d = evaluate_box_depths(depth, [[100, 100, 200, 300]], rng, DepthEvalParams(th=0.8, n=200))
    assert d[0] == pytest.approx(18.69, abs=1e-5)
    # without shrinking, samples also hit the 5 m margin and the 99 m outside: a different mean
    d_full = evaluate_box_depths(depth, [[100, 100, 200, 300]], np.random.default_rng(0),
                                 DepthEvalParams(th=1.0, n=200))
    assert abs(d_full[0] - 18.69) > 0.5


def test_sky_and_missing_depth_are_ignored_and_all_invalid_gives_nan():
    depth = np.full((100, 100), 20.0, np.float32)
    depth[:, :30] = np.inf
    depth[:, 30:45] = 0.0
    d = evaluate_box_depths(depth, [[0, 0, 100, 100]], np.random.default_rng(1), DepthEvalParams(n=100))
    assert d[0] == pytest.approx(20.0)
    sky = np.full((100, 100), np.inf, np.float32)
    assert np.isnan(evaluate_box_depths(sky, [[0, 0, 100, 100]], np.random.default_rng(1))[0])


def test_median_option_is_robust_to_stray_samples():
    depth = np.full((100, 100), 10.0, np.float32)
    depth[:, 90:] = 100.0  # a tenth of the sampled area lies on a far background
    params = dict(th=1.0, n=400)
    mean = evaluate_box_depths(depth, [[0, 0, 100, 100]], np.random.default_rng(2), DepthEvalParams(**params))
    median = evaluate_box_depths(depth, [[0, 0, 100, 100]], np.random.default_rng(2),
                                 DepthEvalParams(**params, reducer="median"))
    assert median[0] == 10.0
    assert 15.0 < mean[0] < 25.0


def test_sampling_is_seeded():
    yy, xx = np.mgrid[0:200, 0:200]
    depth = (5.0 + xx * 0.1 + yy * 0.05).astype(np.float32)
    boxes = [[10, 10, 150, 190], [50, 60, 70, 90]]
    a = evaluate_box_depths(depth, boxes, np.random.default_rng(7), DepthEvalParams(n=5))
    b = evaluate_box_depths(depth, boxes, np.random.default_rng(7), DepthEvalParams(n=5))
    c = evaluate_box_depths(depth, boxes, np.random.default_rng(8), DepthEvalParams(n=5))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


def test_boxes_reaching_outside_the_image_are_clipped_and_empty_input_is_fine():
    depth = np.full((50, 50), 7.0, np.float32)
    d = evaluate_box_depths(depth, [[-40, -40, 80, 90]], np.random.default_rng(0))
    assert d[0] == pytest.approx(7.0)
    assert evaluate_box_depths(depth, np.zeros((0, 4)), np.random.default_rng(0)).shape == (0,)


def test_bad_parameters_are_refused():
    with pytest.raises(ValueError, match="th"):
        DepthEvalParams(th=1.5)
    with pytest.raises(ValueError, match="n"):
        DepthEvalParams(n=0)
