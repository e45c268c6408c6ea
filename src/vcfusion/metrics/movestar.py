"""MOVESTAR fuel and emission model (Wang, Wu & Scora, arXiv:2008.04986).

Implemented from the project's specification (specs/movestar.md), which follows the MATLAB
v1.1 reference: per-second operating modes (OpMode) from speed and vehicle specific power
(VSP), then USEPA MOVES base rates per OpMode summed over the trip.

Edge cases (documented behaviour):
- an empty trajectory, a negative speed, a NaN/inf speed or an unknown vehicle type raise
  :class:`ValueError` with a message saying what was expected;
- a single sample is one second of travel (a = 0 for it);
- a trajectory with zero travelled distance (e.g. all zeros: idling) gives its totals, and
  per-distance values of ``None`` (undefined: no distance to divide by).
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

POLLUTANTS = ("CO", "HC", "NOx", "PM2.5_Ele", "PM2.5_Org", "Energy", "CO2")
OUTPUT_KEYS = POLLUTANTS + ("Fuel",)
MPS_TO_MPH = 2.23693629
METERS_PER_MILE = 1609.34
KM_PER_MILE = 1.60934

# Road-load coefficients (A, B, C, M, f) for zero grade; MOVES source types 21 and 31.
ROAD_LOAD = {
    1: (0.156461, 0.002002, 0.000493, 1.4788, 1.4788),
    2: (0.22112, 0.002838, 0.000698, 1.86686, 1.86686),
}
VEHICLE_TYPE_NAMES = {1: "light-duty passenger car", 2: "light-duty truck"}

# Base rates per OpMode, per hour: CO, HC, NOx, PM2.5_Ele, PM2.5_Org (g/h), Energy (kJ/h), CO2 (g/h).
_RATES_TEXT = {
    1: """
0,1.97892,0.0953798,0.0695436,0.00522486,0.0239643,48371.4,3441.528367
1,0.341669,0.0231352,0.0294708,0.00450976,0.0206844,44749.1,3183.808967
11,6.80345,0.0650524,0.103114,0.00447462,0.0205233,70367,5006.471316
12,11.1072,0.0498479,0.157418,0.00470869,0.0215969,97164,6913.024272
13,10.2406,0.0942146,0.368511,0.0066702,0.0305935,135036,9607.541328
14,14.6935,0.128156,0.650607,0.00661505,0.0303405,170626,12139.69865
15,21.3068,0.178659,1.15309,0.00636392,0.0291887,203467,14476.27012
16,35.9513,0.285382,2.40478,0.0165839,0.0760634,245748,17484.4787
21,8.86745,0.0973768,0.203915,0.00854285,0.0391826,95730.3,6811.019384
22,11.7489,0.0894292,0.331209,0.0113997,0.0522858,108968,7752.855264
23,15.1095,0.0964139,0.500717,0.00823071,0.0377509,132716,9442.477968
24,22.0873,0.183979,0.843921,0.00906222,0.0415647,170266,12114.08537
25,25.0671,0.18329,1.18354,0.0112721,0.0517003,227221,16166.31971
27,37.6451,0.289654,1.86362,0.0180833,0.0829407,299543,21311.88536
28,127.616,1.95524,6.85885,0.0395121,0.181226,403761,28726.78763
29,270.27,3.47139,12.0423,0.189873,0.870871,553155,39355.87194
30,949.244,5.73108,15.8433,0.281271,1.29007,694644,49422.53131
33,6.65783,0.0935418,0.434612,0.0117726,0.053996,136387,9703.662276
35,11.3684,0.129899,1.19894,0.0174424,0.0800013,218699,15559.99645
37,16.7341,0.166455,1.67539,0.0133771,0.0613553,284892,20269.49602
38,116.968,1.32031,5.8239,0.0327562,0.150239,371483,26430.27248
39,123.421,1.91714,8.66952,0.0689814,0.31639,494808,35204.59958
40,362.729,2.50657,10.9191,0.0796885,0.365499,630762,44877.45478
""",
    2: """
0,2.36609,0.0391707,0.0538503,0.00131955,0.0180855,73883.5,5256.663258
1,4.05557,0.000418121,0.0089791,0.00108472,0.014867,56979.3,4053.963236
11,6.52187,0.0228921,0.146868,0.00155411,0.0213005,92164.5,6557.319846
12,2.82379,0.0208503,0.155233,0.00156658,0.0214713,115308,8203.933584
13,9.76815,0.052262,0.363034,0.00211212,0.0289484,165833,11798.68628
14,14.2137,0.0725323,0.657844,0.00271017,0.0371452,210063,14945.56232
15,20.8813,0.103686,1.18797,0.00612354,0.0839285,253242,18017.66182
16,35.9857,0.171948,2.5348,0.017956,0.246103,316272,22502.12026
21,5.8165,0.0387213,0.254133,0.00212064,0.0290653,123291,8771.908068
22,9.33417,0.0462365,0.357951,0.00208597,0.02859,132348,9416.295504
23,13.1798,0.0650499,0.508789,0.00271128,0.0371605,163386,11624.58713
24,25.9039,0.115221,0.930889,0.00293965,0.0402905,211608,15055.48598
25,18.5265,0.124367,1.52098,0.00453134,0.062106,271723,19332.548
27,34.766,0.218173,2.14235,0.00870251,0.119276,374028,26611.34414
28,200.661,3.25428,8.21223,0.0536606,0.735465,499605,35545.89654
29,216.005,4.04662,11.1418,0.0769951,1.05529,684960,48733.53408
30,969.878,7.11962,12.8433,0.245917,3.37051,807005,57416.79174
33,10.9199,0.0703704,0.41958,0.00586679,0.0804096,178086,12670.46273
35,23.846,0.0921036,1.40529,0.00900861,0.123471,272535,19390.32018
37,28.9476,0.117916,2.28006,0.00918422,0.125878,360261,25631.84963
38,68.1954,1.15714,7.50412,0.0132642,0.181797,468102,33304.5211
39,167.612,2.11771,13.3438,0.0320607,0.43942,613382,43640.90254
40,407.603,2.7341,14.3353,0.0359667,0.492955,811659,57747.91453
""",
}


def _parse_rates(text: str) -> dict[int, np.ndarray]:
    rates = {}
    for line in text.strip().splitlines():
        values = [float(x) for x in line.split(",")]
        rates[int(values[0])] = np.array(values[1:])
    return rates


RATES = {vt: _parse_rates(t) for vt, t in _RATES_TEXT.items()}
# the same rates as one array: [vehicle type, OpMode number, pollutant] (unused numbers: NaN)
_RATE_TABLE = np.full((max(RATES) + 1, max(max(r) for r in RATES.values()) + 1, len(POLLUTANTS)), np.nan)
for _vt, _rates in RATES.items():
    for _mode, _row in _rates.items():
        _RATE_TABLE[_vt, _mode] = _row
_ROAD_LOAD_ROWS = np.array([ROAD_LOAD.get(vt, (np.nan,) * 5) for vt in range(max(ROAD_LOAD) + 1)])


def _check_vehicle_type(vehicle_type) -> int:
    if isinstance(vehicle_type, bool) or vehicle_type not in ROAD_LOAD:
        raise ValueError(f"vehicle_type: expected 1 ({VEHICLE_TYPE_NAMES[1]}) or 2 ({VEHICLE_TYPE_NAMES[2]}), "
                         f"got {vehicle_type!r}")
    return int(vehicle_type)


def check_speeds(speeds_mps: Sequence[float]) -> np.ndarray:
    v = np.asarray(speeds_mps, dtype=float).reshape(-1)
    if v.size == 0:
        raise ValueError("speeds_mps: expected at least one 1 Hz speed sample, got an empty trajectory")
    bad = ~np.isfinite(v)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(f"speeds_mps: expected finite speeds in m/s, got {v[i]} at sample {i}")
    if (v < 0).any():
        i = int(np.flatnonzero(v < 0)[0])
        raise ValueError(f"speeds_mps: expected non-negative speeds in m/s, got {v[i]} at sample {i}")
    return v


def accelerations(v: np.ndarray, starts: np.ndarray | None = None) -> np.ndarray:
    """Central difference at 1 Hz; zero at the first and last second (of each trip beginning at
    `starts` in a concatenation of trips)."""
    a = np.zeros_like(v)
    if v.size >= 3:
        a[1:-1] = (v[2:] - v[:-2]) / 2.0
    if starts is not None and v.size:
        a[starts] = 0.0
        a[np.concatenate((starts[1:], [v.size])) - 1] = 0.0
    return a


def vsp(v: np.ndarray, a: np.ndarray, vehicle_type=1) -> np.ndarray:
    """Vehicle specific power (kW/tonne), zero grade; `vehicle_type` one type or one per sample."""
    types = np.asarray(vehicle_type)
    if types.ndim == 0:
        _check_vehicle_type(vehicle_type)
    A, B, C, M, f = _ROAD_LOAD_ROWS[types].T if types.ndim else _ROAD_LOAD_ROWS[types]
    return (A * v + B * v**2 + C * v**3 + M * a * v) / f


_LOW_SPEED = ((0, 3, 6, 9, 12), (11, 12, 13, 14, 15, 16))  # 1 <= mph < 25: VSP edges, modes
_MID_SPEED = ((0, 3, 6, 9, 12, 18, 24, 30), (21, 22, 23, 24, 25, 27, 28, 29, 30))  # 25 <= mph < 50
_HIGH_SPEED = ((6, 12, 18, 24, 30), (33, 35, 37, 38, 39, 40))  # mph >= 50


def _band(power: np.ndarray, band: tuple) -> np.ndarray:
    """The mode of the first VSP edge above each value (the last mode above all edges)."""
    edges, modes = band
    return np.asarray(modes)[np.searchsorted(edges, power, side="right")]


def operating_modes(v: np.ndarray, a: np.ndarray, power: np.ndarray, starts: np.ndarray | None = None) -> np.ndarray:
    """OpMode of every second (spec step 4: the first matching rule wins), all seconds at once
    (of each trip beginning at `starts` in a concatenation of trips)."""
    k = MPS_TO_MPH
    mph, accel = v * k, a * k
    braked = np.zeros(v.size, dtype=bool)  # the two seconds before both below -1 mph/s
    braked[2:] = (accel[:-2] < -1) & (accel[1:-1] < -1)
    if starts is not None:  # ... within the same trip
        first_two = np.concatenate((starts, starts + 1))
        braked[first_two[first_two < v.size]] = False
    return np.select([(accel <= -2) | braked, mph < 1, mph < 25, mph < 50],
                     [0, 1, _band(power, _LOW_SPEED), _band(power, _MID_SPEED)], _band(power, _HIGH_SPEED))


def _fuel(co2):
    return co2 * 12.0 / 44.0 * 13.78 / 12.0


def movestar_trips(v: np.ndarray, starts: np.ndarray, vehicle_types: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """MOVESTAR of many 1 Hz trips at once (the same computation as movestar()): `v` the trips'
    speeds concatenated, trip i beginning at starts[i], of type vehicle_types[i]. Returns the
    totals (trips x OUTPUT_KEYS) and the distance travelled per trip (the sum of its speeds)."""
    lengths = np.diff(np.concatenate((starts, [v.size])))
    types = np.repeat(vehicle_types, lengths)
    a = accelerations(v, starts)
    modes = operating_modes(v, a, vsp(v, a, types), starts)
    sums = np.add.reduceat(_RATE_TABLE[types, modes], starts, axis=0) / 3600.0
    return np.column_stack((sums, _fuel(sums[:, POLLUTANTS.index("CO2")]))), np.add.reduceat(v, starts)


def movestar(speeds_mps: Sequence[float], vehicle_type: int = 1) -> dict:
    """Fuel and emissions of a 1 Hz speed trajectory (m/s).

    Returns ``totals`` (g; Energy in kJ), ``per_mile`` and ``per_km`` (g/mi, g/km; ``None``
    values when the distance travelled is zero), ``TT_s``, ``TD_m``, ``opmodes``, ``vsp``.
    """
    vehicle_type = _check_vehicle_type(vehicle_type)
    v = check_speeds(speeds_mps)
    a = accelerations(v)
    power = vsp(v, a, vehicle_type)
    modes = operating_modes(v, a, power)
    sums, td = movestar_trips(v, np.array([0]), np.array([vehicle_type]))
    totals = {name: float(x) for name, x in zip(OUTPUT_KEYS, sums[0])}
    td = float(td[0])
    if td > 0:
        per_mile = {k: x * METERS_PER_MILE / td for k, x in totals.items()}
        per_km = {k: x / KM_PER_MILE for k, x in per_mile.items()}
    else:  # undefined without distance
        per_mile = {k: None for k in totals}
        per_km = {k: None for k in totals}
    return {"totals": totals, "per_mile": per_mile, "per_km": per_km, "TT_s": float(v.size), "TD_m": td,
            "opmodes": modes.tolist(), "vsp": power.tolist(), "vehicle_type": vehicle_type}


def samples_per_second(step_s: float) -> int:
    """The fewest samples a whole second holds at this period (0 < step_s <= 1): rounding down,
    so that at 0.15 s (6 or 7 per second) or 0.6 s (1 or 2) no whole second counts as partial."""
    return max(1, math.floor(1.0 / step_s + 1e-9))


def resample_to_1hz(time_s: Sequence[float], values: Sequence[float], step_s: float | None = None) -> np.ndarray:
    """Mean of the samples within each whole second, counted from the first sample.

    For samples every 0.01 s (or 0.1 s) starting at t0, second k is [t0 + k, t0 + k + 1).
    A trailing partial second (fewer samples than every whole second holds: samples_per_second)
    is dropped, so that every 1 Hz value is a full-second mean and rightly counts 1 s in MOVESTAR.
    A trajectory shorter than one second raises ValueError.
    """
    t = np.asarray(time_s, dtype=float).reshape(-1)
    x = np.asarray(values, dtype=float).reshape(-1)
    if t.size != x.size:
        raise ValueError(f"resample_to_1hz: {t.size} times but {x.size} values")
    if t.size > 1 and (np.diff(t) <= 0).any():
        raise ValueError("resample_to_1hz: expected strictly increasing sample times")
    if step_s is None:
        step_s = float(np.median(np.diff(t))) if t.size > 1 else 1.0
    if not 0 < step_s <= 1:
        raise ValueError(f"resample_to_1hz: expected a sample period in (0, 1] s, got {step_s}")
    per_second = samples_per_second(step_s)
    # The epsilon keeps float times such as 0.99999999 (for 1.0) in the right second.
    sec = np.floor(t - t[0] + 1e-6).astype(int) if t.size else np.zeros(0, dtype=int)
    counts = np.bincount(sec, minlength=1)
    sums = np.bincount(sec, weights=x, minlength=1)
    full = counts >= per_second
    if not full.any():
        raise ValueError(f"resample_to_1hz: expected at least one whole second of samples, got {t.size} "
                         f"samples every {step_s} s")
    return sums[full] / counts[full]


def trip_emissions(time_s: Sequence[float], speeds_mps: Sequence[float], vehicle_type: int = 1) -> dict:
    """MOVESTAR on a high-rate speed trajectory, resampled to 1 Hz by whole-second means."""
    return movestar(resample_to_1hz(time_s, speeds_mps), vehicle_type)


def is_undefined(value) -> bool:
    return value is None or (isinstance(value, float) and math.isnan(value))


def fuel_rate_gps(speed_mps: float, accel_mps2: float, vehicle_type: int = 1) -> float:
    """MOVESTAR's fuel rate (g/s) at one instant: the operating mode of this speed and acceleration
    (operating_modes' rules on one sample, zero grade) and its base CO2 rate, as fuel. The
    per-second trip model (movestar) takes the acceleration from the 1 Hz speeds and its braking
    mode also from the two seconds before; this is the rate of a single (v, a) sample (a
    controller's reward per tick). Plain floats: it runs once per tick."""
    import bisect

    vehicle_type = _check_vehicle_type(vehicle_type)
    v, a = float(speed_mps), float(accel_mps2)
    if not (math.isfinite(v) and v >= 0.0 and math.isfinite(a)):
        raise ValueError(f"expected a finite speed >= 0 and a finite acceleration, got {speed_mps!r}, {accel_mps2!r}")
    A, B, C, M, f = ROAD_LOAD[vehicle_type]
    power = (A * v + B * v**2 + C * v**3 + M * a * v) / f  # vsp()
    mph, accel_mph = v * MPS_TO_MPH, a * MPS_TO_MPH
    if accel_mph <= -2:
        mode = 0
    elif mph < 1:
        mode = 1
    else:
        edges, modes = _LOW_SPEED if mph < 25 else _MID_SPEED if mph < 50 else _HIGH_SPEED
        mode = modes[bisect.bisect_right(edges, power)]
    return float(_fuel(_RATE_TABLE[vehicle_type, mode, POLLUTANTS.index("CO2")] / 3600.0))
