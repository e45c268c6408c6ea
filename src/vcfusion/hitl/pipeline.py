"""The vision tick beside the simulation: detection, depth step and matching in a second process.

In a drive paced to the wall clock (`vcfusion drive` at `--speed 1`) the loop's process steps SUMO,
renders the display and draws it; the fusion stage (detector, depth step, joint matcher, guidance
levels: :class:`vcfusion.fusion.fuse.VisionFusionHook`, built as a batch run builds it) runs in a
worker process, so on two cores the simulation, the display and the vision tick overlap.

- **Frames**: the camera stage renders the tick's frame in the loop's process (the display shows
  that same render at the tick's display frame); its rgb, depth and instance images are copied into
  one shared-memory block (:mod:`multiprocessing.shared_memory`) that the worker reads; the tick's
  small records (time, ground truth for the render's boxes, the ego, the neighbour twins) go
  through a pipe.
- **One tick in flight**: a vision tick is handed over only while the worker is idle; a tick due
  while it still works on an earlier one is dropped and counted (``vision_ticks_dropped``) and
  not rendered (:meth:`PipelinedFusionHook.gate`), so a slow machine costs vision results, not
  display frames or simulated time.
- **Results**: polled without waiting at every tick and every display frame; the newest
  :class:`VisionResult` (the guidance set with the time and camera pose of the frame it was made
  from) is what the display carries forward with the ego's own motion
  (:func:`vcfusion.hitl.display.tracked_boxes`) until the next one. Its ``fusion`` rows go to the
  run's ``fusion`` table at the next tick, with the time of the frame they describe.
- **Shutdown**: :meth:`VisionPipeline.close` (a drive calls it on every exit: end, error, Ctrl-C)
  asks the worker to stop, waits `STOP_GRACE_S`, then terminates and kills it, and unlinks the
  shared memory. The worker ignores SIGINT (the loop's process decides) and exits when the pipe's
  other end is gone (its parent died).

Results depend on the wall clock (which ticks are dropped, when a result arrives), so only paced
drives use it; batch runs and studies run the same fusion stage in the loop.
"""

from __future__ import annotations

import os
import time as wallclock
import traceback
from dataclasses import dataclass
from multiprocessing import shared_memory

import numpy as np

from vcfusion.errors import InputError, JobError
from vcfusion.records import GuidanceSet
from vcfusion.scenario import Scenario

# The worker still running this long after being asked to stop is terminated (then killed).
STOP_GRACE_S = 5.0
# Longest wait for the worker to load the detector and answer (torch import and weights on a
# loaded 2-core machine: ~10 s measured; a worker that never answers is an error, not a hang).
READY_TIMEOUT_S = 180.0
SHM_PREFIX = "vcfusion-vision-"
# CPU threads of the worker's CNN: one, the other core being the loop's. Two threads that wait
# for each other at every layer collapse when a core is taken: on the shared 2-core VM (load ~14)
# the shipped CNN at 640x480 took 1377 ms median with two threads, 186 ms with one (8 calls each,
# alternated twice); a drive whose worker ran two threads got 19 vision results of 177 due ticks.
WORKER_CNN_THREADS = 1
# Niceness added to the worker's: where the loop's threads (SUMO, the display's render and its
# llvmpipe rasteriser threads) and the worker want the same core, the loop's get it (weight 1024
# against 110 for nice 10, Linux CFS) and the worker takes the rest: when the machine is short,
# vision ticks are dropped (counted), not display frames. Measured on the shared 2-core VM under
# overload (load 9-10.6, the P6 drive, three rounds alternated with the worker at nice 0): dropped
# display frames 189 / 64 / 180 of 531 against 210 / 199 / 257, AR age median 770-1070 ms against
# 300-340 ms. On a quiet machine (load 0.8-1.5) nice 10, 5 and 0 all gave 0 dropped frames and AR age
# median 70 ms (two drives each, docs/performance.md).
WORKER_NICE = 10


class VisionPipelineError(JobError):
    """The vision worker failed (the cause's last line first, then its traceback) or died. A bad
    input the worker finds (a scenario's detector weights, say) is raised as the InputError it is."""

    def __init__(self, cause: str):
        super().__init__("the vision process", cause)


@dataclass(frozen=True)
class VisionResult:
    """One vision tick's outcome as the loop's process received it."""

    seq: int
    time: float  # simulated time of the frame it was made from, s
    guidance: GuidanceSet | None  # None: no frame at that tick (nothing drawn)
    fresh: bool  # False: the stage handed its previous overlay again (between its AR updates)
    pose: tuple[np.ndarray, np.ndarray] | None  # (K, T_world_to_camera) of that frame
    neighbours: object  # the neighbour twins of that tick (their reported velocities carry the boxes)
    detections: object
    submitted_wall: float  # perf_counter when handed over
    received_wall: float  # perf_counter when the loop's process read it


def _layout(width: int, height: int) -> list[tuple[str, tuple[int, ...], np.dtype]]:
    return [("rgb", (height, width, 3), np.dtype(np.uint8)), ("depth", (height, width), np.dtype(np.float32)),
            ("instances", (height, width), np.dtype(np.int32))]


def _views(buf, width: int, height: int) -> dict[str, np.ndarray]:
    out, offset = {}, 0
    for name, shape, dtype in _layout(width, height):
        n = int(np.prod(shape)) * dtype.itemsize
        out[name] = np.ndarray(shape, dtype, buffer=buf, offset=offset)
        offset += n
    return out


def _block_bytes(width: int, height: int) -> int:
    return sum(int(np.prod(shape)) * dtype.itemsize for _, shape, dtype in _layout(width, height))


def _worker_main(conn, scenario: Scenario, seed: int, shm_name: str, size: tuple[int, int], nice: int) -> None:
    """The worker process: build the scenario's fusion stage, answer vision ticks until told to stop
    (at `nice` more than the loop's niceness)."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the loop's process, which stops us
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    os.nice(nice)
    shm = None
    try:
        from vcfusion.cosim import Tick
        from vcfusion.fusion.stage import build_fusion_hook
        from vcfusion.guidance import GuidancePolicy
        from vcfusion.hitl.gcpause import frozen_heap
        from vcfusion.render.renderer import Frame
        from vcfusion.threads import one_blas_thread
        from vcfusion.traffic.network import read_road

        shm = shared_memory.SharedMemory(name=shm_name)
        views = _views(shm.buf, *size)
        road = read_road(scenario.network, scenario.route)
        hook = build_fusion_hook(scenario, seed, GuidancePolicy.from_scenario(scenario, road))
        if hasattr(hook.detector, "threads") and str(getattr(hook.detector, "device", "cpu")) == "cpu":
            hook.detector.threads = WORKER_CNN_THREADS
        if hasattr(hook.detector, "dense"):  # the CNN's first forward pass allocates: not on the first tick
            hook.detector.detect(np.zeros((size[1], size[0], 3), np.uint8))
        last = None  # the overlay handed back last: the stage hands it again between its AR updates
        # the set-up's heap (torch, the detector) out of the collections of the ticks (vcfusion.hitl.gcpause)
        with frozen_heap(), one_blas_thread():
            conn.send(("ready", os.getpid()))
            while True:
                try:
                    msg = conn.recv()
                except EOFError:  # the loop's process is gone
                    return
                if msg[0] == "stop":
                    conn.send(("stopped",))
                    return
                _, seq, time_s, truth, ego, near, meta = msg
                frame = None
                if meta is not None:
                    vehicle_ids, K, T = meta
                    # views into the shared block: the loop's process does not write it until we answer
                    frame = Frame(time_s, views["rgb"], views["depth"], views["instances"], vehicle_ids, K, T)
                tick = Tick(time_s, truth, None, ego, near, frame=frame)
                started = wallclock.perf_counter()
                rows = hook(tick) or []
                busy = wallclock.perf_counter() - started
                fresh = tick.guidance is None or tick.guidance is not last
                last = tick.guidance
                conn.send(("result", seq, rows, tick.guidance, fresh, tick.detections, busy))
    except BaseException as exc:  # noqa: BLE001 -- any failure goes back to the loop's process, which raises it
        try:
            if isinstance(exc, InputError):
                conn.send(("input_error", exc))
            else:
                lines = [line for line in traceback.format_exc().splitlines() if line.strip()]
                conn.send(("error", "\n".join(lines[-1:] + lines)))
        except (OSError, ValueError):
            pass
    finally:
        if shm is not None:
            del views
            shm.close()


class VisionPipeline:
    """The worker process and the shared frame block; :attr:`hook` is the run's fusion stage."""

    def __init__(self, scenario: Scenario, seed: int, *, lossless: bool = False, nice: int = WORKER_NICE):
        from vcfusion.workers import worker_context

        self.scenario = scenario
        self.size = (int(scenario.camera.width_px), int(scenario.camera.height_px))
        self.lossless = lossless  # wait for each result instead of dropping ticks (tests compare with the loop)
        self.nice = nice  # the worker's niceness above the loop's
        self.shm = shared_memory.SharedMemory(create=True, size=_block_bytes(*self.size),
                                              name=f"{SHM_PREFIX}{os.getpid()}-{id(self):x}")
        self._views = _views(self.shm.buf, *self.size)
        ctx = worker_context()
        self._conn, child = ctx.Pipe()
        self.process = ctx.Process(target=_worker_main, args=(child, scenario, seed, self.shm.name, self.size, nice),
                                   daemon=True, name="vcfusion-vision")
        try:
            self.process.start()
        except BaseException:
            self._release_shm()
            raise
        child.close()
        self.worker_pid: int | None = None
        self.closed = False
        self.hook = PipelinedFusionHook(self, scenario)
        # what happened to the vision ticks (VisionPipeline.stats)
        self.submitted = 0
        self.dropped_times: list[float] = []
        self.results = 0
        self.latency_s: list[float] = []
        self.busy_s: list[float] = []
        self.received_wall: list[float] = []
        self._in_flight: tuple | None = None  # (seq, time, pose, neighbours, submitted_wall)
        self.latest: VisionResult | None = None
        self._pending_rows: list[dict] = []
        self._pending_results = 0  # results whose rows the run's table has not taken yet
        self._seq = 0

    # -- the worker -------------------------------------------------------------------------
    def wait_ready(self, timeout_s: float = READY_TIMEOUT_S) -> None:
        """Block until the worker has built its fusion stage (raises VisionPipelineError)."""
        if self.worker_pid is not None:
            return
        deadline = wallclock.perf_counter() + timeout_s
        while not self._conn.poll(0.2):
            if not self.process.is_alive():
                raise VisionPipelineError(f"it exited while starting (exit code {self.process.exitcode})")
            if wallclock.perf_counter() > deadline:
                raise VisionPipelineError(f"it did not start within {timeout_s:g} s")
        msg = self._recv()
        if msg[0] != "ready":
            raise VisionPipelineError(f"it answered {msg[0]!r} while starting")
        self.worker_pid = msg[1]

    def _recv(self):
        try:
            msg = self._conn.recv()
        except (EOFError, OSError):
            self.process.join(1.0)
            raise VisionPipelineError(f"it died (exit code {self.process.exitcode})") from None
        if msg[0] == "input_error":
            raise msg[1]
        if msg[0] == "error":
            raise VisionPipelineError(msg[1])
        return msg

    @property
    def busy(self) -> bool:
        return self._in_flight is not None

    def poll(self, wait: bool = False) -> VisionResult | None:
        """Read the worker's answer if there is one (`wait`: block for it); returns the newest result."""
        if self._in_flight is None:
            return self.latest
        if not wait and not self._conn.poll(0):
            if not self.process.is_alive():
                raise VisionPipelineError(f"it died (exit code {self.process.exitcode})")
            return self.latest
        msg = self._recv()
        if msg[0] != "result" or msg[1] != self._in_flight[0]:
            raise VisionPipelineError(f"it answered {msg[:2]!r}, expected the result of tick {self._in_flight[0]}")
        _, seq, rows, guidance, fresh, detections, busy = msg
        seq, time_s, pose, near, submitted = self._in_flight
        self._in_flight = None
        now = wallclock.perf_counter()
        self.results += 1
        self.latency_s.append(now - submitted)
        self.busy_s.append(busy)
        self.received_wall.append(now)
        self._pending_rows += rows
        self._pending_results += 1
        if fresh or self.latest is None:
            self.latest = VisionResult(seq, time_s, guidance, fresh, pose, near, detections, submitted, now)
        return self.latest

    def drop(self, tick) -> None:
        """Count a vision tick that was due while the worker was busy."""
        self.dropped_times.append(round(float(tick.time), 6))

    def submit(self, tick) -> bool:
        """Hand the tick to the worker; False (the tick dropped and counted) while it is busy."""
        self.poll()
        if self._in_flight is not None:
            self.drop(tick)
            return False
        frame, meta, pose = tick.frame, None, None
        if frame is not None:
            if frame.rgb.shape[:2] != (self.size[1], self.size[0]):
                raise VisionPipelineError(f"a frame of {frame.rgb.shape[1]}x{frame.rgb.shape[0]} px was handed over, "
                                          f"expected the camera's {self.size[0]}x{self.size[1]}")
            for name in ("rgb", "depth", "instances"):
                self._views[name][...] = getattr(frame, name)
            K, T = np.asarray(frame.K, float), np.asarray(frame.T_world_to_camera, float)
            meta, pose = (tuple(frame.vehicle_ids), K, T), (K, T)
        self._seq += 1
        try:
            self._conn.send(("tick", self._seq, float(tick.time), tick.truth, tick.ego, tick.neighbours, meta))
        except (OSError, ValueError):
            raise VisionPipelineError(f"it died (exit code {self.process.exitcode})") from None
        self._in_flight = (self._seq, float(tick.time), pose, tick.neighbours, wallclock.perf_counter())
        self.submitted += 1
        if self.lossless:  # the tick's result before the loop goes on, as the stage in the loop gives it
            self.poll(wait=True)
        return True

    def take_rows(self) -> list[dict]:
        rows, self._pending_rows, self._pending_results = self._pending_rows, [], 0
        return rows

    def stats(self) -> dict:
        """The summary's vision figures (realtime block of a drive)."""
        intervals = np.diff(self.received_wall)
        latency = np.array(self.latency_s)
        return {
            "vision_pipeline": True,
            "vision_worker_nice": self.nice,
            "vision_ticks_due": self.submitted + len(self.dropped_times),
            "vision_results": self.results,
            "vision_ticks_dropped": len(self.dropped_times),
            # the run ended before these reached the fusion table (the last tick's hand-over and
            # results read by the display after the last tick): counted, not logged
            "vision_in_flight_at_end": int(self._in_flight is not None),
            "vision_results_unlogged_at_end": self._pending_results,
            "vision_interval_ms_median": float(1e3 * np.median(intervals)) if len(intervals) else None,
            "vision_latency_ms_median": float(1e3 * np.median(latency)) if len(latency) else None,
            "vision_latency_ms_max": float(1e3 * latency.max()) if len(latency) else None,
            "vision_busy_ms_median": float(1e3 * np.median(self.busy_s)) if self.busy_s else None,
        }

    # -- shutdown -----------------------------------------------------------------------------
    def close(self) -> None:
        """Stop the worker (asked, then terminated, then killed) and unlink the shared memory."""
        if self.closed:
            return
        self.closed = True
        try:
            if self.process.is_alive():
                try:
                    self._conn.send(("stop",))
                except (OSError, ValueError):
                    pass
                self.process.join(STOP_GRACE_S)
            if self.process.is_alive():
                self.process.terminate()
                self.process.join(STOP_GRACE_S)
            if self.process.is_alive():
                self.process.kill()
                self.process.join(STOP_GRACE_S)
        finally:
            self._conn.close()
            self._release_shm()

    def _release_shm(self) -> None:
        self._views = {}
        try:
            self.shm.close()
        finally:
            try:
                self.shm.unlink()
            except FileNotFoundError:
                pass

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class PipelinedFusionHook:
    """The fusion stage of a paced drive (tick hook): hands due vision ticks to the worker, and sets
    ``tick.guidance`` to the newest result's overlay (None before the first). Its ``fusion`` rows
    are the worker's, logged at the tick after they arrive. Due ticks follow the stage's AR update
    period (``ar.period_s``) as in the loop; the worker applies the rest of the stage's rules.
    With :meth:`gate` the camera stage renders only the ticks handed over (the display renders
    the frames it shows itself), so a dropped vision tick costs no render either."""

    table = "fusion"
    needs = ("neighbours", "frame")
    provides = ("detections", "guidance")

    def __init__(self, pipeline: VisionPipeline, scenario: Scenario):
        from vcfusion.fusion.fuse import VisionFusionHook

        self.columns = VisionFusionHook.columns
        self.pipeline = pipeline
        self.period_s = scenario.ar.period_s
        self._next_time = -np.inf
        self._delivered: VisionResult | None = None
        self._decided: tuple = (None, "")  # (the tick, what is done with it): one decision per tick

    def decide(self, tick) -> str:
        """"submit" (due and the worker idle), "drop" (due, the worker busy) or "not_due"; the
        same answer for the camera stage and this stage within one tick."""
        if self._decided[0] is tick:
            return self._decided[1]
        self.pipeline.poll()
        if self.period_s is not None and tick.time < self._next_time - 1e-9:
            decision = "not_due"
        else:
            decision = "drop" if self.pipeline.busy else "submit"
        self._decided = (tick, decision)
        return decision

    def gate(self, camera_hook) -> None:
        """Make the camera stage render only the ticks this stage hands over (and its own rule)."""
        previous = camera_hook.when

        def when(tick) -> bool:
            return self.decide(tick) == "submit" and (previous is None or previous(tick))
        camera_hook.when = when

    def __call__(self, tick) -> list[dict] | None:
        if tick.neighbours is None:
            return None
        p = self.pipeline
        decision = self.decide(tick)
        if decision == "submit":
            p.submit(tick)
            if self.period_s is not None:
                self._next_time = tick.time + self.period_s
        elif decision == "drop":
            p.drop(tick)
        latest = p.latest
        if latest is not None:
            tick.guidance = latest.guidance
            if latest is not self._delivered:
                tick.detections = latest.detections
                self._delivered = latest
        return p.take_rows()
