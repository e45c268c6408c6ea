"""The person's display draws what the car knows: the fusion's matched box (carried between vision
ticks with the ego's own motion and the twin's reported velocity), or in the cloud arm the twin's
reported cuboid; never the renderer's instance map. The trip's right / wrong highlight counts are
those of the boxes drawn.

Real fusion hook, real HumanDriver display path and the study's highlight counting on hand-made
ticks; frames from the test-only cuboid frame source, given a pinhole K and extrinsics here."""

from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from support.cuboid_frames import CuboidFrameSource, ShiftedOntoNeighbour
from vcfusion.cosim import EgoStep, Tick
from vcfusion.detection.detectors import Detections
from vcfusion.driver.cloud_guidance import CloudGuidanceFallback
from vcfusion.fusion.fuse import VisionFusionHook
from vcfusion.metrics.highlights import instance_boxes
from vcfusion.fusion.matching import box_iou
from vcfusion.guidance import GuidancePolicy
from vcfusion.hitl.display import cloud_boxes, tracked_boxes
from vcfusion.hitl.driver import HumanDriver
from vcfusion.hitl.vehicle import ControlSample, VehicleState
from vcfusion.records import Guidance, TwinStates, VehicleStates
from vcfusion.render.renderer import Frame
from vcfusion.studies.guidance import highlight_counts
from vcfusion.traffic.network import read_road

ROAD = read_road(Path(__file__).resolve().parents[2] / "sumo_net" / "highway.net.xml")
POLICY = GuidancePolicy.on_road(ROAD, ego_lane=2, medium=0.3, high=0.6, view_range_m=150.0)
IDS = ("ego", "cutter", "neighbour")
EGO_SPEED = 25.0
TICK_STEPS = 4  # a vision tick every 0.2 s, a display frame every 0.05 s


def _truth(t):
    """The ego in lane 2 at 25 m/s; the cutter 30 m ahead and a neighbour 15 m ahead in lane 1 at 15 m/s."""
    ego_s = 100.0 + EGO_SPEED * t
    s = np.array([ego_s, ego_s + 30.0 - 10.0 * t, ego_s + 15.0 - 10.0 * t])
    d = np.array([ROAD.lane_centre_d(2), ROAD.lane_centre_d(1), ROAD.lane_centre_d(1)])
    x, y = ROAD.to_world(s, d)
    n = 3
    return VehicleStates(time=t, ids=IDS, vtype=("ego", "car", "car"), vclass=("passenger",) * n, x=x, y=y,
                         z=np.zeros(n), heading=np.zeros(n), speed=np.array([EGO_SPEED, 15.0, 15.0]),
                         accel=np.zeros(n), lane=np.array([2, 1, 1], dtype=np.int16), lateral_offset=np.zeros(n),
                         length=np.full(n, 4.6), width=np.full(n, 1.8), height=np.full(n, 1.5))


def _twins(truth, offset_x=0.0):
    """The cloud's twins of the two neighbours (reported `offset_x` m ahead of where they are); it
    warns about the cutter only."""
    k = [1, 2]
    return TwinStates(time=truth.time, ids=tuple(truth.ids[i] for i in k), measured_time=np.full(2, truth.time),
                      x=truth.x[k] + offset_x, y=truth.y[k], z=truth.z[k] + truth.height[k] / 2,
                      heading=truth.heading[k], speed=truth.speed[k], accel=truth.accel[k], lane=truth.lane[k],
                      length=truth.length[k], width=truth.width[k], height=truth.height[k],
                      outputs={"lc_prob": np.array([0.9, 0.05]), "lc_decision": np.array([True, False])})


class PinholeCuboids(CuboidFrameSource):
    """The cuboid frame source as a renderer: frames with K and the extrinsics of its camera."""

    def pose(self, truth):
        i = truth.index_of("ego")
        psi = float(truth.heading[i])
        fwd = np.array([np.cos(psi), np.sin(psi), 0.0])
        rot = np.stack([[np.sin(psi), -np.cos(psi), 0.0], [0.0, 0.0, -1.0], fwd])
        pos = np.array([truth.x[i], truth.y[i], truth.z[i] + self.cam_h]) + 0.5 * truth.length[i] * fwd
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = rot, -rot @ pos
        K = np.array([[self.f, 0.0, self.w / 2], [0.0, self.f, self.h / 2], [0.0, 0.0, 1.0]])
        return K, T

    def render(self, truth):
        f = self(Tick(truth.time, truth, None, None, None))
        K, T = self.pose(truth)
        return Frame(truth.time, f.image, f.depth, f.instances, f.instance_ids, K, T)


class OwnBoxes:
    frame = None

    def detect(self, image):
        return Detections.of(self.frame.gt_boxes, np.full(len(self.frame.gt_boxes), 0.9),
                             np.full(len(self.frame.gt_boxes), 3))


class Pedal:
    name = "test"

    def sample(self, time, dt):
        return ControlSample(0.0, 0.0, 0.0), {}


class Car:
    state = VehicleState(EGO_SPEED, 0.0, 0.0, 0.0)

    def update(self, control, dt, s_front):
        return self.state


def _drive(detector=None, offset_x=0.0, until=0.6):
    """Vision ticks every 0.2 s (fusion with `detector`, or the cloud's guidance without one),
    display frames every 0.05 s; returns the driver and the display table."""
    render = PinholeCuboids()
    driver = HumanDriver(Pedal(), Car(), 0.05, 1e6, guidance_on=True, speed=None, display_fps=20.0, renderer=render)
    if detector is not None:
        def source(tick):
            frame = render(tick)
            detector.frame = frame
            return frame
        stage = VisionFusionHook(source, detector, 0, POLICY, method="baseline")
    else:
        stage = CloudGuidanceFallback(ROAD, POLICY, camera=False)
    for k in range(int(round(until / 0.05)) + 1):
        t = round(0.05 * k, 6)
        truth = _truth(t)
        if k % TICK_STEPS == 0:  # a vision tick
            tick = Tick(t, truth, None, None, _twins(truth, offset_x))
            tick.ego = type("EgoView", (), {"s": float(truth.road_frame(ROAD)[0][0]) + 2.3})()
            stage(tick)
            tick.frame = render.render(truth)
            driver.acceleration(tick)
        driver.step(EgoStep(t, 0.0, EGO_SPEED, lambda truth=truth: truth))
    tables, summary = {}, {}
    driver.finish(tables, summary)
    return driver, tables["display"], render


def _true_box(render, t, vid):
    f = render(Tick(t, _truth(t), None, None, None))
    return f.gt_boxes[list(f.gt_ids).index(vid)]


def test_a_box_shifted_onto_the_neighbour_is_drawn_there_and_counts_as_wrong(monkeypatch):
    # the neighbour is nearer and several times the cutter's outline, which the overlay's size rule
    # (fuse.drawable_box) would refuse to draw and the outline rule (fuse.box_within_outline) would cut
    # to the cutter's outline; this test is about the display showing what is drawn
    import vcfusion.fusion.fuse as fuse

    monkeypatch.setattr(fuse, "MAX_BOX_TO_OUTLINE_AREA", float("inf"))
    monkeypatch.setattr(fuse, "MIN_BOX_INSIDE_OUTLINE", 0.0)
    _, shown, render = _drive(ShiftedOntoNeighbour())
    assert len(shown) == 13  # every frame drew the cutter's warning
    assert set(shown["vehicle_id"]) == {"cutter"} and set(shown["box_vehicle_id"]) == {"neighbour"}
    at_tick = shown[shown["time"] == 0.4].iloc[0]
    cut, nb = _true_box(render, 0.4, "cutter"), _true_box(render, 0.4, "neighbour")
    union = [min(cut[0], nb[0]), min(cut[1], nb[1]), max(cut[2], nb[2]), max(cut[3], nb[3])]
    # the display drew the detector's box, not the cutter's silhouette
    assert np.allclose(at_tick[["x1", "y1", "x2", "y2"]].to_numpy(float), union)
    assert highlight_counts(shown, None, 0.1) == {"highlights_right": 0, "highlights_wrong": 1, "missed_warnings": 0,
                                                 "unseen_warnings": 0}
    # the person's wrong episode is on another vehicle (the study's trip row takes it from the display)
    from vcfusion.studies.guidance import highlight_tallies

    assert highlight_tallies(shown, None, 0.1)["wrong_on_other_vehicle"] == 1


def test_right_boxes_follow_their_vehicle_between_ticks_and_count_as_right():
    _, shown, render = _drive(OwnBoxes())
    assert highlight_counts(shown, None, 0.1) == {"highlights_right": 1, "highlights_wrong": 0, "missed_warnings": 0,
                                                 "unseen_warnings": 0}
    boxes = shown.set_index("time")[["x1", "y1", "x2", "y2"]]
    for t in (0.15, 0.35, 0.55):  # the last frame before the next tick: 0.15 s after the last
        truth = _true_box(render, t, "cutter")[None]
        drawn = boxes.loc[t].to_numpy(float)[None]
        at_tick = boxes.loc[round(t - 0.15, 6)].to_numpy(float)[None]
        # carried forward: on the vehicle's box now, much nearer than the tick's box left in place
        assert box_iou(drawn, truth)[0, 0] > 0.9 > box_iou(at_tick, truth)[0, 0] + 0.05


def test_the_cloud_arm_draws_the_reported_cuboid_not_the_vehicle():
    # the cloud reports the cutter 6 m ahead of where it is: the box is drawn there
    _, shown, render = _drive(None, offset_x=6.0)
    assert set(shown["vehicle_id"]) == {"cutter"} and set(shown["source"]) == {"cloud"}
    from vcfusion.fusion.matching import project_twins
    from vcfusion.fusion.stage import camera_view

    boxes = shown.set_index("time")[["x1", "y1", "x2", "y2"]]
    render = PinholeCuboids()
    for t in (0.4, 0.55):  # at a tick, and 0.15 s after it (carried by the reported 15 m/s)
        truth = _truth(t)
        cam = camera_view(*render.pose(truth), render.w, render.h, t)
        want = project_twins(_twins(truth, 6.0), cam).expected_box[0]
        drawn = boxes.loc[t].to_numpy(float)
        assert np.allclose(drawn, want, atol=1e-6)
        # not the vehicle's silhouette in the instance map
        assert box_iou(drawn[None], _true_box(render, t, "cutter")[None])[0, 0] < 0.8


def test_a_box_is_carried_by_the_ego_motion_and_the_twins_velocity():
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    T0 = np.eye(4)
    T0[:3, :3] = [[0, -1, 0], [0, 0, -1], [1, 0, 0]]  # camera at the origin looking along +x
    T1 = T0.copy()
    T1[:3, 3] = -T0[:3, :3] @ np.array([2.0, 0, 0])  # the ego moved 2 m forward
    box = (300.0, 220.0, 340.0, 260.0)  # 40 px at 20 m
    g = Guidance(0.0, "a", 0.9, "high", box, "a", 20.0)
    (still,) = tracked_boxes([g], K, T0, T1, 0.1, (640, 480))
    assert np.allclose(np.subtract(still.box[2:], still.box[:2]), 40.0 * 20.0 / 18.0)  # a parked car grows
    twins = _twins(_truth(0.0))
    twins = replace(twins, ids=("a", "b"), speed=np.array([20.0, 0.0]), heading=np.zeros(2))
    (along,) = tracked_boxes([g], K, T0, T1, 0.1, (640, 480), twins)  # a car doing the ego's 20 m/s
    assert np.allclose(along.box, box)
    assert tracked_boxes([replace(g, box=None)], K, T0, T1, 0.1, (640, 480)) == []
    boxes, ids = instance_boxes(None, ())
    assert boxes.shape == (0, 4) and ids == ()


def test_cloud_boxes_leave_out_twins_out_of_view():
    render = PinholeCuboids()
    truth = _truth(0.0)
    K, T = render.pose(truth)
    from vcfusion.fusion.stage import camera_view

    cam = camera_view(K, T, render.w, render.h, 0.0)
    twins = _twins(truth)
    behind = replace(twins, x=twins.x - np.array([60.0, 0.0]))  # the cutter reported behind the ego
    items = [Guidance(0.0, "cutter", 0.9, "high", None), Guidance(0.0, "neighbour", 0.9, "high", None)]
    assert [g.vehicle_id for g in cloud_boxes(items, behind, cam)] == ["neighbour"]
    shown = cloud_boxes(items, twins, cam)
    assert [g.vehicle_id for g in shown] == ["cutter", "neighbour"] and all(g.box is not None for g in shown)


class BurningRenderer:
    """A display renderer that uses `cpu_ms` of the thread's CPU per frame, and collects the
    garbage (a full collection) at the frame of time `collect_at`."""

    def __init__(self, cpu_ms: float, collect_at: float):
        self.cpu_ms, self.collect_at, self.times = cpu_ms, collect_at, []

    def render(self, truth):
        import gc
        import time
        from types import SimpleNamespace

        started = time.thread_time()
        while time.thread_time() - started < self.cpu_ms / 1e3:
            pass
        if abs(truth.time - self.collect_at) < 1e-6:
            gc.collect()
        self.times.append(truth.time)
        return SimpleNamespace(time=truth.time, rgb=np.zeros((48, 64, 3), np.uint8))


def _paced_drive(renderer, display_fps: float, steps: int, gc_pauses=None):
    """A paced drive of `steps` 10-ms SUMO steps with an idle device and a still car, the display
    drawn by `renderer`; returns the driver, its tables and summary."""
    import contextlib
    from types import SimpleNamespace

    from vcfusion.cosim import EgoStep
    from vcfusion.hitl.driver import HumanDriver

    control = SimpleNamespace(steer=0.0, throttle=0.0, brake=0.0, lane_change=0)
    device = SimpleNamespace(sample=lambda t, dt: (control, {}), handle=lambda e: None)
    state = SimpleNamespace(accel=0.0, d=1.0, yaw=0.0)
    vehicle = SimpleNamespace(update=lambda c, dt, s: state, state=state)
    driver = HumanDriver(device, vehicle, 0.01, 1000.0, guidance_on=False, speed=1.0, display_fps=display_fps,
                         renderer=renderer, gc_pauses=gc_pauses)
    tables, summary = {}, {}
    with gc_pauses if gc_pauses is not None else contextlib.nullcontext():
        for k in range(steps):
            t = round(0.01 * k, 6)
            driver.step(EgoStep(t, 10.0, 10.0, lambda t=t: SimpleNamespace(time=t)))
        driver.finish(tables, summary)
    return driver, tables, summary


def test_each_due_frame_records_the_loops_work_cpu_and_gc_pauses_of_its_period():
    # a paced 0.3-s drive at 100 steps/s, a 30 frames/s display whose render costs 8 ms of CPU, and
    # one full garbage collection inside the frame at 0.2 s (on a busy machine a frame after it
    # may be dropped)
    from vcfusion.hitl.gcpause import GcPauses

    renderer = BurningRenderer(8.0, 0.2)
    pauses = GcPauses()
    driver, tables, summary = _paced_drive(renderer, 30.0, 31, pauses)
    frames = tables["frames"]
    rt = summary["realtime"]
    # every render is shown, but for one drawn ahead for a frame due after the last step
    assert len(frames) == rt["frames_due"] == 10 and frames.shown.sum() >= 3
    assert len(renderer.times) - frames.shown.sum() in (0, 1)
    # the render's CPU is in the period of the frame it drew (the first frame's period is its own step)
    assert (frames.cpu_ms[frames.shown] >= 8.0).all()
    # the work is the loop's time without the pacing sleep: at least its CPU; with the sleep the
    # periods add up to the drive's wall time up to its last frame (the paced drive sleeps unless
    # the machine falls behind a 0.3-s drive; the sum holds either way)
    assert (frames.work_ms >= frames.cpu_ms - 0.5).all()
    assert frames.work_ms.sum() + 1e3 * driver._slept == pytest.approx(1e3 * frames.wall_s.iloc[-1], abs=1.0)
    assert rt["frame_work_ms_p99"] == pytest.approx(np.percentile(frames.work_ms, 99))
    assert rt["frame_cpu_ms_p99"] == pytest.approx(np.percentile(frames.cpu_ms, 99))
    # the collection: timed, in the period of the frame at 0.2 s, and in the summary
    (full,) = [p for p in pauses.pauses if p[0] == 2]
    at = frames.index[np.isclose(frames.sim_time, 0.2)][0]
    assert frames.gc_ms[at] == pytest.approx(1e3 * full[2], rel=1e-6) and frames.gc_ms.drop(at).sum() < frames.gc_ms[at]
    assert rt["gc_collections_full"] == 1 and rt["gc_pause_ms_max"] >= 1e3 * full[2] - 1e-9
    assert rt["gc_collections"] == len(pauses.pauses) and rt["gc_pause_ms_total"] == pytest.approx(frames.gc_ms.sum())


def test_a_paced_display_flips_each_frame_at_its_due_time_not_at_the_step_that_drew_it():
    # 60 frames/s over 10-ms SUMO steps: a frame is drawn at the last step before it is due and
    # shown at its due time, so the shown frames are a frame period apart (flipped at the steps
    # themselves they were 10 and 20 ms apart: median 20 ms, "50 frames/s")
    _, tables, summary = _paced_drive(BurningRenderer(1.0, -1.0), 60.0, 61)
    frames = tables["frames"]
    assert len(frames) == 37  # due at k / 60 s for k = 0..36 (the last before the step after 0.6 s)
    shown = frames[frames.shown]
    assert len(shown) >= 30
    # each shown frame's state is a step's at or before its due time (never a later one): the last
    # one before it, or the one before that when its draw would not fit (drawn ahead)
    due = np.arange(len(frames)) / 60.0
    drawn_from = frames.sim_time.to_numpy()[frames.shown.to_numpy()]
    assert ((due[frames.shown.to_numpy()] - drawn_from) >= -1e-6).all()
    assert ((due[frames.shown.to_numpy()] - drawn_from) < 0.02).all()
    # flipped at the due time: never before it, and a frame period apart
    assert (shown.wall_s.to_numpy() >= due[frames.shown.to_numpy()] - 1e-4).all()
    intervals = np.diff(frames.wall_s.to_numpy())[frames.shown.to_numpy()[1:] & frames.shown.to_numpy()[:-1]]
    assert np.median(intervals) == pytest.approx(1 / 60, abs=1.5e-3)
    rt = summary["realtime"]
    assert rt["display_fps_median"] == pytest.approx(60.0, abs=6.0)
    walls = shown.wall_s.to_numpy()
    assert rt["frames_shown_per_s"] == pytest.approx((len(walls) - 1) / (walls[-1] - walls[0]))
    assert rt["frame_interval_ms_p5"] <= 1e3 * np.median(intervals) <= rt["frame_interval_ms_p95"]


class SleepingRenderer:
    """A display renderer that takes `ms` of wall time per frame (sleeping: the same on a busy machine)."""

    def __init__(self, ms: float):
        self.ms, self.times = ms, []

    def render(self, truth):
        import time
        from types import SimpleNamespace

        time.sleep(self.ms / 1e3)
        self.times.append(truth.time)
        return SimpleNamespace(time=truth.time, rgb=np.zeros((48, 64, 3), np.uint8))


def test_a_frame_due_too_soon_after_a_step_for_its_draw_is_drawn_a_step_ahead():
    # 60 frames/s over 10-ms steps with a 7-ms draw: the frame due at 133.3 ms, drawn at the
    # 130-ms step, would be shown 3.7 ms late; drawn at the 120-ms step it is shown on time. A
    # frame due at a step itself (every third) is drawn at that step and shown a draw's time late.
    _, tables, summary = _paced_drive(SleepingRenderer(7.0), 60.0, 61)
    frames = tables["frames"]
    # the first draw (imports, warm-up) may make the loop drop the frame after it
    assert len(frames) == 37 and frames.shown[3:].all()
    k = np.arange(len(frames))
    late_ms = 1e3 * (frames.wall_s.to_numpy() - k / 60.0)
    assert (late_ms[frames.shown] > -0.1).all()  # never before its due time
    between = (k % 3 != 0) & (k >= 6)  # due between two steps, after the first draws
    assert np.median(late_ms[between]) < 1.0 and np.percentile(late_ms[between], 90) < 2.0
    # drawn ahead: the frame due 3.3 ms after a step from the step before it (133.3 ms: the 120-ms
    # step); the one due 6.7 ms after a step from that step (116.7 ms: the 110-ms step), since the
    # frame due at the step before (100 ms) leaves no time for a second draw there; none earlier
    drawn_from = frames.sim_time.to_numpy()
    assert drawn_from[7] == pytest.approx(0.11) and drawn_from[8] == pytest.approx(0.12)
    assert (k / 60.0 - drawn_from < 0.02 + 1e-9).all()
