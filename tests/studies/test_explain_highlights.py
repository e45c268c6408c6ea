"""`vcfusion explain-highlights`: every warning episode of a run, judged and explained, with its frame."""

from pathlib import Path

import pandas as pd
import pytest

from vcfusion.commands import main
from vcfusion.studies.explain import explain_episodes, why

REPO = Path(__file__).resolve().parents[2]


def _fusion_rows():
    rows = []
    for k in range(6):  # cutter: right for 3 updates, then its box slips onto the neighbour
        t = round(1.0 + 0.1 * k, 6)
        right = k < 3
        rows.append({"time": t, "vehicle_id": "cutter", "level": "high", "lc_prob": 0.9, "matched": True,
                     "box_vehicle_id": "cutter" if right else "neighbour", "outcome": "right" if right else "wrong",
                     "gt_iou": 0.9 if right else 0.1, "visible_px": 900.0, "x1": 10.0, "y1": 10.0, "x2": 40.0,
                     "y2": 30.0, "frame": k})
    for k in range(4):  # far: warned, hidden, nothing drawn; then a calm twin that is never counted
        rows.append({"time": round(1.0 + 0.1 * k, 6), "vehicle_id": "far", "level": "medium", "lc_prob": 0.4,
                     "matched": False, "box_vehicle_id": "", "outcome": "unseen", "gt_iou": 0.0, "visible_px": 12.0,
                     "x1": float("nan"), "y1": float("nan"), "x2": float("nan"), "y2": float("nan"), "frame": k})
        rows.append({"time": round(1.0 + 0.1 * k, 6), "vehicle_id": "calm", "level": "none", "lc_prob": 0.05,
                     "matched": False, "box_vehicle_id": "", "outcome": "missed", "gt_iou": 0.0, "visible_px": 500.0,
                     "x1": float("nan"), "y1": float("nan"), "x2": float("nan"), "y2": float("nan"), "frame": k})
    return pd.DataFrame(rows)


def test_episodes_are_runs_of_one_outcome_and_say_why():
    ep = explain_episodes(_fusion_rows(), 0.1)
    assert ep[["twin", "outcome", "updates"]].values.tolist() == [["cutter", "right", 3], ["far", "unseen", 4],
                                                                   ["cutter", "wrong", 3]]
    wrong = ep[ep["outcome"] == "wrong"].iloc[0]
    assert wrong["box_vehicle_id"] == "neighbour" and wrong["frame"] == 4 and "shows neighbour" in wrong["why"]
    assert "not a miss" in ep[ep["outcome"] == "unseen"].iloc[0]["why"]
    assert "no box was matched" in why("missed", "a", "", 0.0, 500.0)
    sliver = why("unseen", "a", "", 0.0, 360.0, visible_share=0.12)
    assert "0.12 of its outline" in sliver and "not a miss" in sliver


def test_a_run_without_judged_highlights_is_refused_by_name(tmp_path):
    from vcfusion.errors import InputError

    with pytest.raises(InputError, match="no 'outcome' column"):
        explain_episodes(_fusion_rows().drop(columns="outcome"), 0.1)


@pytest.mark.slow
def test_explain_a_short_curved_run_with_frames(tmp_path, capsys):
    scenario = tmp_path / "short_curved.yaml"
    scenario.write_text(f"extends: {REPO / 'scenarios' / 'curved.yaml'}\nname: short_curved\n"
                        "simulation: {max_time_s: 6.0}\nvision: {enabled: true}\n"
                        "fusion: {enabled: true, detector: oracle}\nar: {video: true}\n")
    assert main(["run", str(scenario), "--seed", "0", "--out", str(tmp_path / "run")]) == 0
    assert main(["explain-highlights", str(tmp_path / "run"), "--out", str(tmp_path / "explained")]) == 0
    table = pd.read_csv(tmp_path / "explained" / "highlights.csv")
    fusion = pd.read_parquet(tmp_path / "run" / "fusion.parquet")
    warned = fusion[fusion["level"].isin(["medium", "high"])]
    assert len(warned) and table["updates"].sum() == len(warned)  # every warned update in one episode
    assert set(table["outcome"]) <= {"right", "wrong", "missed", "unseen"}
    # every undrawn twin is missed exactly when its vehicle's box is large enough and covers enough of its outline
    undrawn = fusion[~fusion["matched"]]
    visible = (undrawn["visible_px"] >= 100) & (undrawn["visible_share"] >= 0.2)
    assert len(undrawn) and ((undrawn["outcome"] == "missed") == visible).all()
    assert fusion["visible_share"].between(0, 1).all()
    drawn = table[table["frame"] >= 0]
    pngs = sorted((tmp_path / "explained" / "frames").glob("*.png"))
    assert len(pngs) == len(drawn) > 0
    assert "warning episodes" in capsys.readouterr().out
    # the command writes a new folder or nothing
    assert main(["explain-highlights", str(tmp_path / "run"), "--out", str(tmp_path / "explained")]) == 2
