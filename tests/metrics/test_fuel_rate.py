"""metrics.movestar.fuel_rate_gps: one (speed, acceleration) sample through MOVESTAR's rules."""

import numpy as np
import pytest

from vcfusion.metrics.movestar import _RATE_TABLE, POLLUTANTS, _fuel, movestar, operating_modes, vsp
from vcfusion.metrics.movestar import fuel_rate_gps


@pytest.mark.parametrize("vehicle_type", [1, 2])
def test_the_rate_is_the_one_of_the_trip_models_operating_mode_for_the_sample(vehicle_type):
    speeds = np.linspace(0.0, 40.0, 81)
    accels = np.linspace(-4.0, 3.0, 57)
    co2 = POLLUTANTS.index("CO2")
    for v in speeds:
        for a in accels:  # each sample a trip of its own (the braking rule looks at earlier seconds)
            va, aa = np.array([v]), np.array([a])
            mode = operating_modes(va, aa, vsp(va, aa, vehicle_type))[0]
            assert fuel_rate_gps(v, a, vehicle_type) == pytest.approx(
                _fuel(_RATE_TABLE[vehicle_type, mode, co2] / 3600.0), rel=1e-12), (v, a)


def test_at_a_steady_speed_it_is_the_trip_models_fuel_per_second():
    assert fuel_rate_gps(19.0, 0.0) == pytest.approx(movestar([19.0] * 10)["totals"]["Fuel"] / 10, rel=1e-12)
    assert fuel_rate_gps(19.0, 1.0) > fuel_rate_gps(19.0, 0.0) > fuel_rate_gps(19.0, -3.0) > 0


def test_a_bad_sample_is_refused():
    with pytest.raises(ValueError, match="finite speed >= 0"):
        fuel_rate_gps(-1.0, 0.0)
    with pytest.raises(ValueError, match="finite"):
        fuel_rate_gps(10.0, float("nan"))
