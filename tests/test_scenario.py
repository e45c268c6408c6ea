import subprocess
import sys

import pytest

from scenario_files import write_scenario
from vcfusion.scenario import ScenarioError, load_scenario

BASE = """
name: t
network: NET_DIR/highway.net.xml
vehicle_types: NET_DIR/vtypes.add.xml
ego: {lane: 2, depart_pos_m: 50, speed_mps: 19}
"""


def test_accident_is_table_ii(accident_path):
    sc = load_scenario(accident_path)
    assert sc.simulation.step_s == 0.01
    assert sc.v2c.period_s == 0.1
    assert sc.ar.period_s == 0.1
    assert sc.ego.trip_distance_m == 300
    assert sc.ego.speed_mps == 19
    assert sum(g.count for g in sc.vehicles) == 6
    changers = [g for g in sc.vehicles if set(g.lanes) <= set(sc.accident.lanes) and max(g.pos_m) < sc.accident.pos_m]
    assert sum(g.count for g in changers) == 3
    assert all(g.speed_mps == 17 for g in sc.vehicles)
    assert sc.network.is_file() and sc.vehicle_types.is_file()


@pytest.mark.parametrize(
    "extra, field, expected",
    [
        ("colour: red\n", "colour", "unknown key"),
        ("v2c: {latency_s: -0.3}\n", "v2c.latency_s", "greater than or equal to 0"),
        ("v2c: {latency_s: soon}\n", "v2c.latency_s", "valid number"),
        ("v2c: {loss_probability: 1.5}\n", "v2c.loss_probability", "less than or equal to 1"),
        ("vehicles: [{name: a, count: 2, lanes: [0], pos_m: [90, 10]}]\n", "vehicles[0].pos_m", "low <= high"),
        ("simulation: {step_s: 0.03}\n", "v2c.period_s", "whole multiple"),
    ],
)
def test_malformed_scenario_names_file_and_field(tmp_path, extra, field, expected):
    path = write_scenario(tmp_path, BASE + extra)
    with pytest.raises(ScenarioError) as err:
        load_scenario(path)
    msg = str(err.value)
    assert str(path) in msg and field in msg and expected in msg


def test_missing_files(tmp_path):
    with pytest.raises(ScenarioError, match="scenario file not found"):
        load_scenario(tmp_path / "nope.yaml")
    path = write_scenario(tmp_path, BASE.replace("highway.net.xml", "missing.net.xml"))
    with pytest.raises(ScenarioError, match=r"network: file not found: .*missing.net.xml"):
        load_scenario(path)


def test_cli_rejects_bad_scenario_without_run_folder(tmp_path):
    path = write_scenario(tmp_path, BASE + "v2c: {latency_s: -1}\n")
    out = tmp_path / "run"
    proc = subprocess.run([sys.executable, "-m", "vcfusion", "run", str(path), "--out", str(out)],
                          capture_output=True, text=True)
    assert proc.returncode == 2
    assert "v2c.latency_s" in proc.stderr and str(path) in proc.stderr
    assert proc.stderr.count("error:") == 1
    assert not out.exists()
    assert not list(tmp_path.glob("run*"))
