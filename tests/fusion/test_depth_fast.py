"""The depth step's compiled and reorganised parts give the results of their plain numpy versions
(tests/support/depth_reference.py) on small synthetic depth images: scans, stereo holes, surfaces
with depth jumps, sky (inf) and zeros."""

import numpy as np
import pytest

from support.road_depth import flat_road_depth, road_camera_pose
from support.depth_reference import (fill_scan_gaps_reference, join_across_outlines_reference, jump_free_reference,
                                     lowest_row_on_its_surface_reference, median_reference, object_segments_reference,
                                     on_road_mask_reference, refine_boxes_reference, restore_outlines_reference)
from vcfusion.fusion.box_refine import (BoxRefineParams, _components, _Heights, _join_across_outlines, _jump_free,
                                       _label_boxes,
                                       _lowest_row_on_its_surface, _restore_outlines, fill_scan_gaps, object_segments,
                                       on_road_mask, refine_boxes)
from vcfusion.fusion.fuse import _median
from vcfusion.fusion.road import DepthNoise
from vcfusion.fusion.sensors import SensorModel

W, H, F, CAM_H = 160, 120, 230.0, 1.4
K = np.array([[F, 0.0, W / 2], [0.0, F, H / 2], [0.0, 0.0, 1.0]])


def _pose(pitch_deg: float) -> np.ndarray:
    """Camera 1.4 m above the road at the origin, looking along +x, pitched down."""
    return road_camera_pose(pitch_deg, CAM_H)


def _scene(rng: np.random.Generator, T: np.ndarray) -> np.ndarray:
    """A flat road seen from T (sky: inf) with a few fronto-parallel blocks standing on it."""
    depth = flat_road_depth(T, K, W, H, 300.0)
    road = depth.copy()
    for _ in range(rng.integers(2, 6)):
        bottom = int(rng.integers(H // 2, H))
        x0 = int(rng.integers(0, W - 8))
        d = float(road[bottom, x0])
        if not np.isfinite(d):
            continue
        w, h = max(int(2.0 * F / d), 2), max(int(rng.uniform(1.4, 3.5) * F / d), 2)
        block = np.s_[max(bottom - h, 0):bottom + 1, x0:x0 + w]
        depth[block] = np.minimum(depth[block], d)
    return depth


def _synthetic_depth(rng: np.random.Generator, shape=(60, 80), hole_share: float = 0.5) -> np.ndarray:
    """A road plane (depth rising towards the horizon), a few boxes nearer than it, sky rows (inf),
    some zeros, and holes: whole rows left out as a scan leaves them, and scattered pixels."""
    H, W = shape
    rows = np.arange(H, dtype=np.float32)[:, None]
    z = np.broadcast_to(4.0 + 400.0 / (rows + 5.0), shape).astype(np.float32).copy()
    for _ in range(6):
        y0, x0 = rng.integers(0, H - 5), rng.integers(0, W - 5)
        z[y0:y0 + rng.integers(3, 20), x0:x0 + rng.integers(3, 25)] = rng.uniform(2, 60)
    z += rng.normal(0, 0.05, shape).astype(np.float32)
    z[: rng.integers(0, 8)] = np.inf
    z[rng.random(shape) < 0.01] = 0.0
    holes = rng.random(shape) < hole_share
    holes[rng.random(H) < 0.6] = True  # a scan's rows between beams
    z[holes] = np.nan
    return z


@pytest.mark.parametrize("seed", range(6))
def test_the_compiled_gap_fill_is_the_numpy_fill(seed):
    rng = np.random.default_rng(seed)
    for hole_share in (0.2, 0.6, 0.9):
        z = _synthetic_depth(rng, hole_share=hole_share)
        road = rng.random(z.shape) < 0.5
        for axis, max_gap, on_road, side in ((0, 6, road, None), (1, 2, None, None), (0, 6, None, None),
                                             (1, 16, None, "left"), (1, 3, road, "left"), (0, 0, None, None)):
            fast = fill_scan_gaps(z, max_gap, 0.5, 0.045, axis, on_road, side)
            reference = fill_scan_gaps_reference(z, max_gap, 0.5, 0.045, axis, on_road, side)
            assert fast.dtype == reference.dtype == np.float32
            np.testing.assert_array_equal(fast, reference)  # bit for bit, nan where nan
        filled = fill_scan_gaps(z, 6, 0.5, 0.045, 0)
        assert np.isnan(filled).sum() < np.isnan(z).sum()  # the test fills something


def test_the_gap_fill_names_a_mask_of_another_shape():
    with pytest.raises(ValueError, match="on_road"):
        fill_scan_gaps(np.ones((4, 5), np.float32), 2, 0.5, 0.045, 0, np.ones((5, 4), bool))


@pytest.mark.parametrize("seed", range(6))
def test_the_compiled_outline_restore_is_the_numpy_restore(seed):
    rng = np.random.default_rng(seed)
    for hole_share in (0.0, 0.2, 0.5):
        z = _synthetic_depth(rng, hole_share=hole_share)
        valid = np.isfinite(z) & (z > 0)
        z = np.where(valid, z, np.float32(0))
        obj = valid & (rng.random(z.shape) < 0.9)
        keep = obj & _jump_free(z, valid, 0.5, 0.045)
        labels = _components(keep)
        removed = obj & ~keep
        fast = _restore_outlines(labels, removed, z, 0.5, 0.045)
        reference = restore_outlines_reference(labels, removed, z, 0.5, 0.045)
        assert fast.dtype == reference.dtype
        np.testing.assert_array_equal(fast, reference)
        assert (fast[removed] > 0).sum() > 0  # pixels were given back
    # a strip given back over several passes, and a pixel with no neighbour on its surface left out
    labels = np.zeros((3, 6), np.int32)
    labels[:, 0] = 1
    removed = np.zeros((3, 6), bool)
    removed[1, 1:5] = True
    z = np.full((3, 6), 10.0, np.float32)
    z[1, 4] = 30.0
    np.testing.assert_array_equal(_restore_outlines(labels, removed, z, 0.5, 0.045)[1], [1, 1, 1, 1, 0, 0])


@pytest.mark.parametrize("sensor", ["exact", "stereo", "lidar", "tof"])
def test_the_row_cropped_road_mask_segments_and_median_are_the_full_image_ones(sensor):
    rng = np.random.default_rng(1)
    refine = BoxRefineParams()
    for pitch in (1.0, 3.0, 8.0):
        T = _pose(pitch)
        truth = _scene(rng, T)
        model = SensorModel(sensor, rng=rng)
        image = rng.integers(0, 255, (H, W, 3), dtype=np.uint8)
        depth, noise = model.depth(truth, K, T, image), model.noise(K)
        np.testing.assert_array_equal(on_road_mask(depth, K, T, noise, refine),
                                      on_road_mask_reference(depth, K, T, noise, refine))
        np.testing.assert_array_equal(_median(depth, 5), median_reference(depth, 5))
        dense = fill_scan_gaps(fill_scan_gaps(depth, 2, 0.5, 0.045, 1), 6, 0.5, 0.045, 0)
        for z, n in ((truth, DepthNoise()), (dense, noise)):
            fast, reference = object_segments(z, K, T, refine, n), object_segments_reference(z, K, T, refine, n)
            assert fast is not None and reference is not None
            assert fast.y_lo == reference.y_lo and fast.regions == reference.regions
            for name in ("z", "valid", "obj", "height", "labels", "areas"):
                np.testing.assert_array_equal(getattr(fast, name), getattr(reference, name))
    # rows without any depth: the road mask is empty, the median all holes, no segments
    empty = np.full((H, W), np.nan, np.float32)
    empty[:10] = np.inf
    assert not on_road_mask(empty, K, T, DepthNoise(), refine).any()
    np.testing.assert_array_equal(_median(empty, 5), median_reference(empty, 5))
    assert object_segments(empty, K, T, refine) is None


# support 0 keeps empty columns, whose median depth (_lateral_extent) is nan, in both versions
@pytest.mark.filterwarnings("ignore:Mean of empty slice", "ignore:invalid value encountered in divide")
@pytest.mark.parametrize("sensor", ["exact", "stereo", "lidar"])
def test_the_refinement_on_bounding_boxes_of_segments_is_the_whole_window_one(sensor):
    rng = np.random.default_rng(2)
    snapped = 0
    for pitch, support in ((1.0, 0.03), (3.0, 0.03), (3.0, 0.0), (8.0, 0.1)):
        T = _pose(pitch)
        truth = _scene(rng, T)
        model = SensorModel(sensor, rng=rng)
        depth, noise = model.depth(truth, K, T, rng.integers(0, 255, (H, W, 3), dtype=np.uint8)), model.noise(K)
        returns = None
        if sensor == "lidar":
            returns = ~np.isnan(depth)
            depth = fill_scan_gaps(fill_scan_gaps(depth, 2, 0.5, 0.045, 1), 6, 0.5, 0.045, 0)
        # loose, tight, shifted and wide boxes around the blocks' object pixels, and boxes anywhere
        obj = np.isfinite(truth) & (truth < np.nanmax(np.where(np.isfinite(truth), truth, 0)) * 0.99)
        boxes = [[x, y, x + rng.uniform(4, 60), y + rng.uniform(4, 40)]
                 for x, y in zip(rng.uniform(0, W - 10, 12), rng.uniform(H / 3, H - 10, 12))]
        labels = _components(obj)
        for k in range(1, labels.max() + 1):
            ys, xs = np.nonzero(labels == k)
            box = np.array([xs.min(), ys.min(), xs.max(), ys.max()], float)
            boxes += [box + rng.uniform(-4, 4, 4), box + [-6, -3, 6, 3]]
        boxes = np.clip(np.array(boxes), 0, [W - 1, H - 1, W - 1, H - 1])
        params = BoxRefineParams(road="from_depth", support=support)
        fast = refine_boxes(np.array(boxes), depth, K, T, params, noise, returns)
        reference = refine_boxes_reference(np.array(boxes), depth, K, T, params, noise, returns)
        for name in ("boxes", "refined", "top_m", "gated"):
            np.testing.assert_array_equal(getattr(fast, name), getattr(reference, name))
        snapped += int(fast.refined.sum())
    assert snapped >= 5  # the test snaps boxes, not only keeps them


def test_the_compiled_label_boxes_are_find_objects_slices():
    from scipy.ndimage import find_objects

    rng = np.random.default_rng(3)
    labels = _components(rng.random((40, 50)) < 0.45)
    labels[labels == 3] = 0  # a label with no pixel
    n = int(labels.max())
    boxes = _label_boxes(labels, n)
    for k, region in enumerate(find_objects(labels, max_label=n)):
        if region is None:
            assert boxes[k, 0] == -1
        else:
            assert (region[0].start, region[0].stop, region[1].start, region[1].stop) == tuple(boxes[k])
    assert (_label_boxes(labels, 2)[:, 0] >= 0).all()  # only labels up to n


@pytest.mark.parametrize("sensor", ["exact", "stereo", "lidar"])
def test_the_compiled_walk_down_a_surface_is_the_numpy_walk(sensor):
    rng = np.random.default_rng(4)
    walked = 0
    for pitch in (1.0, 3.0, 8.0):
        T = _pose(pitch)
        truth = _scene(rng, T)
        depth = SensorModel(sensor, rng=rng).depth(truth, K, T, rng.integers(0, 255, (H, W, 3), dtype=np.uint8))
        if sensor == "lidar":
            depth = fill_scan_gaps(fill_scan_gaps(depth, 2, 0.5, 0.045, 1), 6, 0.5, 0.045, 0)
        heights = _Heights(K, T)
        segments = object_segments(depth, K, T, BoxRefineParams())
        for label, region in enumerate(segments.regions if segments is not None else [], start=1):
            if region is None:
                continue
            sel = segments.labels[region] == label
            x, y = region[1].start, region[0].start + segments.y_lo
            for min_height in (0.05, 0.3):
                fast = _lowest_row_on_its_surface(sel, x, y, depth, heights, min_height, 0.5, 0.045)
                reference = lowest_row_on_its_surface_reference(sel, x, y, depth, heights, min_height, 0.5, 0.045)
                assert fast == reference
                walked += int(fast > y + sel.shape[0] - 1)
    assert walked > 0  # some segments were followed below their lowest pixel


@pytest.mark.parametrize("seed", range(4))
def test_the_compiled_jump_cut_and_join_are_the_numpy_ones(seed):
    rng = np.random.default_rng(seed)
    for hole_share in (0.0, 0.3):
        z = _synthetic_depth(rng, hole_share=hole_share)
        z[rng.random(z.shape) < 0.02] = np.inf
        valid = np.isfinite(z) & (z > 0)
        for jump_m, jump_rel in ((0.5, 0.045), (0.3, 0.1)):
            keep = _jump_free(z, valid, jump_m, jump_rel)
            np.testing.assert_array_equal(keep, jump_free_reference(z, valid, jump_m, jump_rel))
            assert keep.any() and not keep.all()
            zw = np.where(valid, z, np.float32(0))
            labels = _components(valid & keep & (rng.random(z.shape) < 0.95))
            labels = np.where(valid & ~keep, 1 + labels.max() + _components(valid & ~keep), labels).astype(np.int32)
            joined = _join_across_outlines(labels, zw, jump_m, jump_rel)
            reference = join_across_outlines_reference(labels, zw, jump_m, jump_rel)
            assert joined.dtype == reference.dtype
            np.testing.assert_array_equal(joined, reference)
            assert len(np.unique(joined)) < len(np.unique(labels))  # segments were joined


def test_the_compiled_segment_box_is_the_numpy_one():
    from support.depth_reference import segment_box_reference
    from vcfusion.fusion.box_refine import _segment_box

    rng = np.random.default_rng(3)
    for _ in range(200):
        h, w = rng.integers(1, 30, 2)
        sel = rng.random((h, w)) < rng.uniform(0.0, 1.0)
        if rng.random() < 0.3:
            sel[:, : w // 2] = False  # a part empty: its columns fall below the support
        x0, y0 = int(rng.integers(0, 600)), int(rng.integers(0, 400))
        for support in (0.0, 0.15, 0.3, 1.0 / 3.0, 1.0):
            fast, reference = _segment_box(sel, support, x0, y0), segment_box_reference(sel, support, x0, y0)
            assert fast.dtype == reference.dtype and fast.tobytes() == reference.tobytes()
    with pytest.raises(ValueError, match="non-empty 2-D mask"):
        _segment_box(np.zeros((0, 3), bool), 0.3, 0, 0)
