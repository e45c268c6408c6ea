"""The record of an ego collision: who, how fast, what the driver saw, was shown and did before."""

import numpy as np
import pandas as pd
import pytest

from vcfusion.metrics.collisions import describe, ego_collision_records


def _tables():
    t = np.round(np.arange(0.0, 10.01, 0.1), 6)
    driver = pd.DataFrame({"time": t, "leader_id": np.where(t >= 8.0, "cutter", "lead"),
                           "leader_kind": np.where(t >= 8.0, "lane", "lane"), "perceived_gap_m": 30.0 - t,
                           "desired_accel": -1.0, "applied_accel": -0.5, "covering": t >= 7.0,
                           "warnings_active": (t >= 6.5).astype(int), "vehicles_seen": 4, "guidance_enabled": True})
    guidance = pd.DataFrame({"time": [6.5, 6.6, 6.7, 2.0], "vehicle_id": ["cutter"] * 3 + ["far"],
                             "box_vehicle_id": ["other"] * 3 + ["far"], "level": ["high"] * 4,
                             "lc_prob": 0.9, "source": "fusion"})
    collisions = pd.DataFrame({"time": [9.5, 9.6, 9.6], "collider": ["ego", "ego", "a"], "victim": ["cutter", "cutter", "b"],
                               "kind": "collision", "collider_speed": [15.0, 15.0, 3.0],
                               "victim_speed": [9.0, 9.0, 1.0], "lane": "e_2", "pos": 300.0, "end_time": 9.7})
    lane_changes = pd.DataFrame({"vehicle_id": ["cutter", "cutter"], "start_time": [7.0, 1.0], "mid_time": [8.2, 2.0],
                                 "end_time": [9.0, 3.0], "from_lane": [1, 0], "to_lane": [2, 1],
                                 "into_ego_lane": [True, False]})
    events = pd.DataFrame({"time": [7.4, 7.4], "vehicle_id": ["cutter", "lead"], "cue": ["lateral", "lateral"],
                           "twin_id": "", "level": "", "lc_prob": np.nan, "response_time": [8.2, 8.2]})
    # side by side on a road along +x (y = d)
    traj = pd.DataFrame({"time": [9.5, 9.5], "vehicle_id": ["ego", "cutter"], "d": [8.75, 5.3], "x": [300.0, 300.0],
                         "y": [8.75, 5.3], "heading": [0.0, 0.0]})
    vehicles = pd.DataFrame({"vehicle_id": ["ego", "cutter"], "length": [4.6, 4.6], "width": [1.8, 2.5]})
    return {"trajectories": traj, "vehicles": vehicles, "driver": driver, "guidance": guidance, "collisions": collisions, "lane_changes": lane_changes,
            "driver_events": events}


def test_one_record_per_ego_pair_with_what_happened_before():
    (rec,) = ego_collision_records(_tables())  # SUMO repeats a contact every step; a-b is not the ego's
    assert (rec["other"], rec["ego_role"], rec["time"]) == ("cutter", "collider", 9.5)
    assert rec["closing_speed_mps"] == 6.0 and rec["ego_speed_mps"] == 15.0 and rec["other_speed_mps"] == 9.0
    assert [c["mid"] for c in rec["other_lane_changes"]] == [8.2]  # the one in the 5 s before
    assert rec["other_was_leader_s"] == 8.0
    assert [c["cue"] for c in rec["driver_cues"]] == ["lateral"]
    # the cloud warned about the cutter's twin, but the box showed another vehicle
    assert rec["other_warned_twin"] and not rec["other_highlighted"]
    assert rec["shown"] == [{"twin": "cutter", "highlighted": "other", "level": "high", "first": 6.5, "last": 6.7}]
    assert rec["driver"][0]["time"] == 4.5 and rec["driver"][-1]["time"] == 9.5 and len(rec["driver"]) == 11
    text = describe(rec)
    assert "ego ran into cutter at 6.0 m/s closing" in text and "another vehicle highlighted" in text
    # 3.45 m between the centres, 2.15 m of half widths: SUMO's lane bookkeeping, not a body contact
    assert rec["body_clearance_m"] == 1.3 and "no body contact: 1.30 m" in text


def test_overlapping_bodies_are_a_contact():
    tables = _tables()
    tables["trajectories"].loc[1, ["d", "y"]] = 7.5
    (rec,) = ego_collision_records(tables)
    assert rec["body_clearance_m"] == -0.9 and "no body contact" not in describe(rec)


def test_bodies_that_meet_after_the_first_report_are_told_apart_from_the_report():
    # SUMO reports the contact from 9.5 s to 9.7 s: apart at 9.5 s, overlapping at 9.6 s; a sample
    # after the last report does not count
    tables = _tables()
    later = tables["trajectories"].assign(time=9.6)
    later.loc[1, ["d", "y"]] = 7.5
    after = tables["trajectories"].assign(time=9.8)
    after.loc[1, ["d", "y"]] = 8.75
    tables["trajectories"] = pd.concat([tables["trajectories"], later, after], ignore_index=True)
    (rec,) = ego_collision_records(tables)
    assert (rec["body_clearance_m"], rec["least_body_clearance_m"], rec["other_d_m"]) == (1.3, -0.9, 5.3)
    assert "no body contact: 1.30 m" in describe(rec) and "met before SUMO's last report of it (0.90 m" in describe(rec)
    tables["trajectories"] = tables["trajectories"][tables["trajectories"]["time"] != 9.6]
    (rec,) = ego_collision_records(tables)
    assert rec["least_body_clearance_m"] == 1.3 and "met" not in describe(rec)


def test_a_vehicle_turned_toward_the_ego_touches_it_with_its_corner():
    # 0.5 m between the sides as the lanes go, but the cutter is turned 0.4 rad toward the ego and
    # a metre ahead: its front corner reaches across (a record made from lateral positions alone
    # would say no contact)
    tables = _tables()
    tables["trajectories"].loc[1, ["d", "y", "x", "heading"]] = [6.6, 6.6, 301.0, 0.4]
    (rec,) = ego_collision_records(tables)
    assert rec["ego_d_m"] - rec["other_d_m"] - (1.8 + 2.5) / 2 > 0.0
    assert rec["body_clearance_m"] < 0 and "no body contact" not in describe(rec)


def test_footprint_clearance_agrees_with_opencv_and_with_sampled_outlines():
    # overlap or not as OpenCV's rotated-rectangle intersection says; apart, the distance of the
    # nearest points of the two outlines sampled every 3 cm at most
    import cv2
    from scipy.spatial import cKDTree

    from vcfusion.metrics.collisions import footprint_clearance, footprints

    rng = np.random.default_rng(7)

    def outline(corners):
        steps = np.linspace(0.0, 1.0, 400, endpoint=False)[:, None]
        return np.concatenate([c + steps * (np.roll(corners, -1, axis=0)[k] - c) for k, c in enumerate(corners)])

    apart = 0
    for _ in range(200):
        a = (rng.uniform(-5, 5), rng.uniform(-5, 5), rng.uniform(-np.pi, np.pi), rng.uniform(4, 12), rng.uniform(1.7, 2.6))
        b = (rng.uniform(-5, 5), rng.uniform(-5, 5), rng.uniform(-np.pi, np.pi), rng.uniform(4, 12), rng.uniform(1.7, 2.6))
        fa, fb = footprints(*a)[0], footprints(*b)[0]
        gap = footprint_clearance(fa, fb)
        assert gap == pytest.approx(footprint_clearance(fb, fa))
        rect = lambda v: ((v[0], v[1]), (v[3], v[4]), np.degrees(v[2]))  # noqa: E731
        kind, _ = cv2.rotatedRectangleIntersection(rect(a), rect(b))
        if abs(gap) > 1e-3:
            assert (kind == cv2.INTERSECT_NONE) == (gap > 0), (a, b, gap)
        if gap > 1e-3:
            apart += 1
            pa, pb = outline(fa), outline(fb)
            nearest = cKDTree(pb).query(pa)[0].min()
            assert gap == pytest.approx(nearest, abs=0.02)
    assert apart > 50


def test_without_guidance_the_record_says_nothing_was_shown():
    tables = _tables()
    tables["driver"]["guidance_enabled"] = False
    (rec,) = ego_collision_records(tables)
    assert rec["guidance_on"] is False and "guidance off (the cloud warned about it)" in describe(rec)


def test_no_collision_no_record():
    tables = _tables()
    tables["collisions"] = tables["collisions"].iloc[2:]
    assert ego_collision_records(tables) == []
