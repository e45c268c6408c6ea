"""highD recordings (`XX_tracks.csv`, `XX_tracksMeta.csv`, `XX_recordingMeta.csv`) as
:class:`Recording`s, one per driving direction.

highD's frame: image coordinates in metres, x to the right, y DOWNWARD; a track's (x, y) is the
upper-left corner of its bounding box, `width` its extent in x (the vehicle's length) and
`height` in y (its width). recordingMeta's `upperLaneMarkings` / `lowerLaneMarkings` are the y
of the lane lines of the upper / lower roadway ("a;b;c", m). tracksMeta's `drivingDirection` 1
drives leftward (-x) on the upper roadway, 2 rightward (+x) on the lower one; `frameRate` is 25.

Per direction, facing the direction of travel (y grows downward):
- direction 2 (rightward): the rightmost lane is the lowest one (largest y); s = x centre;
  d = lowest marking - y centre; speed / acceleration = xVelocity / xAcceleration;
- direction 1 (leftward): the rightmost lane is the highest one (smallest y); s = (largest x
  centre of the recording) - x centre; d = y centre - highest marking; speed = -xVelocity.
The lane is the one between the markings that holds the box centre (0 = rightmost); a centre
outside them is off the road. Samples are resampled from 25 Hz to the 0.1 s V2C period by
linear interpolation (the lane: the last 25 Hz sample's). `laneId` is only checked: the share
of samples whose laneId equals the lane from the markings under highD's top-to-bottom
numbering (upper lanes 2.., lower lanes from the number of upper markings + 2) is reported.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from vcfusion.prediction.sources.trajectories import Recording, RealDataError, size_defaults, straight_road

TRACKS_COLUMNS = ("frame", "id", "x", "y", "width", "height", "xVelocity", "xAcceleration")
TRACKS_META_COLUMNS = ("id", "class", "drivingDirection")
RECORDING_META_COLUMNS = ("id", "frameRate", "upperLaneMarkings", "lowerLaneMarkings")
CLASS_NAMES = {"car": "passenger", "truck": "truck"}
UPPER, LOWER = 1, 2  # drivingDirection


def recording_prefixes(path: str | Path) -> list[Path]:
    """XX prefixes of the recordings at `path`: a folder (every XX_tracks.csv in it) or one
    XX_tracks.csv (or its XX_ prefix)."""
    path = Path(path)
    if path.is_dir():
        found = sorted(path.glob("*_tracks.csv"))
        if not found:
            raise RealDataError(f"{path}: no highD recording (XX_tracks.csv) in this folder")
        return [f.with_name(f.name.removesuffix("_tracks.csv")) for f in found]
    name = path.name
    for suffix in ("_tracks.csv", "_tracksMeta.csv", "_recordingMeta.csv"):
        if name.endswith(suffix):
            return [path.with_name(name.removesuffix(suffix))]
    raise RealDataError(f"{path}: expected a folder of highD recordings or an XX_tracks.csv file")


def _read(path: Path, required: tuple[str, ...]) -> pd.DataFrame:
    if not path.is_file():
        raise RealDataError(f"{path}: missing (a highD recording has XX_tracks.csv, XX_tracksMeta.csv and "
                            f"XX_recordingMeta.csv)")
    try:
        table = pd.read_csv(path)
    except (pd.errors.ParserError, pd.errors.EmptyDataError, ValueError, UnicodeDecodeError) as exc:
        raise RealDataError(f"{path}: not a readable CSV table: {exc}") from None
    missing = [c for c in required if c not in table.columns]
    if missing:
        raise RealDataError(f"{path}: column(s) {', '.join(missing)} missing; expected highD's columns "
                            f"(at least {', '.join(required)})")
    if not len(table):
        raise RealDataError(f"{path}: no rows")
    return table


def _numeric(table: pd.DataFrame, path: Path, columns) -> None:
    for c in columns:
        values = pd.to_numeric(table[c], errors="coerce")
        if values.isna().any():
            row = int(np.flatnonzero(values.isna().to_numpy())[0])
            raise RealDataError(f"{path}: {c}: expected a number, got {table[c].iloc[row]!r} (data row {row + 1})")
        table[c] = values


def _markings(meta: pd.DataFrame, column: str, path: Path) -> np.ndarray:
    text = str(meta[column].iloc[0])
    try:
        values = np.array(sorted(float(v) for v in text.split(";") if v.strip()))
    except ValueError:
        raise RealDataError(f"{path}: {column}: expected lane-line y positions like '8.5;12.6;16.4', "
                            f"got {text!r}") from None
    if len(values) < 2:
        raise RealDataError(f"{path}: {column}: expected at least two lane lines (one lane), got {text!r}")
    return values


def read_highd(prefix: Path) -> list[Recording]:
    """The two driving directions of one highD recording (a direction without vehicles is left out)."""
    prefix = Path(prefix)
    files = {k: prefix.with_name(f"{prefix.name}_{k}.csv") for k in ("tracks", "tracksMeta", "recordingMeta")}
    rec_meta = _read(files["recordingMeta"], RECORDING_META_COLUMNS)
    _numeric(rec_meta, files["recordingMeta"], ("frameRate",))
    frame_rate = float(rec_meta["frameRate"].iloc[0])
    if not frame_rate > 0:
        raise RealDataError(f"{files['recordingMeta']}: frameRate: expected a positive rate, got {frame_rate}")
    speed_limit = float(pd.to_numeric(rec_meta.get("speedLimit", pd.Series([-1])), errors="coerce").iloc[0])
    markings = {UPPER: _markings(rec_meta, "upperLaneMarkings", files["recordingMeta"]),
                LOWER: _markings(rec_meta, "lowerLaneMarkings", files["recordingMeta"])}
    meta = _read(files["tracksMeta"], TRACKS_META_COLUMNS)
    _numeric(meta, files["tracksMeta"], ("id", "drivingDirection"))
    bad_dir = ~meta["drivingDirection"].isin([UPPER, LOWER])
    if bad_dir.any():
        row = int(np.flatnonzero(bad_dir.to_numpy())[0])
        raise RealDataError(f"{files['tracksMeta']}: drivingDirection: expected 1 (upper, leftward) or 2 (lower, "
                            f"rightward), got {meta['drivingDirection'].iloc[row]!r} (data row {row + 1})")
    tracks = _read(files["tracks"], TRACKS_COLUMNS)
    _numeric(tracks, files["tracks"], TRACKS_COLUMNS)
    unknown = ~tracks["id"].isin(meta["id"])
    if unknown.any():
        raise RealDataError(f"{files['tracks']}: id: {int(tracks['id'][unknown].iloc[0])} has no row in "
                            f"{files['tracksMeta'].name}")
    by_id = meta.set_index("id")
    direction = by_id["drivingDirection"].reindex(tracks["id"]).to_numpy(int)
    vclass = by_id["class"].astype(str).str.lower().map(CLASS_NAMES).fillna("passenger").reindex(tracks["id"]).to_numpy(str)
    xc = tracks["x"].to_numpy(float) + tracks["width"].to_numpy(float) / 2
    yc = tracks["y"].to_numpy(float) + tracks["height"].to_numpy(float) / 2
    sizes = size_defaults(vclass, tracks["width"].to_numpy(float), tracks["height"].to_numpy(float),
                          np.full(len(tracks), np.nan))
    x_far = float(xc.max())
    out = []
    for drive in (UPPER, LOWER):
        rows = direction == drive
        if not rows.any():
            continue
        m = markings[drive]
        n_lanes = len(m) - 1
        j = np.searchsorted(m, yc[rows], side="right") - 1  # lane between markings, counted from the top
        inside = (j >= 0) & (j < n_lanes)
        if drive == UPPER:
            lane, d, s = j, yc[rows] - m[0], x_far - xc[rows]
            sign = -1.0
            lane_id = j + 2
        else:
            lane, d, s = n_lanes - 1 - j, m[-1] - yc[rows], xc[rows]
            sign = 1.0
            lane_id = len(markings[UPPER]) + 2 + j
        lane = np.where(inside, lane, -1)
        samples = pd.DataFrame({
            "vehicle_id": tracks["id"].to_numpy(np.int64)[rows].astype(str),
            "time": tracks["frame"].to_numpy(float)[rows] / frame_rate,
            "s": s, "d": d, "lane": lane,
            "speed": sign * tracks["xVelocity"].to_numpy(float)[rows],
            "accel": sign * tracks["xAcceleration"].to_numpy(float)[rows],
            "length": sizes["length"][rows], "width": sizes["width"][rows], "height": sizes["height"][rows],
            "vclass": vclass[rows],
        })
        side = "upper" if drive == UPPER else "lower"
        quality = {"rows": int(rows.sum()), "rows_off_lanes": int((~inside).sum()),
                   "sizes_filled_by_class": {k: int(v) for k, v in sizes["filled"].items()}}
        if "laneId" in tracks:
            given = pd.to_numeric(tracks["laneId"], errors="coerce").to_numpy()[rows]
            quality["laneId_agreement"] = float(np.mean(given[inside] == lane_id[inside])) if inside.any() else None
        source = {"format": "highd", "file": files["tracks"].name, "recording": prefix.name,
                  "driving_direction": drive, "roadway": side, "frame_rate": frame_rate,
                  "speed_limit": speed_limit, "quality_reader": quality}
        road = straight_road(f"highd-{prefix.name}-{side}", n_lanes, (m[-1] - m[0]) / n_lanes,
                             float(s.max()) + 1.0, speed_limit if speed_limit > 0 else float("nan"))
        out.append(Recording(f"highD {prefix.name} {side}", road, samples, 1.0 / frame_rate, source))
    return out


def read_highd_path(path: str | Path) -> list[Recording]:
    """Every recording at `path` (see :func:`recording_prefixes`), both directions each."""
    return [rec for prefix in recording_prefixes(path) for rec in read_highd(prefix)]
