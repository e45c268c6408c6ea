import re
import subprocess
import sys

import pytest

from scenario_files import REPO, write_scenario
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
        ("simulation: {trajectory_period_s: 2.0}\n", "simulation.trajectory_period_s", "at most 1 s"),
        ("v2c: {latency_s: 2.8, jitter_s: 0.2}\n", "v2c.twin_timeout_s", "more than latency_s + 3 jitter_s"),
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


# --- extends: a scenario merged over its base -------------------------------------------------

def test_accident_ar_holds_only_what_differs_from_accident(accident_path):
    """The shipped variant extends the paper's scenario: same traffic, the vision stages on."""
    base, ar = load_scenario(accident_path), load_scenario(accident_path.with_name("accident_ar.yaml"))
    assert ar.chain == (accident_path.with_name("accident_ar.yaml"), accident_path.with_name("accident.yaml"))
    same = {k: v for k, v in base.to_dict().items() if k not in ("name", "description", "ar", "vision", "fusion")}
    assert {k: ar.to_dict()[k] for k in same} == same
    assert ar.ar.period_s == base.ar.period_s == 0.1  # merged key by key into the base's ar block
    assert ar.ar.video and ar.fusion.enabled and ar.vision.enabled and not base.fusion.enabled
    assert "vehicles" not in __import__("yaml").safe_load(accident_path.with_name("accident_ar.yaml").read_text())


def test_extends_merges_mappings_and_replaces_lists_along_a_chain(tmp_path):
    (tmp_path / "sub").mkdir()
    write_scenario(tmp_path, BASE + "v2c: {latency_s: 0.2, jitter_s: 0.01}\n"
                   "vehicles: [{name: a, count: 2, lanes: [0, 1], pos_m: [80, 120]}]\n", "base.yaml")
    write_scenario(tmp_path, "extends: ../base.yaml\nname: middle\nv2c: {jitter_s: 0.02, gnss_noise_std_m: 0.5}\n"
                   "vehicles: [{name: b, count: 1, lanes: [2], pos_m: [90, 95]}]\n", "sub/middle.yaml")
    leaf = write_scenario(tmp_path, "extends: sub/middle.yaml\nv2c: {latency_s: 0.1}\n", "leaf.yaml")
    sc = load_scenario(leaf)
    assert sc.name == "middle"  # not set in the leaf: from its base
    # mappings merge key by key through the chain: each key from the last file that sets it
    assert (sc.v2c.latency_s, sc.v2c.jitter_s, sc.v2c.gnss_noise_std_m) == (0.1, 0.02, 0.5)
    assert sc.v2c.period_s == 0.1  # set by no file: the default
    # a list replaces the base's list as a whole
    assert [(g.name, g.count, g.lanes) for g in sc.vehicles] == [("b", 1, [2])]
    assert sc.ego.lane == 2 and sc.network.name == "highway.net.xml"
    assert sc.chain == (leaf, tmp_path / "sub" / "middle.yaml", tmp_path / "sub" / ".." / "base.yaml")
    # the run manifest records the merged scenario and the chain of files
    from vcfusion.run import manifest_for

    manifest = manifest_for(sc, 3)
    assert manifest["scenario"]["v2c"]["jitter_s"] == 0.02 and manifest["scenario"]["name"] == "middle"
    assert manifest["scenario_chain"] == [str(p) for p in sc.chain] and manifest["scenario_file"] == str(leaf)


def test_extends_resolves_paths_against_the_file_that_names_them(tmp_path):
    """A base in another folder keeps its relative network path; a variant's own paths are its own."""
    import shutil

    (tmp_path / "net").mkdir()
    (tmp_path / "scen").mkdir()
    shutil.copy(REPO / "sumo_net" / "highway.net.xml", tmp_path / "net" / "road.net.xml")
    shutil.copy(REPO / "sumo_net" / "vtypes.add.xml", tmp_path / "scen" / "types.add.xml")
    (tmp_path / "net" / "base.yaml").write_text("name: b\nnetwork: road.net.xml\nvehicle_types: ../scen/types.add.xml\n"
                                                "ego: {lane: 1}\n")
    (tmp_path / "scen" / "v.yaml").write_text("extends: ../net/base.yaml\nvehicle_types: types.add.xml\n")
    sc = load_scenario(tmp_path / "scen" / "v.yaml")
    assert sc.network == tmp_path / "net" / "road.net.xml"
    assert sc.vehicle_types == tmp_path / "scen" / "types.add.xml"


def test_extends_errors_name_the_file_the_bad_field_came_from(tmp_path):
    write_scenario(tmp_path, BASE + "v2c: {latency_s: -1}\n", "base.yaml")
    leaf = write_scenario(tmp_path, "extends: base.yaml\nsimulation: {stepp_s: 0.01}\n", "leaf.yaml")
    with pytest.raises(ScenarioError) as err:
        load_scenario(leaf)
    lines = sorted(str(err.value).splitlines())  # one line per problem, each naming its own file
    assert len(lines) == 2
    assert lines[0].startswith(f"{tmp_path / 'base.yaml'} (extended by {leaf}): v2c.latency_s: ")
    assert lines[1].startswith(f"{leaf}: simulation.stepp_s: unknown key")
    # a field the leaf overrides is the leaf's; a check across fields names the field's file
    write_scenario(tmp_path, "extends: base.yaml\nv2c: {latency_s: 0.0, period_s: 0.015}\n", "leaf2.yaml")
    with pytest.raises(ScenarioError, match=r"leaf2.yaml: v2c.period_s: expected a whole multiple") as err:
        load_scenario(tmp_path / "leaf2.yaml")
    assert "base.yaml" not in str(err.value)
    write_scenario(tmp_path, BASE.replace("lane: 2", "lane: 7"), "base3.yaml")
    (tmp_path / "leaf3.yaml").write_text("extends: base3.yaml\nname: x\n")
    with pytest.raises(ScenarioError, match=r"base3.yaml \(extended by .*leaf3.yaml\): ego.lane: expected a lane"):
        load_scenario(tmp_path / "leaf3.yaml")


@pytest.mark.parametrize("files, start, expected", [
    ({"a.yaml": "extends: a.yaml\nname: a\n"}, "a.yaml", r"a.yaml: extends: a.yaml makes a cycle"),
    ({"a.yaml": "extends: b.yaml\n", "b.yaml": "extends: c.yaml\n", "c.yaml": "extends: a.yaml\n"}, "a.yaml",
     r"c.yaml: extends: a.yaml makes a cycle \(.*a.yaml -> .*b.yaml -> .*c.yaml -> .*a.yaml\)"),
    ({"a.yaml": "extends: missing.yaml\nname: a\n"}, "a.yaml",
     r"a.yaml: extends: file not found: missing.yaml \(relative to the scenario file\)"),
    ({"a.yaml": "extends: b.yaml\n", "b.yaml": "extends: gone/base.yaml\n"}, "a.yaml",
     r"b.yaml: extends: file not found: gone/base.yaml"),
    ({"a.yaml": "extends: [b.yaml]\n"}, "a.yaml", r"a.yaml: extends: expected the path of a base scenario file"),
    ({"a.yaml": "extends: b.yaml\n", "b.yaml": "name: [unclosed\n"}, "a.yaml", r"b.yaml: line 2, column 1: not valid YAML"),
])
def test_extends_refuses_cycles_missing_bases_and_bad_values(tmp_path, files, start, expected):
    for name, text in files.items():
        (tmp_path / name).write_text(text)
    with pytest.raises(ScenarioError, match=expected):
        load_scenario(tmp_path / start)


def test_ids_are_the_text_written_even_where_yaml_would_read_a_boolean_or_a_number(tmp_path):
    """OSM and netconvert name edges `123456` or `0123`, and a ramp may be called `off`: YAML 1.1
    reads those as 123456, 83 (octal) and False. A route or vType id is the text written; a
    true/false field still takes yes / off."""
    net = (REPO / "sumo_net" / "onramp.net.xml").read_text()
    for old, new in (("main_in", "0123"), ("main_out", "1e3"), ("accel", "off")):
        net = re.sub(rf"\b{old}\b", new, net)
    (tmp_path / "n.net.xml").write_text(net)
    vtypes = (REPO / "sumo_net" / "vtypes.add.xml").read_text().replace('id="car"', 'id="7"')
    (tmp_path / "v.add.xml").write_text(vtypes)
    path = write_scenario(tmp_path, """
name: 2026
network: n.net.xml
vehicle_types: v.add.xml
route: [0123, off, 1e3]
simulation: {max_time_s: 60}
vehicles:
  - {name: 1, count: 2, vtype: 7, lanes: [1], pos_m: [10, 300], speed_mps: 20.0}
  - {name: ramp, count: 1, vtype: 7, route: [ramp, off, 1e3], lanes: [0], pos_m: [10, 200], speed_mps: 20.0}
metrics: {enabled: off, exclude_groups: [1]}
prediction: {enabled: no}
""")
    s = load_scenario(path)
    assert s.name == "2026"
    assert s.route == ["0123", "off", "1e3"]
    assert s.vehicles[1].route == ["ramp", "off", "1e3"]
    assert (s.vehicles[0].name, s.vehicles[0].vtype, s.metrics.exclude_groups) == ("1", "7", ["1"])
    assert s.metrics.enabled is False and s.prediction.enabled is False
    assert s.simulation.max_time_s == 60.0 and type(s.vehicles[0].count) is int
