"""The ego's TTC, time headway and headway of a run, by vcfusion's metrics and by CommonRoad-CriMe
on the run's CommonRoad export (vcfusion.control.commonroad), sample by sample.

vcfusion (metrics.traffic.follow_measures, the trajectories at trajectory_period_s): the leader
is the nearest vehicle ahead in the ego's lane (by s, within metrics.leader_range_m); gap =
bumper to bumper along the road frame; TTC = gap / closing speed where the ego closes in
(constant velocities); time headway = gap / the ego's speed.

CriMe (commonroad-crime 0.4.5) on the same leader and time step: HW = the distance along the
curvilinear frame of the ego's lanelet between the ego's front and the leader's rear; TTC with
constant accelerations where the accelerations differ by more than 0.1 m/s^2 (Jansson 2005,
eq. 5.26), the constant-velocity TTC otherwise; THW = the time the ego's recorded trajectory
takes to reach the leader's rear position (inf where the trajectory ends first). CriMe 0.4.5
has no DRAC.

Needs commonroad-crime, which pins commonroad-io 2024.3 and protobuf 3.20.2; `make setup` installs
them without their pins and commonroad-io runs on protobuf's pure-Python runtime
(vcfusion.control.commonroad.use_pure_python_protobuf).
"""

from __future__ import annotations

import json
import logging
import math
import warnings
from pathlib import Path

import numpy as np
import pandas as pd

from vcfusion.records import EGO_ID


def crime_problem() -> str | None:
    """Why commonroad-crime cannot be used here (None when it loads)."""
    from vcfusion.control.commonroad import use_pure_python_protobuf

    use_pure_python_protobuf()
    try:
        import commonroad.common.file_reader  # noqa: F401
        from commonroad_crime.measure import HW, THW, TTC  # noqa: F401
    except ImportError as exc:
        return f"needs commonroad-crime with commonroad-io 2024.3 (`make setup` installs both): {exc}"
    except TypeError as exc:  # commonroad-io's protobuf modules under a newer protobuf runtime
        return f"commonroad-io does not load with this environment's protobuf ({' '.join(str(exc).split()[:6])}...)"
    return None


def ours(folder: Path, leader_range_m: float = 250.0) -> pd.DataFrame:
    """The ego's gap, TTC and time headway to its leader at every trajectory sample (vcfusion)."""
    from vcfusion.metrics.traffic import follow_measures

    traj = pd.read_parquet(Path(folder) / "trajectories.parquet", columns=["time", "vehicle_id", "lane", "s", "speed"])
    vehicles = pd.read_parquet(Path(folder) / "vehicles.parquet", columns=["vehicle_id", "length"])
    codes = {vid: k for k, vid in enumerate(vehicles["vehicle_id"])}
    code = traj["vehicle_id"].map(codes).to_numpy()
    m = follow_measures(traj["time"].to_numpy(), traj["lane"].to_numpy(), traj["s"].to_numpy(),
                        traj["speed"].to_numpy(), code, vehicles["length"].to_numpy(), leader_range_m)
    ego = (traj["vehicle_id"] == EGO_ID).to_numpy() & (m["leader"] >= 0)
    ids = vehicles["vehicle_id"].to_numpy()
    return pd.DataFrame({"time": m["time"][ego], "leader": ids[m["leader"][ego]], "hw_m": m["gap"][ego],
                         "ttc_s": m["ttc"][ego], "thw_s": m["headway"][ego]})


def crosscheck(folder: Path, xml: Path) -> pd.DataFrame:
    """Per ego sample with a leader: vcfusion's and CriMe's HW, TTC and THW (columns *_ours, *_crime)."""
    from commonroad.common.file_reader import CommonRoadFileReader
    from commonroad_crime.data_structure.configuration import CriMeConfiguration
    from commonroad_crime.measure import HW, THW, TTC

    table = json.loads(Path(xml).with_suffix(".ids.json").read_text())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        scenario, _ = CommonRoadFileReader(str(xml)).open(lanelet_assignment=True)
    config = CriMeConfiguration()
    config.update(ego_id=table["ego_obstacle_id"], sce=scenario)
    mine = ours(folder)
    rows = []
    previous = logging.root.manager.disable
    logging.disable(logging.WARNING)  # CriMe logs every projection it cannot make
    try:
        measures = [m(config) for m in (HW, TTC, THW)]  # built once: each builds the ego's curvilinear frame
        for time, leader in zip(mine["time"], mine["leader"]):
            step, other = int(round(time / table["dt"])), table["obstacle_ids"][leader]
            rows.append([float(m.compute(other, step, verbose=False)) for m in measures])
    finally:
        logging.disable(previous)
    crime = np.array(rows, dtype=float).reshape(-1, 3)
    out = mine.rename(columns={"hw_m": "hw_m_ours", "ttc_s": "ttc_s_ours", "thw_s": "thw_s_ours"})
    for k, name in enumerate(("hw_m_crime", "ttc_s_crime", "thw_s_crime")):
        out[name] = crime[:, k]
    return out


def agreement(samples: pd.DataFrame) -> dict:
    """Median (and 90th percentile) relative difference |crime - ours| / ours of each measure over
    the samples where both are finite, with their count."""
    out = {}
    for measure in ("hw_m", "ttc_s", "thw_s"):
        a, b = samples[f"{measure}_ours"].to_numpy(), samples[f"{measure}_crime"].to_numpy()
        both = np.isfinite(a) & np.isfinite(b) & (a > 0)
        rel = np.abs(b[both] - a[both]) / a[both]
        out[measure] = {"samples": int(both.sum()), "of": int(len(a)),
                        "median_rel_diff": float(np.median(rel)) if len(rel) else math.nan,
                        "p90_rel_diff": float(np.percentile(rel, 90)) if len(rel) else math.nan}
    return out
