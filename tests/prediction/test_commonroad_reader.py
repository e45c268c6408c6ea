"""The CommonRoad import (vcfusion.prediction.sources.commonroad) on hand-written 2020a scenario
files: two lanelets side by side, an obstacle that changes lanelet (with a boundary flicker on
the way), a file that repeats the recording with another planning problem, a folder, a .tar.xz."""

import json
import tarfile

import numpy as np
import pandas as pd
import pytest

pytest.importorskip("commonroad", reason="the CommonRoad reader needs commonroad-io (extra `commonroad`)")

from vcfusion.commands import main  # noqa: E402
from vcfusion.prediction.sources.commonroad import read_commonroad  # noqa: E402
from vcfusion.prediction.sources.trajectories import RealDataError  # noqa: E402


# ---------------------------------------------------------------- hand-written CommonRoad 2020a files
# a straight road of two lanelets side by side, heading south-east like the US-101 scenarios;
# obstacles given by their centre in the road's own (s, d) frame

HEADING = -0.7  # rad, the road's direction (x east, y north)
LANE_W = 3.5
LENGTH = 300.0
ORIGIN = np.array([-40.0, 50.0])
U = np.array([np.cos(HEADING), np.sin(HEADING)])  # along the road
LEFT = np.array([-U[1], U[0]])  # to its left


def world(s: float, d: float) -> np.ndarray:
    """The point s along the road and d left of its right edge (two lanes: d in [0, 7])."""
    return ORIGIN + s * U + d * LEFT


def _point(p) -> str:
    return f"<point><x>{p[0]:.4f}</x><y>{p[1]:.4f}</y></point>"


def _bound(d: float) -> str:
    return "".join(_point(world(s, d)) for s in np.linspace(0.0, LENGTH, 7))


def lanelets_xml() -> str:
    """Lanelet 1 (right lane, d 0-3.5) and 2 (left lane, d 3.5-7), same direction, adjacent."""
    return (f'<lanelet id="1"><leftBound>{_bound(LANE_W)}</leftBound><rightBound>{_bound(0.0)}</rightBound>'
            '<adjacentLeft ref="2" drivingDir="same"/><laneletType>highway</laneletType></lanelet>'
            f'<lanelet id="2"><leftBound>{_bound(2 * LANE_W)}</leftBound><rightBound>{_bound(LANE_W)}</rightBound>'
            '<adjacentRight ref="1" drivingDir="same"/><laneletType>highway</laneletType></lanelet>')


def _state(tag: str, step: int, p, speed: float | None, orientation: float) -> str:
    v = f"<velocity><exact>{speed:.4f}</exact></velocity>" if speed is not None else ""
    return (f"<{tag}><position>{_point(p)}</position><orientation><exact>{orientation:.5f}</exact></orientation>"
            f"<time><exact>{step}</exact></time>{v}<acceleration><exact>0</exact></acceleration></{tag}>")


def obstacle_xml(oid: int, first_step: int, s0: float, speed: float, d_of_t, n_steps: int, length: float = 4.5,
                 width: float = 1.8, kind: str = "car", with_speed: bool = True) -> str:
    """A car driving at `speed` from s0, its lateral position d_of_t(t) (t in s since its first step)."""
    states = []
    for k in range(n_steps):
        t = k * 0.1
        p = world(s0 + speed * t, d_of_t(t))
        tag = "initialState" if k == 0 else "state"
        states.append(_state(tag, first_step + k, p, speed if with_speed else None, HEADING))
    trajectory = "".join(states[1:])
    return (f'<dynamicObstacle id="{oid}"><type>{kind}</type><shape><rectangle><length>{length}</length>'
            f'<width>{width}</width></rectangle></shape>{states[0]}<trajectory>{trajectory}</trajectory>'
            "</dynamicObstacle>")


def planning_problem_xml(pid: int, s: float) -> str:
    p = world(s, LANE_W / 2)
    return (f'<planningProblem id="{pid}"><initialState><position>{_point(p)}</position>'
            f"<velocity><exact>20</exact></velocity><orientation><exact>{HEADING}</exact></orientation>"
            "<yawRate><exact>0</exact></yawRate><slipAngle><exact>0</exact></slipAngle>"
            "<time><exact>0</exact></time></initialState>"
            f'<goalState><time><intervalStart>10</intervalStart><intervalEnd>50</intervalEnd></time></goalState>'
            "</planningProblem>")


def scenario_xml(benchmark_id: str, obstacles: list[str], planning_problem: int = 100) -> str:
    return ('<?xml version="1.0" ?>\n'
            f'<commonRoad affiliation="test" author="test" benchmarkID="{benchmark_id}" commonRoadVersion="2020a" '
            f'date="2020-01-01" source="hand-written" timeStepSize="0.1">'
            "<location><geoNameId>-999</geoNameId><gpsLatitude>999</gpsLatitude><gpsLongitude>999</gpsLongitude>"
            "</location><scenarioTags><highway/></scenarioTags>"
            f"{lanelets_xml()}{''.join(obstacles)}{planning_problem_xml(planning_problem, 10.0)}</commonRoad>\n")


def cosine(t, t0, t1, a, b):
    u = np.clip((t - t0) / (t1 - t0), 0.0, 1.0)
    return a + (b - a) * (1 - np.cos(np.pi * u)) / 2


# ---------------------------------------------------------------- tests

def changer_d(t):
    """Right lane centre to left lane centre between 3 and 7 s (crossing the line at 5 s), with a
    flicker over the line at 4.0-4.2 s."""
    d = cosine(t, 3.0, 7.0, LANE_W / 2, 1.5 * LANE_W)
    return LANE_W + 0.1 if 4.0 <= t < 4.25 else d


def write_files(folder, shift=20):
    folder.mkdir(parents=True, exist_ok=True)
    changer = lambda first: obstacle_xml(501, first, 20.0, 20.0, changer_d, 100, length=4.8)  # noqa: E731
    keeper = lambda first: obstacle_xml(502, first, 60.0, 22.0, lambda t: 1.5 * LANE_W, 80, length=12.0,  # noqa: E731
                                        width=2.5, kind="truck")
    # file 1: the recording; file 2: the same recording written with its clock `shift` steps later,
    # another planning problem, one more car (seen 3 s after the truck) and a pedestrian
    (folder / "USA_Test-1_1_T-1.xml").write_text(scenario_xml("USA_Test-1_1_T-1", [changer(0), keeper(5)], 901))
    extra = obstacle_xml(503, 5 + 30 + shift, 0.0, 25.0, lambda t: LANE_W / 2, 40, with_speed=False)
    walker = obstacle_xml(504, shift, 5.0, 1.0, lambda t: -1.0, 10, kind="pedestrian")
    (folder / "USA_Test-1_2_T-1.xml").write_text(
        scenario_xml("USA_Test-1_2_T-1", [changer(shift), keeper(5 + shift), extra, walker], 902))
    return folder


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    folder = write_files(tmp_path_factory.mktemp("cr") / "xml")
    recordings, notes = read_commonroad([folder])
    assert len(recordings) == 1 and notes["recordings"] == 1 and notes["files_read"] == 2
    return folder, recordings[0]


def test_duplicated_files_are_one_recording_each_obstacle_once(recording):
    _, rec = recording
    q = rec.source["quality_reader"]
    assert len(q["files"]) == 2
    assert q["obstacles_duplicated"] == 2  # the changer and the truck of the second file
    assert q["obstacles_dropped_type_pedestrian"] == 1
    assert q["speed_from_positions_rows"] == 40  # the extra car's states have no velocity
    samples = rec.samples
    assert sorted(samples["vehicle_id"].unique()) == ["501", "502", "503"]
    first = samples.groupby("vehicle_id")["time"].min()
    # the second file's clock aligned on the shared obstacles: the extra car 3 s after the truck
    assert first["502"] - first["501"] == pytest.approx(0.5)
    assert first["503"] - first["502"] == pytest.approx(3.0)
    assert samples.groupby("vehicle_id").size()["501"] == 100  # not twice
    extra = samples[samples["vehicle_id"] == "503"]
    assert np.allclose(extra["speed"], 25.0, atol=1e-3)  # from the positions


def test_lanes_s_d_and_sizes_from_the_lanelet_network(recording):
    _, rec = recording
    assert rec.road.num_lanes == 2 and rec.road.lane_width_m == pytest.approx(LANE_W, abs=1e-3)
    s = rec.samples.set_index(["vehicle_id", "time"]).sort_index()
    truck = s.loc["502"]
    assert (truck["lane"] == 1).all()  # lanelet 2, the left one of two
    assert np.allclose(truck["d"], 1.5 * LANE_W, atol=1e-3)
    assert np.allclose(np.diff(truck["s"]), 2.2, atol=1e-3)  # 22 m/s along the road
    assert truck["s"].iloc[0] == pytest.approx(60.0, abs=1e-3)
    assert (truck["length"] == 12.0).all() and (truck["vclass"] == "truck").all()
    car = s.loc["501"]
    t = car.index.to_numpy()
    assert (car["lane"].to_numpy()[t < 4.0] == 0).all() and (car["lane"].to_numpy()[t >= 5.05] == 1).all()
    assert (car["lane"].to_numpy()[(t >= 4.0) & (t < 4.25)] == 1).all()  # the flicker, as recorded


def test_import_lane_change_flicker_repaired_and_counted(recording, tmp_path, capsys):
    folder, _ = recording
    archive = tmp_path / "scenarios.tar.xz"
    with tarfile.open(archive, "w:xz") as tar:
        for f in sorted(folder.glob("*.xml")):
            tar.add(f, arcname=f"xml/{f.name}")
    out = tmp_path / "data"
    assert main(["dataset", "--from-commonroad", str(archive), "--out", str(out), "--chunk", "60"]) == 0
    printed = capsys.readouterr().out
    assert "2 scenario files -> 1 distinct recordings" in printed
    meta = json.loads((out / "dataset.json").read_text(), parse_constant=pytest.fail)
    assert meta["source"]["format"] == "commonroad"
    rec = meta["recordings"][0]
    assert rec["quality"]["lane_flicker_removed"] == 1
    assert rec["quality_reader"]["obstacles_duplicated"] == 2
    lc = pd.concat([pd.read_parquet(f) for f in (out / "runs").glob("seed_*/lane_changes.parquet")])
    assert list(lc["vehicle_id"]) == ["501"]  # one change, not three
    one = lc.iloc[0]
    assert (one["from_lane"], one["to_lane"], one["direction"]) == (0, 1, 1)
    assert one["mid_time"] == pytest.approx(5.0, abs=0.11)  # its centre crosses the line at 5 s
    assert one["start_time"] < one["mid_time"] and 6.0 < one["end_time"] <= 7.3
    samples = pd.concat([pd.read_parquet(f) for f in (out / "runs").glob("seed_*/samples.parquet")])
    car = samples[samples["vehicle_id"] == "501"].set_index("time")
    end = one["end_time"]
    assert car.loc[round(end - 4.9, 1), "window_label"] == 1  # the same Fig. 5 labels as NGSIM / SUMO
    twins = pd.concat([pd.read_parquet(f) for f in (out / "runs").glob("seed_*/twins.parquet")])
    assert twins["d_known"].all()


def test_folder_and_archive_give_the_same_recording(recording, tmp_path):
    folder, rec = recording
    archive = tmp_path / "s.tar.xz"
    with tarfile.open(archive, "w:xz") as tar:
        for f in sorted(folder.glob("*.xml")):
            tar.add(f, arcname=f.name)
    again, _ = read_commonroad([archive])
    pd.testing.assert_frame_equal(again[0].samples, rec.samples)


def test_bad_commonroad_input_names_the_file_and_writes_nothing(tmp_path, capsys):
    bad = tmp_path / "broken.xml"
    bad.write_text("<commonRoad><lanelet id='1'>")
    out = tmp_path / "data"
    assert main(["dataset", "--from-commonroad", str(bad), "--out", str(out)]) == 2
    assert "broken.xml" in capsys.readouterr().err and not out.exists()
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(RealDataError, match="empty: no CommonRoad scenario"):
        read_commonroad([empty])


def test_two_vehicles_under_one_id_in_one_recording_stay_two(tmp_path):
    changer = lambda first: obstacle_xml(501, first, 20.0, 20.0, changer_d, 100)  # noqa: E731
    a = obstacle_xml(600, 0, 100.0, 21.0, lambda t: LANE_W / 2, 50)
    b = obstacle_xml(600, 0, 150.0, 19.0, lambda t: 1.5 * LANE_W, 50)  # another car, same id, other file
    (tmp_path / "USA_Test-2_1_T-1.xml").write_text(scenario_xml("USA_Test-2_1_T-1", [changer(0), a], 901))
    (tmp_path / "USA_Test-2_2_T-1.xml").write_text(scenario_xml("USA_Test-2_2_T-1", [changer(0), b], 902))
    recordings, _ = read_commonroad([tmp_path])
    assert len(recordings) == 1
    samples = recordings[0].samples
    assert sorted(samples["vehicle_id"].unique()) == ["501", "600", "600-2"]
    assert samples.groupby("vehicle_id").size()["600"] == 50
    assert recordings[0].source["quality_reader"]["obstacle_ids_renamed"] == 1
