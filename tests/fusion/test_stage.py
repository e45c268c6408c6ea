"""The fusion stage wired from a scenario: checks of the scenario blocks, the fusion hook fed by
a camera hook through `tick.frame`, and (once the rendering stage is present) `vcfusion run`
with real renders writing the fusion table and the AR video."""

import json
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest
import yaml

from support.cuboid_frames import CuboidFrameSource
from vcfusion.cosim import CoSimulation
from vcfusion.driver.idm import IdmController
from vcfusion.guidance import GuidancePolicy
from vcfusion.traffic.network import read_road
from vcfusion.scenario import ScenarioError, load_scenario
from vcfusion.fusion.overlay import OverlayRecorder
from vcfusion.fusion.stage import build_fusion_hook

ROOT = Path(__file__).resolve().parents[2]


def scenario_file(tmp_path, **changes) -> Path:
    raw = yaml.safe_load((ROOT / "scenarios" / "accident.yaml").read_text())
    raw["network"] = str(ROOT / "sumo_net" / "highway.net.xml")
    raw["vehicle_types"] = str(ROOT / "sumo_net" / "vtypes.add.xml")
    raw["simulation"]["max_time_s"] = 3.0
    for block, values in changes.items():
        raw.setdefault(block, {}).update(values)
    path = tmp_path / "fusion.yaml"
    path.write_text(yaml.safe_dump(raw))
    return path


def test_scenario_checks_the_fusion_blocks(tmp_path):
    with pytest.raises(ScenarioError, match="ar.video: expected fusion.enabled"):
        load_scenario(scenario_file(tmp_path, ar={"video": True}))
    with pytest.raises(ScenarioError, match="ar.medium_threshold"):
        load_scenario(scenario_file(tmp_path, ar={"medium_threshold": 0.8, "high_threshold": 0.5}))
    with pytest.raises(ScenarioError, match="fusion.weights: file not found"):
        load_scenario(scenario_file(tmp_path, fusion={"weights": "nope.pt"}))
    with pytest.raises(ScenarioError, match="fusion.method"):
        load_scenario(scenario_file(tmp_path, fusion={"method": "magic"}))
    with pytest.raises(ScenarioError, match="fusion.enabled: expected vision.enabled"):
        load_scenario(scenario_file(tmp_path, fusion={"enabled": True}))
    # a video of frames at warnings only would have no frame rate (and no file without a warning)
    with pytest.raises(ScenarioError, match="ar.video: expected vision.only_when_warning: false"):
        load_scenario(scenario_file(tmp_path, vision={"enabled": True, "only_when_warning": True},
                                    fusion={"enabled": True}, ar={"video": True}))
    # the video's frames: AR updates that have a camera frame
    for every, ar_period, expected in ((1, 0.1, 0.1), (3, 0.1, 0.3), (3, 0.2, 0.6), (2, 0.4, 0.4)):
        sc = load_scenario(scenario_file(tmp_path, vision={"enabled": True, "every_ticks": every},
                                         fusion={"enabled": True}, ar={"period_s": ar_period}))
        assert sc.overlay_period_s() == pytest.approx(expected)


class FakeCameraHook:
    """Stands in for the rendering stage's camera hook: sets the tick's frame."""

    table = "camera"
    provides = ("frame",)

    def __init__(self):
        self.source = CuboidFrameSource()

    def __call__(self, tick):
        tick.frame = self.source(tick)


@pytest.mark.slow
def test_fusion_hook_reads_the_camera_hooks_frame(tmp_path):
    sc = load_scenario(scenario_file(tmp_path, fusion={"detector": "oracle"}, ar={"period_s": 0.2}))
    with OverlayRecorder(tmp_path / "video") as rec:
        fusion = build_fusion_hook(sc, 1, GuidancePolicy.from_scenario(sc, read_road(sc.network)), rec)
        result = CoSimulation(sc, 1, controller=IdmController.for_scenario(sc), hooks=[FakeCameraHook(), fusion]).run()
    table = result.tables["fusion"]
    # twins the overlay rules leave undrawn (a far car of a few pixels: "small") are not matches to count
    drawable = table[table["undrawn"].isin(["", "no_match"])]
    assert len(drawable) > 0.5 * len(table) and drawable["matched"].mean() > 0.9
    # the AR period (0.2 s) halves the V2C tick rate (0.1 s)
    assert table["time"].nunique() == pytest.approx(3.0 / 0.2, abs=1) == rec.count


@pytest.mark.slow
def test_run_with_rendered_camera_writes_fusion_table_and_video(tmp_path, monkeypatch):
    from vcfusion.commands import main

    monkeypatch.chdir(tmp_path)
    path = scenario_file(tmp_path, vision={"enabled": True}, fusion={"enabled": True, "detector": "oracle"},
                         ar={"video": True})
    assert main(["run", str(path), "--seed", "1", "--out", "runs/a"]) == 0
    table = pd.read_parquet(tmp_path / "runs" / "a" / "fusion.parquet")
    drawable = table[table["undrawn"].isin(["", "no_match"])]
    assert len(drawable) > 20 and drawable["matched"].mean() > 0.9
    # everything the run writes is in its run folder, listed by its summary
    run = tmp_path / "runs" / "a"
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name, "runs"]
    assert sorted(p.name for p in (tmp_path / "runs").iterdir()) == ["a"]
    files = json.loads((run / "summary.json").read_text())["files"]
    assert files == sorted(p.name + "/" * p.is_dir() for p in run.iterdir())
    assert {"overlay.mp4", "frames/", "fusion.parquet", "manifest.json"} <= set(files)
    assert len(list((run / "frames").glob("*.png"))) == table["time"].nunique()
    cap = cv2.VideoCapture(str(run / "overlay.mp4"))
    ok, first = cap.read()
    assert ok and first.shape == (480, 640, 3)
    assert cap.get(cv2.CAP_PROP_FRAME_COUNT) == table["time"].nunique()
    assert np.asarray(first).std() > 5  # a rendered scene, not a blank frame
    assert cap.get(cv2.CAP_PROP_FPS) == pytest.approx(10.0)
    # a camera every 3rd tick and AR updates every 2nd: a frame every 0.6 s, and the video plays at
    # that rate (it ran 3x too fast at 1 / ar.period_s)
    path = scenario_file(tmp_path, vision={"enabled": True, "every_ticks": 3},
                         fusion={"enabled": True, "detector": "oracle"}, ar={"video": True, "period_s": 0.2})
    assert main(["run", str(path), "--seed", "1", "--out", "runs/b"]) == 0
    times = np.sort(pd.read_parquet(tmp_path / "runs" / "b" / "fusion.parquet")["time"].unique())
    assert np.allclose(np.diff(times), 0.6)
    cap = cv2.VideoCapture(str(tmp_path / "runs" / "b" / "overlay.mp4"))
    assert cap.get(cv2.CAP_PROP_FRAME_COUNT) == len(times) and cap.get(cv2.CAP_PROP_FPS) == pytest.approx(1 / 0.6, rel=1e-3)
