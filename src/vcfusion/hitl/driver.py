"""HumanDriver: the ego controller when a person drives (vcfusion.cosim's per-step controller).

Every SUMO step (`step`):
1. pacing: with `speed` (1 = real time) it waits until the wall clock reaches the step's
   simulated time; a step that starts late is not waited for, and its lag (wall clock minus
   simulated time since the start) is measured. `speed=None` (replays only) runs as fast as the
   machine goes;
2. input: SDL events go to the device, the device gives the step's ControlSample;
3. vehicle model: the controls become the acceleration and the lateral position / yaw that the
   loop imposes on SUMO for the next step;
4. display: when a display frame is due (every 1/display_fps of simulated time) before the next
   step, it renders this step's state of the ego camera (at a tick, the camera stage's render of
   that tick is the same image: reused), draws the overlay and HUD and, paced, shows it when the
   wall clock reaches the frame's due time (flipped at the step itself, a 60 frames/s display over
   10-ms steps showed its frames 10 and 20 ms apart). A paced frame due so soon after the next
   step that its draw would make it late there is drawn a step ahead, where the draw fits before
   that step, and shown from the next step's call (`_draw_ahead`). Frames are dropped before the simulation is
   slowed: when the step is already later than one frame period, the frame is not drawn (unless
   no frame was shown for MAX_FRAME_GAP frame periods, or its image is the tick's render, made
   already: showing it costs the overlay and the flip, about 1 ms, and it is counted late, not
   dropped). A tick's render runs before the step's pacing, so its own time is in the tick's lag:
   the frame it made was the one most often dropped (37-46 % of the drops in profiled drives, a
   third of the frames being at ticks; `tools/hitl_frame_profile.py`). A SUMO step longer than a frame period
   (step_s 0.1 s against 30 frames/s) shows one frame per step: the frames due in between are
   counted as dropped (the display cannot be faster than the simulation's step).
Every step's wall time, simulated time, lag, raw readings and mapped controls go to the
`inputs` table; every displayed or dropped frame to `frames`; `finish` adds both and the
summary's `realtime` block (display_fps_median: 1 / the median interval between shown frames;
frames_shown_per_s; frame_interval_ms_p5 / _p95; late_frames, dropped_frames, max_lag_s,
input_to_display_ms_median, the frame work figures below) and `hitl` block.

Frame work: every due frame's row also says what the loop did in the frame period that ended
with it (from the end of the previous due frame's handling to the end of its own): `work_ms`, the
loop's wall time minus the pacing sleep (SUMO steps, tick stages, render, overlay, flip: above the
frame period the loop cannot keep up), `cpu_ms`, the loop thread's CPU time in it (the work's own
cost; work above it is time the thread waited for a core or for the renderer's threads), and
`gc_ms`, Python's garbage collection pauses in it (with `gc_pauses`, vcfusion.hitl.gcpause). The
summary gives `frame_work_ms_p50` / `_p95` / `_p99`, `frame_cpu_ms_p99`, `frames_over_budget`
(work above one frame period) and the trip's collections (`gc_collections`, `gc_collections_full`,
`gc_pause_ms_max`, `gc_pause_ms_total`). With guidance on and a display, every box drawn on a shown frame goes to `display`
(time, the twin it warns of, level, source, the box, and `box_vehicle_id`: the meant vehicle when
the box covers its visible box at IoU >= 0.5, else the vehicle whose visible box it overlaps most,
judged after drawing (`metrics.highlights.judge_highlight`), for scoring only): the
guidance study counts a person's right and wrong highlights from it, i.e. from what was shown.
"""

from __future__ import annotations

import time as wallclock
from collections import deque
from typing import NamedTuple

import numpy as np

from vcfusion.control.api import Command
from vcfusion.cosim import EgoCommand, EgoStep
from vcfusion.hitl.display import HudInfo, carried_twins, cloud_boxes, compose, tracked_boxes
from vcfusion.hitl.vehicle import VehicleModel


# A late frame is dropped, unless none was shown for this many frame periods: a machine that
# cannot keep real time even without frames would otherwise show a frozen picture; then the
# display keeps about 1/4 of its rate and the lag grows (measured).
MAX_FRAME_GAP = 4
# A frame due after the next SUMO step by less than the longest of the last this-many draws is
# drawn a step early (HumanDriver._draw_ahead): a few frames, so that one slow draw (a collection,
# a busy core) sets the lead for a moment only.
DRAW_TIMES_KEPT = 8


DISPLAY_COLUMNS = ("time", "vehicle_id", "box_vehicle_id", "lc_prob", "level", "source", "x1", "y1", "x2", "y2")


class DrawnFrame(NamedTuple):
    """A display frame drawn and not yet shown (HumanDriver._frame -> _show)."""
    time_s: float  # the simulated time of the state drawn
    lag: float  # the drawing step's lag behind the wall clock, s
    due: float  # the simulated time the frame is due
    image: np.ndarray
    items: list  # the overlay's items drawn on it
    frame: object  # the render (its instance map scores the drawn boxes)
    started: float  # wall clock when the draw started and ended
    drawn: float
    poll: float  # wall clock of the input poll whose command moved the state drawn
    ar_age_ms: float


class DriveAborted(Exception):
    """The person ended the trip (Escape or closing the window): nothing is written."""


class HumanDriver:
    finish_tables = ("inputs", "frames", "display")
    finish_summary = ("realtime", "hitl")

    def __init__(self, device, vehicle: VehicleModel, dt: float, trip_end_s: float, *, guidance_on: bool,
                 speed: float | None = 1.0, display_fps: float = 30.0, pygame=None, window=None, renderer=None,
                 video=None, info: dict | None = None, on_start=None, vision=None, gc_pauses=None):
        self.device = device
        self.vehicle = vehicle
        self.dt = dt
        self.trip_end_s = trip_end_s
        self.guidance_on = guidance_on
        self.speed = speed
        self.frame_period = 1.0 / display_fps
        self.pg = pygame
        self.window = window
        self.renderer = renderer
        self.video = video
        self._last_image = None  # the frame on the screen (the video repeats it for a dropped frame)
        self.info = info or {}
        self.on_start = on_start  # called once when the trip's clock starts (e.g. to start other recorders)
        # the vision worker of a paced drive (vcfusion.hitl.pipeline.VisionPipeline): its newest result
        # is the overlay, read at every display frame; None: the tick's guidance is
        self.vision = vision
        self._shown_result = None
        # the overlay shows the tick's guidance; the HUD works without it
        self.needs = ("ego", "neighbours", "guidance") if guidance_on else ("ego",)
        self._guidance = ()
        self._guidance_source = "none"
        self._shown_set = None  # the GuidanceSet on the screen, and what the car knew when it was made:
        self._update_time = 0.0  # its tick's time, s
        self._update_pose = None  # (K, T_world_to_camera) of the camera at that tick (the ego's own pose)
        self._update_twins = None  # the neighbour twins as the cloud reported them at that tick
        self._wall0: float | None = None
        self._sim0 = 0.0
        self._next_frame = 0.0
        self._last_poll = None
        self._last_shown: float | None = None
        self._tick_frame = None
        # a paced display's draw times (render + overlay + compose, wall s), and a frame drawn a
        # step ahead of its due time, shown from the next step's call
        self._draw_times: deque[float] = deque(maxlen=DRAW_TIMES_KEPT)
        self._ahead: DrawnFrame | None = None
        # frame work (module doc): the garbage collections' timer (vcfusion.hitl.gcpause.GcPauses,
        # entered by the caller), the pacing sleep so far (s) and (wall, thread CPU, sleep, GC) at the
        # end of the last due frame
        self.gc_pauses = gc_pauses
        self._slept = 0.0
        self._mark: tuple[float, float, float, float] | None = None
        self.rows: dict[str, list] = {k: [] for k in ("wall_s", "sim_time", "lag_s", "keys", "raw_axes", "raw_buttons",
                                                      "steer", "throttle", "brake", "lane_change", "accel", "d", "yaw")}
        self.frame_rows: dict[str, list] = {k: [] for k in ("sim_time", "wall_s", "shown", "lag_s", "render_ms",
                                                            "input_to_display_ms", "ar_age_ms", "work_ms",
                                                            "cpu_ms", "gc_ms")}
        self.display_rows: list[dict] = []

    # -- the loop's controller interface ------------------------------------------------
    def acceleration(self, tick) -> float:
        if self.vision is None and tick.guidance is not None and tick.guidance is not self._shown_set:
            # a new overlay (the fusion hook hands the same set again between its updates)
            self._shown_set = tick.guidance
            self._guidance = tick.guidance.items
            self._guidance_source = tick.guidance.source
            self._update_time = tick.time
            self._update_twins = tick.neighbours
            frame = tick.frame
            self._update_pose = (np.asarray(frame.K, float), np.asarray(frame.T_world_to_camera, float)) \
                if hasattr(frame, "T_world_to_camera") else None
        # the camera stage's render of this tick (when it has one) is also this step's display frame
        self._tick_frame = tick.frame if hasattr(tick.frame, "instances") else None
        return self.vehicle.state.accel

    def act(self, observation) -> Command:
        """The controller API's tick call (vcfusion.control): the tick's guidance and camera frame
        go to the display; the pedals and the wheel act every SUMO step (`step`)."""
        return Command(self.acceleration(observation))

    def step(self, st: EgoStep) -> EgoCommand:
        now = wallclock.perf_counter()
        if self._wall0 is None:
            self._wall0, self._sim0, self._next_frame = now, st.time, st.time
            self._mark = (now, wallclock.thread_time(), 0.0, self._gc_total())
            if self.on_start is not None:
                self.on_start()
        lag = 0.0
        if self.speed is not None:
            due = self._wall_at(st.time)
            now = self._sleep_until(due, now)
            lag = max(0.0, now - due)
        if self.pg is not None:
            for event in self.pg.event.get():
                if event.type == self.pg.QUIT or (event.type == self.pg.KEYDOWN and event.key == self.pg.K_ESCAPE):
                    raise DriveAborted("the driver ended the trip (Escape / window closed)")
                self.device.handle(event)
        control, raw = self.device.sample(st.time, self.dt)
        state = self.vehicle.update(control, self.dt, st.s_front)
        r = self.rows
        r["wall_s"].append(now - self._wall0)
        r["sim_time"].append(round(st.time, 6))
        r["lag_s"].append(lag)
        r["keys"].append(raw.get("keys", ""))
        r["raw_axes"].append(raw.get("axes", []))
        r["raw_buttons"].append(raw.get("buttons", []))
        for name in ("steer", "throttle", "brake", "lane_change"):
            r[name].append(getattr(control, name))
        r["accel"].append(state.accel)
        r["d"].append(state.d)
        r["yaw"].append(state.yaw)
        if self._ahead is not None:  # drawn at an earlier step, due before the next one
            self._show(self._ahead)
            self._ahead = None
        if self.renderer is not None and self._next_frame < st.time + self.dt - 1e-9:
            due = []  # the frames due before the next step
            while self._next_frame < st.time + self.dt - 1e-9:
                due.append(self._next_frame)
                self._next_frame += self.frame_period
            # the first shows this step's state at its own due time; the others (a step longer than
            # a frame period) have nothing new to show: they count as dropped
            self._frame(st, lag, due[0])
            for later in due[1:]:
                self._dropped(later, lag)
        if self.renderer is not None and self.speed is not None and self._draw_ahead(st):
            self._frame(st, lag, self._next_frame, ahead=True)
            self._next_frame += self.frame_period
        self._last_poll = now
        return EgoCommand(state.accel, state.d, state.yaw)

    def _dropped(self, sim_time: float, lag: float) -> None:
        if self.video is not None and self._last_image is not None:
            # the screen kept the last frame shown: so does the video, which then plays in simulated
            # time (without it a drive with dropped frames gave a video seconds shorter than the trip)
            self.video.add(self._last_image)
        f = self.frame_rows
        f["sim_time"].append(round(sim_time, 6))
        f["wall_s"].append(wallclock.perf_counter() - self._wall0)
        f["shown"].append(False)
        f["lag_s"].append(lag)
        f["render_ms"].append(np.nan)
        f["input_to_display_ms"].append(np.nan)
        f["ar_age_ms"].append(np.nan)
        self._close_period()

    def _wall_at(self, sim_time: float) -> float:
        """The wall clock at which a paced drive reaches `sim_time`."""
        return self._wall0 + (sim_time - self._sim0) / self.speed

    def _sleep_until(self, wall: float, now: float) -> float:
        """Sleep until the wall clock reaches `wall` (the pacing sleep, counted); the time after."""
        if now >= wall:
            return now
        wallclock.sleep(wall - now)
        woke = wallclock.perf_counter()
        self._slept += woke - now
        return woke

    def _gc_total(self) -> float:
        return self.gc_pauses.total_s if self.gc_pauses is not None else 0.0

    def _close_period(self) -> None:
        """The frame work of the period that ends with this due frame (module doc)."""
        now, cpu, gc_total = wallclock.perf_counter(), wallclock.thread_time(), self._gc_total()
        wall0, cpu0, slept0, gc0 = self._mark
        f = self.frame_rows
        f["work_ms"].append(1000.0 * (now - wall0 - (self._slept - slept0)))
        f["cpu_ms"].append(1000.0 * (cpu - cpu0))
        f["gc_ms"].append(1000.0 * (gc_total - gc0))
        self._mark = (now, cpu, self._slept, gc_total)

    def _draw_ahead(self, st: EgoStep) -> bool:
        """Whether the next frame is drawn now, a step early: it falls due after the next step by
        less than a draw takes (the most of the last DRAW_TIMES_KEPT draws), so drawn there it would
        be shown late by the rest of the draw, and a draw still fits before the next step is due
        (a late loop has no time to spare). A frame due exactly at a step is drawn at that step (at
        a V2C tick its image is the tick's render, made already). One drawn ahead is never dropped;
        one due after the trip's last step is not shown."""
        if not self._draw_times:
            return False
        draw_s = max(self._draw_times)
        after_next = self._next_frame - (st.time + self.dt)
        on_step = abs(after_next / self.dt - round(after_next / self.dt)) < 1e-6
        return (not on_step and after_next < draw_s * self.speed
                and wallclock.perf_counter() + draw_s <= self._wall_at(st.time + self.dt))

    def _frame(self, st: EgoStep, lag: float, due: float, ahead: bool = False) -> None:
        """Draw this step's state as the display frame due at simulated time `due` (before the next
        step's, or after it when drawn `ahead`: then it is shown from the next step's call); a paced
        drive shows it at that time's wall clock."""
        starved = self._last_shown is None or wallclock.perf_counter() - self._last_shown > MAX_FRAME_GAP * self.frame_period
        tick_frame = self._tick_frame
        rendered = tick_frame is not None and abs(tick_frame.time - st.time) < 1e-9  # this step's image is made
        if self.speed is not None and lag > self.frame_period and not starved and not rendered:
            self._dropped(due, lag)  # behind the clock: drop the frame rather than slow the simulation further
            return
        started = wallclock.perf_counter()
        frame = tick_frame if rendered else self.renderer.render(st.states())
        if self.vision is not None:
            self._take_vision_result()
        items = self._drawn(frame, st.time) if self.guidance_on else []
        hud = HudInfo(st.time, st.speed, self.trip_end_s - st.s_front, self.guidance_on, lag)
        image = compose(frame.rgb, items, hud)
        drawn = wallclock.perf_counter()
        self._draw_times.append(drawn - started)
        drawn_frame = DrawnFrame(
            st.time, lag, due, image, items, frame, started, drawn,
            # the state shown was moved by the previous step's command: input to display counts from that poll
            self._last_poll or started,
            # how old the overlay's picture of the world is: from the frame it was made from to this one
            1000.0 * (st.time - self._update_time) if self._shown_set is not None else np.nan)
        if ahead:
            self._ahead = drawn_frame
        else:
            self._show(drawn_frame)

    def _show(self, d: DrawnFrame) -> None:
        """Show a drawn frame and record it: a paced drive flips it when the wall clock reaches its
        due time, not at the step that drew it (flipped at the step, a 60 frames/s display over
        10-ms steps came 10 and 20 ms apart: H200, docs/performance.md)."""
        if self.speed is not None:
            self._sleep_until(self._wall_at(d.due), wallclock.perf_counter())
        if self.window is not None:
            self.window.show(d.image)
        shown = self._last_shown = wallclock.perf_counter()  # the flip (the bookkeeping below comes after it)
        self._log_drawn(d.time_s, d.items, d.frame)
        if self.video is not None:
            self.video.add(d.image)
            self._last_image = d.image
        f = self.frame_rows
        f["sim_time"].append(round(d.time_s, 6))
        f["wall_s"].append(shown - self._wall0)
        f["shown"].append(True)
        f["lag_s"].append(d.lag)
        f["render_ms"].append(1000.0 * (d.drawn - d.started))
        f["input_to_display_ms"].append(1000.0 * (shown - d.poll))
        f["ar_age_ms"].append(d.ar_age_ms)
        self._close_period()

    def _take_vision_result(self) -> None:
        """The vision worker's newest overlay, when it is new (as acceleration() takes a tick's)."""
        result = self.vision.poll()
        if result is None or result is self._shown_result:
            return
        self._shown_result = result
        if result.guidance is None:  # no frame at that tick: the overlay on the screen stays
            return
        self._shown_set = result.guidance
        self._guidance = result.guidance.items
        self._guidance_source = result.guidance.source
        self._update_time = result.time
        self._update_twins = result.neighbours
        self._update_pose = result.pose

    def _drawn(self, frame, time_s: float) -> list:
        """The overlay's items with the boxes drawn on this frame (vcfusion.hitl.display)."""
        dt = time_s - self._update_time
        if self._guidance_source == "cloud":
            from vcfusion.fusion.stage import camera_view

            camera = camera_view(frame.K, frame.T_world_to_camera, frame.width, frame.height, time_s)
            return cloud_boxes(self._guidance, carried_twins(self._update_twins, dt), camera)
        if self._update_pose is None:  # no camera pose of the tick: the boxes stay where the fusion drew them
            return [g for g in self._guidance if g.box is not None]
        K, T_then = self._update_pose
        return tracked_boxes(self._guidance, K, T_then, np.asarray(frame.T_world_to_camera, float), dt,
                             (frame.width, frame.height), self._update_twins)

    def _log_drawn(self, time_s: float, items: list, frame) -> None:
        from vcfusion.metrics.highlights import instance_boxes, judge_highlight

        gt_boxes, gt_ids = None, ()
        for g in items:
            if g.level == "none":  # not drawn (compose draws warnings only)
                continue
            # scoring only, after it was drawn: the vehicle the drawn box shows, by the one
            # definition of a right highlight (vcfusion.metrics.highlights)
            if gt_boxes is None:
                gt_boxes, gt_ids = instance_boxes(frame.instances, tuple(frame.vehicle_ids))
            owner = judge_highlight(g.vehicle_id, g.box, gt_boxes, gt_ids).box_vehicle_id
            self.display_rows.append({"time": round(time_s, 6), "vehicle_id": g.vehicle_id,
                                      "box_vehicle_id": owner or "", "lc_prob": float(g.lc_prob), "level": g.level,
                                      "source": self._guidance_source, "x1": g.box[0], "y1": g.box[1],
                                      "x2": g.box[2], "y2": g.box[3]})

    # -- end of the trip ------------------------------------------------------------------
    def finish(self, tables, summary: dict) -> None:
        import pandas as pd
        import pyarrow as pa

        # the trip's collections, from its clock's start to its last due frame (those of the tables
        # made below are not the drive's)
        pauses = [p for p in self.gc_pauses.since(self._wall0) if p[1] <= self._mark[0]] \
            if self.gc_pauses is not None and self._wall0 is not None else None
        r = self.rows
        columns = {k: v for k, v in r.items() if k not in ("raw_axes", "raw_buttons")}
        inputs = pa.table({**{k: pa.array(v) for k, v in columns.items()},
                           "raw_axes": pa.array(r["raw_axes"], type=pa.list_(pa.float64())),
                           "raw_buttons": pa.array(r["raw_buttons"], type=pa.list_(pa.int8()))})
        inputs = inputs.select(["wall_s", "sim_time", "lag_s", "keys", "raw_axes", "raw_buttons", "steer", "throttle",
                                "brake", "lane_change", "accel", "d", "yaw"])
        tables["inputs"] = inputs.to_pandas()
        tables["frames"] = pd.DataFrame(self.frame_rows)
        if self.renderer is not None and self.guidance_on:  # a trip with a display that drew guidance
            tables["display"] = pd.DataFrame(self.display_rows, columns=list(DISPLAY_COLUMNS))
        summary["realtime"] = realtime_summary(self.frame_rows, r["lag_s"], self.speed, self.frame_period, pauses) | (
            self.vision.stats() if self.vision is not None else {"vision_pipeline": False, "vision_ticks_dropped": 0})
        summary["hitl"] = self.info | {"guidance": "on" if self.guidance_on else "off",
                                      "speed": "max" if self.speed is None else self.speed,
                                      # when the wheel was found unplugged (the car coasted, wheel centred)
                                      "device_disconnects": list(getattr(self.device, "disconnects", []))}


def realtime_summary(frames: dict[str, list], step_lags: list[float], speed: float | None,
                     frame_period: float = 1.0 / 30.0, gc_pauses: list[tuple[int, float, float]] | None = None) -> dict:
    """How well the trip kept to the wall clock (see the module doc). `gc_pauses`: the trip's
    garbage collections (generation, start, pause s); None: not timed."""
    shown = np.array(frames["shown"], dtype=bool)
    wall = np.array(frames["wall_s"], dtype=float)[shown]
    intervals = np.diff(wall)
    period_lag = np.array(frames["lag_s"], dtype=float)
    to_display = np.array(frames["input_to_display_ms"], dtype=float)[shown]
    age = np.array(frames.get("ar_age_ms", [np.nan] * len(shown)), dtype=float)[shown]
    age = age[np.isfinite(age)]
    late_limit = frame_period  # a frame more than one frame period behind its simulated time
    work = np.array(frames.get("work_ms", []), dtype=float)
    cpu = np.array(frames.get("cpu_ms", []), dtype=float)

    def pct(values: np.ndarray, q: float) -> float | None:
        return float(np.percentile(values, q)) if len(values) else None
    pause_ms = np.array([1000.0 * p[2] for p in gc_pauses or ()])
    return {
        "frames_due": int(len(shown)),
        "frames_shown": int(shown.sum()),
        "dropped_frames": int((~shown).sum()),
        "late_frames": int((~shown).sum() + (period_lag[shown] > late_limit).sum()) if speed is not None else 0,
        "display_fps_median": float(1.0 / np.median(intervals)) if len(intervals) and np.median(intervals) > 0 else None,
        # the rate a frame counter shows, and the spread of the flips (the median interval alone
        # hides a display that alternates 10- and 20-ms gaps: "50 frames/s" at 60 shown a second)
        "frames_shown_per_s": float(len(intervals) / (wall[-1] - wall[0])) if len(intervals) and wall[-1] > wall[0] else None,
        "frame_interval_ms_p5": pct(1000.0 * intervals, 5),
        "frame_interval_ms_p95": pct(1000.0 * intervals, 95),
        "max_lag_s": float(max(step_lags)) if step_lags and speed is not None else None,
        "input_to_display_ms_median": float(np.median(to_display)) if len(to_display) else None,
        "ar_age_ms_median": float(np.median(age)) if len(age) else None,
        "ar_age_ms_max": float(age.max()) if len(age) else None,
        "frame_work_ms_p50": pct(work, 50),
        "frame_work_ms_p95": pct(work, 95),
        "frame_work_ms_p99": pct(work, 99),
        "frame_cpu_ms_p99": pct(cpu, 99),
        "frames_over_budget": int((work > 1000.0 * frame_period).sum()),
        "gc_collections": len(gc_pauses) if gc_pauses is not None else None,
        "gc_collections_full": sum(1 for p in gc_pauses if p[0] == 2) if gc_pauses is not None else None,
        "gc_pause_ms_max": float(pause_ms.max()) if len(pause_ms) else (0.0 if gc_pauses is not None else None),
        "gc_pause_ms_total": float(pause_ms.sum()) if gc_pauses is not None else None,
    }


def forward_controls(pygame, device):
    """An event handler for the start screen: axis motions reach the device (a pedal pressed
    while reading the instructions counts as touched), and so do the driving keys pressed or
    released there (a key already held when the trip starts drives from its first step: SDL sends
    no repeat); buttons, the start keys and the lane-change keys do not (they start, or would
    queue a lane change)."""
    skipped = {pygame.K_RETURN, pygame.K_SPACE, pygame.K_ESCAPE, *getattr(device, "lane_keys", {})}

    def handle(event) -> None:
        if event.type == pygame.JOYAXISMOTION or (event.type in (pygame.KEYDOWN, pygame.KEYUP)
                                                 and event.key not in skipped):
            device.handle(event)
    return handle
