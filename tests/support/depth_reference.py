"""Reference (plain numpy) versions of the depth step's compiled or reorganised parts: the fast
code in vcfusion.fusion.box_refine must give the same results on synthetic depth
(tests/fusion/test_depth_fast.py)."""

from __future__ import annotations

import cv2
import numpy as np
from scipy.ndimage import find_objects

from vcfusion.fusion.box_refine import (ObjectSegments, RefinedBoxes, _box_iou, _components, _core, _farther,
                                       _grown_sides, _Heights, _join_pairs, _lateral_extent, _restore_outlines,
                                       _same_surface, _segment_box, _spans_jump, _surface_sides, _unmeasured_sides,
                                       gate_by_noise)


def fill_scan_gaps_reference(depth: np.ndarray, max_gap_px: int, jump_m: float, jump_rel: float, axis: int = 0,
                   on_road: np.ndarray | None = None, occlusion_side: str | None = None) -> np.ndarray:
    """box_refine.fill_scan_gaps as shifted whole-image comparisons, one per gap width (valid arguments only)."""
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


def restore_outlines_reference(labels: np.ndarray, removed: np.ndarray, z: np.ndarray, jump_m: float,
                      jump_rel: float) -> np.ndarray:
    """Segment labels with the pixels the cut removed given back: each removed pixel (the farther of
    a jumping pair, so the outline of a vehicle a nearer one hides) takes the label of a 4-neighbour
    on its own surface (no jump either way), pass after pass until no pixel changes, so a strip of
    them (the lower part of a truck seen 1-2 px wide between two nearer vehicles, where every pixel
    is the farther one of some pair) goes back to its surface whole, not one pixel deep. Without
    this a sliver of a hidden car, 12 px wide, loses a pixel on each hidden side and its box misses
    IoU 0.7 with the true one. Each pass reads the labels the previous one left; of several
    neighbours, right, left, below, above is the order of preference."""
    H, W = labels.shape
    idx = np.flatnonzero(removed & (labels == 0))  # the pixels still to give back
    if not idx.size:
        return labels.copy()
    outside = H * W  # one slot past the image: label 0, infinitely far, so never taken
    flat = np.zeros(outside + 1, labels.dtype)
    flat[:-1] = labels.ravel()
    z_flat = np.append(np.asarray(z, np.float32).ravel(), np.float32(np.inf))
    ys, xs = np.divmod(idx, W)
    neighbours = np.stack([np.where(xs + 1 < W, idx + 1, outside), np.where(xs > 0, idx - 1, outside),
                           np.where(ys + 1 < H, idx + W, outside), np.where(ys > 0, idx - W, outside)])
    # a neighbour off the pixel's surface is never taken: pointed at the empty slot once, not tested each pass
    on_surface = _same_surface(z_flat[idx][None], z_flat[neighbours], jump_m, jump_rel)
    neighbours = np.where(on_surface, neighbours, outside)
    while idx.size:
        found = flat[neighbours]  # (4, n): each pass reads the labels the previous one left
        found = found[(found > 0).argmax(axis=0), np.arange(idx.size)]  # the first labelled one
        given = found > 0
        if not given.any():
            break
        flat[idx[given]] = found[given]
        idx, neighbours = idx[~given], neighbours[:, ~given]
    return flat[:-1].reshape(H, W)


def jump_free_reference(z: np.ndarray, valid: np.ndarray, jump_m: float, jump_rel: float) -> np.ndarray:
    """box_refine._jump_free as shifted whole-image comparisons: False at the farther pixel of each
    4-neighbour pair whose depths jump (no depth reads inf)."""
    zj = np.where(valid, z, np.float32(np.inf))
    keep = np.ones(z.shape, bool)
    for a, b, a_view, b_view in ((zj[:-1], zj[1:], keep[:-1], keep[1:]),
                                 (zj[:, :-1], zj[:, 1:], keep[:, :-1], keep[:, 1:])):
        a_view &= ~_farther(a, b, jump_m, jump_rel)
        b_view &= ~_farther(b, a, jump_m, jump_rel)
    return keep


def join_across_outlines_reference(labels: np.ndarray, z: np.ndarray, jump_m: float, jump_rel: float) -> np.ndarray:
    """box_refine._join_across_outlines with its touching pairs from shifted whole-image comparisons
    (the joining of the pairs is box_refine's own)."""
    pairs = []
    for a, b, za, zb in ((labels[:-1], labels[1:], z[:-1], z[1:]), (labels[:, :-1], labels[:, 1:], z[:, :-1], z[:, 1:])):
        touch = (a > 0) & (b > 0) & (a != b)
        if touch.any():
            la, lb = a[touch], b[touch]
            same = _same_surface(za[touch], zb[touch], jump_m, jump_rel)
            pairs.append(np.stack([la[same], lb[same]]))
    return _join_pairs(labels, np.concatenate(pairs, axis=1) if pairs else np.zeros((2, 0), int))


def on_road_mask_reference(depth: np.ndarray, K: np.ndarray, T_world_to_camera: np.ndarray, noise,
                 refine) -> np.ndarray:
    """(H, W) bool: the measured pixels within ``refine.scan_road_m`` (+ ``noise_k`` sigma of their
    height's noise) of the road whose z = 0 plane `T_world_to_camera` defines (a fitted road's pose)."""
    heights = _Heights(K, T_world_to_camera)
    finite = np.isfinite(depth)
    z = np.where(finite, depth, np.float32(0)).astype(np.float32)
    tolerance = refine.scan_road_m + heights.noise_margin(z, noise, refine.noise_k)
    return finite & (np.abs(heights.window(z, 0, 0)) < tolerance)


def object_segments_reference(depth: np.ndarray, K: np.ndarray, T_world_to_camera: np.ndarray,
                    refine, noise=None) -> ObjectSegments | None:
    """The image's object pixels cut into segments (module docstring); None when it holds none
    (``noise``: the depth's DepthNoise, raising the object pixels' height threshold)."""
    params = refine.proposals
    if params is None:
        raise ValueError("depth segments: the proposals are switched off (BoxRefineParams.proposals is None)")
    z = np.asarray(depth, np.float32)
    valid = np.isfinite(z) & (z > 0)
    z = np.where(valid, z, np.float32(0))
    heights = _Heights(K, T_world_to_camera)
    height = heights.window(z, 0, 0)
    obj = valid & (height > params.min_height_m + heights.noise_margin(z, noise, refine.noise_k)) \
        & (height < refine.max_height_m)
    rows = np.flatnonzero(obj.any(axis=1))
    if not len(rows):
        return None
    # only the rows holding object pixels (the sky and the road ahead hold none)
    y_lo, y_hi = int(rows[0]), int(rows[-1]) + 1
    y_lo = max(y_lo - 1, 0)  # and the row above them: what stands above a segment's top
    obj, height, z, valid = obj[y_lo:y_hi], height[y_lo:y_hi], z[y_lo:y_hi], valid[y_lo:y_hi]
    # cut at depth jumps: the farther pixel of each jumping neighbour pair leaves the mask
    keep = obj & jump_free_reference(z, valid, refine.jump_m, refine.jump_rel)
    labels = _restore_outlines(_components(keep), obj & ~keep, z, refine.jump_m, refine.jump_rel)
    # what no neighbour on its surface took back is a segment of its own, not left out: a vehicle seen
    # 1 px wide between nearer things (every pixel the farther one of a jumping pair), e.g. the piece
    # of a sliver below a mirror of the car beside it, which then joins its box (join_fragments)
    islands = obj & (labels == 0)
    if islands.any():
        labels = np.where(islands, _components(islands) + labels.max(), labels)
    labels = join_across_outlines_reference(labels, z, refine.jump_m, refine.jump_rel)
    return ObjectSegments(z, valid, obj, height, labels, np.bincount(labels.ravel()),
                          find_objects(labels), y_lo)


def median_reference(depth: np.ndarray, size: int) -> np.ndarray:
    """A size x size median of a depth image with holes (nan): holes stay holes, and a pixel the
    median takes into a hole (more than half its window missing) becomes one."""
    z = np.asarray(depth, np.float32)
    hole = ~np.isfinite(z)
    far = np.isposinf(z)
    filled = np.where(hole, np.float32(0), z)
    out = cv2.medianBlur(filled, size)
    return np.where(far, np.float32(np.inf), np.where(hole | (out <= 0), np.float32(np.nan), out)).astype(np.float32)


def refine_boxes_reference(boxes: np.ndarray, depth: np.ndarray, K: np.ndarray, T_world_to_camera: np.ndarray,
                 params, noise=None,
                 returns: np.ndarray | None = None) -> RefinedBoxes:
    """box_refine.refine_boxes with every candidate segment measured over the whole window."""
    boxes = np.asarray(boxes, float).reshape(-1, 4)
    depth = np.asarray(depth)
    if depth.ndim != 2:
        raise ValueError(f"depth: expected a 2-D depth image (H, W), got shape {depth.shape}")
    heights = _Heights(K, T_world_to_camera)
    K = np.asarray(K, float)
    H, W = depth.shape
    out = boxes.copy()
    refined = np.zeros(len(boxes), bool)
    top_m = np.full(len(boxes), np.nan)
    gated = np.zeros(len(boxes), bool)
    p = params
    dense_noisy = noise is not None and (noise.b > 0 or noise.c > 0) and returns is None
    box_z = np.full(len(boxes), np.nan)
    for k, b in enumerate(boxes):
        if dense_noisy and b[2] > b[0] and b[3] > b[1]:
            zc = depth[_core(b, 0, 0)]
            zc = zc[np.isfinite(zc) & (zc > 0)]
            box_z[k] = float(np.median(zc)) if zc.size else np.nan
    for i, b in enumerate(boxes):
        w, h = b[2] - b[0], b[3] - b[1]
        if not (w > 0 and h > 0):
            continue
        mx, my = max(p.margin * w, 3.0), max(p.margin * h, 3.0)
        x0, y0 = max(0, int(np.floor(b[0] - mx))), max(0, int(np.floor(b[1] - my)))
        x1, y1 = min(W, int(np.ceil(b[2] + mx)) + 1), min(H, int(np.ceil(b[3] + my)) + 1)
        if x1 <= x0 or y1 <= y0:
            continue
        z = depth[y0:y1, x0:x1].astype(np.float32)
        core = _core(b, x0, y0)  # at least one pixel
        if np.isnan(z[core]).mean() > 1 - p.gate_valid_share:  # no measurement (holes, a sparse scan)
            gated[i] = True
            continue
        if returns is not None:
            # a box crossed by too few of the scan's rows: its outline lies between them, unseen
            core_returns = returns[y0:y1, x0:x1][core]
            if not core_returns.size or np.median(core_returns.sum(axis=0)) < p.scan_min_rows:
                gated[i] = True
                continue
        valid = np.isfinite(z) & (z > 0)
        if noise is not None and not noise.exact and valid[core].any() \
                and gate_by_noise(float(np.median(z[core][valid[core]])), noise, p):
            gated[i] = True  # too noisy at this depth to tell one surface from the next
            continue
        z = np.where(valid, z, np.float32(0))
        height = heights.window(z, x0, y0)
        obj = valid & (height > p.min_height_m + heights.noise_margin(z, noise, p.noise_k))
        core_z = z[core][obj[core]]
        if core_z.size < 3:
            continue
        jump_free = jump_free_reference(z, valid, p.jump_m, p.jump_rel)
        log_z = np.log(core_z)
        edges = np.arange(log_z.min(), log_z.max() + 0.05, 0.04)
        hist, edges = np.histogram(log_z, bins=edges)
        jump = ~jump_free
        segmentations = []  # (labels, cut at depth jumps) per way of splitting the window's object pixels
        for j in np.argsort(-hist, kind="stable")[: p.candidates]:
            if hist[j] == 0:
                break
            z0 = float(np.exp(edges[j]))
            band = obj & (z > z0 - 0.3 * p.band_m - 0.03 * z0) & (z < z0 + p.band_m + 0.03 * z0)
            segmentations.append((_components(band), False))
            cut = band & jump_free
            if (band > cut).any():
                segmentations.append((_restore_outlines(_components(cut), band & ~cut, z, p.jump_m, p.jump_rel), True))
        # and the surfaces whole, however deep (the side of a truck in the next lane runs 15 m away)
        whole = obj & jump_free
        segmentations.append((_restore_outlines(_components(whole), obj & ~whole, z, p.jump_m, p.jump_rel), True))
        candidates = []  # (IoU with the detected box, segment box, segment mask, cut at depth jumps)
        for labels, is_cut in segmentations:
            for label in np.unique(labels[core]):
                if label == 0:
                    continue
                sel = labels == label
                candidate = _segment_box(sel, p.support, x0, y0)
                iou = _box_iou(candidate, b)
                if iou > p.min_iou:
                    candidates.append((iou, candidate, sel, is_cut))
        best = best_sel = None
        if candidates:
            candidates.sort(key=lambda c: -c[0])  # stable: of equal overlaps, the first found
            _, best, best_sel, best_is_cut = candidates[0]
            # a box over two vehicles side by side (two trucks in neighbouring lanes a few metres
            # apart in depth, inside one band) snaps best to the pair: when that segment spans a depth
            # jump and is wider than any vehicle, a jump-free segment no wider that still explains the
            # box takes its place, and the other vehicle, no longer inside a box, becomes a proposal.
            # Jump-free, because a car mid lane change, seen at an angle, is 3-4 m across the view
            # with its side, one surface: its wheels and mirrors must not pass for a second vehicle
            if (_spans_jump(best_sel, best_is_cut, jump)
                    and _lateral_extent(best_sel, z, x0, K, p.support) > p.pair_width_m):
                for iou, candidate, sel, is_cut in candidates[1:]:
                    if iou < p.pair_min_iou:
                        break
                    if (not _spans_jump(sel, is_cut, jump)
                            and _lateral_extent(sel, z, x0, K, p.support) <= p.pair_width_m):
                        best, best_sel = candidate, sel
                        break
        if best is not None:
            if p.surface_sides:
                whole_window = (slice(None), slice(None))
                best = _surface_sides(best, b, whole_window, best_sel, segmentations[-1][0], x0, y0, p.support)
            if p.grown_sides and dense_noisy:
                best = _grown_sides(best, b, (slice(None), slice(None)), best_sel, z, x0, y0, p.jump_m, p.jump_rel,
                                    np.delete(boxes, i, axis=0), np.delete(box_z, i))
            if returns is not None:
                best = _unmeasured_sides(best, b, np.isnan(depth[y0:y1, x0:x1]), x0, y0, p.unmeasured_share)
            elif p.hole_side_share > 0 and dense_noisy:
                best = _unmeasured_sides(best, b, np.isnan(depth[y0:y1, x0:x1]), x0, y0, p.unmeasured_share,
                                         p.hole_side_share)
            out[i] = best
            refined[i] = True
            top_m[i] = float(np.percentile(height[best_sel], 95))
    return RefinedBoxes(out, refined, top_m, gated)


def lowest_row_on_its_surface_reference(sel: np.ndarray, x: int, y: int, depth: np.ndarray, heights: _Heights,
                               min_height_m: float, jump_m: float, jump_rel: float) -> int:
    """The lowest image row a segment reaches when each of its columns is followed down from its
    lowest pixel over the same surface (no depth jump from the pixel above) while the pixels stand
    more than ``min_height_m`` above the road. `sel` is the segment's mask in its bounding box, whose
    pixel (0, 0) is image pixel (x, y). Why: the proposals' object pixels stand 0.3 m above the road
    (no kerbs or markings), so a proposed vehicle's box stopped above its bumper and tyres, which the
    ground truth spans: 17 px for a car 8 m ahead."""
    cols = np.flatnonzero(sel.any(axis=0))
    rows = y + sel.shape[0] - 1 - np.argmax(sel[::-1, cols], axis=0)  # each column's lowest pixel
    row0 = int(rows.min())
    if row0 >= depth.shape[0] - 1:
        return int(rows.max())
    z = np.asarray(depth[row0:, x:x + sel.shape[1]], np.float32)
    z = np.where(np.isfinite(z) & (z > 0), z, np.float32(0))  # no depth: off any surface
    h = heights.window(z, x, row0)[:, cols]
    z = z[:, cols]
    k = np.arange(len(cols))
    at = rows - row0  # per column: the row reached, in the window
    going = np.ones(len(cols), bool)
    while going.any():
        nxt = np.minimum(at + 1, len(z) - 1)
        going &= (nxt > at) & (h[nxt, k] > min_height_m) & _same_surface(z[nxt, k], z[at, k], jump_m, jump_rel)
        at = np.where(going, nxt, at)
    return int(row0 + at.max())


def segment_box_reference(sel: np.ndarray, support: float, x0: int, y0: int) -> np.ndarray:
    """box_refine._segment_box as array expressions."""
    cols, rows = sel.sum(axis=0), sel.sum(axis=1)
    xs = np.flatnonzero(cols >= support * cols.max())
    ys = np.flatnonzero(rows >= support * rows.max())
    return np.array([x0 + xs[0] - 0.5, y0 + ys[0] - 0.5, x0 + xs[-1] + 0.5, y0 + ys[-1] + 0.5])
