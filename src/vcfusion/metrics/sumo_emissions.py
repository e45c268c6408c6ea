"""SUMO's own emission model (HBEFA / PHEMlight, as the vehicle types configure it), per vehicle.

The vehicles the scenario's `metrics.sumo_emissions` names (default: those MOVESTAR does not rate)
carry SUMO's emissions device (SumoSession); their trip totals come from SUMO's tripinfo output
(`--tripinfo-output.write-unfinished`: vehicles still on the road when the run ends are
included). SUMO's device adds each step after the insertion step at the step's mean speed over
the time the vehicle moved; SUMO's per-step `--emission-output` rates the speed at the step's
end (and also lists the insertion step): the two agree within 0.5 % per vehicle in free flow,
1 % in stop-and-go and 0.2 % over all vehicles (tests/metrics).

The parked accident vehicles (of a type no moving vehicle has) carry no device: SUMO rates a
stopped vehicle the same every step (0 by its models, after the insertion step's idle value), so
SumoSession reads their per-step values at the insertion step and at the end and sums them over
the steps: exactly the sum of the emission output. When no moving vehicle is rated, SUMO writes
no tripinfo at all (its per-step cost is the largest part of the metrics'; docs/performance.md).

SUMO writes mg (fuel in mg since SUMO 1.14) and Wh; the table here is in grams and Wh.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import pyarrow as pa

# tripinfo <emissions> attribute -> column of the sumo_emissions table (mg -> g)
POLLUTANT_COLUMNS = {"CO_abs": "co_g", "CO2_abs": "co2_g", "HC_abs": "hc_g", "NOx_abs": "nox_g",
                     "PMx_abs": "pmx_g", "fuel_abs": "fuel_g"}
COLUMNS = ["vehicle_id", "vtype", "emission_class", "depart_s", "duration_s", "route_length_m",
           *POLLUTANT_COLUMNS.values(), "electricity_wh"]


def emission_table(tripinfo_file: Path | None, parked: list[tuple], emission_classes: dict[str, str]) -> pa.Table:
    """The run's sumo_emissions table: the tripinfo file's vehicles (None: no file) and the parked
    vehicles' rows (SumoSession.parked_emissions: id, vType, depart, duration, distance, then the
    totals in mg and Wh), sorted by vehicle id."""
    rows = _tripinfo_rows(tripinfo_file, emission_classes) if tripinfo_file is not None else []
    rows += [(vid, vtype, emission_classes.get(vtype, ""), depart, duration, distance,
              *(x / 1000.0 for x in totals[:-1]), totals[-1])
             for vid, vtype, depart, duration, distance, *totals in parked]
    return _table(rows)


def _tripinfo_rows(tripinfo_file: Path, emission_classes: dict[str, str]) -> list[tuple]:
    """One row per vehicle of the tripinfo file: its emission class (by vType) and totals (g, Wh)."""
    rows = []
    for trip in ET.parse(tripinfo_file).getroot().iter("tripinfo"):
        em = trip.find("emissions")
        if em is None:  # a vehicle without the device: nothing to report for it
            continue
        vtype = trip.get("vType")
        # a vehicle whose speed limit the scenario sets runs on a copy of its type, 'TYPE@VEHICLE'
        rows.append((trip.get("id"), vtype, emission_classes.get(vtype.split("@")[0], ""), float(trip.get("depart")),
                     float(trip.get("duration")), float(trip.get("routeLength")),
                     *(float(em.get(attr)) / 1000.0 for attr in POLLUTANT_COLUMNS),
                     float(em.get("electricity_abs"))))
    return rows


def _table(rows: list[tuple]) -> pa.Table:
    """(Arrow built from plain lists: this runs at the end of every run.)"""
    rows.sort(key=lambda row: row[0])  # stable
    values = list(zip(*rows)) if rows else [()] * len(COLUMNS)
    return pa.table({name: pa.array(column, type=pa.string() if i < 3 else pa.float64())
                     for i, (name, column) in enumerate(zip(COLUMNS, values))})
