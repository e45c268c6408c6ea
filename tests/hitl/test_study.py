"""The study protocol: counterbalanced plan, SSQ scoring and screen, a whole session (replayed)."""

import json

import pytest
from scenario_files import write_scenario

from vcfusion.commands import main
from vcfusion.hitl.study import SSQ_SYMPTOMS, ask_ssq, default_order, ssq_scores, trip_plan


def test_the_plan_pairs_seeds_alternates_conditions_and_balances_positions():
    for order in ("on-first", "off-first"):
        plan = trip_plan([3, 4, 5, 6], order)
        assert len(plan) == 8
        assert sorted(plan) == sorted([(s, on) for s in (3, 4, 5, 6) for on in (True, False)])  # paired
        assert all(a[1] != b[1] for a, b in zip(plan[:3], plan[1:4]))  # alternating in the first half
        assert all(plan[k][0] == plan[k + 4][0] for k in range(4))  # each seed again 4 trips later
        assert plan[0][1] == (order == "on-first")
        positions = {on: sum(k for k, (_, c) in enumerate(plan) if c == on) for on in (True, False)}
        assert positions[True] == positions[False]  # same mean position in the session
    assert {default_order(f"P{k:02d}") for k in range(10)} == {"on-first", "off-first"}


def test_ssq_scores_follow_kennedy_1993():
    assert ssq_scores([0] * 16) == {"nausea": 0.0, "oculomotor": 0.0, "disorientation": 0.0, "total": 0.0}
    worst = ssq_scores([3] * 16)  # the published maxima of the scales
    assert worst["nausea"] == pytest.approx(200.34) and worst["oculomotor"] == pytest.approx(159.18)
    assert worst["disorientation"] == pytest.approx(292.32) and worst["total"] == pytest.approx(235.62)
    only_nausea = [0] * 16
    only_nausea[[s for s, _ in SSQ_SYMPTOMS].index("Nausea")] = 2  # nausea counts in N and D
    assert ssq_scores(only_nausea) == pytest.approx({"nausea": 19.08, "oculomotor": 0.0, "disorientation": 27.84,
                                                     "total": 14.96})
    with pytest.raises(ValueError):
        ssq_scores([4] * 16)


def test_the_questionnaire_reads_number_keys_on_the_window():
    from vcfusion.hitl.display import Window
    from vcfusion.hitl.sdl import init_sdl

    pygame = init_sdl(headless=True)
    window = Window(pygame, (320, 240))
    try:
        pygame.event.clear()
        answers = [k % 4 for k in range(16)]
        for a in answers:
            pygame.event.post(pygame.event.Event(pygame.KEYDOWN, key=pygame.K_0 + a, mod=0, unicode=str(a), scancode=0))
        assert ask_ssq(pygame, window, "now", timeout_s=1.0) == answers
    finally:
        window.close()


@pytest.mark.slow
def test_a_session_drives_practice_and_counterbalanced_trips(tmp_path):
    path = write_scenario(tmp_path, """
name: hitl_study_test
network: NET_DIR/highway.net.xml
vehicle_types: NET_DIR/vtypes.add.xml
simulation: {step_s: 0.01, max_time_s: 2.0, lanechange_duration_s: 3.0, trajectory_period_s: 0.1}
v2c: {period_s: 0.1}
camera: {width_px: 96, height_px: 64}
ego: {vtype: ego, lane: 1, depart_pos_m: 80.0, speed_mps: 15.0, desired_speed_mps: 15.0, trip_distance_m: 900.0}
vehicles:
  - {name: far, count: 1, vtype: car, lanes: [0], pos_m: [600.0, 601.0], speed_mps: 15.0, desired_speed_mps: 15.0}
""")
    (tmp_path / "in.csv").write_text("time_s,throttle,brake,steer\n0,0.3,0,0\n")
    out = tmp_path / "session"
    # through the command, as a person runs it: --headless must not wait for a key on its screens
    # (there is no one to press one: it hung)
    assert main(["study", "hitl", str(path), "--participant", "P01", "--trips", "1", "--order", "off-first",
                 "--input", "replay:" + str(tmp_path / "in.csv"), "--speed", "max", "--headless",
                 "--out", str(out)]) == 0
    protocol = json.loads((out / "protocol.json").read_text())
    assert [(t["seed"], t["guidance"]) for t in protocol["trips"]] == [(0, "off"), (0, "on")]
    for name in ["practice"] + [t["run"] for t in protocol["trips"]]:
        summary = json.loads((out / name / "summary.json").read_text())
        assert summary["hitl"]["participant"] == "P01"
    assert json.loads((out / "trip_01_seed0_off" / "summary.json").read_text())["hitl"]["guidance"] == "off"
    # the two arms of the seed saw the same traffic and the same inputs: the same trajectories
    assert (out / "trip_01_seed0_off" / "trajectories.parquet").read_bytes() == \
        (out / "trip_02_seed0_on" / "trajectories.parquet").read_bytes()
