"""SUMO's tripinfo file holds the vehicles its emission model rates, and only them: the file is
read for their totals alone, and SUMO's tripinfo device on every other vehicle cost every step."""

import xml.etree.ElementTree as ET
from functools import partial

import libsumo
import numpy as np

from scenario_files import SCENARIOS
from vcfusion.metrics.sumo_emissions import read_tripinfo_emissions
from vcfusion.metrics.traffic import sumo_model_rates
from vcfusion.scenario import load_scenario
from vcfusion.traffic.session import SumoSession


def test_tripinfo_lists_the_rated_vehicles_only(tmp_path):
    sc = load_scenario(SCENARIOS / "accident.yaml")  # trucks: the two parked accident vehicles
    tripinfo = tmp_path / "tripinfo.xml"
    session = SumoSession(sc, 0, tmp_path / "lc.xml", np.random.default_rng(0), None,
                          (tripinfo, partial(sumo_model_rates, sc.metrics)))
    try:
        for _ in range(50):
            session.step()
        on_road = set(libsumo.vehicle.getIDList())
    finally:
        session.close()
    listed = [trip.get("id") for trip in ET.parse(tripinfo).getroot().iter("tripinfo")]
    assert sorted(listed) == ["accident0", "accident1"]
    assert len(on_road) > len(listed)  # the cars were there, without a tripinfo entry
    table = read_tripinfo_emissions(tripinfo, session.emission_classes)
    assert table.column("vehicle_id").to_pylist() == ["accident0", "accident1"]
    assert all(x > 0 for x in table.column("co2_g").to_pylist())
