from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from support.fusion_helpers import make_twins, pinhole_camera, vehicle_box
from vcfusion.detection.detectors import OracleDetector
from vcfusion.fusion.fuse import METHODS, CameraFrame, fuse_frame
from vcfusion.studies.identification import (accuracy_at, accuracy_vs_iou, default_conditions, identification_rows,
                                            summary_lines, write_study_outputs)


def hand_rows():
    # 4 target-frames; IoUs per method chosen by hand
    ious = {"baseline": [1.0, 0.72, 0.3, 0.0], "paper": [1.0, 0.72, 0.69, 0.95], "joint": [1.0, 0.9, 0.8, 0.95]}
    rows = []
    for method, vals in ious.items():
        for k, v in enumerate(vals):
            rows.append({"seed": 0, "latency_s": 0.0, "gnss_noise_m": 0.0, "detector": "oracle", "time": k * 0.1,
                         "vehicle_id": f"v{k}", "method": method, "matched": v > 0, "iou": v})
    # a latency condition where the baseline gets one of two right at 0.7
    for method, vals in {"baseline": [0.8, 0.1], "paper": [0.8, 0.8], "joint": [0.9, 0.9]}.items():
        for k, v in enumerate(vals):
            rows.append({"seed": 0, "latency_s": 0.5, "gnss_noise_m": 0.0, "detector": "oracle", "time": k * 0.1,
                         "vehicle_id": f"v{k}", "method": method, "matched": True, "iou": v})
    return pd.DataFrame(rows)


def test_accuracy_vs_iou_counts_by_hand():
    rows = hand_rows()
    clean = rows[rows["latency_s"] == 0]
    curve = accuracy_vs_iou(clean).set_index(["method", "iou_threshold"])["accuracy"]
    assert curve[("baseline", 0.5)] == 0.5 and curve[("baseline", 0.7)] == 0.5 and curve[("baseline", 0.75)] == 0.25
    assert curve[("paper", 0.7)] == 0.75 and curve[("paper", 0.65)] == 1.0
    assert curve[("joint", 0.7)] == 1.0 and curve[("joint", 0.95)] == 0.5
    # the threshold itself counts (IoU exactly 0.95 at threshold 0.95)
    assert curve[("paper", 0.95)] == 0.5
    sweep = accuracy_at(rows, 0.7).set_index(["latency_s", "method"])
    assert sweep.loc[(0.5, "baseline"), "accuracy"] == 0.5 and sweep.loc[(0.5, "baseline"), "n"] == 2
    assert sweep.loc[(0.0, "joint"), "accuracy"] == 1.0
    assert any("latency 0.50 s" in line and "baseline  50.0%" in line for line in summary_lines(rows))


def test_study_outputs_are_written(tmp_path):
    paths = write_study_outputs(hand_rows(), tmp_path / "renders")
    for key in ("rows", "accuracy_iou", "latency_noise", "accuracy_iou_plot", "latency_noise_plot"):
        assert paths[key].is_file() and paths[key].stat().st_size > 0
    csv = pd.read_csv(paths["accuracy_iou"])
    assert len(csv) == 3 * 10 and set(csv["method"]) == {"baseline", "paper", "joint"}
    assert not [p for p in (tmp_path / "renders").iterdir() if p.name.startswith(".")]


def test_default_conditions_share_the_clean_run():
    conds = default_conditions((0.0, 0.5), (0.0, 2.0))
    assert [(c.latency_s, c.gnss_noise_m) for c in conds] == [(0.0, 0.0), (0.5, 0.0), (0.0, 2.0)]


def test_rows_from_a_fused_hand_made_frame():
    """Two cars in the camera's lane (Fig. 3 geometry) with oracle boxes; a third twin not visible."""
    cam = pinhole_camera()
    xs, ys = np.array([15.0, 27.0]), np.array([0.0, 1.8])  # the far car half a lane to the left
    gt = np.stack([vehicle_box(cam, x, y) for x, y in zip(xs, ys)])
    depth = np.full((480, 640), np.inf, np.float32)
    for k in (1, 0):  # far first, the near car paints over it
        x1, y1, x2, y2 = gt[k].astype(int)
        depth[y1:y2, x1:x2] = xs[k] - 2.25
    frame = CameraFrame(time=0.0, image=np.zeros((480, 640, 3), np.uint8), depth=depth, camera=cam,
                        gt_boxes=gt, gt_ids=("near", "far"))
    twins = make_twins(["near", "far", "gone"], [15.0, 27.0, 60.0], [0.0, 1.8, 0.0])
    result = fuse_frame(frame, twins, OracleDetector(), np.random.default_rng(0))
    rows = pd.DataFrame(identification_rows(frame, result, seed=1, latency_s=0.0, gnss_noise_m=0.0, detector="oracle"))
    assert len(rows) == 2 * len(METHODS)  # two visible targets x the methods ("gone" has no ground-truth box)
    # the far car's anchor lies in both boxes (the ambiguous case), the near car's in its own only
    assert rows.groupby("vehicle_id")["n_anchor_boxes"].unique().map(list).to_dict() == {"near": [1], "far": [2]}
    by = rows.set_index(["vehicle_id", "method"])["iou"]
    assert by[("far", "baseline")] == 0.0  # the paper's baseline: equal oracle scores, cannot identify
    assert by[("far", "baseline_centre")] == pytest.approx(1.0)
    assert by[("far", "paper")] == pytest.approx(1.0) and by[("far", "joint")] == pytest.approx(1.0)
    assert by[("near", "joint")] == pytest.approx(1.0) and by[("near", "paper")] == pytest.approx(1.0)
    assert set(rows["method"]) == set(METHODS)
    assert (rows["seed"] == 1).all() and (rows["detector"] == "oracle").all()


def test_summary_splits_scenarios_and_anchor_cases():
    rows = hand_rows()
    # targets v0, v1 in scenario "a" with one anchor box; v2, v3 in "b", ambiguous (two boxes)
    rows["scenario"] = np.where(rows["vehicle_id"].isin(["v0", "v1"]), "a", "b")
    rows["n_anchor_boxes"] = np.where(rows["vehicle_id"].isin(["v0", "v1"]), 1, 2)
    lines = summary_lines(rows)
    assert any("scenario b (n=2)" in line and "baseline   0.0%" in line and "paper  50.0%" in line for line in lines)
    assert any("anchor in >=2 boxes (n=2)" in line and "joint 100.0%" in line for line in lines)
    assert any("anchor in   1 boxes (n=2)" in line and "baseline 100.0%" in line for line in lines)


def test_study_refuses_two_scenarios_of_one_name(tmp_path):
    from vcfusion.scenario import load_scenario
    from vcfusion.studies.identification import run_identification_study

    sc = load_scenario(Path(__file__).resolve().parents[2] / "scenarios" / "overlap.yaml")
    with pytest.raises(ValueError, match="distinct scenario names"):
        run_identification_study([sc, sc], [0], None, {"oracle": OracleDetector()}, tmp_path, progress=False)
    assert not any(tmp_path.iterdir())


def test_the_study_runs_each_scenario_with_the_sensors_asked_for():
    from scenario_files import SCENARIOS

    from vcfusion.errors import UsageError
    from vcfusion.fusion.stage import run_sensors
    from vcfusion.scenario import load_scenario
    from vcfusion.commands.study import with_sensors

    sc = load_scenario(SCENARIOS / "accident.yaml")
    assert with_sensors(sc, None, None) is sc and run_sensors(sc, 0) is None  # exact: nothing applied
    sensed = with_sensors(sc, "stereo", 0.3)
    cam = sensed.camera
    assert cam.depth == "stereo" and cam.pose_noise.mount_std_deg == 0.3 and cam.pose_noise.body_motion
    a, b = run_sensors(sensed, 5), run_sensors(sensed, 5)
    assert a.depth_model == "stereo" and np.array_equal(a.mount, b.mount)  # the run's seed draws them
    assert not np.array_equal(a.mount, run_sensors(sensed, 6).mount)
    with pytest.raises(UsageError, match="--pose-noise-deg"):
        with_sensors(sc, None, -1.0)
