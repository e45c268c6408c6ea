"""`vcfusion compare-lane-changes` on two tiny datasets whose lane changes have known kinematics:
cosine lateral moves of 3 s ("sim") and 6 s ("real") between two 3.5 m lanes, with a leader and a
follower in the target lane at known gaps."""

import json
import math

import numpy as np
import pandas as pd
import pytest

from vcfusion.commands import main
from vcfusion.prediction.manoeuvres import DECISION_TAU_S
from vcfusion.prediction.sources.trajectories import (LATERAL_SETTLED_MPS, LATERAL_SMOOTH_S, SAMPLE_COLUMNS,
                                                      Recording, import_recordings, straight_road)

W = 3.5
SPEED = 20.0
LEN = 4.0


def _vehicle(vid, s0, d_of_t, t1=60.0):
    t = np.round(np.arange(0.0, t1 + 1e-9, 0.1), 6)
    d = np.array([d_of_t(x) for x in t])
    return pd.DataFrame({"vehicle_id": vid, "time": t, "s": s0 + SPEED * t, "d": d,
                         "lane": np.floor(d / W + 1e-9).astype(int), "speed": SPEED, "accel": 0.0, "length": LEN,
                         "width": 1.8, "height": 1.5, "vclass": "passenger"})


def _move(t, t0, duration, a, b):
    u = min(max((t - t0) / duration, 0.0), 1.0)
    return a + (b - a) * (1 - math.cos(math.pi * u)) / 2


def recording(duration, lead_gap, lag_gap, twice=False):
    """Three changers (0.5 km apart) crossing to the left lane at 20 s (t0 = 20 - duration / 2); the
    first comes back at 40 s when `twice`. Each has a leader and a follower in the left lane at
    lead_gap / lag_gap (bumper to bumper, all at one speed) and a leader in its own lane 60 m ahead."""
    frames = []
    for k in range(3):
        s0 = 100.0 + 500.0 * k
        t0 = 20.0 - duration / 2

        def d_of_t(t, t0=t0, back=twice and k == 0):
            d = _move(t, t0, duration, W / 2, 1.5 * W)
            return _move(t, 40.0 - duration / 2, duration, 1.5 * W, W / 2) if back and t > 30.0 else d

        frames.append(_vehicle(f"c{k}", s0, d_of_t))
        frames.append(_vehicle(f"lead{k}", s0 + LEN + lead_gap, lambda t: 1.5 * W))
        frames.append(_vehicle(f"lag{k}", s0 - LEN - lag_gap, lambda t: 1.5 * W))
        frames.append(_vehicle(f"own{k}", s0 + LEN + 60.0, lambda t: W / 2))
    samples = pd.concat(frames, ignore_index=True)[SAMPLE_COLUMNS]
    road = straight_road("test", 2, W, 2000.0, float("nan"))
    return Recording("synthetic", road, samples, 0.1, {"format": "synthetic", "file": "synthetic"})


def expected_duration(duration):
    """The settled rule on the cosine's lateral speed (A pi / 2T) sin(pi u): above the threshold
    for all but 2 arcsin(threshold 2T / (A pi)) / pi of T."""
    return duration * (1 - 2 * math.asin(LATERAL_SETTLED_MPS * 2 * duration / (W * math.pi)) / math.pi)


@pytest.fixture(scope="module")
def compared(tmp_path_factory):
    root = tmp_path_factory.mktemp("cmp")
    import_recordings([recording(3.0, 30.0, 40.0, twice=True)], root / "sim", 5.0, 2.0, progress=False)
    import_recordings([recording(6.0, 20.0, 25.0)], root / "real", 5.0, 2.0, progress=False)
    # the simulated dataset as a simulation writes it: SUMO's trajectory table (s, d) beside the twins
    for folder in (root / "sim" / "runs").glob("seed_*"):
        tw = pd.read_parquet(folder / "twins.parquet")
        pd.DataFrame({"time": tw["time"], "vehicle_id": tw["vehicle_id"], "s": tw["x"], "d": tw["y"] + 2 * W,
                      "lane": tw["lane"], "speed": tw["speed"]}).to_parquet(folder / "trajectories.parquet")
        tw.assign(y=tw["y"] + 100.0).to_parquet(folder / "twins.parquet")  # not read when trajectories exist
    out = root / "out"
    code = main(["compare-lane-changes", str(root / "sim"), str(root / "real"), "--out", str(out),
                 "--names", "sim,real", "--label", "synthetic test data"])
    assert code == 0
    return out


def test_known_kinematics(compared):
    ev = pd.read_parquet(compared / "events.parquet")
    sim, real = ev[ev["dataset"] == "sim"], ev[ev["dataset"] == "real"]
    assert len(sim) == 4 and len(real) == 3  # the sim's first car changes twice
    # the rule on the exact speed, widened by at most the smoothing window of the lateral speed
    for table, duration in ((sim, 3.0), (real, 6.0)):
        low, high = expected_duration(duration) - 0.1, expected_duration(duration) + LATERAL_SMOOTH_S
        assert ((table["duration_s"] >= low) & (table["duration_s"] <= high)).all()
    left = sim[sim["direction"] == 1]
    assert np.allclose(left["gap_target_lead_m"], 30.0, atol=1e-6)
    assert np.allclose(left["gap_target_lag_m"], 40.0, atol=1e-6)
    assert np.allclose(real["gap_target_lead_m"], 20.0, atol=1e-6)
    assert np.allclose(real["dv_leader_mps"], 0.0) and np.allclose(real["dv_target_lead_mps"], 0.0)
    # midpoints: the first sample in the new lane; going back, d = 3.5 m at 40.0 s is still the left lane
    assert sorted(sim["time_since_last_change_s"].dropna()) == pytest.approx([20.1])
    assert real["time_since_last_change_s"].isna().all()
    # peak lateral speed of a cosine move: A pi / 2T (less a little from the 1 s smoothing)
    assert np.allclose(real["lateral_speed_peak_mps"], W * math.pi / 12, rtol=0.05)


def test_profiles_and_ks(compared):
    prof = pd.read_parquet(compared / "profiles.parquet")
    at = prof[(prof["quantity"] == "lateral_offset_m")].set_index(["dataset", "tau_s"])["p50"]
    # offset towards the new lane 1 s before the crossing: -(A / 2) sin(pi / T)
    assert at[("sim", -1.0)] == pytest.approx(-W / 2 * math.sin(math.pi / 3), abs=0.02)
    assert at[("real", -1.0)] == pytest.approx(-W / 2 * math.sin(math.pi / 6), abs=0.02)
    assert at[("real", 0.0)] == pytest.approx(0.0, abs=1e-9)
    ks = pd.read_csv(compared / "ks.csv").set_index("quantity")
    assert ks.loc["duration_s", "ks"] == 1.0  # every sim change shorter than every real one
    assert ks.loc["gap_target_lead_m", "ks"] == 1.0
    assert ks.loc["dv_leader_mps", "ks"] == 0.0  # the same in both
    assert ks.loc["duration_s", "n_sim"] == 4 and ks.loc["duration_s", "n_real"] == 3
    md = (compared / "ks.md").read_text()
    assert "synthetic test data" in md and "| duration_s | real | 4 | 3 |" in md
    meta = json.loads((compared / "compare.json").read_text())
    assert meta["lane_changes"] == {"sim": 4, "real": 3} and meta["decision_tau_s"] == DECISION_TAU_S
    # 12 vehicles x 601 ticks of 0.1 s on the main lanes
    assert meta["rates"]["real"]["vehicle_hours"] == pytest.approx(12 * 601 * 0.1 / 3600)
    assert meta["rates"]["real"]["per_vehicle_hour"] == pytest.approx(3 / (12 * 601 * 0.1 / 3600))
    assert (compared / "profiles.png").stat().st_size > 0 and (compared / "quantities.png").stat().st_size > 0


def test_existing_out_and_bad_dataset_exit_2(compared, tmp_path, capsys):
    (tmp_path / "a").mkdir()
    assert main(["compare-lane-changes", str(tmp_path / "a"), str(compared.parent / "real"), "--out",
                 str(tmp_path / "x")]) == 2
    assert "not a dataset folder" in capsys.readouterr().err and not (tmp_path / "x").exists()
    assert main(["compare-lane-changes", str(compared.parent / "sim"), str(compared.parent / "real"), "--out",
                 str(compared)]) == 2
    assert "already exists" in capsys.readouterr().err
