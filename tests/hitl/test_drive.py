"""`vcfusion drive` end to end on real SUMO, real SDL (dummy video driver) and the real renderer:
a virtual joystick and posted key events drive the ego; replays reproduce trips exactly."""

import os
import subprocess
import sys
import threading
import time

import numpy as np
import pandas as pd
import pytest
from scenario_files import SCENARIOS, write_scenario

from vcfusion.scenario import load_scenario

# Tables that depend on the simulation alone (camera / fusion tables carry wall-clock timings,
# inputs / frames are the wall-clock record itself).
SIMULATION_TABLES = ("trajectories", "ego", "twins", "vehicles", "collisions", "lane_changes", "guidance")

SCENARIO = """
name: hitl_test
network: NET_DIR/highway.net.xml
vehicle_types: NET_DIR/vtypes.add.xml
simulation: {step_s: 0.01, max_time_s: MAX_TIME, lanechange_duration_s: 3.0, trajectory_period_s: 0.1}
v2c: {period_s: 0.1}
camera: {width_px: 160, height_px: 120}
ego: {vtype: ego, lane: 1, depart_pos_m: 80.0, speed_mps: 15.0, desired_speed_mps: 15.0, trip_distance_m: 900.0}
vehicles:
VEHICLES
"""
FAR_AHEAD = "  - {name: far, count: 1, vtype: car, lanes: [0], pos_m: [600.0, 601.0], speed_mps: 15.0, desired_speed_mps: 15.0}"


def scenario(tmp_path, max_time: float, vehicles: str = FAR_AHEAD, name: str = "s.yaml"):
    text = SCENARIO.replace("MAX_TIME", str(max_time)).replace("VEHICLES", vehicles)
    return load_scenario(write_scenario(tmp_path, text, name))


@pytest.fixture(scope="module")
def sdl():
    from vcfusion.hitl.sdl import init_sdl

    return init_sdl(headless=True)


def ego_trace(run_dir) -> pd.DataFrame:
    t = pd.read_parquet(run_dir / "trajectories.parquet")
    return t[t.vehicle_id == "ego"].set_index("time")


def drive(sc, out, **kw):
    from vcfusion.hitl.drive import drive as run_drive

    defaults = dict(seed=0, guidance_on=True, speed=1.0, headless=True, display_fps=15.0, start_screen_s=0.0)
    return run_drive(sc, out_dir=out, **(defaults | kw))


def at_wall_times(actions):
    """(wall seconds from the trip's start, action) pairs played in a thread: a person acting on
    the clock. Returns (the thread, the drive's on_start)."""
    go = threading.Event()

    def play():
        go.wait(60)
        started = time.perf_counter()
        for at, act in actions:
            time.sleep(max(0.0, at - (time.perf_counter() - started)))
            act()
    thread = threading.Thread(target=play, daemon=True)
    thread.start()
    return thread, go.set


@pytest.mark.slow
def test_a_virtual_joystick_drives_the_ego(tmp_path, sdl):
    from vcfusion.hitl.calibration import PRESETS
    from vcfusion.hitl.sdl import VirtualJoystick

    js = VirtualJoystick(axes=4, buttons=6)
    (tmp_path / "wheel.json").write_text(PRESETS["G29"].model_dump_json())
    try:
        # pedals +1 released / -1 floored (G29 map); wheel: negative = left
        thread, on_start = at_wall_times([(0.3, lambda: js.set_axis(2, -1.0)), (0.3, lambda: js.set_axis(3, 1.0)),
                                          (2.5, lambda: js.set_axis(2, 1.0)),
                                (2.5, lambda: js.set_axis(3, 0.0)),  # brake half pressed
                                (4.0, lambda: js.set_axis(3, 1.0)), (4.0, lambda: js.set_axis(0, -0.6)),
                                (6.5, lambda: js.set_axis(0, 0.0))])
        result = drive(scenario(tmp_path, 9.0), tmp_path / "run", input_spec="joystick",
                       axis_map_file=tmp_path / "wheel.json", on_start=on_start)
        thread.join()
    finally:
        js.detach()
    inputs = pd.read_parquet(tmp_path / "run" / "inputs.parquet")
    ego = ego_trace(tmp_path / "run")
    throttle = inputs.sim_time[inputs.throttle > 0.99]
    brake = inputs.sim_time[inputs.brake > 0.49]
    steer = inputs.sim_time[inputs.steer > 0.59]
    assert len(throttle) > 100 and len(brake) > 50 and len(steer) > 100
    speed_at = lambda t: float(np.interp(t, ego.index, ego.speed))  # noqa: E731
    assert speed_at(throttle.max()) > speed_at(throttle.min()) + 3.0  # ~3 m/s^2 while floored
    assert speed_at(brake.max()) < speed_at(brake.min()) - 3.0  # ~4.5 m/s^2 at half brake
    assert ego.lane.iloc[0] == 1 and ego.lane.iloc[-1] == 2  # steered one lane to the left
    assert result.summary["collisions"] == 0
    assert result.summary["hitl"]["input"].startswith("joystick:Virtual")


@pytest.mark.slow
def test_followers_brake_for_the_steered_ego_and_collisions_are_detected(tmp_path):
    # ego in lane 1; a follower in lane 0 behind it. The ego steers into lane 0 and brakes to a stop.
    follower = "  - {name: follower, count: 1, vtype: car, lanes: [0], pos_m: [50.0, 50.01], speed_mps: 15.0, desired_speed_mps: 15.0}"
    (tmp_path / "in.csv").write_text("time_s,throttle,brake,steer\n0,0,0,0\n0.5,0,0,-0.5\n4,0,0,0\n5,0,0.6,0\n")
    drive(scenario(tmp_path, 12.0, follower), tmp_path / "run", input_spec="replay:" + str(tmp_path / "in.csv"),
          speed=None, window=False)
    t = pd.read_parquet(tmp_path / "run" / "trajectories.parquet")
    ego, fol = (t[t.vehicle_id == v].set_index("time") for v in ("ego", "follower0"))
    assert ego.lane.iloc[-1] == 0 and ego.speed.iloc[-1] == 0.0
    assert fol.speed.min() < 1.0  # it stopped behind the ego ...
    assert (ego.s - fol.s).loc[fol.index].min() > 4.6  # ... without driving into it
    assert len(pd.read_parquet(tmp_path / "run" / "collisions.parquet")) == 0

    # ego floored in lane 1 toward a slow car ahead in lane 1: SUMO's collision check sees it
    slow = "  - {name: slow, count: 1, vtype: car, lanes: [1], pos_m: [130.0, 130.01], speed_mps: 5.0, desired_speed_mps: 5.0}"
    (tmp_path / "in2.csv").write_text("time_s,throttle,brake,steer\n0,1,0,0\n")
    result = drive(scenario(tmp_path, 8.0, slow, "s2.yaml"), tmp_path / "run2",
                   input_spec="replay:" + str(tmp_path / "in2.csv"), speed=None, window=False)
    collisions = pd.read_parquet(tmp_path / "run2" / "collisions.parquet")
    assert result.summary["collisions"] > 0
    assert (collisions.collider == "ego").all() and (collisions.victim == "slow0").all()


def same_tables(a, b) -> None:
    for name in SIMULATION_TABLES:
        assert (a / f"{name}.parquet").read_bytes() == (b / f"{name}.parquet").read_bytes(), name


@pytest.mark.slow
def test_a_keyboard_drive_recorded_and_replayed_gives_the_same_trip(tmp_path, sdl):
    import pygame

    def key(kind, k):
        return lambda: pygame.event.post(pygame.event.Event(kind, key=k, mod=0, unicode="", scancode=0))

    down, up = pygame.KEYDOWN, pygame.KEYUP
    thread, on_start = at_wall_times([(0.2, key(down, pygame.K_w)), (1.5, key(up, pygame.K_w)), (1.6, key(down, pygame.K_q)),
                            (1.7, key(up, pygame.K_q)), (3.0, key(down, pygame.K_DOWN)), (3.6, key(up, pygame.K_DOWN)),
                            (3.7, key(down, pygame.K_RIGHT)), (4.0, key(up, pygame.K_RIGHT))])
    sc = scenario(tmp_path, 7.0)
    live = drive(sc, tmp_path / "live", input_spec="keyboard", participant="P01", on_start=on_start)
    thread.join()
    inputs = pd.read_parquet(tmp_path / "live" / "inputs.parquet")
    assert "w" in set(inputs["keys"]) and "down" in set(inputs["keys"])
    assert (inputs.lane_change == 1).sum() == 1 and inputs.throttle.max() == 1.0
    rt = live.summary["realtime"]
    assert rt["frames_shown"] > 0 and rt["max_lag_s"] is not None and live.summary["hitl"]["participant"] == "P01"
    frames = pd.read_parquet(tmp_path / "live" / "frames.parquet")
    assert len(frames) == rt["frames_due"] and frames.sim_time.is_monotonic_increasing

    replay = "replay:" + str(tmp_path / "live" / "inputs.parquet")
    drive(sc, tmp_path / "replay1", input_spec=replay, speed=None, record_video=True)
    drive(sc, tmp_path / "replay2", input_spec=replay, speed=None, window=False)
    same_tables(tmp_path / "live", tmp_path / "replay1")
    import cv2

    video = cv2.VideoCapture(str(tmp_path / "replay1" / "drive.mp4"))
    shown = pd.read_parquet(tmp_path / "replay1" / "frames.parquet").shown.sum()
    assert int(video.get(cv2.CAP_PROP_FRAME_COUNT)) == shown > 0  # every displayed frame, none dropped at max
    assert not list(tmp_path.glob(".*video*"))  # the staging folder is gone
    same_tables(tmp_path / "replay1", tmp_path / "replay2")
    ego = ego_trace(tmp_path / "live")
    assert ego.lane.iloc[-1] == 2  # the Q key changed lanes to the left


@pytest.mark.slow
def test_cut_ins_are_judged_against_the_lane_the_person_drives_in(tmp_path):
    # accident scenario: the ego starts in lane 2, the person moves to lane 1 at once and drives
    # slowly; the changers merging from the closed lane 0 into lane 1 now cut into the ego's lane
    sc = load_scenario(SCENARIOS / "accident.yaml")
    sc = sc.model_copy(update={"simulation": sc.simulation.model_copy(update={"max_time_s": 14.0})})
    (tmp_path / "in.csv").write_text("time_s,throttle,brake,steer,lane_change\n0,0,0.15,0,0\n0.2,0,0.15,0,-1\n")
    result = drive(sc, tmp_path / "run", seed=1, input_spec="replay:" + str(tmp_path / "in.csv"), speed=None,
                   window=False)
    lc = pd.read_parquet(tmp_path / "run" / "lane_changes.parquet")
    ego = ego_trace(tmp_path / "run")
    # the person's own lane change is a row too (SUMO does not report a vehicle it is told to place)
    own = lc[lc.vehicle_id == "ego"]
    assert len(own) == 1 and own.reason.iloc[0] == "person"
    assert (own.from_lane.iloc[0], own.to_lane.iloc[0], own.direction.iloc[0]) == (2, 1, -1)
    # midpoint as SUMO defines it: the centre line enters the new lane (SUMO's own lane index of
    # the placed ego follows its front bumper, which crosses earlier)
    assert own.mid_time.iloc[0] == ego.index[ego.d < 7.0][0] >= ego.index[ego.lane == 1][0]
    assert own.start_time.iloc[0] < own.mid_time.iloc[0] < own.end_time.iloc[0]  # centred before and after
    lc = lc[lc.vehicle_id != "ego"]
    lane_at_mid = ego.lane.reindex(lc.mid_time.round(1).to_numpy()).to_numpy()
    assert (lc.into_ego_lane == (lc.to_lane.to_numpy() == lane_at_mid)).all()
    into_lane_1 = lc[lc.into_ego_lane]
    assert len(into_lane_1) >= 2 and (into_lane_1.to_lane == 1).all()  # lane 2 was the start lane
    assert result.summary["cut_ins_ahead_of_ego"] == int((lc.into_ego_lane & lc.ahead_of_ego).sum())
    # SUMO's changers respect the placed ego: none merged into its lane overlapping it (gap =
    # changer's rear - ego's front; overlap: between -(both lengths) and 0), and nothing collided
    overlap = (into_lane_1.gap_to_ego_m < 0) & (into_lane_1.gap_to_ego_m > -(4.6 + 4.6))
    assert not overlap.any() and result.summary["collisions"] == 0


@pytest.mark.slow
def test_a_drive_in_a_real_x11_window(tmp_path):
    # SDL's X11 driver, unlike the dummy one, has an OpenGL framebuffer path that crashed in
    # display.flip after the camera's OSMesa render (sdl.SDL_HINTS)
    path = write_scenario(tmp_path, SCENARIO.replace("MAX_TIME", "1.5").replace("VEHICLES", FAR_AHEAD))
    (tmp_path / "in.csv").write_text("time_s,throttle,brake,steer\n0,0.5,0,0.2\n")
    # -displayfd: Xvfb picks a free display number and writes it when it is ready
    xvfb = subprocess.Popen(["Xvfb", "-displayfd", "1", "-screen", "0", "320x240x24"], stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, text=True)
    try:
        display = ":" + xvfb.stdout.readline().strip()
        env = os.environ | {"DISPLAY": display, "SDL_VIDEODRIVER": "x11"}
        proc = subprocess.run([sys.executable, "-m", "vcfusion", "drive", str(path), "--input",
                               f"replay:{tmp_path / 'in.csv'}", "--speed", "max", "--out", str(tmp_path / "run")],
                              env=env, capture_output=True, text=True, timeout=300)
    finally:
        xvfb.terminate()
        xvfb.wait()
    assert proc.returncode == 0, proc.stderr[-2000:]
    frames = pd.read_parquet(tmp_path / "run" / "frames.parquet")
    assert frames.shown.all() and len(frames) >= 40  # 1.5 s at 30 frames/s


def test_the_car_stays_on_the_lanes_present_where_it_is_and_stops_at_its_top_speed():
    from vcfusion.hitl.vehicle import ControlSample, VehicleModel
    from vcfusion.traffic.network import read_road

    sc = load_scenario(SCENARIOS / "onramp_camera.yaml")
    road = read_road(sc.network, sc.route)  # track 0, the acceleration lane, only along `accel`
    accel_lane = road.lane_spans(0)[0]
    before, inside = accel_lane[0] - 150.0, accel_lane[0] + 50.0
    # full right lock before the acceleration lane: at the barrier of track 1 (it steered the car
    # onto the ramp, where SUMO put it off its route and the trip was lost)
    car = VehicleModel(road, 20.0, float(road.lane_centre_d(1, before)), 1.8, max_speed_mps=40.0)
    for _ in range(100):
        d = car.update(ControlSample(-1.0, 0.0, 0.0), 0.1, before).d
    assert d == pytest.approx(float(road.road_bounds(before)[0]) + 0.9)
    assert car.update(ControlSample(0.0, 0.0, 0.0, lane_change=-1), 0.1, before).target_lane is None  # no lane there
    # where the acceleration lane is, the same lock takes the car into it
    for _ in range(100):
        d = car.update(ControlSample(-1.0, 0.0, 0.0), 0.1, inside).d
    assert int(road.lane_of(inside, d)) == 0
    # throttle floored: the vType's maxSpeed is the top speed
    for _ in range(600):
        top = car.update(ControlSample(0.0, 1.0, 0.0), 0.1, inside).speed
    assert top == pytest.approx(40.0)


def test_where_a_lane_ends_the_barrier_pushes_the_car_out_of_it_gradually_before_the_end():
    # the car left in the acceleration lane: at its end it was pushed 2.65 m across in one step (and
    # SUMO, asked to place it past the end of its lane, dropped it from its route: the trip ended)
    from vcfusion.hitl.vehicle import BARRIER_SLOPE, ControlSample, VehicleModel
    from vcfusion.traffic.network import read_road

    sc = load_scenario(SCENARIOS / "onramp_camera.yaml")
    road = read_road(sc.network, sc.route)
    start, end = road.lane_spans(0)[0]
    s, dt, speed = start + 20.0, 0.01, 20.0
    car = VehicleModel(road, speed, float(road.lane_centre_d(0, s)), 1.8, max_speed_mps=speed)
    d = car.state.d
    steps = []
    while s < end + 30.0:
        new_d = car.update(ControlSample(0.0, 0.0, 0.0), dt, s).d  # wheel centred, no pedals
        steps.append(abs(new_d - d))
        d, s = new_d, s + speed * dt
        if s < end - 3.5 / BARRIER_SLOPE - 1.0:
            assert int(road.lane_of(s, d)) == 0  # far from the end the lane is the car's to keep
        if s >= end:
            assert int(road.lane_of(s, d)) == 1 and d >= float(road.road_bounds(s)[0]) + 0.9 - 1e-9
    assert max(steps) <= BARRIER_SLOPE * speed * dt + 1e-6  # never faster across than the taper


@pytest.mark.slow
def test_a_trip_that_stays_in_the_acceleration_lane_goes_on_past_its_end(tmp_path):
    # two lane changes to the right take the ego into the acceleration lane and it holds its wheel:
    # the trip ended "off route" where that lane ends (SUMO dropped the ego), now it goes on
    sc = load_scenario(SCENARIOS / "onramp_camera.yaml")
    sc = sc.model_copy(update={"simulation": sc.simulation.model_copy(update={"max_time_s": 30.0})})
    replay = tmp_path / "in.csv"
    replay.write_text("time_s,throttle,brake,steer,lane_change\n0,0,0,0,0\n8.0,0,0,0,-1\n8.01,0,0,0,0\n"
                      "12.0,0,0,0,-1\n12.01,0,0,0,0\n")
    result = drive(sc, tmp_path / "run", input_spec=f"replay:{replay}", speed=None)
    assert result.summary["end_reason"] == "max_time"
    ego = ego_trace(tmp_path / "run")
    assert (ego.lane == 0).any()  # it did drive in the acceleration lane
    assert ego.s.max() > 1000.0  # and past its end (about 946 m)


def test_frames_due_between_two_long_steps_count_as_dropped(tmp_path):
    # a 0.1 s SUMO step under a 30 frames/s display: one frame per step can be drawn, the two due
    # in between are dropped frames (they were not counted, and the summary said nothing was lost)
    text = SCENARIO.replace("MAX_TIME", "2.0").replace("VEHICLES", FAR_AHEAD).replace("step_s: 0.01", "step_s: 0.1")
    sc = load_scenario(write_scenario(tmp_path, text))
    (tmp_path / "in.csv").write_text("time_s,throttle,brake,steer\n0,0.2,0,0\n")
    result = drive(sc, tmp_path / "run", input_spec=f"replay:{tmp_path / 'in.csv'}", speed=None, window=True,
                   display_fps=30.0, record_video=True)
    rt = result.summary["realtime"]
    assert rt["frames_shown"] == 20 and rt["frames_due"] == pytest.approx(60, abs=3)
    assert rt["dropped_frames"] == rt["frames_due"] - rt["frames_shown"]
    # the video repeats the frame on the screen for each dropped one: it lasts as long as the trip
    # (it held the 20 frames shown only, at 30 frames/s: a third of the trip's time)
    import cv2

    cap = cv2.VideoCapture(str(tmp_path / "run" / "drive.mp4"))
    assert cap.get(cv2.CAP_PROP_FPS) == pytest.approx(30.0)
    assert cap.get(cv2.CAP_PROP_FRAME_COUNT) == rt["frames_due"]


def test_a_replayed_trip_keeps_its_guidance_condition(tmp_path):
    # replaying a guidance-off trip's inputs without --guidance: the replay is a guidance-off trip
    # (labelled "on" it went to the wrong arm of the guidance study)
    import json

    from vcfusion.commands import main

    path = write_scenario(tmp_path, SCENARIO.replace("MAX_TIME", "1.0").replace("VEHICLES", FAR_AHEAD))
    trip = tmp_path / "trip"
    trip.mkdir()
    (trip / "inputs.csv").write_text("time_s,throttle,brake,steer\n0,0.2,0,0\n")
    (trip / "summary.json").write_text(json.dumps({"hitl": {"guidance": "off"}}))
    for extra, expected in (([], "off"), (["--guidance", "on"], "on")):
        out = tmp_path / f"replayed-{expected}"
        assert main(["drive", str(path), "--input", f"replay:{trip / 'inputs.csv'}", "--speed", "max", "--headless",
                     "--no-window", "--out", str(out), *extra]) == 0
        assert json.loads((out / "summary.json").read_text())["hitl"]["guidance"] == expected


def test_a_replay_drives_the_recorded_trips_seed_and_participant(tmp_path, capsys):
    # a replay of a trip's inputs under another seed was accepted silently (the inputs then steer
    # through other traffic), and the replayed folder lost the participant
    import json

    from vcfusion.commands import main

    path = write_scenario(tmp_path, SCENARIO.replace("MAX_TIME", "1.0").replace("VEHICLES", FAR_AHEAD))
    (tmp_path / "in.csv").write_text("time_s,throttle,brake,steer\n0,0.2,0,0\n")
    common = ["--speed", "max", "--headless", "--no-window"]
    assert main(["drive", str(path), "--input", f"replay:{tmp_path / 'in.csv'}", "--seed", "2", "--participant",
                 "P1", "--out", str(tmp_path / "trip"), *common]) == 0
    replay = f"replay:{tmp_path / 'trip' / 'inputs.parquet'}"
    assert main(["drive", str(path), "--input", replay, "--out", str(tmp_path / "again"), *common]) == 0
    manifest = json.loads((tmp_path / "again" / "manifest.json").read_text())
    assert manifest["seed"] == 2 and manifest["hitl"]["participant"] == "P1"
    for name in ("trajectories", "ego"):
        assert pd.read_parquet(tmp_path / "trip" / f"{name}.parquet").equals(
            pd.read_parquet(tmp_path / "again" / f"{name}.parquet")), name
    capsys.readouterr()
    assert main(["drive", str(path), "--input", replay, "--seed", "5", "--out", str(tmp_path / "other"), *common]) == 2
    assert "was driven on seed 2" in capsys.readouterr().err and not (tmp_path / "other").exists()
    # another scenario: allowed (another camera, say), and said
    other = write_scenario(tmp_path, SCENARIO.replace("MAX_TIME", "0.8").replace("VEHICLES", FAR_AHEAD), "o.yaml")
    assert main(["drive", str(other), "--input", replay, "--out", str(tmp_path / "variant"), *common]) == 0
    assert "driven on another scenario (it differs in: simulation)" in capsys.readouterr().err
