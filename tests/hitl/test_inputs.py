"""Input layer: axis maps, calibration, SDL's virtual joystick (real SDL, dummy video driver)."""

import json

import pytest

from vcfusion.errors import UsageError
from vcfusion.hitl.calibration import PRESETS, AxisMap, AxisRange, axis_map_from_phases, load_axis_map, preset_for
from vcfusion.hitl.inputs import JoystickInput, ReplayInput
from vcfusion.hitl.sdl import VirtualJoystick, init_sdl


def test_calibration_finds_axes_ranges_and_inversion_and_round_trips(tmp_path):
    # a wheel on axis 1 (left = +0.9, right = -0.95: inverted), throttle on axis 3 (rest +1,
    # floored -1: inverted), brake on axis 0 (rest -1, pressed +0.8), axis 2 noise
    rest = [-1.0, 0.0, 0.01, 1.0]
    held = {"steer_left": [-1.0, 0.9, 0.02, 1.0], "steer_right": [-1.0, -0.95, 0.0, 1.0],
            "throttle": [-1.0, 0.0, 0.02, -1.0], "brake": [0.8, 0.0, 0.0, 1.0]}
    m = axis_map_from_phases(rest, held, device="test wheel")
    assert (m.steer.axis, m.throttle.axis, m.brake.axis) == (1, 3, 0)
    assert m.steer.inverted and m.throttle.inverted and not m.brake.inverted
    assert m.steer.steer(0.9) == pytest.approx(1.0) and m.steer.steer(-0.95) == pytest.approx(-1.0)
    assert m.throttle.pedal(1.0) == 0.0 and m.throttle.pedal(-1.0) == 1.0
    assert m.brake.pedal(-1.0) == 0.0 and m.brake.pedal(0.8) == 1.0 and m.brake.pedal(-0.1) == pytest.approx(0.5)
    path = tmp_path / "wheel.json"
    m.save(path)
    assert load_axis_map(path) == m
    assert not list(tmp_path.glob("*.tmp-writing*"))


def test_a_wheel_that_turns_further_one_way_rests_at_zero_steer():
    # full left reads -1.0, full right only 0.8, at rest 0.0: read linearly over -1 .. 0.8 the centred
    # wheel steered 11 % right; the rest reading is the centre, each side scaled on its own
    rest = [0.0, 1.0, 1.0]
    held = {"steer_left": [-1.0, 1.0, 1.0], "steer_right": [0.8, 1.0, 1.0], "throttle": [0.0, -1.0, 1.0],
            "brake": [0.0, 1.0, -1.0]}
    steer = axis_map_from_phases(rest, held).steer
    assert steer.centre == 0.0 and steer.steer(0.0) == 0.0
    assert steer.steer(-1.0) == pytest.approx(1.0) and steer.steer(0.8) == pytest.approx(-1.0)
    assert steer.steer(-0.5) == pytest.approx(0.5) and steer.steer(0.4) == pytest.approx(-0.5)
    assert steer.steer(0.95) == pytest.approx(-1.0)  # past the calibrated lock: full lock
    # without a centre (the presets, maps written before): halfway, as before
    assert AxisRange(axis=0, min=-1.0, max=0.8).steer(-0.1) == pytest.approx(0.0)
    with pytest.raises(ValueError, match="centre"):
        AxisRange(axis=0, min=-1.0, max=0.8, centre=0.9)


def test_calibration_refuses_a_control_that_moved_nothing():
    rest = [0.0, 0.0, 0.0]
    held = {"steer_left": [-1.0, 0, 0], "steer_right": [1.0, 0, 0], "throttle": [0.0, 0.9, 0], "brake": [0, 0, 0.05]}
    with pytest.raises(UsageError, match="no axis moved for brake"):
        axis_map_from_phases(rest, held)


def test_a_bad_axis_map_file_is_named_with_its_field(tmp_path):
    path = tmp_path / "bad.json"
    data = PRESETS["G29"].model_dump()
    data["brake"]["min"] = 1.0  # max must be above min
    path.write_text(json.dumps(data))
    with pytest.raises(UsageError, match=r"bad.json: brake"):
        load_axis_map(path)
    data = PRESETS["G29"].model_dump()
    data["brake"]["axis"] = data["throttle"]["axis"]
    path.write_text(json.dumps(data))
    with pytest.raises(UsageError, match="three different axes"):
        load_axis_map(path)


def test_presets_by_device_name():
    assert preset_for("Logitech G29 Driving Force Racing Wheel USB", 6) == PRESETS["G29"]
    assert preset_for("Logitech G923 Racing Wheel for Xbox One and PC", 4) == PRESETS["G923"]
    assert preset_for("Xbox Wireless Controller", 6).steer.deadzone > 0
    assert preset_for("Some Stick", 2) is None


@pytest.fixture(scope="module")
def sdl():
    return init_sdl(headless=True)


def test_untouched_pedals_read_released_and_touched_ones_follow_the_map(sdl):
    js = VirtualJoystick(axes=4, buttons=6)
    try:
        device = JoystickInput(js.pygame_joystick, PRESETS["G29"])  # pedals: +1 released, -1 floored
        for event in sdl.event.get():
            device.handle(event)
        control, raw = device.sample(0.0, 0.01)
        # SDL reports 0 for every axis at first: with the G29 map that would be half pressed
        assert raw["axes"][2] == 0.0 and PRESETS["G29"].throttle.pedal(0.0) == pytest.approx(0.5)
        assert (control.throttle, control.brake, control.steer) == (0.0, 0.0, 0.0)
        js.set_axis(2, -1.0)  # throttle floored
        js.set_axis(0, -0.5)  # wheel half left
        js.set_button(5, True)  # left paddle
        for event in sdl.event.get():
            device.handle(event)
        control, _ = device.sample(0.01, 0.01)
        assert control.throttle == pytest.approx(1.0, abs=1e-4)
        assert control.brake == 0.0  # still untouched
        assert control.steer == pytest.approx(0.5, abs=1e-4) and control.lane_change == 1
        assert device.sample(0.02, 0.01)[0].lane_change == 0  # a button press asks once
    finally:
        js.detach()


def test_an_axis_map_naming_an_axis_the_device_lacks_is_named_by_its_file(sdl, tmp_path):
    # the message named the map's device field, "axis map '': ..." for a hand-written file
    from vcfusion.hitl.inputs import open_input

    data = PRESETS["G29"].model_dump() | {"device": ""}
    data["brake"] = dict(data["brake"], axis=9)
    path = tmp_path / "wheel.json"
    path.write_text(json.dumps(data))
    js = VirtualJoystick(axes=4, buttons=6)
    try:
        with pytest.raises(UsageError, match=rf"{path.name}: axis 9 used, but .* has 4 axes"):
            open_input("joystick", path)
    finally:
        js.detach()


def test_an_unplugged_wheel_releases_the_pedals_and_is_taken_back_when_plugged_in(sdl):
    js = VirtualJoystick(axes=4, buttons=6)
    try:
        device = JoystickInput(js.pygame_joystick, PRESETS["G29"])
        js.set_axis(2, -1.0)  # throttle floored
        for event in sdl.event.get():
            device.handle(event)
        assert device.sample(0.0, 0.01)[0].throttle == pytest.approx(1.0, abs=1e-4)
    finally:
        js.detach()
    for event in sdl.event.get():
        device.handle(event)
    # SDL would read the lost axes as 0: both Logitech pedals half pressed
    lost = [device.sample(t, 0.01)[0] for t in (0.01, 0.02)]
    assert all((c.throttle, c.brake, c.steer) == (0.0, 0.0, 0.0) for c in lost)
    assert device.disconnects == [0.01]
    again = VirtualJoystick(axes=4, buttons=6)
    try:
        for event in sdl.event.get():
            device.handle(event)
        assert device.connected and device.sample(0.03, 0.01)[0].throttle == 0.0  # untouched again
        again.set_axis(3, -1.0)  # brake floored on the device plugged back in
        for event in sdl.event.get():
            device.handle(event)
        assert device.sample(0.04, 0.01)[0].brake == pytest.approx(1.0, abs=1e-4)
        assert device.disconnects == [0.01]
    finally:
        again.detach()


def test_a_pedal_within_its_dead_zone_reads_released():
    brake = AxisRange(axis=3, min=-1.0, max=1.0, inverted=True, deadzone=0.1)  # +1 released, -1 floored
    assert brake.pedal(0.95) == 0.0 and brake.pedal(0.85) == 0.0
    assert brake.pedal(-1.0) == pytest.approx(1.0) and brake.pedal(0.0) == pytest.approx((0.5 - 0.1) / 0.9)


def test_replay_files_are_checked_and_sampled_and_held(tmp_path):
    path = tmp_path / "r.csv"
    path.write_text("time_s,throttle,brake,steer,lane_change\n0.0,0.5,0,0,0\n1.0,0,0.2,-0.3,1\n")
    r = ReplayInput(path)
    assert r.sample(0.5, 0.01)[0].throttle == 0.5
    c = r.sample(1.0, 0.01)[0]
    assert (c.throttle, c.brake, c.steer, c.lane_change) == (0.0, 0.2, -0.3, 1)
    assert r.sample(1.01, 0.01)[0].lane_change == 0 and r.sample(5.0, 0.01)[0].brake == 0.2
    path.write_text("time_s,throttle,brake\n0.0,0.5,0\n")
    with pytest.raises(UsageError, match="missing column 'steer'"):
        ReplayInput(path)
    path.write_text("time_s,throttle,brake,steer\n0.0,1.5,0,0\n")
    with pytest.raises(UsageError, match=r"r.csv: column 'throttle', row 1"):
        ReplayInput(path)


def test_calibrate_reads_a_virtual_wheel_held_in_each_position(sdl, tmp_path):
    from vcfusion.hitl.drive import calibrate

    js = VirtualJoystick(axes=4, buttons=3)
    # what the person does in each phase: wheel on axis 0, throttle axis 2, brake axis 3 (pedals
    # +1 released, -1 floored, as Logitech pedals); the left paddle is button 2, no right paddle
    positions = {"steer_left": {0: -1.0}, "steer_right": {0: 1.0}, "throttle": {0: 0.0, 2: -1.0},
                 "brake": {2: 1.0, 3: -1.0}, "lane_left": {3: 1.0}, "lane_right": {}, "rest": {}}

    def act(phase):
        for a, v in positions[phase].items():
            js.set_axis(a, v)
        js.set_button(2, phase == "lane_left")

    try:
        axis_map = calibrate(tmp_path / "wheel.json", headless=True, phase_s=0.6, size=(160, 120), on_phase=act)
    finally:
        js.detach()
    assert (axis_map.lane_left_button, axis_map.lane_right_button) == (2, None)
    assert (axis_map.steer.axis, axis_map.throttle.axis, axis_map.brake.axis) == (0, 2, 3)
    assert not axis_map.steer.inverted and axis_map.throttle.inverted and axis_map.brake.inverted
    assert (axis_map.throttle.min, axis_map.throttle.max) == pytest.approx((-1.0, 1.0), abs=1e-3)
    assert load_axis_map(tmp_path / "wheel.json") == axis_map


def test_drive_refuses_bad_input_with_exit_2(tmp_path, capsys):
    from scenario_files import SCENARIOS

    from vcfusion.commands import main

    assert main(["drive", str(SCENARIOS / "accident.yaml"), "--speed", "max", "--headless"]) == 2
    assert "--speed max: only for replay" in capsys.readouterr().err
    (tmp_path / "in.csv").write_text("time_s,throttle,brake\n0,0,0\n")
    assert main(["drive", str(SCENARIOS / "accident.yaml"), "--input", f"replay:{tmp_path / 'in.csv'}",
                 "--out", str(tmp_path / "run"), "--no-window"]) == 2
    assert "missing column 'steer'" in capsys.readouterr().err
    assert not (tmp_path / "run").exists()


def test_the_window_shows_the_image_as_given(sdl):
    import numpy as np

    from vcfusion.hitl.display import HudInfo, Window, compose

    image = np.zeros((60, 80, 3), np.uint8)
    image[:, :40] = (200, 30, 10)  # left half red-ish, a white square at the bottom right
    image[50:58, 70:78] = 255
    window = Window(sdl, (80, 60))
    try:
        window.show(image)
        shown = sdl.surfarray.array3d(window.surface).transpose(1, 0, 2)  # (w, h, 3) -> (h, w, 3)
        assert (shown == image).all()
        hud = compose(image, [], HudInfo(1.0, 10.0, 100.0, False))
        assert (hud[:, 40:][hud[:, 40:].sum(axis=2) > 0].shape[0]) > 64  # HUD text drawn over the black half
    finally:
        window.close()


def test_keys_pressed_with_the_start_key_reach_the_drive(sdl):
    from vcfusion.hitl.display import Window
    from vcfusion.hitl.inputs import KeyboardInput

    window = Window(sdl, (160, 120))
    try:
        sdl.event.clear()
        for key in (sdl.K_RETURN, sdl.K_UP):
            sdl.event.post(sdl.event.Event(sdl.KEYDOWN, key=key, mod=0, unicode="", scancode=0))
        window.wait_for_start(["start"], lambda event: None, timeout_s=1.0)
        keyboard = KeyboardInput()
        for event in sdl.event.get():
            keyboard.handle(event)
        assert keyboard.sample(0.0, 0.1)[0].throttle > 0  # Up, pressed right after Enter, is held
    finally:
        window.close()


def test_a_driving_key_held_before_the_start_key_drives_from_the_first_step(sdl):
    # Up pressed while reading the instructions, held, then Enter: SDL sends no repeat, so the
    # swallowed key-down left the throttle at 0 for the whole trip; a lane key pressed there does
    # not queue a lane change
    from vcfusion.hitl.display import Window
    from vcfusion.hitl.driver import forward_controls
    from vcfusion.hitl.inputs import KeyboardInput

    window = Window(sdl, (160, 120))
    try:
        sdl.event.clear()
        keyboard = KeyboardInput()
        for key in (sdl.K_UP, sdl.K_q, sdl.K_RETURN):
            sdl.event.post(sdl.event.Event(sdl.KEYDOWN, key=key, mod=0, unicode="", scancode=0))
        window.wait_for_start(["start"], forward_controls(sdl, keyboard), timeout_s=1.0)
        controls = [keyboard.sample(0.1 * k, 0.1)[0] for k in range(10)]
        assert controls[-1].throttle > 0.5 and not any(c.lane_change for c in controls)
    finally:
        window.close()
