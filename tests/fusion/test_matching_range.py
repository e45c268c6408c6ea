"""The ego's neighbour twins must cover every vehicle whose box the matcher could give a warned twin."""

from pathlib import Path

import pytest

from vcfusion.fusion.matching import JointMatcherParams
from vcfusion.fusion.stage import matching_reach_m, require_matching_range
from vcfusion.scenario import ScenarioError, load_scenario
from vcfusion.studies.guidance import StudyError, run_guidance_study

REPO = Path(__file__).resolve().parents[2]


def test_reach_is_the_view_range_plus_the_depth_gate_there():
    p = JointMatcherParams()
    r = 150.0 + 12.0
    assert matching_reach_m(150.0) == pytest.approx(r + p.depth_gate * (p.depth_sigma_rel * r + p.depth_sigma_abs_m))
    assert 190 < matching_reach_m(150.0) <= 200  # the shipped ego scenarios' 200 m covers it


@pytest.mark.parametrize("name", ["accident.yaml", "curved.yaml", "onramp_camera.yaml", "exit_camera.yaml",
                                  "accident_heavy.yaml"])
def test_the_shipped_ego_scenarios_cover_the_reach(name):
    require_matching_range(load_scenario(REPO / "scenarios" / name))


def test_a_neighbour_range_short_of_the_reach_is_refused_before_any_trip(tmp_path):
    path = tmp_path / "short_range.yaml"
    path.write_text(f"extends: {REPO / 'scenarios' / 'curved.yaml'}\nv2c: {{neighbour_range_m: 150.0}}\n")
    with pytest.raises(ScenarioError, match=r"v2c.neighbour_range_m: expected at least 199 m .* got 150 m"):
        require_matching_range(load_scenario(path))
    with pytest.raises((ScenarioError, StudyError), match="neighbour_range_m"):
        run_guidance_study(path, trips=2, workers=1, out=tmp_path / "study", renders=tmp_path / "renders",
                           progress=False, arms=("none", "fusion"))
    assert not (tmp_path / "study").exists()
