"""`vcfusion run --arm`: one arm of a guidance-study trip as a run folder (for explain-highlights)."""

from pathlib import Path

import pandas as pd

from vcfusion.commands import build_parser, main
from vcfusion.scenario import load_scenario
from vcfusion.studies.guidance import ARMS, CAMERA_ARMS, arm_run_scenario, arm_scenario, simulate_arm

REPO = Path(__file__).resolve().parents[2]
ACCIDENT = REPO / "scenarios" / "accident.yaml"


def test_a_run_of_a_study_arm_drives_the_study_trip(tmp_path):
    egos = {}
    for arm in ("none", "cloud"):
        assert main(["run", str(ACCIDENT), "--seed", "0", "--arm", arm, "--out", str(tmp_path / arm)]) == 0
        egos[arm] = pd.read_parquet(tmp_path / arm / "ego.parquet")
        study = simulate_arm(load_scenario(ACCIDENT), 0, arm)["tables"]["ego"]
        pd.testing.assert_frame_equal(egos[arm], pd.DataFrame(study).reset_index(drop=True), check_exact=True)
    # the arm decides: the guided ego drives otherwise than the unguided one on this seed
    assert not egos["none"][["s", "speed"]].equals(egos["cloud"][["s", "speed"]])


def test_only_the_guidance_switch_and_the_camera_arms_frames_differ_from_the_studys_arm():
    sc = load_scenario(ACCIDENT)
    for arm in ARMS:
        run, study = arm_run_scenario(sc, arm), arm_scenario(sc, arm)
        assert run.driver.guidance == (arm != "none")
        assert run.ar.video == (arm in CAMERA_ARMS)
        assert study.ar.video is False
        same = run.model_copy(update={"driver": study.driver, "ar": study.ar})
        assert same.model_dump() == study.model_dump()


def test_the_run_commands_arms_are_the_studys():
    parser = build_parser()
    run = parser._subparsers._group_actions[0].choices["run"]
    arm = next(a for a in run._actions if a.dest == "arm")
    assert tuple(arm.choices) == ARMS
