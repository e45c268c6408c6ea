"""The fusion stage wired from a scenario file into `vcfusion run` (the renderer replaced by the
test-only cuboid frame source through the documented plug)."""

import sys
import types
from pathlib import Path

import cv2
import pandas as pd
import pytest
import yaml

from cuboid_frames import CuboidFrameSource
from vcfusion.cli import main
from vcfusion.scenario import ScenarioError, load_scenario

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


@pytest.fixture
def fake_renderer(monkeypatch):
    module = types.ModuleType("vcfusion.vision.render")
    module.fusion_frame_source = lambda scenario, seed: CuboidFrameSource()
    monkeypatch.setitem(sys.modules, "vcfusion.vision.render", module)
    import vcfusion.vision as vision

    monkeypatch.setattr(vision, "render", module, raising=False)


def test_scenario_checks_the_fusion_blocks(tmp_path):
    with pytest.raises(ScenarioError, match="ar.video: expected fusion.enabled"):
        load_scenario(scenario_file(tmp_path, ar={"video": True}))
    with pytest.raises(ScenarioError, match="ar.medium_threshold"):
        load_scenario(scenario_file(tmp_path, ar={"medium_threshold": 0.8, "high_threshold": 0.5}))
    with pytest.raises(ScenarioError, match="fusion.weights: file not found"):
        load_scenario(scenario_file(tmp_path, fusion={"enabled": True, "weights": "nope.pt"}))
    with pytest.raises(ScenarioError, match="fusion.method"):
        load_scenario(scenario_file(tmp_path, fusion={"method": "magic"}))


@pytest.mark.slow
def test_run_with_fusion_and_video_writes_table_and_mp4(tmp_path, monkeypatch, fake_renderer, capsys):
    monkeypatch.chdir(tmp_path)
    path = scenario_file(tmp_path, fusion={"enabled": True, "detector": "oracle"},
                         ar={"video": True, "period_s": 0.2})
    assert main(["run", str(path), "--seed", "1", "--out", "runs/a"]) == 0
    table = pd.read_parquet(tmp_path / "runs" / "a" / "fusion.parquet")
    assert table["matched"].mean() > 0.9
    # the AR period (0.2 s) halves the V2C tick rate (0.1 s)
    assert table["time"].nunique() == pytest.approx(3.0 / 0.2, abs=1)
    video = tmp_path / "renders" / "a" / "overlay.mp4"
    cap = cv2.VideoCapture(str(video))
    assert cap.read()[0] and cap.get(cv2.CAP_PROP_FRAME_COUNT) == table["time"].nunique()


def test_run_without_renderer_fails_clearly(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "vcfusion.vision.render", None)  # import fails
    path = scenario_file(tmp_path, fusion={"enabled": True, "detector": "oracle"})
    assert main(["run", str(path), "--seed", "1", "--out", str(tmp_path / "r")]) == 2
    assert "renderer" in capsys.readouterr().err
    assert not (tmp_path / "r").exists()
