"""Shipped scenarios by name, `vcfusion scenarios`, `vcfusion --version`, and `build-net` when the
networks are an installed package's (package data found with importlib.resources)."""

import re
from pathlib import Path

import pytest

from scenario_files import REPO
from vcfusion import resources
from vcfusion.commands import main
from vcfusion.errors import ScenarioError
from vcfusion.scenario import find_scenario, load_scenario


def test_the_package_data_is_the_checkouts_scenarios_and_networks():
    # in a checkout the package's data folders are the top-level ones (linked), not copies
    assert resources.scenarios_dir() == (REPO / "scenarios").resolve()
    assert resources.networks_dir() == (REPO / "sumo_net").resolve()
    assert resources.networks_dir_is_checkout()
    assert (resources.assets_dir() / "detector.pt").is_file()
    files = sorted((REPO / "scenarios").rglob("*.yaml"))
    assert list(resources.shipped_scenarios().values()) == [p.resolve() for p in files]
    assert "families/dense" in resources.shipped_scenarios()


def test_a_shipped_scenario_by_name_from_another_folder(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    scenario = load_scenario("accident")
    assert scenario.name == "accident" and scenario.source == (REPO / "scenarios" / "accident.yaml").resolve()
    # its network and vehicle types are found relative to the file, not to the working directory
    assert scenario.network == (REPO / "sumo_net" / "highway.net.xml").resolve()
    assert scenario.vehicle_types == (REPO / "sumo_net" / "vtypes.add.xml").resolve()
    assert load_scenario("families/dense").name == "family_dense"  # extends ../dense.yaml


def test_a_file_of_that_name_comes_before_the_shipped_scenario(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "accident").write_text("name: mine\n")
    assert find_scenario("accident") == Path("accident")
    with pytest.raises(ScenarioError, match=r"^accident: network: required field is missing"):
        load_scenario("accident")  # the file here, not the shipped scenario


def test_neither_a_file_nor_a_shipped_name_lists_the_shipped_names(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    expected = (r"^acident: scenario file not found \(expected a scenario file, or the name of a shipped scenario: "
                r"accident, accident_ar, .*, overlap_platoons\)$")
    with pytest.raises(ScenarioError, match=expected):
        find_scenario("acident")
    assert main(["run", "acident"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: acident: scenario file not found") and "families/dense" in err
    assert not (tmp_path / "runs").exists()
    # a path with a .yaml suffix is a file only: accident.yaml here is not the shipped one
    with pytest.raises(ScenarioError, match=r"^accident.yaml: scenario file not found"):
        find_scenario("accident.yaml")


def test_scenarios_lists_every_shipped_scenario_with_its_description(capsys):
    assert main(["scenarios"]) == 0
    lines = capsys.readouterr().out.splitlines()
    rows = {m.group(1): m.group(2) for m in (re.match(r"^  (\S+)\s+(.*)$", line) for line in lines[1:]) if m}
    assert list(rows) == list(resources.shipped_scenarios())
    # the scenario's own description field, else its leading comment
    assert rows["accident"].startswith("Accident lane closure (paper Table II): two stopped trucks block lanes 0 and 1")
    assert rows["families/dense"].startswith('Lane-change dataset family "dense"')
    assert all(rows.values())


def test_version_comes_from_the_distribution(capsys):
    from importlib import metadata

    with pytest.raises(SystemExit) as exit_:
        main(["--version"])
    assert exit_.value.code == 0
    assert capsys.readouterr().out.strip() == f"vcfusion {metadata.version('vcfusion')}"


def test_build_net_of_an_installed_package_needs_a_folder(monkeypatch, capsys):
    monkeypatch.setattr(resources, "networks_dir_is_checkout", lambda: False)
    before = {p.name: p.stat().st_mtime_ns for p in resources.networks_dir().iterdir()}
    assert main(["build-net"]) == 2
    assert capsys.readouterr().err.startswith("error: --net-dir: required when vcfusion is installed")
    assert {p.name: p.stat().st_mtime_ns for p in resources.networks_dir().iterdir()} == before
