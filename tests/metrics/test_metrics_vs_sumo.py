"""The per-vehicle run metrics against SUMO's own outputs on the same dense run.

One run of the dense scenario with SUMO's SSM device on every vehicle (all encounters logged
with their TTC and DRAC every step), its per-step emission output, and our metrics:
- TTC and DRAC per (follower, leader) pair and sample against SSM's following encounters;
- conflict episodes per pair (the same episode rule applied to SSM's TTC series);
- SUMO emission totals (tripinfo) against the sum of SUMO's per-step emission output (within
  stated tolerances: the two integrate a step differently), and exactly for the parked accident
  vehicles (rated from SUMO's per-step values, without the device);
- MOVESTAR totals against movestar() on the vehicle's whole-second speeds.
"""

import xml.etree.ElementTree as ET
from collections import defaultdict

import numpy as np
import pandas as pd
import pytest

from scenario_files import SCENARIOS
from vcfusion.metrics.movestar import movestar, resample_to_1hz
from vcfusion.metrics.traffic import MOVESTAR_KEYS, conflict_episodes, follow_measures
from vcfusion.run import build_cosimulation
from vcfusion.scenario import load_scenario

THRESHOLD_S = 3.0  # above the 1.5 s default so that a 60 s dense run has a few dozen conflicts
FOLLOWING_FOLLOWER = 2  # SSM encounter type: the device's vehicle follows the foe in its lane


@pytest.fixture(scope="module")
def dense_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("dense")
    sc = load_scenario(SCENARIOS / "dense.yaml")
    sc = sc.model_copy(update={
        "simulation": sc.simulation.model_copy(update={"max_time_s": 60.0}),
        # SUMO's model on every vehicle, so that its totals can be checked on cars and trucks
        "metrics": sc.metrics.model_copy(update={"ttc_threshold_s": THRESHOLD_S, "sumo_emissions": "all"})})
    cosim = build_cosimulation(sc, 0)
    ssm, emission = tmp / "ssm.xml", tmp / "emission.xml"
    cosim.extra_sumo_args = [
        "--device.ssm.probability", "1", "--device.ssm.file", str(ssm), "--device.ssm.measures", "TTC DRAC",
        # thresholds no encounter stays under: every encounter is written with its full time series
        "--device.ssm.thresholds", "1000 0", "--device.ssm.trajectories", "true", "--device.ssm.range", "250",
        "--emission-output", str(emission)]
    result = cosim.run()
    return sc, result, ssm, emission


def _ssm_following(ssm_file) -> dict[tuple[str, str], dict[float, tuple[float, float]]]:
    """(follower, leader) -> {time: (TTC, DRAC)} over SSM's samples of type following-follower."""
    pairs: dict = defaultdict(dict)
    for conflict in ET.parse(ssm_file).getroot().iter("conflict"):
        times = conflict.find("timeSpan").get("values").split()
        types = conflict.find("typeSpan").get("values").split()
        ttc = conflict.find("TTCSpan").get("values").split()
        drac = conflict.find("DRACSpan").get("values").split()
        key = (conflict.get("ego"), conflict.get("foe"))
        for t, kind, a, b in zip(times, types, ttc, drac):
            if int(kind) == FOLLOWING_FOLLOWER:
                pairs[key][round(float(t), 2)] = (np.nan if a == "NA" else float(a), np.nan if b == "NA" else float(b))
    return pairs


def _our_samples(result, sc) -> pd.DataFrame:
    """Every trajectory sample with its leader and measures (the same function the metrics use)."""
    traj = result.tables["trajectories"]
    lengths = result.tables["vehicles"].set_index("vehicle_id")["length"]
    ids, code = np.unique(traj["vehicle_id"].to_numpy(), return_inverse=True)
    m = follow_measures(traj["time"].to_numpy(), traj["lane"].to_numpy(), traj["s"].to_numpy(),
                        traj["speed"].to_numpy(), code, lengths.reindex(ids).to_numpy(dtype=float),
                        sc.metrics.leader_range_m)
    leader = np.where(m["leader"] >= 0, ids[np.maximum(m["leader"], 0)], "")
    return pd.DataFrame({"time": np.round(m["time"], 2), "vehicle_id": ids[code], "leader_id": leader,
                         "ttc": m["ttc"], "drac": m["drac"]})


@pytest.mark.slow
def test_ttc_drac_and_conflicts_match_sumo_ssm(dense_run):
    sc, result, ssm_file, _ = dense_run
    ssm = _ssm_following(ssm_file)
    ours = _our_samples(result, sc)
    ours = ours[ours["leader_id"] != ""]
    ttc_pairs, drac_pairs = [], []
    for (follower, leader), g in ours.groupby(["vehicle_id", "leader_id"]):
        theirs = ssm.get((follower, leader), {})
        for t, ttc, drac in zip(g["time"], g["ttc"], g["drac"]):
            if t not in theirs:
                continue
            a, b = theirs[t]
            if np.isfinite(ttc) and np.isfinite(a):
                ttc_pairs.append((ttc, a))
                drac_pairs.append((drac, b))
    assert len(ttc_pairs) > 2000, len(ttc_pairs)
    print(f"{len(ttc_pairs)} samples with a TTC on both sides")
    ours_ttc, sumo_ttc = np.array(ttc_pairs).T
    near = sumo_ttc < 30.0  # beyond, TTC is the ratio of two small numbers: compare the range that matters
    rel = np.abs(ours_ttc - sumo_ttc) / sumo_ttc
    # SSM writes two decimals: 0.005 s of rounding is 0.3 % at 1.5 s
    print(f"TTC < 30 s: median relative difference {np.median(rel[near]):.2e}, 95th percentile "
          f"{np.percentile(rel[near], 95):.2e}")
    assert np.median(rel[near]) < 0.005, np.median(rel[near])
    assert np.percentile(rel[near], 95) < 0.02, np.percentile(rel[near], 95)
    ours_drac, sumo_drac = np.array(drac_pairs).T
    big = sumo_drac > 0.1
    assert np.median(np.abs(ours_drac[big] - sumo_drac[big]) / sumo_drac[big]) < 0.01
    assert np.percentile(np.abs(ours_drac[big] - sumo_drac[big]), 95) < 0.02 + 0.02 * sumo_drac[big].mean()

    # conflicts: the same episode rule on SSM's TTC series of each pair gives the same count
    ours_count = result.tables["conflicts"].groupby(["vehicle_id", "leader_id"]).size().to_dict()
    theirs_count, theirs_min = {}, {}
    for pair, samples in ssm.items():
        times = sorted(samples)
        ttc = np.array([samples[t][0] for t in times])
        # a gap in SSM's samples of the pair ends an episode, as a change of leader ends ours
        segment = np.cumsum(np.r_[0, np.diff(times) > 0.11])
        n = len(conflict_episodes(ttc, segment, THRESHOLD_S))
        if n:
            theirs_count[pair] = n
            theirs_min[pair] = np.nanmin(ttc)
    assert sum(ours_count.values()) >= 20, ours_count
    differ = {p for p in set(ours_count) | set(theirs_count) if ours_count.get(p, 0) != theirs_count.get(p, 0)}
    # a pair may differ only where its TTC grazes the threshold (SSM rounds to 0.01 s)
    grazing = {p for p in differ if abs(theirs_min.get(p, THRESHOLD_S) - THRESHOLD_S) < 0.05}
    assert len(differ - grazing) <= max(1, 0.05 * len(ours_count)), sorted(differ - grazing)
    total_ours, total_theirs = sum(ours_count.values()), sum(theirs_count.values())
    print(f"conflicts: ours {total_ours}, SSM {total_theirs}; pairs differing {len(differ)} ({len(grazing)} grazing)")
    assert abs(total_ours - total_theirs) <= 0.05 * total_theirs + 1, (total_ours, total_theirs)
    # the metrics table counts exactly the episodes of the conflicts table
    per_vehicle = result.tables["metrics"].set_index("vehicle_id")["conflicts"]
    assert per_vehicle.sum() == len(result.tables["conflicts"])


@pytest.mark.slow
def test_sumo_emission_totals_are_the_sum_of_sumo_steps(dense_run):
    sc, result, _, emission_file = dense_run
    step = sc.simulation.step_s
    sums: dict = defaultdict(lambda: defaultdict(float))
    first: dict = {}
    first_values: dict = {}
    classes: dict = {}
    for ts in ET.parse(emission_file).getroot().iter("timestep"):
        for v in ts.iter("vehicle"):
            vid = v.get("id")
            classes[vid] = v.get("eclass")
            if vid not in first:  # the insertion step: the device counts from the next one
                first[vid] = float(ts.get("time"))
                first_values[vid] = {attr: float(v.get(attr)) * step / 1000.0
                                     for attr in ("CO", "CO2", "HC", "NOx", "PMx", "fuel")}
                continue
            for attr in ("CO", "CO2", "HC", "NOx", "PMx", "fuel"):
                sums[vid][attr] += float(v.get(attr)) * step / 1000.0  # mg/s -> g
    table = result.tables["sumo_emissions"].set_index("vehicle_id")
    totals = defaultdict(lambda: np.zeros(2))
    assert len(table) > 60 and set(table.index) == set(first)
    for vid, row in table.iterrows():
        assert row["emission_class"] == classes[vid]
        columns = (("CO", "co_g"), ("CO2", "co2_g"), ("HC", "hc_g"), ("NOx", "nox_g"), ("PMx", "pmx_g"),
                   ("fuel", "fuel_g"))
        if vid.startswith("accident"):
            # parked at their stop from the first step, rated without SUMO's device: exactly the sum
            # of the emission output over every step, the insertion step's idle value included (the
            # output's 0.01 mg/s rounding apart)
            assert row["co2_g"] > 0
            for attr, col in columns:
                assert row[col] == pytest.approx(first_values[vid][attr] + sums[vid][attr], rel=1e-6, abs=1e-6)
            continue
        for attr, col in columns:
            # SUMO's device integrates each step at the step's mean speed over the time actually
            # moved, the emission output rates the speed at the step's end: they differ by < 0.5 %
            # per vehicle in free flow and < 1 % in stop-and-go (measured with --precision 6)
            assert row[col] == pytest.approx(sums[vid][attr], rel=0.015, abs=1e-3), (vid, attr)
            totals[col] += (row[col], sums[vid][attr])
    for col, (ours, theirs) in totals.items():
        assert ours == pytest.approx(theirs, rel=2e-3), col  # over all vehicles: within 0.2 %
    # trucks get SUMO's model; MOVESTAR only the light-duty types
    metrics = result.tables["metrics"].set_index("vehicle_id")
    trucks = metrics[metrics["vclass"] == "truck"]
    assert len(trucks) and trucks["sumo_co2_g"].notna().all() and (trucks["movestar_type"] == 0).all()
    assert trucks["movestar_fuel_g"].isna().all()
    moving = metrics[metrics["distance_m"] > 0]
    assert np.allclose(moving["sumo_co2_g_per_km"], moving["sumo_co2_g"] / (moving["distance_m"] / 1000.0))


@pytest.mark.slow
def test_movestar_totals_equal_movestar_on_whole_second_speeds(dense_run):
    sc, result, _, _ = dense_run
    traj = result.tables["trajectories"]
    metrics = result.tables["metrics"].set_index("vehicle_id")
    checked = 0
    for vid, g in traj.groupby("vehicle_id"):
        row = metrics.loc[vid]
        if row["movestar_type"] == 0 or row["movestar_seconds"] == 0:
            continue
        g = g.sort_values("time")
        em = movestar(resample_to_1hz(g["time"].to_numpy(), g["speed"].to_numpy()), int(row["movestar_type"]))
        totals = em["totals"]
        for key, name in MOVESTAR_KEYS.items():
            expected = totals["PM2.5_Ele"] + totals["PM2.5_Org"] if key == "PM2.5" else totals[key]
            assert row[f"movestar_{name}"] == pytest.approx(expected, rel=1e-12), (vid, key)
        assert row["movestar_seconds"] == em["TT_s"]
        if em["TD_m"] > 0:
            assert row["movestar_fuel_g_per_km"] == pytest.approx(em["per_km"]["Fuel"], rel=1e-12)
        checked += 1
    assert checked > 50


@pytest.mark.slow
def test_by_default_sumo_rates_the_vehicles_movestar_does_not():
    sc = load_scenario(SCENARIOS / "dense.yaml")
    sc = sc.model_copy(update={"simulation": sc.simulation.model_copy(update={"max_time_s": 15.0})})
    result = build_cosimulation(sc, 1).run()
    m = result.tables["metrics"].set_index("vehicle_id")
    trucks, cars = m[m["vclass"] == "truck"], m[m["vclass"] == "passenger"]
    assert len(trucks) >= 4 and len(cars) > 30
    assert trucks["sumo_co2_g"].notna().all() and trucks["movestar_fuel_g"].isna().all()
    assert cars["sumo_co2_g"].isna().all() and (cars["movestar_seconds"] > 0).all()
    rated = set(result.tables["sumo_emissions"].query("co2_g > 0 or fuel_g > 0")["vehicle_id"])
    assert rated == set(trucks.index)
    traffic = result.summary["metrics"]["traffic"]
    counted_trucks = trucks[trucks["counted"]]
    grams = cars["movestar_fuel_g"].sum() + counted_trucks["sumo_fuel_g"].sum()
    km = cars["movestar_distance_m"].sum() / 1000 + counted_trucks["distance_m"].sum() / 1000
    assert traffic["fuel_g_per_km"] == pytest.approx(grams / km)
    assert traffic["sumo_fuel_g_per_km"] > traffic["movestar_fuel_g_per_km"]  # trucks burn more per km
