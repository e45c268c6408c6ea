"""NGSIM releases unlike US-101's original file: rows without lateral position (empty Local_X),
a metric file, lanes numbered from the right edge, neighbours named but absent (a truncated file)."""

import json

import numpy as np
import pandas as pd
import pytest

from vcfusion.commands import main
from vcfusion.prediction.sources.ngsim import NGSIM_COLUMNS, read_ngsim

FT = 0.3048


def rows(unit=1.0, lane_one="left", lateral=True):
    """Two cars 10 s at 10 Hz on a 3-lane road (lane width 12 ft): car 1 from the rightmost lane to
    the middle one at 5 s; car 2 in the leftmost lane, whose Preceding names car 9 (not in the file).
    Positions in feet x unit (unit = FT: the same file written in metres)."""
    out = []
    for vid, y0, lane_from_left in ((1, 0.0, 3), (2, 200.0, 1)):
        for k in range(101):
            t = k / 10
            lane = lane_from_left if not (vid == 1 and t >= 5.0) else 2
            x = (lane - 0.5) * 12.0
            out.append({"Vehicle_ID": vid, "Frame_ID": 100 + k, "Total_Frames": 101,
                        "Global_Time": 1118846980000 + 100 * (100 + k),
                        "Local_X": x * unit if lateral else np.nan, "Local_Y": (y0 + 60.0 * t) * unit,
                        "Global_X": 0.0, "Global_Y": 0.0, "v_Length": 15.0 * unit, "v_Width": 6.0 * unit,
                        "v_Class": 2, "v_Vel": 60.0 * unit, "v_Acc": 0.0, "Preceding": 9 if vid == 2 else 0,
                        "Following": 0, "Space_Headway": 0.0, "Time_Headway": 0.0,
                        "Lane_ID": lane if lane_one == "left" else 4 - lane})
    return pd.DataFrame(out)[list(NGSIM_COLUMNS)]


def _lanes(rec):
    return rec.samples.groupby("vehicle_id")["lane"].agg(["first", "last"])


def test_metric_file_with_lanes_from_the_right_reads_as_the_original(tmp_path):
    feet = tmp_path / "feet.csv"
    rows().to_csv(feet, index=False)
    metric = tmp_path / "metric.csv"
    rows(unit=FT, lane_one="right").to_csv(metric, index=False)
    a = read_ngsim(feet, (1, 3))[0]
    b = read_ngsim(metric, (1, 3), units="m", lane_one="right")[0]
    assert _lanes(a).loc["1"].tolist() == [0, 1] and _lanes(a).loc["2"].tolist() == [2, 2]
    for column in ("time", "s", "d", "lane", "speed", "length", "width"):
        assert np.allclose(a.samples[column].to_numpy(float), b.samples[column].to_numpy(float), atol=1e-9), column
    assert a.samples["speed"].iloc[0] == pytest.approx(60.0 * FT)
    # read as feet, the metric file would be 3.3 times too slow: the units matter
    assert read_ngsim(metric, (1, 3), lane_one="right")[0].samples["speed"].iloc[0] == pytest.approx(60.0 * FT * FT)


def test_rows_without_lateral_position_and_absent_neighbours(tmp_path):
    bare = tmp_path / "no-lateral.csv"
    rows(lateral=False).to_csv(bare, index=False)  # Local_X written as empty fields
    assert ",," in bare.read_text().splitlines()[1]
    out = tmp_path / "data"
    assert main(["dataset", "--from-ngsim", str(bare), "--out", str(out), "--main-lanes", "1-3"]) == 0
    meta = json.loads((out / "dataset.json").read_text(), parse_constant=pytest.fail)
    q = meta["recordings"][0]["quality_reader"]
    assert q["lateral_unknown_rows"] == 202
    assert q["rows_naming_a_leader_absent_from_the_file"] == 101  # car 2 names car 9 in every row
    assert q["rows_naming_a_follower_absent_from_the_file"] == 0
    lc = pd.concat([pd.read_parquet(f) for f in (out / "runs").glob("seed_*/lane_changes.parquet")])
    assert list(lc["vehicle_id"]) == ["1"] and lc["mid_time"].iloc[0] == pytest.approx(5.0)
    assert lc["start_time"].isna().all() and lc["end_time"].isna().all()  # no lateral motion to time them
    twins = pd.concat([pd.read_parquet(f) for f in (out / "runs").glob("seed_*/twins.parquet")])
    assert not twins["d_known"].any()


def test_bad_units_option_exits_2(tmp_path, capsys):
    f = tmp_path / "x.csv"
    rows().to_csv(f, index=False)
    with pytest.raises(SystemExit):
        main(["dataset", "--from-ngsim", str(f), "--out", str(tmp_path / "o"), "--ngsim-units", "yd"])
    assert "--ngsim-units" in capsys.readouterr().err and not (tmp_path / "o").exists()
