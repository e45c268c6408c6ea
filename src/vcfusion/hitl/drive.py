"""One trip driven by a person (`vcfusion drive`), and the wheel calibration (`--calibrate`).

The trip is the scenario's ordinary run (build_cosimulation: camera, fusion, cloud guidance),
with the driver model replaced by a HumanDriver; it lands in an ordinary run folder with two
more tables (inputs, frames) and the summary's `realtime` and `hitl` blocks, so every metric and
study that reads run folders reads human trips too.

At real speed the fusion stage runs in a worker process beside the loop (vcfusion.hitl.pipeline):
the loop never waits for a vision tick (one due while the worker is busy is dropped and counted).
There, too, the heap built before the trip is frozen out of the garbage collector's collections
for the trip (vcfusion.hitl.gcpause.frozen_heap), and every collection is timed (the frames'
`gc_ms`, the summary's `gc_collections`).
"""

from __future__ import annotations

import shutil
import time as wallclock
from contextlib import nullcontext
from pathlib import Path

from vcfusion.errors import UsageError
from vcfusion.scenario import Scenario

INSTRUCTIONS = [
    "vcfusion: drive the ego car",
    "",
    "Keyboard: Up / W throttle, Down / S brake, Left / A and Right / D steer,",
    "Q / E change lane left / right.  Wheel: steer and pedals (paddles change lane).",
    "Drive to the end of the trip. Highlighted cars may change into your lane",
    "(yellow: maybe, red: likely) when guidance is on.",
    "",
    "Press Enter, Space or a wheel button to start; Escape ends the trip.",
]


def drive(scenario: Scenario, seed: int, *, input_spec: str, guidance_on: bool, speed: float | None,
          out_dir: Path | None, participant: str = "", axis_map_file: Path | None = None,
          record_video: bool = False, window: bool = True, headless: bool = False,
          display_fps: float = 30.0, start_screen_s: float | None = None, on_start=None, shared_window=None,
          vision_pipeline: bool | None = None):
    """Drive one trip; returns the RunResult (run folder written when out_dir is given).
    `start_screen_s`: how long the instruction screen waits at most (None: until a key press;
    replays skip it); `on_start`: called when the trip's clock starts (other recorders of a study,
    e.g. an eye tracker, start with it); `shared_window`: a Window to draw in and leave open (a
    study session keeps one window for all its screens and trips). `vision_pipeline`: run the fusion
    stage in a worker process beside the loop (vcfusion.hitl.pipeline); None: where the drive is
    paced to the wall clock (`speed` set) and the scenario fuses the camera; False: in the loop."""
    from vcfusion.hitl.inputs import open_input
    from vcfusion.hitl.sdl import init_sdl

    if scenario.ego is None:
        raise UsageError(f"{scenario.source}: ego: a person drives the ego; the scenario has no ego block")
    replay = input_spec.startswith("replay:")
    if speed is None and not replay:
        raise UsageError("--speed max: only for replay:FILE inputs (a person drives in real time)")
    if out_dir is not None and Path(out_dir).exists():
        raise UsageError(f"--out: {out_dir} already exists; choose a new run folder")
    if record_video and (not window or out_dir is None):
        raise UsageError("--record-video: needs the window and a run folder")
    if vision_pipeline is None:
        vision_pipeline = speed is not None and scenario.fusion.enabled
    if vision_pipeline and not scenario.fusion.enabled:
        raise UsageError(f"{scenario.source}: fusion.enabled: the vision pipeline runs the fusion stage; the "
                         "scenario has none")
    pygame = init_sdl(headless) if (window or not replay) else None
    device = open_input(input_spec, axis_map_file)

    pipeline = None
    if vision_pipeline:
        from vcfusion.hitl.pipeline import VisionPipeline

        # started first: the worker loads the detector while SUMO and the renderer start here
        pipeline = VisionPipeline(scenario, seed, lossless=speed is None)
    try:
        return _drive(scenario, seed, pipeline, pygame, device, replay, input_spec=input_spec,
                      guidance_on=guidance_on, speed=speed, out_dir=out_dir, participant=participant,
                      record_video=record_video, window=window, display_fps=display_fps,
                      start_screen_s=start_screen_s, on_start=on_start, shared_window=shared_window)
    finally:
        if pipeline is not None:
            pipeline.close()  # on every exit: the end of the trip, an error, Ctrl-C


def _drive(scenario, seed, pipeline, pygame, device, replay, *, input_spec, guidance_on, speed, out_dir, participant,
           record_video, window, display_fps, start_screen_s, on_start, shared_window):
    from vcfusion.control.stage import ControllerStage
    from vcfusion.hitl.gcpause import GcPauses, frozen_heap
    from vcfusion.hitl.driver import HumanDriver
    from vcfusion.hitl.vehicle import VehicleModel
    from vcfusion.run import build_cosimulation, manifest_for
    from vcfusion.runio import write_run_folder
    from vcfusion.traffic.network import read_road, read_vehicle_types
    from vcfusion.traffic.session import frame_of

    cosim = build_cosimulation(scenario, seed, guidance_enabled=guidance_on,
                               fusion_hook=pipeline.hook if pipeline is not None else None)
    if pipeline is not None:  # the camera stage renders the ticks the worker takes
        pipeline.hook.gate(next(h for h in cosim.hooks if h.table == "camera"))
    ego = scenario.ego
    # the ego's own route (a scenario may give it one): its positions and the loop's s_front are along it
    road = frame_of(scenario, read_road(scenario.network, scenario.route), ego.route)
    vtype = read_vehicle_types(scenario.vehicle_types)[ego.vtype]
    vehicle = VehicleModel(road, ego.speed_mps, float(road.lane_centre_d(ego.lane, ego.depart_pos_m)),
                           float(vtype.get("width", 1.8)), max_speed_mps=float(vtype.get("maxSpeed", 55.56)))
    renderer = win = video = staging = None
    owns_renderer = False
    if window:
        from vcfusion.hitl.display import Window

        camera_hook = next((h for h in cosim.hooks if h.table == "camera"), None)
        if camera_hook is not None:
            renderer = camera_hook.renderer  # one OpenGL context for the vision tick and the display
        else:
            from vcfusion.render.renderer import EgoCameraRenderer

            renderer, owns_renderer = EgoCameraRenderer.for_scenario(scenario), True
        win = shared_window or Window(pygame, (scenario.camera.width_px, scenario.camera.height_px),
                                      f"vcfusion drive: {scenario.name} seed {seed}")
        if record_video:
            import tempfile

            from vcfusion.fusion.overlay import OverlayRecorder
            from vcfusion.runio import video_staging_prefix

            # staged beside the run folder (same file system) and moved into it with the tables
            Path(out_dir).parent.mkdir(parents=True, exist_ok=True)
            staging = Path(tempfile.mkdtemp(prefix=video_staging_prefix(out_dir), dir=Path(out_dir).parent))
            video = OverlayRecorder(staging / "video", fps=display_fps, write_png=False, video_name="drive.mp4")
    gc_pauses = GcPauses()
    info = {"participant": participant, "input": device.name, "seed": seed,
            "axis_map": device.map.model_dump() if hasattr(device, "map") else None}
    # the person at the wheel, as a controller of the API (vcfusion.control)
    cosim.controller = ControllerStage(HumanDriver(device, vehicle, scenario.simulation.step_s,
                                                   ego.depart_pos_m + ego.trip_distance_m, guidance_on=guidance_on,
                                                   speed=speed, display_fps=display_fps, pygame=pygame, window=win,
                                                   renderer=renderer, video=video, info=info, on_start=on_start,
                                                   vision=pipeline, gc_pauses=gc_pauses))
    try:
        if win is not None and not replay:
            from vcfusion.hitl.driver import forward_controls

            win.wait_for_start(INSTRUCTIONS + [f"guidance: {'on' if guidance_on else 'off'}"],
                               forward_controls(pygame, device), start_screen_s)
        if pipeline is not None:
            pipeline.wait_ready()  # the trip's clock starts with the vision worker ready
        # paced: the set-up's heap out of the trip's collections (vcfusion.hitl.gcpause)
        with gc_pauses, frozen_heap() if speed is not None else nullcontext():
            result = cosim.run()
        if out_dir is not None:
            extra = {}
            if video is not None:
                extra = {"drive.mp4": video.close() / "drive.mp4"}
                video = None
            manifest = manifest_for(scenario, seed) | {"hitl": info | {"guidance": guidance_on}}
            write_run_folder(Path(out_dir), result.tables, manifest, result.summary, extra_files=extra)
            result.tables.relocate(Path(out_dir))
    finally:
        if video is not None:
            video.abort()
        if staging is not None:
            shutil.rmtree(staging, ignore_errors=True)
        if owns_renderer:
            renderer.close()
        if win is not None and win is not shared_window:
            win.close()
    return result


def calibrate(out_path: Path, *, headless: bool = False, phase_s: float = 4.0, joystick_index: int = 0,
              size: tuple[int, int] = (800, 450), on_phase=None):
    """Ask the person to hold each control in turn and write the axis map to `out_path`.

    Phases (each `phase_s`; the reading is the median of its second half): wheel full left, full
    right, throttle floored, brake floored, the lane-change paddles (or buttons) left and right,
    then everything released. The rest reading comes last because SDL reports an axis that sent
    nothing yet as 0: after each pedal was pressed once, the released pedals report their true rest
    value. A paddle is the button held through most of its phase; with none held, the device's
    preset's button (if any) is kept. `on_phase(name)` is called as each phase starts."""
    import numpy as np

    from vcfusion.hitl.calibration import axis_map_from_phases, preset_for
    from vcfusion.hitl.display import Window, text_screen
    from vcfusion.hitl.sdl import init_sdl

    pygame = init_sdl(headless)
    pygame.event.pump()
    if pygame.joystick.get_count() <= joystick_index:
        raise UsageError("--calibrate: SDL sees no joystick or wheel; is it plugged in?")
    js = pygame.joystick.Joystick(joystick_index)
    js.init()
    win = Window(pygame, size, "vcfusion drive --calibrate")
    prompts = {"steer_left": "Turn the wheel fully LEFT and hold it", "steer_right": "Turn the wheel fully RIGHT and hold it",
               "throttle": "Floor the THROTTLE pedal and hold it", "brake": "Press the BRAKE pedal fully and hold it",
               "lane_left": "Hold the LEFT paddle (lane change left); no paddle: wait",
               "lane_right": "Hold the RIGHT paddle (lane change right); no paddle: wait",
               "rest": "Centre the wheel; feet off all pedals"}
    readings: dict[str, list[float]] = {}
    held_buttons: dict[str, int | None] = {}
    try:
        for phase, prompt in prompts.items():
            samples, buttons = [], []
            if on_phase is not None:
                on_phase(phase)
            started = wallclock.perf_counter()
            while (elapsed := wallclock.perf_counter() - started) < phase_s:
                pygame.event.pump()
                win.show(text_screen(size, [js.get_name(), "", prompt, f"{phase_s - elapsed:.0f}"]))
                if elapsed >= phase_s / 2:
                    samples.append([js.get_axis(i) for i in range(js.get_numaxes())])
                    buttons.append([js.get_button(i) for i in range(js.get_numbuttons())])
                wallclock.sleep(0.02)
            if phase.startswith("lane_"):
                share = np.mean(np.array(buttons, dtype=float), axis=0) if buttons and buttons[0] else np.zeros(0)
                held_buttons[phase] = int(np.argmax(share)) if len(share) and share.max() > 0.5 else None
            else:
                readings[phase] = [float(v) for v in np.median(np.array(samples), axis=0)]
    finally:
        win.close()
    rest = readings.pop("rest")
    axis_map = axis_map_from_phases(rest, readings, device=js.get_name())
    preset = preset_for(js.get_name(), js.get_numaxes())
    paddles = {f"{phase}_button": held if held is not None else getattr(preset, f"{phase}_button", None)
               for phase, held in held_buttons.items()}
    axis_map = axis_map.model_copy(update=paddles)
    axis_map.save(Path(out_path))
    return axis_map
