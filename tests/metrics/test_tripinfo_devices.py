"""Which vehicles SUMO's emission model rates, and how: moving vehicles of a rated type carry SUMO's
emissions device and are the only ones in the tripinfo file (a tripinfo device on every other
vehicle cost every step); the parked accident vehicles are rated from SUMO's per-step values
without any device, and with no moving vehicle rated SUMO writes no tripinfo at all (its output
costs every step)."""

import xml.etree.ElementTree as ET
from collections import defaultdict
from functools import partial

import libsumo
import numpy as np
import pytest

from scenario_files import SCENARIOS
from vcfusion.metrics.sumo_emissions import emission_table
from vcfusion.metrics.traffic import sumo_model_rates
from vcfusion.scenario import load_scenario
from vcfusion.traffic.session import SumoSession

# emission-output attribute -> sumo_emissions column, and its scale from SUMO's mg (Wh) to ours
EMISSION_OUTPUT = {"CO": ("co_g", 1e-3), "CO2": ("co2_g", 1e-3), "HC": ("hc_g", 1e-3), "NOx": ("nox_g", 1e-3),
                   "PMx": ("pmx_g", 1e-3), "fuel": ("fuel_g", 1e-3), "electricity": ("electricity_wh", 1.0)}


def _session(sc, tmp_path, extra=None):
    return SumoSession(sc, 0, tmp_path / "lc.xml", np.random.default_rng(0), extra,
                       (tmp_path / "tripinfo.xml", partial(sumo_model_rates, sc.metrics)))


def _with(sc, **metrics):
    return sc.model_copy(update={"metrics": sc.metrics.model_copy(update=metrics)})


def test_parked_vehicles_are_rated_without_tripinfo_as_the_sum_of_sumo_steps(tmp_path):
    sc = load_scenario(SCENARIOS / "accident.yaml")  # rated by default: the two parked trucks only
    emission = tmp_path / "emission.xml"
    # SUMO's own per-step values, with full precision (its default writes 0.01 mg/s)
    session = _session(sc, tmp_path, ["--emission-output", str(emission), "--precision", "6"])
    try:
        for _ in range(300):
            session.step()
        on_road = set(libsumo.vehicle.getIDList())
        session.finish()  # the run went to its end: the parked trucks are rated
    finally:
        session.close()
    assert session.tripinfo_file is None and not (tmp_path / "tripinfo.xml").exists()
    assert len(on_road) > 2
    table = emission_table(session.tripinfo_file, session.parked_emissions, session.emission_classes)
    assert table.column("vehicle_id").to_pylist() == ["accident0", "accident1"]
    sums: dict = defaultdict(lambda: defaultdict(float))
    steps: dict = defaultdict(int)
    for ts in ET.parse(emission).getroot().iter("timestep"):
        for v in ts.iter("vehicle"):
            steps[v.get("id")] += 1
            for attr in EMISSION_OUTPUT:
                sums[v.get("id")][attr] += float(v.get(attr)) * sc.simulation.step_s
    rows = table.to_pylist()
    for row in rows:
        vid = row["vehicle_id"]
        assert steps[vid] == 301  # on the road from the insertion step (in _populate) to the end
        assert row["emission_class"] == session.emission_classes["truck"]
        assert row["depart_s"] == 0.0 and row["route_length_m"] == 0.0
        assert row["duration_s"] == pytest.approx(3.01)
        for attr, (col, scale) in EMISSION_OUTPUT.items():
            assert row[col] == pytest.approx(sums[vid][attr] * scale, rel=1e-6, abs=1e-12), (vid, attr)
    assert rows[0]["co2_g"] > 0 and rows[0]["fuel_g"] > 0  # the insertion step's idle value


def test_moving_rated_vehicles_alone_are_in_the_tripinfo_file(tmp_path):
    sc = load_scenario(SCENARIOS / "dense.yaml")  # rated: moving truck_mixed and the parked accident trucks
    session = _session(sc, tmp_path)
    try:
        for _ in range(20):
            session.step()
        on_road = set(libsumo.vehicle.getIDList())
        types = {vid: libsumo.vehicle.getTypeID(vid) for vid in on_road}
        session.finish()
    finally:
        session.close()
    listed = {trip.get("id") for trip in ET.parse(session.tripinfo_file).getroot().iter("tripinfo")}
    assert listed == {vid for vid, vt in types.items() if vt.split("@")[0] == "truck_mixed"} and listed
    assert [row[0] for row in session.parked_emissions] == ["accident0", "accident1"]
    table = emission_table(session.tripinfo_file, session.parked_emissions, session.emission_classes)
    assert set(table.column("vehicle_id").to_pylist()) == listed | {"accident0", "accident1"}
    assert all(x > 0 for x in table.column("co2_g").to_pylist())


@pytest.mark.parametrize("setting", ["none", "others"])
def test_no_tripinfo_and_no_rows_when_sumo_rates_nothing(tmp_path, setting):
    sc = load_scenario(SCENARIOS / "accident.yaml")
    if setting == "others":  # the trucks get MOVESTAR's light-duty truck model: SUMO rates nothing
        sc = _with(sc, movestar={"passenger": 1, "truck": 2})
    else:
        sc = _with(sc, sumo_emissions="none")
    session = _session(sc, tmp_path)
    try:
        for _ in range(20):
            session.step()
    finally:
        session.close()
    assert session.tripinfo_file is None and not (tmp_path / "tripinfo.xml").exists()
    assert session.parked_emissions == []
    assert emission_table(None, [], session.emission_classes).num_rows == 0
