"""NGSIM and highD imports (vcfusion.prediction.sources) on small files written in the published
layouts (column names and units verbatim), and their round trip through `vcfusion evaluate`."""

import gzip
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from vcfusion.commands import main
from vcfusion.prediction.features import FEATURE_NAMES, LATERAL_NAMES, SEQUENCE_EXTRA_NAMES
from vcfusion.prediction.sources.ngsim import NGSIM_COLUMNS
from vcfusion.prediction.sources.trajectories import (END_AFTER_MID_S, SAMPLE_COLUMNS, Recording, clean_lane_flicker,
                                                      straight_road, twin_tracks)

FT = 0.3048
SHIPPED_MODEL = Path(__file__).resolve().parents[2] / "src" / "vcfusion" / "assets" / "lane_change_mlp.npz"


# ---------------------------------------------------------------- NGSIM files

def _cosine(t, t0, t1, a, b):
    u = np.clip((t - t0) / (t1 - t0), 0.0, 1.0)
    return a + (b - a) * (1 - np.cos(np.pi * u)) / 2


def ngsim_vehicle(vid, t0, t1, front_ft, speed_ftps, lane_id, length_ft=15.0, width_ft=6.0, vclass=2,
                  change=None, local_x=None, skip=()):
    """Rows of one vehicle in NGSIM's columns: 10 Hz frames, feet; `change` = (start, end, new Lane_ID)
    moves Local_X from lane centre to lane centre on a cosine and flips Lane_ID at the line."""
    rows = []
    for k in range(int(round(t0 * 10)), int(round(t1 * 10)) + 1):
        t = k / 10
        if any(a <= t < b for a, b in skip):
            continue
        lane, x = lane_id, (lane_id - 0.5) * 12.0
        if change is not None:
            ts, te, to = change
            x = _cosine(t, ts, te, (lane_id - 0.5) * 12.0, (to - 0.5) * 12.0)
            lane = to if abs(x - (to - 0.5) * 12.0) < abs(x - (lane_id - 0.5) * 12.0) else lane_id
        rows.append({"Vehicle_ID": vid, "Frame_ID": 1000 + k, "Total_Frames": 0, "Global_Time": 1118846980200 + 100 * k,
                     "Local_X": x if local_x is None else local_x, "Local_Y": front_ft + speed_ftps * (t - t0),
                     "Global_X": 6042842.0, "Global_Y": 2133118.0, "v_Length": length_ft, "v_Width": width_ft,
                     "v_Class": vclass, "v_Vel": speed_ftps, "v_Acc": 0.0, "Lane_ID": lane, "Preceding": 0,
                     "Following": 0, "Space_Headway": 0.0, "Time_Headway": 0.0})
    return rows


def ngsim_rows() -> pd.DataFrame:
    rows = []
    # 1: a change from Lane_ID 3 to 2 (to the left) between 20 and 24 s
    rows += ngsim_vehicle(1, 0, 60, 0.0, 50.0, 3, change=(20.0, 24.0, 2))
    # 2: a truck whose length is missing (0): the class default
    rows += ngsim_vehicle(2, 0, 60, 300.0, 50.0, 3, length_ft=0.0, width_ft=0.0, vclass=3)
    # 3: no lateral position (Local_X 0) and a change from 4 to 5 (to the right) at about 32 s
    rows += [r | {"Local_X": 0.0} for r in ngsim_vehicle(3, 0, 60, 100.0, 48.0, 4, change=(30.0, 34.0, 5))]
    # 4: every row twice
    rows += ngsim_vehicle(4, 0, 60, 150.0, 47.0, 1) * 2
    # 5: id reused: 0-10 s in lane 1, then 40-60 s in lane 4 elsewhere
    rows += ngsim_vehicle(5, 0, 10, 600.0, 45.0, 1) + ngsim_vehicle(5, 40, 60, 20.0, 45.0, 4)
    # 6: leaves the main lanes into auxiliary lane 6 at about 32 s
    rows += ngsim_vehicle(6, 0, 60, 400.0, 46.0, 5, change=(30.0, 34.0, 6))
    # 7: 0.5 s of missing frames
    rows += ngsim_vehicle(7, 0, 60, 500.0, 44.0, 2, skip=[(30.0, 30.5)])
    # 8: lane flicker: Lane_ID 2 -> 3 for 0.3 s -> 2
    flick = ngsim_vehicle(8, 0, 60, 700.0, 44.0, 2)
    for r in flick:
        if 25.0 <= (r["Frame_ID"] - 1000) / 10 < 25.3:
            r["Lane_ID"] = 3
    rows += flick
    # 9: the leader of 1 in Lane_ID 3 ahead of it, with NGSIM's own front-to-front Space_Headway
    leader = ngsim_vehicle(9, 0, 15, 100.0, 50.0, 3)
    for r in leader:
        r["Following"] = 1
    rows += leader
    frame = pd.DataFrame(rows)[list(NGSIM_COLUMNS)]
    # 1 follows 9 for 0-15 s: Space_Headway = 100 ft front to front
    one = (frame["Vehicle_ID"] == 1) & (frame["Frame_ID"] <= 1150)
    frame.loc[one, ["Preceding", "Space_Headway"]] = [9, 100.0]
    return frame


@pytest.fixture(scope="module")
def ngsim_dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("ngsim")
    csv = root / "trajectories-0750am-0805am.csv"
    ngsim_rows().to_csv(csv, index=False)
    out = root / "data"
    assert main(["dataset", "--from-ngsim", str(csv), "--out", str(out), "--chunk", "30"]) == 0
    return root, csv, out


def _tables(out: Path, name: str) -> pd.DataFrame:
    return pd.concat([pd.read_parquet(f) for f in sorted((out / "runs").glob(f"seed_*/{name}.parquet"))],
                     ignore_index=True)


def test_ngsim_lane_change_times_and_gaps(ngsim_dataset):
    _, _, out = ngsim_dataset
    meta = json.loads((out / "dataset.json").read_text(), parse_constant=pytest.fail)  # strict JSON: no NaN
    lc = _tables(out, "lane_changes").set_index("vehicle_id")
    assert sorted(lc.index) == ["1", "3"]  # no event from flicker, id reuse, the aux lane or the gap
    one = lc.loc["1"]
    assert (one["from_lane"], one["to_lane"], one["direction"], one["reason"]) == (2, 3, 1, "unknown")
    assert abs(one["mid_time"] - 22.0) <= 0.15  # Local_X crosses the line at 22 s
    assert abs(one["start_time"] - 20.0) <= 0.3 and abs(one["end_time"] - 24.0) <= 0.3
    three = lc.loc["3"]
    assert (three["from_lane"], three["to_lane"], three["direction"]) == (1, 0, -1)
    assert np.isnan(three["start_time"]) and np.isnan(three["end_time"])  # no Local_X: no lateral motion
    q = meta["recordings"][0]["quality"]
    n4 = len(ngsim_vehicle(4, 0, 60, 150.0, 47.0, 1))
    assert q["duplicate_samples"] == n4
    assert q["tracks_split_at_gaps"] == 1 and q["gaps_interpolated"] == 1 and q["lane_flicker_removed"] == 1
    assert meta["recordings"][0]["quality_reader"]["rows_by_lane_outside_main"]["6"] > 0
    twins = _tables(out, "twins")
    ticks = twins.groupby("vehicle_id")["time"].agg(["min", "max", "count"])
    assert set(ticks.index) == {"1", "2", "3", "4", "5", "5.1", "6", "7", "8", "9"}
    assert ticks.loc["4", "count"] == n4  # duplicates dropped
    assert ticks.loc["7", "count"] == 601  # the 0.5 s gap interpolated: a twin every 0.1 s
    assert (ticks.loc["5", "max"], ticks.loc["5.1", "min"]) == (10.0, 40.0)
    assert ticks.loc["6", "max"] < 33.0  # gone when it enters lane 6
    assert not twins.loc[twins["vehicle_id"] == "3", "d_known"].any()
    seven = twins[twins["vehicle_id"] == "7"].sort_values("time")
    assert np.allclose(np.diff(seven["x"]), 4.4 * FT, atol=1e-6)  # s interpolated across the gap
    vehicles = _tables(out, "vehicles").set_index("vehicle_id")
    assert vehicles.loc["2", "length"] == 10.0 and vehicles.loc["2", "vclass"] == "truck"  # class default
    assert vehicles.loc["1", "length"] == pytest.approx(15 * FT)


def test_ngsim_labels_and_features_are_the_simulation_code(ngsim_dataset):
    _, _, out = ngsim_dataset
    samples = _tables(out, "samples")
    assert list(samples.columns[:9]) == ["seed", "time", "vehicle_id", "event_id", "lc_reason", "time_to_lc",
                                         "time_since_lc", "window_label", "stream_label"]
    assert list(samples.columns[9:]) == [*FEATURE_NAMES, *SEQUENCE_EXTRA_NAMES, *LATERAL_NAMES]
    lc = _tables(out, "lane_changes").set_index("vehicle_id")
    one = samples[samples["vehicle_id"] == "1"].set_index("time")
    end = lc.loc["1", "end_time"]
    assert one.loc[round(end - 4.9, 1), "window_label"] == 1 and one.loc[round(end - 5.0, 1), "window_label"] == -1
    assert one.loc[round(end - 7.1, 1), "window_label"] == 0
    # the change without a seen end ends END_AFTER_MID_S after its midpoint
    three = samples[samples["vehicle_id"] == "3"].set_index("time")
    assert three.loc[lc.loc["3", "mid_time"], "time_to_lc"] == pytest.approx(END_AFTER_MID_S)
    # gap to the leader = NGSIM's front-to-front Space_Headway minus the leader's length
    raw = ngsim_rows()
    head = raw[(raw["Vehicle_ID"] == 1) & (raw["Preceding"] == 9)]
    t = ((head["Frame_ID"] - 1000) / 10).round(1).to_numpy()
    expected = (head["Space_Headway"] - 15.0).to_numpy() * FT
    assert np.allclose(one.loc[t[t >= 1.0], "gap_lead_own"], expected[t >= 1.0], atol=1e-4)
    assert np.allclose(one.loc[t, "speed"], 50 * FT, atol=1e-5)
    # lane 0 = rightmost: vehicle 4 in Lane_ID 1 (leftmost of 5) has no lane to its left
    four = samples[samples["vehicle_id"] == "4"]
    assert (four["lane"] == 4).all() and (four["left_lane_exists"] == 0).all() and (four["right_lane_exists"] == 1).all()


def test_ngsim_headerless_gz_and_missing_columns(ngsim_dataset, tmp_path):
    _, _, out = ngsim_dataset
    rows = ngsim_rows()
    txt = tmp_path / "trajectories.txt.gz"
    with gzip.open(txt, "wt") as f:  # NGSIM's own form: no header, whitespace, 18 columns
        rows.to_csv(f, sep=" ", header=False, index=False)
    again = tmp_path / "again"
    assert main(["dataset", "--from-ngsim", str(txt), "--out", str(again), "--chunk", "30"]) == 0
    pd.testing.assert_frame_equal(_tables(again, "samples"), _tables(out, "samples"))
    # no Local_X and no v_Length columns at all: lanes from Lane_ID, lengths by class
    bare = tmp_path / "bare.csv"
    rows.drop(columns=["Local_X", "v_Length", "v_Acc"]).to_csv(bare, index=False)
    data = tmp_path / "bare"
    assert main(["dataset", "--from-ngsim", str(bare), "--out", str(data), "--chunk", "30"]) == 0
    lc = _tables(data, "lane_changes")
    assert sorted(lc["vehicle_id"]) == ["1", "3"] and lc["end_time"].isna().all()
    assert (_tables(data, "vehicles")["length"].isin([4.5, 10.0])).all()
    # main lanes 1-6 keep vehicle 6 on the road: its move into lane 6 becomes a lane change
    wide = tmp_path / "wide"
    assert main(["dataset", "--from-ngsim", str(bare), "--out", str(wide), "--main-lanes", "1-6"]) == 0
    lc = _tables(wide, "lane_changes").set_index("vehicle_id")
    assert lc.loc["6", "from_lane"] == 1 and lc.loc["6", "to_lane"] == 0


def test_ngsim_combined_release_one_site_its_periods_apart(ngsim_dataset, tmp_path, capsys):
    """The combined release: every site in one CSV (Location), a site's periods with their own
    Vehicle_IDs and Frame_IDs (told apart by Global_Time - 100 ms x Frame_ID), numbers written with
    thousands separators. One site's import equals its periods imported as separate files."""
    _, _, out = ngsim_dataset
    period1 = ngsim_rows().assign(Location="us-101")
    period2 = period1.assign(Global_Time=period1["Global_Time"] + 15 * 60 * 1000)  # 15 min later, same ids
    other = period1.assign(Location="i-80", Local_Y=period1["Local_Y"] + 50.0)
    combined = pd.concat([other, period1, period2], ignore_index=True)
    for column in ("Global_Time", "Global_X"):
        combined[column] = combined[column].map(lambda v: f"{v:,.1f}" if column == "Global_X" else f"{v:,}")
    csv = tmp_path / "Next_Generation_Simulation.csv"
    combined.to_csv(csv, index=False)
    assert '"1,118,846,980,200"' in csv.read_text()[:2000]
    # without a site: one line naming the sites and the option
    assert main(["dataset", "--from-ngsim", str(csv), "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert "Location: the file mixes ['i-80', 'us-101']" in err and "--ngsim-location" in err
    assert main(["dataset", "--from-ngsim", str(csv), "--ngsim-location", "lankershim", "--out",
                 str(tmp_path / "x")]) == 2
    assert "no such Location; the file has ['i-80', 'us-101']" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()
    data = tmp_path / "us101"
    assert main(["dataset", "--from-ngsim", str(csv), "--ngsim-location", "US-101", "--out", str(data),
                 "--chunk", "30"]) == 0
    meta = json.loads((data / "dataset.json").read_text())
    assert [r["name"] for r in meta["recordings"]] == ["ngsim Next_Generation_Simulation-us-101-period1",
                                                       "ngsim Next_Generation_Simulation-us-101-period2"]
    # each period is the single-period file's recording: the same lane changes, twice
    lc = _tables(data, "lane_changes")
    one = _tables(out, "lane_changes")
    assert len(lc) == 2 * len(one) and sorted(lc["vehicle_id"]) == sorted(list(one["vehicle_id"]) * 2)
    assert meta["recordings"][0]["quality"] == json.loads((out / "dataset.json").read_text())["recordings"][0]["quality"]


@pytest.mark.parametrize("mutate, needle", [
    (lambda df: df.drop(columns=["Lane_ID"]), "Lane_ID"),
    (lambda df: df.assign(v_Vel=df["v_Vel"].astype(object).where(df.index != 3, "fast")), "v_Vel: expected a number"),
    (lambda df: df.assign(Location="us-101", Direction=np.where(df.index % 2, 2, 4)), "Direction: the file mixes"),
])
def test_ngsim_bad_files_exit_2_and_write_nothing(tmp_path, capsys, mutate, needle):
    bad = tmp_path / "bad.csv"
    mutate(ngsim_rows()).to_csv(bad, index=False)
    out = tmp_path / "out"
    assert main(["dataset", "--from-ngsim", str(bad), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "bad.csv" in err and needle in err
    assert not out.exists() and not list(tmp_path.glob("out*"))
    assert main(["dataset", "--from-ngsim", str(bad), "--out", str(out), "--main-lanes", "5-1"]) == 2
    assert "--main-lanes" in capsys.readouterr().err
    assert main(["dataset", "--out", str(out)]) == 2
    assert "exactly one of" in capsys.readouterr().err


def test_lane_flicker_only_between_equal_lanes():
    lane, removed = clean_lane_flicker(np.array([2] * 20 + [3] * 3 + [2] * 20 + [3] * 3 + [4] * 20), 10)
    assert removed == 1 and list(lane[20:23]) == [2, 2, 2] and list(lane[43:46]) == [3, 3, 3]


def test_a_moment_on_a_lane_off_the_main_road_is_flicker_not_an_exit():
    # 0.3 s on an auxiliary lane's id (lane -1: off the modelled road) between two stretches of
    # lane 0: one twin, its labels kept; a real exit (the rest of the track off the road) still cuts
    t = np.round(np.arange(0, 8, 0.1), 6)

    def twins_of(lane):
        samples = pd.DataFrame({"vehicle_id": "7", "time": t, "s": 25 * t, "d": np.full(len(t), 1.83), "lane": lane,
                                "speed": 25.0, "accel": 0.0, "length": 4.5, "width": 1.8, "height": 1.5,
                                "vclass": "passenger"})[SAMPLE_COLUMNS]
        rec = Recording("r", straight_road("r", 5, 3.66, 300, 30), samples, 0.1, {"format": "ngsim"})
        return twin_tracks(rec)

    blip = np.zeros(len(t), int)
    blip[30:33] = -1
    twins, vehicles, changes, quality = twins_of(blip)
    assert vehicles["vehicle_id"].tolist() == ["7"] and len(twins) == len(t) and len(changes) == 0
    assert quality["lane_flicker_removed"] == 1
    leaves = np.zeros(len(t), int)
    leaves[50:] = -1
    assert twins_of(leaves)[1]["vehicle_id"].tolist() == ["7"] and len(twins_of(leaves)[0]) == 50


# ---------------------------------------------------------------- highD files

UPPER = [8.0, 11.5, 15.0]  # y of the lane lines, m (image frame: y down)
LOWER = [21.0, 24.5, 28.0]


def highd_vehicle(vid, direction, t0, t1, x_centre0, speed, lane_top_index, change=None, length=4.5, width=1.8):
    """Track rows at 25 Hz; lane_top_index counts the lanes of the roadway from the top; `change` =
    (start, end, new top index) moves the box centre from lane centre to lane centre."""
    marks = UPPER if direction == 1 else LOWER
    centre = lambda j: (marks[j] + marks[j + 1]) / 2  # noqa: E731
    sign = -1.0 if direction == 1 else 1.0
    rows = []
    for frame in range(int(round(t0 * 25)), int(round(t1 * 25)) + 1):
        t = frame / 25
        yc = centre(lane_top_index)
        if change is not None:
            yc = _cosine(t, change[0], change[1], centre(lane_top_index), centre(change[2]))
        j = int(np.searchsorted(marks, yc, side="right") - 1)
        lane_id = j + 2 if direction == 1 else len(UPPER) + 2 + j
        xc = x_centre0 + sign * speed * (t - t0)
        rows.append({"frame": frame, "id": vid, "x": xc - length / 2, "y": yc - width / 2, "width": length,
                     "height": width, "xVelocity": sign * speed, "yVelocity": 0.0, "xAcceleration": 0.0,
                     "yAcceleration": 0.0, "frontSightDistance": 100.0, "backSightDistance": 100.0, "dhw": 0.0,
                     "thw": 0.0, "ttc": 0.0, "precedingXVelocity": 0.0, "precedingId": 0, "followingId": 0,
                     "leftPrecedingId": 0, "leftAlongsideId": 0, "leftFollowingId": 0, "rightPrecedingId": 0,
                     "rightAlongsideId": 0, "rightFollowingId": 0, "laneId": lane_id})
    return rows


def write_highd(folder: Path, number: int, vehicles: list[tuple]) -> None:
    """vehicles: (id, drivingDirection, class, rows)."""
    folder.mkdir(parents=True, exist_ok=True)
    p = f"{number:02d}"
    tracks = pd.DataFrame([r for _, _, _, rows in vehicles for r in rows])
    tracks.to_csv(folder / f"{p}_tracks.csv", index=False)
    meta = []
    for vid, direction, cls, rows in vehicles:
        xs = [r["x"] for r in rows]
        meta.append({"id": vid, "width": rows[0]["width"], "height": rows[0]["height"],
                     "initialFrame": rows[0]["frame"], "finalFrame": rows[-1]["frame"], "numFrames": len(rows),
                     "class": cls, "drivingDirection": direction, "traveledDistance": abs(xs[-1] - xs[0]),
                     "minXVelocity": 30.0, "maxXVelocity": 30.0, "meanXVelocity": 30.0, "minDHW": -1,
                     "minTHW": -1, "minTTC": -1, "numLaneChanges": 0})
    pd.DataFrame(meta).to_csv(folder / f"{p}_tracksMeta.csv", index=False)
    pd.DataFrame([{"id": number, "frameRate": 25, "locationId": 2, "speedLimit": -1.0, "month": "09.2017",
                   "weekDay": "Tue", "startTime": "08:38", "duration": 60.0, "totalDrivenDistance": 1.0,
                   "totalDrivenTime": 1.0, "numVehicles": len(vehicles), "numCars": len(vehicles), "numTrucks": 0,
                   "upperLaneMarkings": ";".join(map(str, UPPER)),
                   "lowerLaneMarkings": ";".join(map(str, LOWER))}]).to_csv(folder / f"{p}_recordingMeta.csv",
                                                                           index=False)


def highd_recording(folder: Path, number: int) -> None:
    write_highd(folder, number, [
        # upper roadway, leftward: from the top lane (the rightmost) down one lane (to the left), 10-14 s
        (1, 1, "Car", highd_vehicle(1, 1, 0, 40, 400.0, 25.0, 0, change=(10.0, 14.0, 1))),
        (2, 1, "Car", highd_vehicle(2, 1, 0, 40, 380.0, 25.0, 0)),  # ahead of 1 (smaller x) in its lane
        # lower roadway, rightward: from the bottom lane (the rightmost) up one lane (to the left), 6-10 s
        (3, 2, "Car", highd_vehicle(3, 2, 0, 40, 10.0, 30.0, 1, change=(6.0, 10.0, 0))),
        (4, 2, "Truck", highd_vehicle(4, 2, 0, 40, 40.0, 30.0, 1, length=12.0, width=2.5)),  # ahead of 3
        (5, 2, "Car", highd_vehicle(5, 2, 20, 40, 5.0, 28.0, 0)),
    ])


@pytest.fixture(scope="module")
def highd_dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("highd")
    highd_recording(root / "data", 1)
    highd_recording(root / "data", 2)
    out = root / "out"
    assert main(["dataset", "--from-highd", str(root / "data"), "--out", str(out), "--chunk", "10"]) == 0
    return root, out


def test_highd_both_directions(highd_dataset):
    root, out = highd_dataset
    meta = json.loads((out / "dataset.json").read_text())
    assert [r["name"] for r in meta["recordings"]] == ["highD 01 upper", "highD 01 lower", "highD 02 upper",
                                                     "highD 02 lower"]
    for rec in meta["recordings"]:
        assert rec["road"]["num_lanes"] == 2 and rec["road"]["lane_width_m"] == pytest.approx(3.5)
        assert rec["quality_reader"]["laneId_agreement"] == 1.0
    seeds = {int(k): v for k, v in meta["seeds"].items()}
    first = [s for s, v in seeds.items() if v["recording"] == "highD 01 upper"]
    run = out / "runs" / f"seed_{first[0]:04d}"
    lc = pd.read_parquet(run / "lane_changes.parquet").set_index("vehicle_id")
    ev = lc.loc["1"]
    # the top lane of the leftward roadway is its rightmost: moving down is a change to the left
    assert (ev["from_lane"], ev["to_lane"], ev["direction"]) == (0, 1, 1)
    assert abs(ev["mid_time"] - 12.0) <= 0.15 and abs(ev["start_time"] - 10.0) <= 0.3
    assert abs(ev["end_time"] - 14.0) <= 0.3
    lower = [s for s, v in seeds.items() if v["recording"] == "highD 01 lower"]
    lc = pd.concat([pd.read_parquet(out / "runs" / f"seed_{s:04d}" / "lane_changes.parquet") for s in lower])
    ev = lc.set_index("vehicle_id").loc["3"]
    assert (ev["from_lane"], ev["to_lane"], ev["direction"]) == (0, 1, 1)  # bottom lane up = to the left
    assert abs(ev["mid_time"] - 8.0) <= 0.15 and abs(ev["end_time"] - 10.0) <= 0.3
    samples = pd.concat([pd.read_parquet(out / "runs" / f"seed_{s:04d}" / "samples.parquet") for s in lower])
    three = samples[samples["vehicle_id"] == "3"].sort_values("time")
    assert np.allclose(np.diff(three["time"]), 0.1)  # 25 Hz resampled to the V2C period
    assert np.allclose(three["speed"], 30.0)  # along the driving direction
    early = three.set_index("time").loc[1.0:5.0]
    # leader 4 (truck, 12 m) 30 m ahead centre to centre: bumper gap 30 - 6 - 2.25
    assert np.allclose(early["gap_lead_own"], 30.0 - 6.0 - 2.25, atol=1e-4)
    assert (early["lane"] == 0).all() and (early["left_lane_exists"] == 1).all()
    upper = pd.read_parquet(run / "samples.parquet")
    one = upper[upper["vehicle_id"] == "1"].set_index("time").loc[1.0:5.0]
    assert np.allclose(one["speed"], 25.0) and np.allclose(one["gap_lead_own"], 20.0 - 4.5, atol=1e-4)
    # a truck's size from the track's box: width (x) is its length
    vehicles = pd.read_parquet(out / "runs" / f"seed_{lower[0]:04d}" / "vehicles.parquet").set_index("vehicle_id")
    assert vehicles.loc["4", "length"] == 12.0 and vehicles.loc["4", "vclass"] == "truck"


def test_highd_single_recording_and_bad_meta(tmp_path, capsys):
    highd_recording(tmp_path / "data", 1)
    out = tmp_path / "one"
    assert main(["dataset", "--from-highd", str(tmp_path / "data" / "01_tracks.csv"), "--out", str(out)]) == 0
    assert len(json.loads((out / "dataset.json").read_text())["recordings"]) == 2
    meta = pd.read_csv(tmp_path / "data" / "01_tracksMeta.csv")
    meta.loc[2, "drivingDirection"] = 3
    meta.to_csv(tmp_path / "data" / "01_tracksMeta.csv", index=False)
    assert main(["dataset", "--from-highd", str(tmp_path / "data"), "--out", str(tmp_path / "bad")]) == 2
    err = capsys.readouterr().err
    assert "01_tracksMeta.csv" in err and "drivingDirection" in err and not (tmp_path / "bad").exists()
    (tmp_path / "data" / "01_recordingMeta.csv").unlink()
    assert main(["dataset", "--from-highd", str(tmp_path / "data"), "--out", str(tmp_path / "bad")]) == 2
    assert "01_recordingMeta.csv: missing" in capsys.readouterr().err


# ---------------------------------------------------------------- round trip through `vcfusion evaluate`

def _check_evaluation(folder: Path, out: Path, split: str) -> dict:
    result = json.loads((folder / "evaluation.json").read_text())
    metrics = pd.read_csv(folder / "metrics.csv")
    meta = json.loads((out / "dataset.json").read_text())
    assert result["split"] == split
    default = result["default"]
    assert (default["predictor"], default["variant"]) == ("MLP", "aggressive")  # the shipped model's default
    row = metrics[(metrics["predictor"] == "MLP") & (metrics["variant"] == "aggressive")].iloc[0]
    if result["lane_changes"]:
        assert default["predicted"] == pytest.approx(row["predicted_share"]) and 0.0 <= default["predicted"] <= 1.0
    else:  # no lane change among these seeds: no share (null, never a NaN in the JSON)
        assert default["predicted"] is None and np.isnan(row["predicted_share"])
    assert default["false_alarms_per_veh_h"] == pytest.approx(row["false_alarms_per_vehicle_hour"])
    assert "advance_final_mean_s" in default
    assert len(result["variants"]) == len(metrics)
    return result | {"meta": meta}


def test_imports_round_trip_through_evaluate(ngsim_dataset, highd_dataset, tmp_path):
    _, _, ngsim = ngsim_dataset
    assert main(["evaluate", str(SHIPPED_MODEL), str(ngsim), "--split", "all", "--out", str(tmp_path / "e1")]) == 0
    result = _check_evaluation(tmp_path / "e1", ngsim, "all")
    q = result["meta"]["recordings"][0]["quality"]
    assert result["lane_changes"] == q["lane_changes"] == 2 and result["vehicles"] == q["twins"]
    assert result["seeds"] == sorted(int(s) for s in result["meta"]["seeds"]) == [0, 1]
    # two seeds: no train + validation seeds to fit baselines on; the model is scored alone
    assert not result["baselines"]["fitted"] and {v["predictor"] for v in result["variants"]} == {"MLP"}
    assert "no baselines" in (tmp_path / "e1" / "report.md").read_text()
    _, highd = highd_dataset
    assert main(["evaluate", str(SHIPPED_MODEL), str(highd), "--split", "all", "--out", str(tmp_path / "e2")]) == 0
    result = _check_evaluation(tmp_path / "e2", highd, "all")
    assert result["lane_changes"] == 4 and len(result["seeds"]) == len(result["meta"]["seeds"]) == 6
    assert result["baselines"]["fitted"] and result["baselines"]["scored_on_their_training_seeds"]
    assert {v["predictor"] for v in result["variants"]} == {"MLP", "logistic regression", "gap/speed rule"}
    assert main(["evaluate", str(SHIPPED_MODEL), str(highd), "--out", str(tmp_path / "e3")]) == 0
    result = _check_evaluation(tmp_path / "e3", highd, "test")
    assert result["seeds"] == result["meta"]["splits"]["test"] and result["lane_changes"] == 0
    assert not result["baselines"]["scored_on_their_training_seeds"]
