"""The guidance study's trip log: a study stopped part way continues from its finished trips, and
refuses a folder that holds another study's."""

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from vcfusion.errors import UsageError
from vcfusion.studies.guidance import TRIP_LOG, read_trip_log, run_guidance_study, trip_line

REPO = Path(__file__).resolve().parents[2]


def test_a_trip_record_reads_back_as_the_same_table_rows():
    rows = [{"seed": np.int64(3), "arm": "none", "fuel_g_per_km": np.float64(61.25), "ttc": math.nan,
             "tit": math.inf, "target_id": None, "differs": np.bool_(True), "count": 7, "share": 0.1 + 0.2},
            {"seed": np.int64(3), "arm": "cloud", "fuel_g_per_km": 59.0, "ttc": 4.5, "tit": 0.0,
             "target_id": "changer0", "differs": False, "count": np.int32(2), "share": 1 / 3}]
    record = json.loads(trip_line(3, rows))
    assert record["seed"] == 3
    pd.testing.assert_frame_equal(pd.DataFrame(record["rows"]), pd.DataFrame(rows))


def test_a_row_value_the_log_cannot_write_is_named():
    with pytest.raises(TypeError, match="Timestamp"):
        trip_line(0, [{"when": pd.Timestamp(0)}])


def short_accident(tmp_path: Path, desired_speed: float = 30.0) -> Path:
    path = tmp_path / f"short_accident_{desired_speed:g}.yaml"
    path.write_text(f"extends: {REPO / 'scenarios' / 'accident.yaml'}\nname: accident\n"
                    f"simulation: {{max_time_s: 6.0}}\nego: {{desired_speed_mps: {desired_speed}}}\n")
    return path


@pytest.mark.slow
def test_a_study_stopped_part_way_continues_from_its_logged_trips(tmp_path):
    scenario, out = short_accident(tmp_path), tmp_path / "study"
    kwargs = dict(trips=3, workers=1, out=out, renders=tmp_path / "renders", progress=False, arms=("none", "cloud"))
    first = run_guidance_study(scenario, **kwargs)
    whole = first["trips"]
    log = out / TRIP_LOG
    header, *records = log.read_text().splitlines()
    assert sorted(json.loads(r)["seed"] for r in records) == [0, 1, 2]
    # as a study killed while writing trip 1's line leaves it: trips 0 and 2 whole, trip 1 cut short
    by_seed = {json.loads(r)["seed"]: r for r in records}
    log.write_text("\n".join([header, by_seed[0], by_seed[2], by_seed[1][: len(by_seed[1]) // 2]]))
    assert sorted(read_trip_log(log, json.loads(header)["study"])) == [0, 2]

    again = run_guidance_study(scenario, **kwargs)
    assert again["info"]["trips_from_log"] == 2 and again["info"]["trips_ok"] == 3
    assert "2 trips taken from the trip log" in again["text"]
    # the logged trips are taken as they were, their wall times too; trip 1 is simulated again: the
    # same figures, another wall time
    logged = again["trips"]["seed"] != 1
    pd.testing.assert_frame_equal(again["trips"][logged], whole[logged])
    pd.testing.assert_frame_equal(again["trips"].drop(columns="arm_wall_s"), whole.drop(columns="arm_wall_s"))
    # the log holds every trip once more, the cut line gone
    assert sorted(json.loads(r)["seed"] for r in log.read_text().splitlines()[1:]) == [0, 1, 2]

    # a longer study into the same folder runs only the new seed
    longer = run_guidance_study(scenario, **(kwargs | {"trips": 4}))
    assert longer["info"]["trips_from_log"] == 3
    pd.testing.assert_frame_equal(longer["trips"][longer["trips"]["seed"] < 3].reset_index(drop=True),
                                  again["trips"])

    # another study's trips are never taken: other arms, another scenario; the log is left as it was
    kept = log.read_text()
    with pytest.raises(UsageError, match=r"another study \(it differs in: the arms, an arm's resolved scenario"):
        run_guidance_study(scenario, **(kwargs | {"arms": ("none", "oracle")}))
    with pytest.raises(UsageError, match=r"it differs in: an arm's resolved scenario or the files it reads\)"):
        run_guidance_study(short_accident(tmp_path, 25.0), **kwargs)
    assert log.read_text() == kept


def test_a_log_damaged_before_its_last_line_is_refused_with_its_line(tmp_path):
    log = tmp_path / TRIP_LOG
    identity = {"arm_order": ["none"], "code_sha256": "x"}
    log.write_text(json.dumps({"study": identity}) + "\n" + trip_line(0, [{"arm": "none"}]) + "{not json\n"
                   + trip_line(2, [{"arm": "none"}]))
    with pytest.raises(UsageError, match=r"trips\.jsonl: line 3: expected a trip record"):
        read_trip_log(log, identity)
    log.write_text("seed,arm\n0,none\n")
    with pytest.raises(UsageError, match=r"line 1: expected a guidance study's trip log"):
        read_trip_log(log, identity)
