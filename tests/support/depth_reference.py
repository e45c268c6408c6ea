"""Reference (plain numpy) versions of the depth step's compiled or reorganised parts, as they were
before: the fast code in vcfusion.fusion.box_refine must give the same results on synthetic depth
(tests/fusion/test_depth_fast.py)."""

from __future__ import annotations

import numpy as np

from vcfusion.fusion.box_refine import _farther, _same_surface


def fill_scan_gaps_reference(depth: np.ndarray, max_gap_px: int, jump_m: float, jump_rel: float, axis: int = 0,
                   on_road: np.ndarray | None = None, occlusion_side: str | None = None) -> np.ndarray:
    """A sparse scan's depth (nan where no return lands) with the gaps between returns filled along
    ``axis`` (0: down each column, 1: along each row), where two returns at most ``max_gap_px + 1``
    pixels apart bound the gap: linearly in inverse depth between them (exact on a plane) when they
    lie on one surface (no depth jump, :func:`_same_surface`) or both on the road (``on_road``, (H, W)
    bool: returns within the road's noise of the fitted road; far down the road two beams' returns
    lie metres apart), else each pixel takes the nearer return's depth (the edge between two surfaces
    half-way between the returns). A gap wider than that, or open at the image's edge, stays nan.
    ``inf`` (a return with nothing within range) counts as a return. ``occlusion_side="left"`` (along
    rows of a stereo pair's left image): a gap whose right end is nearer than its left by a depth
    jump is the band the right camera could not see behind the nearer surface's left edge, and takes
    the farther depth whole."""
    if occlusion_side not in (None, "left"):
        raise ValueError(f"occlusion_side: expected None or 'left', got {occlusion_side!r}")
    if axis not in (0, 1):
        raise ValueError(f"axis: expected 0 (columns) or 1 (rows), got {axis}")
    z = np.asarray(depth, np.float32)
    measured = ~np.isnan(z)
    # only the rows holding returns can hold a gap between two of them (the sky above a scan's highest
    # beam holds none)
    rows = np.flatnonzero(measured.any(axis=1))
    if not len(rows):
        return z.copy()
    if rows[0] > 0 or rows[-1] < z.shape[0] - 1:
        lo, hi = int(rows[0]), int(rows[-1]) + 1
        out = z.copy()
        out[lo:hi] = fill_scan_gaps_reference(z[lo:hi], max_gap_px, jump_m, jump_rel, axis,
                                    None if on_road is None else on_road[lo:hi], occlusion_side)
        return out
    H, W = z.shape
    # per pixel, how far the nearest return lies before (above / left) and after it along the axis,
    # within max_gap_px + 1 (0: none that near); one shifted comparison per distance
    before = np.zeros(z.shape, np.int16)
    after = np.zeros(z.shape, np.int16)
    n = H if axis == 0 else W
    for d in range(1, min(max_gap_px + 1, n - 1) + 1):
        if axis == 0:
            b_view, b_src, a_view, a_src = before[d:], measured[:-d], after[:-d], measured[d:]
        else:
            b_view, b_src, a_view, a_src = before[:, d:], measured[:, :-d], after[:, :-d], measured[:, d:]
        b_view[(b_view == 0) & b_src] = d
        a_view[(a_view == 0) & a_src] = d
    gap = ~measured & (before > 0) & (after > 0) & (before + after <= max_gap_px + 1)
    if not gap.any():
        return z.copy()
    r, c = np.nonzero(gap)
    da, db = before[r, c], after[r, c]
    if axis == 0:
        za, zb = z[r - da, c], z[r + db, c]
        road_a, road_b = (None, None) if on_road is None else (on_road[r - da, c], on_road[r + db, c])
    else:
        za, zb = z[r, c - da], z[r, c + db]
        road_a, road_b = (None, None) if on_road is None else (on_road[r, c - da], on_road[r, c + db])
    t = (da / (da + db)).astype(np.float32)
    with np.errstate(invalid="ignore", divide="ignore"):
        same = np.isfinite(za) & np.isfinite(zb) & (za > 0) & (zb > 0) & _same_surface(za, zb, jump_m, jump_rel)
        if on_road is not None:
            same |= np.isfinite(za) & np.isfinite(zb) & road_a & road_b
        inverse = np.float32(1) / (np.float32(1) / za + t * (np.float32(1) / zb - np.float32(1) / za))
        edge = np.where(t <= 0.5, za, zb)
        if occlusion_side == "left":
            # a stereo pair's occlusion band: left of a nearer surface, the farther one the right
            # camera could not see (the right end nearer than the left by a jump): the farther's
            edge = np.where(_farther(za, zb, jump_m, jump_rel), za, edge)
        value = np.where(same, inverse, edge)
    out = z.copy()
    out[r, c] = value
    return out
