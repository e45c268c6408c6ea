"""The depth step's compiled and reorganised parts give the results of their plain numpy versions
(tests/support/depth_reference.py) on small synthetic depth images: scans, stereo holes, surfaces
with depth jumps, sky (inf) and zeros."""

import numpy as np
import pytest

from support.depth_reference import fill_scan_gaps_reference
from vcfusion.fusion.box_refine import fill_scan_gaps


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
