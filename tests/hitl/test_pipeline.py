"""The vision tick beside the simulation (vcfusion.hitl.pipeline): the worker gives the loop's
results, a paced drive records what it claims, and the worker and its shared memory are gone after
the end, an error and Ctrl-C."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scenario_files import SCENARIOS

from vcfusion.scenario import load_scenario

# the accident with the camera, fusion and AR overlay, small frames and the oracle detector (seconds)
SMALL = """
extends: {base}
name: small_ar
camera: {{width_px: 160, height_px: 120}}
ar: {{video: false}}
fusion: {{detector: oracle}}
simulation: {{max_time_s: {max_time}}}
"""
TABLES = ("trajectories", "ego", "twins", "vehicles", "collisions", "lane_changes", "camera", "fusion", "guidance")


def small_scenario(tmp_path: Path, max_time: float) -> Path:
    path = tmp_path / f"small{max_time:g}.yaml"
    path.write_text(SMALL.format(base=(SCENARIOS / "accident_ar.yaml").as_posix(), max_time=max_time))
    return path


def replay_file(tmp_path: Path) -> str:
    (tmp_path / "in.csv").write_text("time_s,throttle,brake,steer\n0,0.2,0,0\n1.5,0,0.3,0.1\n")
    return "replay:" + str(tmp_path / "in.csv")


def shm_segments(pid: int) -> list[str]:
    from vcfusion.hitl.pipeline import SHM_PREFIX

    return [p.name for p in Path("/dev/shm").glob(f"{SHM_PREFIX}{pid}-*")]


def drive(sc, out, **kw):
    from vcfusion.hitl.drive import drive as run_drive

    defaults = dict(seed=1, guidance_on=True, headless=True, display_fps=30.0, start_screen_s=0.0)
    return run_drive(sc, out_dir=out, **(defaults | kw))


@pytest.fixture
def recorded_pipelines(monkeypatch):
    """Every VisionPipeline a drive makes, kept for the test to inspect after the drive."""
    import vcfusion.hitl.pipeline as module

    made = []

    class Recorded(module.VisionPipeline):
        def __init__(self, *args, **kw):
            super().__init__(*args, **kw)
            made.append(self)

    monkeypatch.setattr(module, "VisionPipeline", Recorded)
    return made


def gone(pipeline) -> bool:
    return not pipeline.process.is_alive() and pipeline.process.exitcode is not None \
        and not Path("/dev/shm", pipeline.shm.name).exists()


@pytest.mark.slow
def test_the_worker_gives_the_tables_of_the_fusion_stage_in_the_loop(tmp_path, recorded_pipelines):
    # lossless (a replay at full speed): each tick waits for its result, so the run is the loop's run
    sc = load_scenario(small_scenario(tmp_path, 2.5))
    inline = drive(sc, tmp_path / "inline", input_spec=replay_file(tmp_path), speed=None, vision_pipeline=False)
    piped = drive(sc, tmp_path / "piped", input_spec=replay_file(tmp_path), speed=None, vision_pipeline=True)
    fusion = pd.read_parquet(tmp_path / "inline" / "fusion.parquet")
    assert len(fusion) > 20 and fusion.matched.any()  # the comparison compares something
    for name in TABLES:
        assert (tmp_path / "inline" / f"{name}.parquet").read_bytes() == \
               (tmp_path / "piped" / f"{name}.parquet").read_bytes(), name
    assert inline.summary["realtime"]["vision_pipeline"] is False
    rt = piped.summary["realtime"]
    assert rt["vision_pipeline"] is True and rt["vision_ticks_dropped"] == 0
    assert rt["vision_results"] == rt["vision_ticks_due"] == fusion.time.nunique()
    (pipeline,) = recorded_pipelines
    assert gone(pipeline)


@pytest.mark.slow
def test_a_paced_drive_records_its_vision_ticks_and_the_age_of_what_it_shows(tmp_path, recorded_pipelines):
    import gc

    sc = load_scenario(small_scenario(tmp_path, 3.0))
    frozen = []  # objects frozen out of the collections when the trip's clock starts
    result = drive(sc, tmp_path / "run", input_spec=replay_file(tmp_path), speed=1.0,
                   on_start=lambda: frozen.append(gc.get_freeze_count()))
    (pipeline,) = recorded_pipelines
    assert gone(pipeline)
    # the set-up's heap was frozen for the paced trip, and is given back after it
    assert frozen[0] > 0 and gc.get_freeze_count() == 0
    rt = result.summary["realtime"]
    run = tmp_path / "run"
    camera = pd.read_parquet(run / "camera.parquet")
    fusion = pd.read_parquet(run / "fusion.parquet")
    frames = pd.read_parquet(run / "frames.parquet")
    # every tick was due (ar.period_s = the V2C period): handed over (rendered) or dropped, and
    # every one handed over answered
    ticks = pd.read_parquet(run / "twins.parquet").time.nunique()
    assert rt["vision_pipeline"] is True
    assert rt["vision_ticks_due"] == ticks == len(camera) + rt["vision_ticks_dropped"]
    assert len(camera) == rt["vision_results"] + rt["vision_in_flight_at_end"]
    assert rt["vision_ticks_dropped"] == len(pipeline.dropped_times)
    assert not set(pipeline.dropped_times) & set(camera.time)  # a dropped tick was neither rendered nor fused
    # the fusion table: the frames the worker fused, each one the camera stage's render
    logged = rt["vision_results"] - rt["vision_results_unlogged_at_end"]
    assert fusion.time.nunique() == logged > 0 and set(fusion.time) <= set(camera.time)
    # every frame shown after the first result carries the overlay of a fused frame, and its age
    shown = frames[frames.shown]
    age = shown.ar_age_ms.to_numpy()
    first = np.flatnonzero(np.isfinite(age))[0]
    assert np.isfinite(age[first:]).all() and (age[first:] >= 0).all()
    made_from = np.round(shown.sim_time.to_numpy()[first:] - age[first:] / 1e3, 6)
    assert set(made_from) <= set(np.round(camera.time, 6))
    assert rt["ar_age_ms_median"] == pytest.approx(float(np.median(age[first:])))
    assert rt["ar_age_ms_max"] == pytest.approx(float(age[first:].max()))
    assert rt["vision_latency_ms_median"] > 0 and rt["frames_due"] == len(frames)
    # each due frame's period: the loop's work and CPU time, and the trip's collections
    assert (frames.work_ms > 0).all() and (frames.cpu_ms > 0).all() and (frames.gc_ms >= 0).all()
    assert rt["frame_work_ms_p99"] == pytest.approx(float(np.percentile(frames.work_ms, 99)))
    assert rt["frames_over_budget"] == int((frames.work_ms > 1000 / 30).sum())
    assert rt["gc_pause_ms_total"] == pytest.approx(frames.gc_ms.sum(), abs=1e-6)


@pytest.mark.slow
def test_an_error_in_the_loop_or_in_the_worker_leaves_no_process_and_no_shared_memory(tmp_path, recorded_pipelines,
                                                                                    monkeypatch):
    from vcfusion.errors import ScenarioError
    from vcfusion.hitl.driver import HumanDriver
    from vcfusion.hitl.pipeline import VisionPipelineError

    sc = load_scenario(small_scenario(tmp_path, 3.0))
    step = HumanDriver.step

    def failing_at(n, act):
        calls = []

        def failing(self, st):
            calls.append(st.time)
            if len(calls) == n:
                act(self)
            return step(self, st)
        return failing

    def raise_here(driver):
        raise RuntimeError("a failure in the loop's process")

    monkeypatch.setattr(HumanDriver, "step", failing_at(50, raise_here))
    with pytest.raises(RuntimeError, match="a failure in the loop"):
        drive(sc, tmp_path / "run", input_spec=replay_file(tmp_path), speed=1.0)
    assert gone(recorded_pipelines[0]) and recorded_pipelines[0].worker_pid is not None

    # the worker killed mid-trip (the out-of-memory killer, say): the drive stops and says so
    monkeypatch.setattr(HumanDriver, "step", failing_at(50, lambda driver: os.kill(driver.vision.worker_pid,
                                                                                   signal.SIGKILL)))
    with pytest.raises(VisionPipelineError, match="the vision process failed: it died"):
        drive(sc, tmp_path / "run", input_spec=replay_file(tmp_path), speed=1.0)
    assert gone(recorded_pipelines[1])
    monkeypatch.setattr(HumanDriver, "step", step)

    # the worker cannot build its stage (no such detector weights): the scenario's error, as the
    # stage in the loop raises it
    sc = sc.model_copy(update={"fusion": sc.fusion.model_copy(update={"detector": "cnn",
                                                                      "weights": tmp_path / "missing.pt"})})
    with pytest.raises(ScenarioError, match="fusion.weights.*missing.pt"):
        drive(sc, tmp_path / "run", input_spec=replay_file(tmp_path), speed=1.0)
    assert gone(recorded_pipelines[2])
    assert not (tmp_path / "run").exists()
    assert not shm_segments(os.getpid())


def descendants(pid: int) -> set[int]:
    """Every live process below `pid` (from /proc)."""
    children: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        children.setdefault(int(fields[1]), []).append(int(stat.parent.name))
    out, todo = set(), [pid]
    while todo:
        for child in children.get(todo.pop(), []):
            out.add(child)
            todo.append(child)
    return out


def alive(pid: int) -> bool:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


@pytest.mark.slow
def test_ctrl_c_stops_the_worker_and_unlinks_the_shared_memory(tmp_path):
    env = os.environ | {"SDL_VIDEODRIVER": "dummy", "SDL_AUDIODRIVER": "dummy", "PYOPENGL_PLATFORM": "osmesa"}
    cmd = [sys.executable, "-m", "vcfusion", "drive", str(small_scenario(tmp_path, 30.0)), "--input",
           replay_file(tmp_path), "--headless", "--out", str(tmp_path / "run")]
    # its own process group, as a terminal's foreground job: Ctrl-C reaches every process in it
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    try:
        deadline = time.monotonic() + 120
        while not shm_segments(proc.pid) or len(descendants(proc.pid)) < 2:  # the fork server and the worker
            assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read() if proc.poll() else "slow"
            time.sleep(0.2)
        workers = descendants(proc.pid)
        time.sleep(3.0)
        os.killpg(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 130, err[-2000:]
    deadline = time.monotonic() + 10
    while any(alive(p) for p in workers) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not [p for p in workers if alive(p)]
    assert not shm_segments(proc.pid)
    assert not (tmp_path / "run").exists()


class FakeWorker:
    """The pipeline's side the hook talks to, without a process: busy while a tick is held."""

    def __init__(self):
        self.busy, self.latest, self.handed, self.dropped = False, None, [], []

    def poll(self, wait=False):
        return self.latest

    def submit(self, tick):
        self.handed.append(tick.time)
        self.busy = True
        return True

    def drop(self, tick):
        self.dropped.append(tick.time)

    def take_rows(self):
        return []


class FakeCamera:
    def __init__(self, when=None):
        self.when = when


def test_a_tick_due_while_the_worker_is_busy_is_dropped_and_not_rendered():
    from types import SimpleNamespace

    from vcfusion.hitl.pipeline import PipelinedFusionHook

    sc = load_scenario(SCENARIOS / "accident_ar.yaml")
    worker = FakeWorker()
    hook = PipelinedFusionHook(worker, sc.model_copy(update={"ar": sc.ar.model_copy(update={"period_s": 0.2})}))
    camera = FakeCamera(when=lambda tick: tick.time != 0.2)  # the camera's own rule: no frame at 0.2 s
    hook.gate(camera)
    rendered = []
    for k, busy_after in enumerate([False, False, True, True, False, False]):
        tick = SimpleNamespace(time=round(0.1 * k, 6), neighbours=(), guidance=None, detections=None)
        if camera.when(tick):
            rendered.append(tick.time)
        hook(tick)
        worker.busy = busy_after
    # 0.0 handed over; 0.1 not due (AR period 0.2 s); 0.2 handed over; 0.3 not due; 0.4 due but
    # the worker busy: dropped; 0.5 due (0.4 was not taken), the worker idle: handed over
    assert worker.handed == [0.0, 0.2, 0.5] and worker.dropped == [0.4]
    # only ticks handed over are rendered, and never against the camera's own rule (0.2 s is handed
    # over without a frame, as the stage in the loop gets it)
    assert rendered == [0.0, 0.5]


def test_the_summary_takes_the_age_of_the_shown_frames_only():
    from vcfusion.hitl.driver import realtime_summary

    frames = {"shown": [True, False, True, True], "wall_s": [0.0, 0.04, 0.07, 0.1], "lag_s": [0.0] * 4,
              "input_to_display_ms": [5.0, np.nan, 5.0, 5.0], "ar_age_ms": [np.nan, np.nan, 40.0, 100.0]}
    rt = realtime_summary(frames, [0.0], 1.0)
    assert rt["ar_age_ms_median"] == 70.0 and rt["ar_age_ms_max"] == 100.0


@pytest.mark.slow
def test_batch_runs_and_full_speed_replays_never_start_the_worker(tmp_path, recorded_pipelines):
    # their tables must not depend on the wall clock: the fusion stage runs in the loop
    from vcfusion.run import execute_run

    sc = load_scenario(small_scenario(tmp_path, 1.0))
    result = execute_run(sc, 0, tmp_path / "batch")
    assert len(pd.read_parquet(tmp_path / "batch" / "fusion.parquet")) > 0 and "realtime" not in result.summary
    import gc

    frozen = []
    replay = drive(sc, tmp_path / "replay", input_spec=replay_file(tmp_path), speed=None,
                   on_start=lambda: frozen.append(gc.get_freeze_count()))
    assert replay.summary["realtime"]["vision_pipeline"] is False
    assert frozen == [0]  # a replay at full speed keeps the collector as it is
    assert not recorded_pipelines


@pytest.mark.slow
def test_the_worker_runs_nicer_than_the_loop_so_the_display_wins_a_shared_core(tmp_path):
    from vcfusion.hitl.pipeline import WORKER_NICE, VisionPipeline

    with VisionPipeline(load_scenario(small_scenario(tmp_path, 1.0)), 0) as pipeline:
        pipeline.wait_ready()
        loop_nice = os.getpriority(os.PRIO_PROCESS, 0)
        worker_nice = os.getpriority(os.PRIO_PROCESS, pipeline.worker_pid)
        assert worker_nice == min(19, loop_nice + WORKER_NICE) and (worker_nice > loop_nice or loop_nice == 19)
        assert pipeline.stats()["vision_worker_nice"] == WORKER_NICE
    assert gone(pipeline)
