"""NGSIM vehicle trajectories (US-101, I-80, ...): the 18-column file, as a :class:`Recording`.

Columns (NGSIM's names and units: feet, feet/s, 10 Hz frames): Vehicle_ID, Frame_ID,
Total_Frames, Global_Time, Local_X, Local_Y, Global_X, Global_Y, v_Length, v_Width, v_Class,
v_Vel, v_Acc, Lane_ID, Preceding, Following, Space_Headway, Time_Headway. A `.csv` with that
header (names matched without regard to case; extra columns such as the combined release's
Location are allowed), or the original headerless whitespace-separated `.txt` with the 18
columns in this order; either may be gzip-compressed (`.gz`).

The combined release (data.transportation.gov, every site in one CSV with a Location column)
is read one site at a time (`location`, e.g. "us-101"; a file that mixes sites without one is
refused, naming them). Its periods (US-101's 7:50-8:05, 8:05-8:20 and 8:20-8:35, each with its
own Vehicle_IDs and Frame_IDs) are told apart by Global_Time - 100 ms x Frame_ID, constant within
a period's file, and become recordings of their own. Numbers written with thousands separators
("1,113,433,136,100", as spreadsheet exports write them) are read as numbers.

How the fields are used (and the documented defaults for gaps of real releases):
- time = (Frame_ID - first Frame_ID) x 0.1 s;
- s = Local_Y (front centre, along the direction of travel) - length / 2: the footprint centre;
- units: NGSIM's feet (`units="ft"`, the default) or metres (`units="m"`, as metric re-releases
  write them): lengths, positions, speeds and accelerations are scaled by the one factor;
- lane: Lane_ID 1 is the leftmost lane (`lane_one="left"`, NGSIM's convention; `"right"` for a
  release that numbers from the right edge). `main_lanes` = (first, last) Lane_IDs of the road
  (default 1-5: US-101's five main lanes; I-80's six are 1-6). Lane index = last - Lane_ID
  (numbered from the right: Lane_ID - first);
  samples on other lanes (US-101 6 auxiliary, 7 on-ramp, 8 off-ramp; I-80 7 on-ramp) are off
  the road: the twin leaves there and a later return is a new twin;
- d = last x 12 ft - Local_X (the main lanes assumed 12 ft wide from the left edge); Local_X
  missing, zero or empty: lateral position unknown (the lane still comes from Lane_ID; lane-change
  start / end then stay unknown and the labels use mid + END_AFTER_MID_S);
- v_Length / v_Width missing, zero or empty: by v_Class (1 motorcycle, 2 auto, 3 truck;
  trajectories.CLASS_SIZE_M), v_Class missing: auto; height is not recorded: by class;
- v_Vel is required; v_Acc missing: from the speed;
- Preceding, Following, Space_Headway, Time_Headway, Global_*, Total_Frames are not used: the
  cloud computes neighbours and gaps from the positions, as for simulated runs (zero headways,
  NGSIM's "no leader", do not matter). Preceding / Following are only checked: the rows that
  name a leader or follower absent from the file (a truncated release: neighbours the features
  cannot see) are counted in the reader's quality report.
"""

from __future__ import annotations

import gzip
import re
from pathlib import Path

import numpy as np
import pandas as pd

from vcfusion.prediction.sources.trajectories import (
    Recording, RealDataError, size_defaults, straight_road,
)

NGSIM_COLUMNS = ("Vehicle_ID", "Frame_ID", "Total_Frames", "Global_Time", "Local_X", "Local_Y", "Global_X",
                 "Global_Y", "v_Length", "v_Width", "v_Class", "v_Vel", "v_Acc", "Lane_ID", "Preceding",
                 "Following", "Space_Headway", "Time_Headway")
REQUIRED = ("Vehicle_ID", "Frame_ID", "Local_Y", "Lane_ID", "v_Vel")
FT_M = 0.3048
LANE_WIDTH_FT = 12.0
FRAME_S = 0.1
CLASS_NAMES = {1: "motorcycle", 2: "passenger", 3: "truck"}
DEFAULT_MAIN_LANES = (1, 5)
UNIT_M = {"ft": FT_M, "m": 1.0}
LANE_ONE = ("left", "right")


def parse_main_lanes(text: str) -> tuple[int, int]:
    """'1-5' -> (1, 5); a single lane '3' -> (3, 3)."""
    m = re.fullmatch(r"\s*(\d+)\s*(?:-\s*(\d+)\s*)?", text or "")
    if not m or int(m.group(1)) < 1 or (m.group(2) and int(m.group(2)) < int(m.group(1))):
        raise RealDataError(f"--main-lanes: expected a range of NGSIM Lane_IDs like '1-5', got {text!r}")
    first = int(m.group(1))
    return first, int(m.group(2) or first)


def _open_text(path: Path):
    return gzip.open(path, "rt") if path.suffix == ".gz" else open(path)


def read_ngsim_table(path: Path, location: str | None = None) -> pd.DataFrame:
    """The file's columns under NGSIM's names (numeric); RealDataError naming what is wrong.
    `location`: the combined release's rows of that Location only (case and spaces ignored)."""
    if not path.is_file():
        raise RealDataError(f"{path}: no such NGSIM file")
    try:
        with _open_text(path) as f:
            first = f.readline()
    except (OSError, UnicodeDecodeError, EOFError) as exc:
        raise RealDataError(f"{path}: cannot read it as text{' (gzip)' if path.suffix == '.gz' else ''}: {exc}") from None
    if not first.strip():
        raise RealDataError(f"{path}: empty file; expected the NGSIM columns {', '.join(NGSIM_COLUMNS)}")
    sep = "," if "," in first else r"\s+"
    has_header = re.search(r"[A-Za-z_]", first) is not None
    try:
        table = pd.read_csv(path, sep=sep, header=0 if has_header else None, low_memory=False)
    except (pd.errors.ParserError, ValueError) as exc:
        raise RealDataError(f"{path}: not a readable NGSIM table: {exc}") from None
    if has_header:
        canonical = {c.lower(): c for c in NGSIM_COLUMNS}
        table.columns = [canonical.get(str(c).strip().lower(), str(c).strip()) for c in table.columns]
    else:
        if table.shape[1] != len(NGSIM_COLUMNS):
            raise RealDataError(f"{path}: a file without header must have NGSIM's {len(NGSIM_COLUMNS)} columns "
                                f"({', '.join(NGSIM_COLUMNS)}), found {table.shape[1]}")
        table.columns = list(NGSIM_COLUMNS)
    missing = [c for c in REQUIRED if c not in table.columns]
    if missing:
        raise RealDataError(f"{path}: column(s) {', '.join(missing)} missing; expected NGSIM's columns "
                            f"{', '.join(NGSIM_COLUMNS)} (at least {', '.join(REQUIRED)})")
    if location is not None:
        if "Location" not in table.columns:
            raise RealDataError(f"{path}: --ngsim-location {location!r}: the file has no Location column (it holds "
                                "one site: leave the option out)")
        names = table["Location"].astype(str).str.strip().str.lower()
        if not (names == location.strip().lower()).any():
            raise RealDataError(f"{path}: --ngsim-location {location!r}: no such Location; the file has "
                                f"{sorted(set(names))}")
        table = table[names == location.strip().lower()].reset_index(drop=True)
    for column in ("Location", "Direction"):  # columns of the combined release (all sites in one file)
        if column in table.columns and table[column].nunique() > 1:
            option = " (--ngsim-location NAME)" if column == "Location" else ""
            raise RealDataError(f"{path}: {column}: the file mixes {sorted(map(str, table[column].unique()))}; "
                                f"import one location{option} and one direction of travel at a time")
    if not len(table):
        raise RealDataError(f"{path}: no rows")
    for c in NGSIM_COLUMNS:
        if c not in table.columns:
            continue
        if pd.api.types.is_numeric_dtype(table[c]):  # read as numbers (empty fields: NaN)
            values, bad = table[c], pd.Series(False, index=table.index)
        else:
            text = table[c].astype(str).str.strip()
            numbers = text
            if text.str.fullmatch(r"-?\d{1,3}(,\d{3})+(\.\d*)?|-?\d*(\.\d*)?|nan|").all():
                numbers = text.str.replace(",", "", regex=False)  # thousands separators
            values = pd.to_numeric(numbers.where(table[c].notna()), errors="coerce")
            bad = values.isna() & table[c].notna() & (text != "")
        if c in REQUIRED:
            bad |= values.isna()
        if bad.any():
            row = int(np.flatnonzero(bad.to_numpy())[0])
            raise RealDataError(f"{path}: {c}: expected a number, got {table[c].iloc[row]!r} "
                                f"(data row {row + 1})")
        table[c] = values
    return table


def read_ngsim(path: str | Path, main_lanes: tuple[int, int] = DEFAULT_MAIN_LANES,
               location: str | None = None, units: str = "ft", lane_one: str = "left") -> list[Recording]:
    """The file's recordings: one per period (see the module's notes), in time order."""
    path = Path(path)
    if units not in UNIT_M:
        raise RealDataError(f"--ngsim-units: expected one of {', '.join(UNIT_M)}, got {units!r}")
    if lane_one not in LANE_ONE:
        raise RealDataError(f"--ngsim-lane-one: expected one of {', '.join(LANE_ONE)}, got {lane_one!r}")
    table = read_ngsim_table(path, location)
    name = path.name
    for suffix in (".gz", ".csv", ".txt"):
        name = name.removesuffix(suffix)
    if location is not None:
        name += f"-{location.strip().lower()}"
    period = np.zeros(len(table))  # without Global_Time: one period
    if "Global_Time" in table and table["Global_Time"].notna().all():
        # the period's start (ms): a period's rows agree on it to the ms, so rounded to the second
        period = np.round(table["Global_Time"].to_numpy(float) - 100.0 * table["Frame_ID"].to_numpy(float), -3)
    starts = np.unique(period)
    if len(starts) == 1:
        return [_recording(table, path, name, main_lanes, units, lane_one)]
    return [_recording(table[period == p].reset_index(drop=True), path, f"{name}-period{k + 1}", main_lanes,
                       units, lane_one) for k, p in enumerate(starts)]


def _absent_neighbours(table: pd.DataFrame, column: str) -> int:
    """Rows whose `column` (Preceding / Following) names a vehicle with no row at that frame."""
    if column not in table or table[column].isna().all():
        return 0
    named = table[column].fillna(0).to_numpy(np.int64)
    present = set(zip(table["Vehicle_ID"].to_numpy(np.int64).tolist(), table["Frame_ID"].to_numpy(np.int64).tolist()))
    frames = table["Frame_ID"].to_numpy(np.int64)
    return int(sum(1 for v, f in zip(named.tolist(), frames.tolist()) if v > 0 and (v, f) not in present))


def _recording(table: pd.DataFrame, path: Path, name: str, main_lanes: tuple[int, int], units: str = "ft",
               lane_one: str = "left") -> Recording:
    first, last = main_lanes
    unit = UNIT_M[units]
    n = len(table)
    lane_id = table["Lane_ID"].to_numpy(np.int64)
    on_main = (lane_id >= first) & (lane_id <= last)
    vclass = table["v_Class"].map(CLASS_NAMES).fillna("passenger").to_numpy(str) if "v_Class" in table \
        else np.full(n, "passenger")
    nan = np.full(n, np.nan)
    sizes = size_defaults(vclass, table["v_Length"].to_numpy(float) * unit if "v_Length" in table else nan,
                          table["v_Width"].to_numpy(float) * unit if "v_Width" in table else nan, nan)
    local_x = table["Local_X"].to_numpy(float) * unit if "Local_X" in table else nan
    lane_w = LANE_WIDTH_FT * FT_M
    # d left of the main lanes' right edge; Local_X from the left edge of the section (0 / empty: unknown)
    d = np.where(local_x > 0, (last - first + 1 if lane_one == "right" else last) * lane_w - local_x, np.nan)
    frame = table["Frame_ID"].to_numpy(np.int64)
    samples = pd.DataFrame({
        "vehicle_id": table["Vehicle_ID"].to_numpy(np.int64).astype(str),
        "time": (frame - frame.min()) * FRAME_S,
        "s": table["Local_Y"].to_numpy(float) * unit - sizes["length"] / 2,
        "d": d,
        "lane": np.where(on_main, (lane_id - first) if lane_one == "right" else (last - lane_id), -1),
        "speed": table["v_Vel"].to_numpy(float) * unit,
        "accel": table["v_Acc"].to_numpy(float) * unit if "v_Acc" in table else nan,
        "length": sizes["length"], "width": sizes["width"], "height": sizes["height"], "vclass": vclass,
    })
    off = pd.Series(lane_id[~on_main]).value_counts().sort_index()
    source = {
        "format": "ngsim", "file": path.name, "recording": name, "main_lanes": [first, last], "units": units,
        "lane_one": lane_one,
        "quality_reader": {
            "rows": n, "sizes_filled_by_class": sizes["filled"],
            "lateral_unknown_rows": int(np.isnan(d).sum()),
            "rows_by_lane_outside_main": {str(k): int(v) for k, v in off.items()},
            "rows_naming_a_leader_absent_from_the_file": _absent_neighbours(table, "Preceding"),
            "rows_naming_a_follower_absent_from_the_file": _absent_neighbours(table, "Following"),
        },
    }
    road = straight_road(f"ngsim-{name}", last - first + 1, lane_w,
                         float(np.nanmax(samples["s"])) + 1.0, float("nan"))
    return Recording(f"ngsim {name}", road, samples, FRAME_S, source)
