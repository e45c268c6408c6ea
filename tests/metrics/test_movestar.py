"""MOVESTAR against the spec's published reference vector and its edge cases."""

import math

import numpy as np
import pytest

from vcfusion.metrics.movestar import movestar, resample_to_1hz, trip_emissions, vsp

REF_SPEEDS = [31, 31.5, 31.8, 32, 32.1, 32.2, 32.3, 32.1, 31.9, 31.7, 31.5, 30, 28.5, 27,
              28.3, 28.8, 29.3, 29.8, 30.3, 30.8, 31.3, 30.8, 31.1, 30.6, 30.2, 29.8, 29.4, 30, 30.2, 30.5]
REF_OPMODES = [37, 39, 38, 38, 38, 38, 37, 35, 35, 35, 33, 0, 0, 0, 40, 39, 39, 39, 39, 39, 37, 35,
               35, 33, 33, 33, 37, 39, 38, 37]
REF_TOTALS = {"CO": 0.551277, "HC": 0.00685283, "NOx": 0.0325122, "PM2.5_Ele": 0.000262,
              "PM2.5_Org": 0.00120169, "Energy": 2544.57, "CO2": 181.041, "Fuel": 56.6988}
REF_PER_MILE = {"CO": 0.967705, "HC": 0.0120294, "NOx": 0.0570716, "PM2.5_Ele": 0.000459913,
                "PM2.5_Org": 0.00210943, "Energy": 4466.71, "CO2": 317.797, "Fuel": 99.5283}


def test_reference_vector_opmodes_and_vsp():
    out = movestar(REF_SPEEDS, vehicle_type=1)
    assert out["opmodes"] == REF_OPMODES
    assert [round(x, 6) for x in out["vsp"][:3]] == [14.512562, 27.696127, 23.404136]
    assert round(float(vsp(np.array([31.0]), np.array([0.0]))[0]), 6) == 14.512562


def test_reference_vector_totals_and_per_mile_to_printed_precision():
    out = movestar(REF_SPEEDS, vehicle_type=1)
    for key, ref in REF_TOTALS.items():
        # The reference printed 6 significant digits (0.000262 = 0.000262000): compare as printed.
        assert f"{out['totals'][key]:.6g}" == f"{ref:.6g}", key
    for key, ref in REF_PER_MILE.items():
        assert f"{out['per_mile'][key]:.6g}" == f"{ref:.6g}", key
    assert out["TT_s"] == 30
    assert f"{out['TD_m'] / 1609.34:.7g}" == "0.5696745"
    assert out["per_km"]["Fuel"] == pytest.approx(out["per_mile"]["Fuel"] / 1.60934)


def test_all_zero_trajectory_has_totals_and_undefined_per_distance():
    out = movestar([0.0] * 10)
    assert out["opmodes"] == [1] * 10
    assert out["TD_m"] == 0.0
    assert out["totals"]["CO2"] == pytest.approx(10 * 3183.808967 / 3600)
    assert all(v is None for v in out["per_km"].values())
    assert all(v is None for v in out["per_mile"].values())


def test_single_sample_is_one_second_without_acceleration():
    out = movestar([20.0])
    assert out["TT_s"] == 1 and out["TD_m"] == 20.0
    # 20 m/s = 44.7 mph, a = 0: VSP = (A v + B v^2 + C v^3) / f = 5.32 -> [3, 6) in 25-50 mph
    assert out["vsp"][0] == pytest.approx((0.156461 * 20 + 0.002002 * 400 + 0.000493 * 8000) / 1.4788)
    assert out["opmodes"] == [23]


@pytest.mark.parametrize("bad, match", [([10, -0.1, 10], "non-negative"), ([10, float("nan")], "finite"),
                                        ([], "at least one")])
def test_bad_speeds_raise_clear_errors(bad, match):
    with pytest.raises(ValueError, match=match):
        movestar(bad)


@pytest.mark.parametrize("vt", [0, 3, "1", True])
def test_unknown_vehicle_type(vt):
    with pytest.raises(ValueError, match="vehicle_type"):
        movestar([10.0], vehicle_type=vt)


def test_truck_differs_from_car():
    car, truck = movestar(REF_SPEEDS, 1), movestar(REF_SPEEDS, 2)
    assert truck["totals"]["CO2"] > car["totals"]["CO2"]


def test_opmode_band_edges():
    k = 2.23693629
    # exactly 25 mph is in the 25-50 band, exactly 1 mph is not idle
    assert movestar([25 / k])["opmodes"] == [22]
    assert movestar([1 / k])["opmodes"] == [12]
    assert movestar([0.99 / k])["opmodes"] == [1]
    # braking: a <= -2 mph/s at the middle sample
    assert movestar([10, 9, 10 - 4 / k])["opmodes"][1] == 0


def test_resample_averages_whole_seconds_and_drops_partial_tail():
    t = np.round(np.arange(1, 251) * 0.01, 2)  # 2.5 s of 0.01 s samples
    v = np.where(t < 1.005, 10.0, 20.0)
    out = resample_to_1hz(t, v)
    assert out.tolist() == [10.0, 20.0]
    t10 = np.round(np.arange(0, 30) * 0.1, 1)
    assert resample_to_1hz(t10, t10).tolist() == pytest.approx([0.45, 1.45, 2.45])
    with pytest.raises(ValueError, match="whole second"):
        resample_to_1hz([0.0, 0.1], [1.0, 2.0])


def test_trip_emissions_constant_speed_matches_1hz_input():
    t = np.round(np.arange(0, 1000) * 0.01, 2)
    a = trip_emissions(t, np.full(t.size, 19.0))
    b = movestar([19.0] * 10)
    assert a["totals"] == b["totals"] and not math.isnan(a["per_km"]["Fuel"])
