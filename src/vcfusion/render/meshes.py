"""Trimesh models of the highway and its surroundings (no OpenGL here); vehicles are in
:mod:`vcfusion.render.vehicles`.

The road is built once per run from the road frame of the camera's route
(:class:`~vcfusion.traffic.roadframe.RoadFrame`: s along the route, d left of its right edge,
lanes as tracks that begin and end along s), and from the network's other edges near the route
(a ramp before it joins, the other carriageway), each drawn in its own one-edge frame the same way:

- asphalt over every lane where the lane exists, with slightly darker wheel tracks (the shader adds
  grain and patches); a lane that ends inside the route (an acceleration lane, a lane drop)
  narrows to nothing over TAPER_M beyond its end (drawn only: SUMO's lane ends at its end);
- markings: a solid edge line along both outer edges (0.30 m wide on the right, 0.15 m on the
  left); 0.15 m dashes between lanes (6 m dash, 12 m gap, as on German motorways); between a
  lane that does not run the whole route (an acceleration lane, a lane that drops) and its
  neighbour, the German block marking ("Blockmarkierung" of the RMS): 0.30 m dashes, 6 m long
  with 6 m gaps;
- paved shoulders beyond the edge lines, guard rails (posts every 4 m and a beam) beyond them,
  reflector posts every 50 m, trees and bushes on the verges; none of these where another road's
  asphalt comes within NEAR_M of the outer edge (the gore between a ramp and the main line gets
  grass between the two edge lines), and no tree near another road;
- a grass ground plane.

A line of constant d is straight between two of the frame's vertices (the frame's map is linear
along it), so every strip is cut at those vertices and is exact; on a straight road (a
:class:`~vcfusion.traffic.network.Road`) only at its pieces' ends, as it always was. Every part
carries face colours and a material (the colour's alpha byte, see
:mod:`vcfusion.render.materials`).
"""

from __future__ import annotations

import zlib

import numpy as np
import trimesh

from vcfusion.render.materials import ASPHALT, FOLIAGE, GRASS, MATTE, METAL, PAINT_MARK, coloured
from vcfusion.traffic.roadframe import RoadFrame, edge_lane_shapes

# RGB 0-255.
ASPHALT_RGB = (72, 74, 78)
TRACK_RGB = (64, 66, 70)  # wheel tracks: polished darker
SHOULDER_RGB = (92, 93, 96)
MARKING_RGB = (232, 232, 225)
GRASS_RGB = (84, 116, 60)
RAIL_RGB = (175, 180, 185)
POST_RGB = (110, 112, 116)
DELINEATOR_RGB = (236, 236, 232)
BARK_RGB = (80, 62, 46)
LEAF_RGBS = ((56, 92, 44), (70, 104, 48), (48, 80, 40), (86, 110, 52))
SKY = (0.62, 0.76, 0.92)  # the sky colour about 25 degrees above the horizon (0-1); see vcfusion.render.sky

MARK_Z = 0.02  # paint above the asphalt, against z-fighting
DASH_M, GAP_M = 6.0, 12.0
LINE_W = 0.15
SHOULDER_M = 2.5
RAIL_OFFSET_M = 0.6  # guard rail beyond the shoulder
POST_SPACING_M = 4.0
DELINEATOR_SPACING_M = 50.0
TREE_SPACING_M = 40.0  # one candidate tree site per side every this many metres
ROAD_PIECE_M = 50.0  # the scene's unit of culling along s
ROUTE_MARGIN_M = 150.0  # the route's road goes on beyond its ends, so it never ends in view
TAPER_M = 60.0  # an ending lane narrows to nothing over this length beyond its end
BLOCK_W, BLOCK_DASH_M, BLOCK_GAP_M = 0.30, 6.0, 6.0  # the block marking beside an auxiliary lane
NEAR_M = 2 * (SHOULDER_M + RAIL_OFFSET_M) + 0.5  # closer asphalt of another road: no shoulder, rail, posts
LANE_SAMPLE_M = 2.0  # lanes sampled this often for the tests of nearness between roads
OTHER_EDGES_WITHIN_M = 200.0  # other edges of the network drawn when this near the route


def _unit(key: str) -> float:
    """A stable pseudo-random number in [0, 1) for a key."""
    return zlib.crc32(key.encode()) / 2**32


def _box(x0, x1, y0, y1, z0, z1, rgb, material=MATTE) -> trimesh.Trimesh:
    box = trimesh.creation.box(extents=(x1 - x0, y1 - y0, z1 - z0))
    box.apply_translation(((x0 + x1) / 2, (y0 + y1) / 2, (z0 + z1) / 2))
    return coloured(box, rgb, material)




def _ribbon(road: RoadFrame, s, d_right, d_left, z: float, rgb, material=MATTE) -> trimesh.Trimesh:
    """A flat strip between two lines of the road frame sampled at s (k,): d_right (k,) and
    d_left (k,) to its right and left (scalars broadcast); one quad per pair of samples."""
    s = np.asarray(s, dtype=np.float64)
    k = len(s)
    dr = np.broadcast_to(np.asarray(d_right, dtype=np.float64), s.shape)
    dl = np.broadcast_to(np.asarray(d_left, dtype=np.float64), s.shape)
    xs, ys = road.to_world(np.concatenate([s, s]), np.concatenate([dr, dl]))
    verts = np.column_stack([xs, ys, np.full(2 * k, z)])
    i = np.arange(k - 1)
    # per quad (right i, right i+1, left i+1, left i), split along right i - left i+1
    faces = np.concatenate([np.column_stack([i, i + 1, k + i + 1]), np.column_stack([i, k + i + 1, k + i])])
    faces = faces.reshape(2, -1, 3).transpose(1, 0, 2).reshape(-1, 3)
    # Face normals must point up whatever the road's direction.
    a, b, c = verts[faces[:, 0]], verts[faces[:, 1]], verts[faces[:, 2]]
    down = np.cross(b - a, c - a)[:, 2] < 0
    faces[down] = faces[down][:, ::-1]
    return coloured(trimesh.Trimesh(verts, faces, process=False), rgb, material)


def _placed(road: RoadFrame, mesh: trimesh.Trimesh, s: float, d: float, heading: float | None = None) -> trimesh.Trimesh:
    """A mesh modelled around the origin (x along the road, y to its left) placed at (s, d)."""
    x, y = road.to_world(s, d)
    h = float(road.heading(s, d)) if heading is None else heading
    T = np.eye(4)
    T[:2, :2] = [[np.cos(h), -np.sin(h)], [np.sin(h), np.cos(h)]]
    T[:2, 3] = [float(x), float(y)]
    mesh.apply_transform(T)
    return mesh


def _post(road: RoadFrame, s: float, d: float, half: float, z0: float, z1: float, rgb) -> trimesh.Trimesh:
    return _placed(road, _box(-half, half, -half, half, z0, z1, rgb), s, d)


def _beam(road: RoadFrame, s: np.ndarray, d: np.ndarray, rgb, material) -> list[trimesh.Trimesh]:
    """A guard rail's beam along the polyline (s, d): one box per chord."""
    xs, ys = road.to_world(s, d)
    parts = []
    for i in range(len(s) - 1):
        dx, dy = xs[i + 1] - xs[i], ys[i + 1] - ys[i]
        length = float(np.hypot(dx, dy))
        box = _box(-length / 2, length / 2, -0.05, 0.05, 0.45, 0.78, rgb, material)
        T = np.eye(4)
        h = np.arctan2(dy, dx)
        T[:2, :2] = [[np.cos(h), -np.sin(h)], [np.sin(h), np.cos(h)]]
        T[:2, 3] = [(xs[i] + xs[i + 1]) / 2, (ys[i] + ys[i + 1]) / 2]
        parts.append(box.apply_transform(T))
    return parts


def _tree(size: float, leaf_rgb) -> trimesh.Trimesh:
    """A low-poly deciduous tree or bush at the origin (a trunk and a crown of two blobs)."""
    parts = []
    trunk_h = 0.35 * size
    if size > 2.5:
        trunk = trimesh.creation.cylinder(radius=0.04 * size, height=trunk_h, sections=6)
        trunk.apply_translation((0.0, 0.0, trunk_h / 2))
        parts.append(coloured(trunk, BARK_RGB, MATTE))
    for dx, dz, rad in ((0.0, 0.62, 0.36), (0.12, 0.8, 0.26)):
        blob = trimesh.creation.icosphere(subdivisions=1, radius=rad * size)
        blob.apply_scale((1.0, 1.0, 0.85))
        blob.apply_translation((dx * size, 0.0, dz * size if size > 2.5 else 0.5 * dz * size))
        parts.append(coloured(blob, leaf_rgb, FOLIAGE))
    return trimesh.util.concatenate(parts)


def _runs(ok: np.ndarray, joined: np.ndarray) -> list[tuple[int, int]]:
    """Maximal runs [j0, j1] (inclusive) of segments that are `ok` and `joined` to the next."""
    runs, start = [], None
    for j in range(len(ok)):
        if ok[j] and start is None:
            start = j
        if start is not None and (not ok[j] or (j + 1 < len(ok) and not joined[j])):
            end = j if ok[j] else j - 1
            runs.append((start, end))
            start = None
    if start is not None:
        runs.append((start, len(ok) - 1))
    return runs


def _auxiliary_tracks(spans: list[np.ndarray], s_lo: float, s_hi: float, step_m: float = 1.0) -> list[bool]:
    """Per track: an auxiliary lane (acceleration, deceleration, dropped lane), which a block marking
    separates from the through lanes. Such a lane begins (or ends) along the road beside lanes on its
    left that are already there before it (or go on after it). Only beginning or ending is not
    enough: on a route that starts on a ramp, the main line's lanes begin where the ramp joins them
    and are the through lanes there."""
    def covered(track: int, s: float) -> bool:
        return bool(np.any((spans[track][:, 0] <= s) & (s <= spans[track][:, 1])))

    out = []
    for t, sp in enumerate(spans):
        left = range(t + 1, len(spans))
        out.append(any((a > s_lo + 1e-6 and any(covered(u, a - step_m) for u in left))
                       or (b < s_hi - 1e-6 and any(covered(u, b + step_m) for u in left)) for a, b in sp))
    return out


class RoadLayout:
    """Where a road frame has lanes, edges and markings over [s_lo, s_hi], per segment of a grid
    of s; built once, then cut into pieces by :meth:`piece`.

    Segment j is [grid[j], grid[j + 1]]; per segment and track `cover` (0 none, 1 lane,
    2 taper of an ending lane) and the track's right/left d at both ends (`right`, `left`, shape
    (tracks, segments, 2)); the road's outer edges `outer_right`/`outer_left` (segments, 2);
    `near` (segments, 2): another road's asphalt within NEAR_M of the right / left edge.
    """

    def __init__(self, road: RoadFrame, s_lo: float, s_hi: float, name: str = ""):
        self.road, self.s_lo, self.s_hi, self.name = road, s_lo, s_hi, name
        spans = []
        for t in range(road.num_tracks):
            sp = road.lane_spans(t).copy()
            # beyond the route's ends its end pieces' lanes continue (the frame's convention)
            sp[sp[:, 0] <= 1e-9, 0] = s_lo
            sp[sp[:, 1] >= road.length_m - 1e-9, 1] = s_hi
            spans.append(sp)
        self.auxiliary = _auxiliary_tracks(spans, s_lo, s_hi)
        cuts = [s_lo, s_hi, *np.arange(s_lo, s_hi, ROAD_PIECE_M)]
        for sp in spans:
            cuts += [*sp.ravel(), *(sp[:, 1] + TAPER_M)]
        if not road.is_straight:
            cuts += [*road.breaks_s]
        grid = np.unique(np.clip(np.asarray(cuts, dtype=np.float64), s_lo, s_hi))
        grid = grid[np.concatenate([[True], np.diff(grid) > 1e-6])]
        self.grid = grid
        n_t, n_seg = road.num_tracks, len(grid) - 1
        mid = 0.5 * (grid[:-1] + grid[1:])
        cover = np.zeros((n_t, n_seg), dtype=np.int8)
        right = np.zeros((n_t, n_seg, 2))
        left = np.zeros((n_t, n_seg, 2))
        for t in range(n_t):
            r, l = road.lane_bounds(np.full(n_seg, t), mid)
            right[t], left[t] = np.repeat(r[:, None], 2, axis=1), np.repeat(l[:, None], 2, axis=1)
            for a, b in spans[t]:
                cover[t, (mid > a) & (mid < b)] = 1
        self.cover, self.right, self.left = cover, right, left
        # (track, its taper's segments, end s, on the road's right side)
        self._tapers: list[tuple[int, np.ndarray, float, bool]] = []
        for t in range(n_t):
            for a, b in spans[t]:
                self._taper(t, b, mid)
        self._outer_edges()
        self.near = np.zeros((n_seg, 2), dtype=bool)
        self.others: tuple = ()  # lane samples (x, y, half widths) of the scene's other roads

    def _outer_edges(self) -> None:
        big = 1e9
        on = self.cover[..., None] > 0
        paved = on[..., 0].any(axis=0)
        self.outer_right = np.where(paved[:, None], np.where(on, self.right, big).min(axis=0), np.nan)
        self.outer_left = np.where(paved[:, None], np.where(on, self.left, -big).max(axis=0), np.nan)
        self.lane_samples = self._lane_samples()

    def drop_tapers_continuing_on(self, x: np.ndarray, y: np.ndarray) -> None:
        """No taper for a lane that does not end but leaves the route onto another road (an exit
        lane): that road's lanes (centre points x, y) go on from where it ends, through the
        junction (within 20 m ahead, beside or outside the lane)."""
        if not len(x):
            return
        s, d = self.road.to_frame(x, y)
        kept = []
        for t, segs, end, on_right in self._tapers:
            right, left = (float(v) for v in self.road.lane_bounds(t, end - 1e-6))
            beside = (d > right - 3.5) & (d < left) if on_right else (d > right) & (d < left + 3.5)
            if ((s > end - 1.0) & (s < end + 20.0) & beside).any():
                self.cover[t, segs] = 0
            else:
                kept.append((t, segs, end, on_right))
        if len(kept) != len(self._tapers):
            self._tapers = kept
            self._outer_edges()

    def _taper(self, t: int, end: float, mid: np.ndarray) -> None:
        """Track t ends at `end` (inside the road): it narrows to nothing over TAPER_M beyond it,
        on the side where it is the road's outermost lane."""
        if end >= self.s_hi:
            return
        before = np.flatnonzero(mid < end)
        if not len(before):
            return
        j = before[-1]
        present = np.flatnonzero(self.road.lane_exists(np.arange(self.road.num_tracks), mid[j]))
        if t == present.min():
            moving, fixed = self.right, self.left
        elif t == present.max():
            moving, fixed = self.left, self.right
        else:
            return  # a lane ending between others: no taper
        r0, fix = moving[t, j, 1], fixed[t, j, 1]
        segs = [k for k in np.flatnonzero((mid > end) & (mid < end + TAPER_M)) if not self.cover[t, k]]
        for k in segs:
            self.cover[t, k] = 2
            fixed[t, k] = fix
            moving[t, k] = r0 + (fix - r0) * (self.grid[k:k + 2] - end) / TAPER_M
        self._tapers.append((t, np.array(segs, dtype=np.int64), end, moving is self.right))

    def _lane_samples(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World points along every lane's centre line, LANE_SAMPLE_M apart, and half widths."""
        xs, ys, hws = [], [], []
        for t in range(self.road.num_tracks):
            for j in np.flatnonzero(self.cover[t] > 0):
                a, b = self.grid[j], self.grid[j + 1]
                s = np.linspace(a, b, max(2, int(np.ceil((b - a) / LANE_SAMPLE_M)) + 1))
                frac = (s - a) / (b - a)
                r = self.right[t, j, 0] + frac * (self.right[t, j, 1] - self.right[t, j, 0])
                l = self.left[t, j, 0] + frac * (self.left[t, j, 1] - self.left[t, j, 0])
                x, y = self.road.to_world(s, 0.5 * (r + l))
                xs.append(x), ys.append(y), hws.append(0.5 * (l - r))
        if not xs:
            return np.zeros(0), np.zeros(0), np.zeros(0)
        return np.concatenate(xs), np.concatenate(ys), np.concatenate(hws)

    def mark_near(self, x: np.ndarray, y: np.ndarray, half_width: np.ndarray) -> None:
        """Flag the segments whose outer edges another road's lanes (centre points, half widths)
        come within NEAR_M of, from outside (asphalt that overlaps this road's is part of it)."""
        if not len(x):
            return
        s, d = self.road.to_frame(x, y)
        order = np.argsort(s)
        s, d, hw = s[order], d[order], np.asarray(half_width)[order]
        lo = np.searchsorted(s, self.grid[:-1] - LANE_SAMPLE_M)
        hi = np.searchsorted(s, self.grid[1:] + LANE_SAMPLE_M)
        for j in np.flatnonzero(hi > lo):
            r, l = self.outer_right[j], self.outer_left[j]
            if np.isnan(r).any():
                continue
            dd, hh = d[lo[j]:hi[j]], hw[lo[j]:hi[j]]
            centre = 0.5 * (r.mean() + l.mean())
            right_side = (dd < centre) & (dd + hh > r.min() - NEAR_M) & (dd + hh <= r.max() + 0.5)
            left_side = (dd > centre) & (dd - hh < l.max() + NEAR_M) & (dd - hh >= l.min() - 0.5)
            self.near[j, 0] |= bool(right_side.any())
            self.near[j, 1] |= bool(left_side.any())

    # -------------------------------------------------------------- one piece of the road
    def _segments(self, s0: float, s1: float) -> np.ndarray:
        g = self.grid
        return np.flatnonzero((g[:-1] >= s0 - 1e-9) & (g[1:] <= s1 + 1e-9))

    @staticmethod
    def _joined(values: np.ndarray, segs: np.ndarray) -> np.ndarray:
        """Per consecutive pair of segments: the value at the first's end equals the second's start."""
        a, b = values[segs[:-1], 1], values[segs[1:], 0]
        return (np.abs(a - b) < 1e-6) & (segs[1:] == segs[:-1] + 1)

    def _line(self, segs: np.ndarray, run: tuple[int, int], values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(s, value) samples of a per-segment value along a run of segments (indices into segs)."""
        js = segs[run[0]:run[1] + 1]
        s = np.append(self.grid[js], self.grid[js[-1] + 1])
        v = np.append(values[js, 0], values[js[-1], 1])
        return s, v

    def piece(self, s0: float, s1: float, trees: bool = True) -> trimesh.Trimesh | None:
        """The road between s0 and s1 (grid points): asphalt, shoulders, markings, guard rails,
        roadside objects (one mesh); None where there is no road."""
        road, segs = self.road, self._segments(s0, s1)
        if not len(segs):
            return None
        r_edge, l_edge = self.outer_right, self.outer_left
        paved = ~np.isnan(r_edge[segs, 0])
        edge_runs = [_runs(paved, self._joined(v, segs)) for v in (r_edge, l_edge)]
        side_runs = [_runs(paved & ~self.near[segs, k], self._joined(v, segs)) for k, v in enumerate((r_edge, l_edge))]
        parts: list[trimesh.Trimesh] = []
        # Shoulders, then the edge lines.
        for run in side_runs[0]:
            s, r = self._line(segs, run, r_edge)
            parts.append(_ribbon(road, s, r - SHOULDER_M, r, 0.0, SHOULDER_RGB, ASPHALT))
        for run in side_runs[1]:
            s, l = self._line(segs, run, l_edge)
            parts.append(_ribbon(road, s, l, l + SHOULDER_M, 0.0, SHOULDER_RGB, ASPHALT))
        for run in edge_runs[0]:
            s, r = self._line(segs, run, r_edge)
            parts.append(_ribbon(road, s, r + 0.05, r + 0.05 + 2 * LINE_W, MARK_Z, MARKING_RGB, PAINT_MARK))
        for run in edge_runs[1]:
            s, l = self._line(segs, run, l_edge)
            parts.append(_ribbon(road, s, l - 0.05 - LINE_W, l - 0.05, MARK_Z, MARKING_RGB, PAINT_MARK))
        # Each lane: darker wheel tracks (0.6 m wide, centred 1.2 m either side of the lane centre).
        for t in range(road.num_tracks):
            lane = self.cover[t, segs] == 1
            for run in _runs(lane, self._joined(self.right[t], segs) & self._joined(self.left[t], segs)):
                s, r = self._line(segs, run, self.right[t])
                _, l = self._line(segs, run, self.left[t])
                w = l - r
                cuts = [r, r + 0.3, r + 0.9, r + w / 2 - 0.45, r + w / 2 + 0.45, l - 0.9, l - 0.3, l]
                for k in range(len(cuts) - 1):
                    rgb = TRACK_RGB if k in (1, 5) else ASPHALT_RGB
                    parts.append(_ribbon(road, s, cuts[k], cuts[k + 1], 0.0, rgb, ASPHALT))
            for run in _runs(self.cover[t, segs] == 2, self._joined(self.right[t], segs) & self._joined(self.left[t], segs)):
                s, r = self._line(segs, run, self.right[t])
                _, l = self._line(segs, run, self.left[t])
                parts.append(_ribbon(road, s, r, l, 0.0, ASPHALT_RGB, ASPHALT))
        # Lines between lanes, dashes laid on a global grid so that adjacent pieces join seamlessly.
        for t in range(road.num_tracks - 1):
            both = (self.cover[t, segs] == 1) & (self.cover[t + 1, segs] == 1)
            block = self.auxiliary[t] or self.auxiliary[t + 1]
            dash, period, width = (BLOCK_DASH_M, BLOCK_DASH_M + BLOCK_GAP_M, BLOCK_W) if block else (DASH_M, DASH_M + GAP_M, LINE_W)
            for run in _runs(both, self._joined(self.left[t], segs)):
                s, d = self._line(segs, run, self.left[t])
                for a in np.arange(np.floor(s[0] / period) * period, s[-1], period):
                    lo, hi = max(a, s[0]), min(a + dash, s[-1])
                    if hi - lo <= 1e-6:
                        continue
                    ss = np.concatenate([[lo], s[(s > lo) & (s < hi)], [hi]])
                    dd = np.interp(ss, s, d)
                    parts.append(_ribbon(road, ss, dd - width / 2, dd + width / 2, MARK_Z, MARKING_RGB, PAINT_MARK))
        # Guard rails: the beam facing the road, posts behind it; reflector posts beyond.
        for k, (values, side) in enumerate(((r_edge, -1.0), (l_edge, 1.0))):
            offset = side * (SHOULDER_M + RAIL_OFFSET_M)
            for run in side_runs[k]:
                s, e = self._line(segs, run, values)
                parts += _beam(road, s, e + offset, RAIL_RGB, METAL)
                for sp in np.arange(np.ceil(s[0] / POST_SPACING_M) * POST_SPACING_M, s[-1], POST_SPACING_M):
                    parts.append(_post(road, sp, float(np.interp(sp, s, e)) + offset + side * 0.12, 0.06, 0.0, 0.72,
                                       POST_RGB))
        for k, (values, side) in enumerate(((r_edge, -1.0), (l_edge, 1.0))):
            offset = side * (SHOULDER_M + RAIL_OFFSET_M + 0.35)
            for run in side_runs[k]:
                s, e = self._line(segs, run, values)
                for sp in np.arange(np.ceil(s[0] / DELINEATOR_SPACING_M) * DELINEATOR_SPACING_M, s[-1],
                                    DELINEATOR_SPACING_M):
                    dp = float(np.interp(sp, s, e)) + offset
                    parts.append(_post(road, sp, dp, 0.06, 0.0, 1.0, DELINEATOR_RGB))
                    parts.append(_post(road, sp, dp, 0.065, 0.75, 0.92, (20, 20, 20)))
            if trees:
                parts += self._trees(s0, s1, segs, side_runs[k], values, side)
        return trimesh.util.concatenate(parts) if parts else None

    def _trees(self, s0, s1, segs, runs, values, side) -> list[trimesh.Trimesh]:
        """Trees and bushes on one verge between s0 and s1, on a global grid of sites."""
        parts = []
        spans = [self._line(segs, run, values) for run in runs]
        for k in range(int(np.ceil(s0 / TREE_SPACING_M)), int(np.ceil(s1 / TREE_SPACING_M))):
            key = f"{self.name}{k}/{side}"
            if _unit(key + "/skip") < 0.25:
                continue
            s = k * TREE_SPACING_M + TREE_SPACING_M * 0.8 * _unit(key + "/s")
            if not s0 <= s < s1:
                continue
            inside = [(ss, e) for ss, e in spans if ss[0] <= s <= ss[-1]]
            if not inside:
                continue  # no verge there (another road alongside)
            edge = float(np.interp(s, *inside[0]))
            d = edge + side * (SHOULDER_M + 6.0 + 25.0 * _unit(key + "/d"))
            size = 2.0 + 8.0 * _unit(key + "/size")
            if self._near_other_road(s, d, 0.4 * size + 3.0):
                continue
            leaf = LEAF_RGBS[int(4 * _unit(key + "/leaf"))]
            parts.append(_placed(self.road, _tree(size, leaf), s, d))
        return parts

    def _near_other_road(self, s: float, d: float, clearance: float) -> bool:
        if not self.others:
            return False
        x, y = self.road.to_world(s, d)
        ox, oy, hw = self.others
        return bool((np.hypot(ox - x, oy - y) < hw + clearance).any())


def _densified(points: np.ndarray, step_m: float) -> np.ndarray:
    """A polyline's points with points added so that none are farther apart than step_m."""
    out = [points[:1]]
    for a, b in zip(points[:-1], points[1:]):
        n = max(1, int(np.ceil(np.hypot(*(b - a)) / step_m)))
        out.append(a + (b - a) * (np.arange(1, n + 1) / n)[:, None])
    return np.concatenate(out)


def nearby_edges(road: RoadFrame, s_lo: float, s_hi: float) -> list[str]:
    """The network's other normal edges with a lane point within OTHER_EDGES_WITHIN_M of the
    route's road between s_lo and s_hi (the camera sees them)."""
    if road.is_straight or road.net_file is None:
        return []  # a network of one straight edge
    out = []
    for edge, shapes in edge_lane_shapes(road.net_file).items():
        if edge in road.route:
            continue
        pts = np.concatenate([_densified(shape, 25.0) for shape in shapes])
        s, d = road.to_frame(pts[:, 0], pts[:, 1])
        near = (s > s_lo) & (s < s_hi) & (d > -OTHER_EDGES_WITHIN_M) & (d < road.max_width_m + OTHER_EDGES_WITHIN_M)
        if near.any():
            out.append(edge)
    return out


def road_layouts(road: RoadFrame) -> list[RoadLayout]:
    """The layouts of the scene's roads: the route's (beyond its ends by ROUTE_MARGIN_M), then
    every other edge near it in its own one-edge frame; each knows the others' lanes."""
    s_lo, s_hi = road_extent(road)
    layouts = [RoadLayout(road, s_lo, s_hi)]
    for edge in nearby_edges(road, s_lo, s_hi):
        frame = RoadFrame.from_net(road.net_file, [edge])
        layouts.append(RoadLayout(frame, 0.0, frame.length_m, name=f"{edge}/"))
    def others(k):
        samples = [o.lane_samples for m, o in enumerate(layouts) if m != k]
        return tuple(np.concatenate(parts) for parts in zip(*samples)) if samples else ()

    for k, layout in enumerate(layouts):
        if others(k):
            layout.drop_tapers_continuing_on(*others(k)[:2])
    for k, layout in enumerate(layouts):
        layout.others = others(k)
        if layout.others:
            layout.mark_near(*layout.others)
    return layouts


def road_extent(road: RoadFrame, margin_m: float = ROUTE_MARGIN_M) -> tuple[float, float]:
    """Range of s covered by the modelled road (beyond the network's ends, so the road never ends in view)."""
    return -margin_m, road.length_m + margin_m


def road_pieces(layouts: list[RoadLayout]) -> list[tuple[str, trimesh.Trimesh]]:
    """(name, mesh) of every ROAD_PIECE_M piece of the layouts' roads (the scene's culling units)."""
    pieces = []
    for layout in layouts:
        for s0 in np.arange(layout.s_lo, layout.s_hi, ROAD_PIECE_M):
            s1 = min(s0 + ROAD_PIECE_M, layout.s_hi)
            mesh = layout.piece(s0, s1)
            if mesh is not None:
                pieces.append((f"road@{layout.name}{s0:.0f}", mesh))
    return pieces


def ground_mesh(road: RoadFrame, layouts: list[RoadLayout] | None = None, margin_m: float = 600.0) -> trimesh.Trimesh:
    """Grass around the road (slightly below it), far enough to meet the horizon haze."""
    if road.is_straight:
        return _ribbon(road, [-margin_m, road.length_m + margin_m], -margin_m, road.width_m + margin_m, -0.05,
                       GRASS_RGB, GRASS)
    # around everything drawn: the lane samples' bounding box
    pts = [np.column_stack(layout.lane_samples[:2]) for layout in (layouts or road_layouts(road))]
    lo, hi = np.concatenate(pts).min(axis=0) - margin_m, np.concatenate(pts).max(axis=0) + margin_m
    verts = np.array([[lo[0], lo[1], -0.05], [hi[0], lo[1], -0.05], [hi[0], hi[1], -0.05], [lo[0], hi[1], -0.05]])
    return coloured(trimesh.Trimesh(verts, [[0, 1, 2], [0, 2, 3]], process=False), GRASS_RGB, GRASS)
