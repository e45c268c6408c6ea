"""The worker pool (vcfusion.workers.run_jobs) with real worker processes that die."""

import ctypes
import os
import signal
import tempfile
import threading
import time
from pathlib import Path

import pytest

from vcfusion import interrupts
from vcfusion.interrupts import is_interrupt
from vcfusion.workers import JobFailed, death_cause, run_jobs


def _job(k: int, how: str, folder: str):
    """Job k: returns (k, pid, its temporary folder), or ends its worker the way `how` says."""
    if how == "sigkill":
        os.kill(os.getpid(), signal.SIGKILL)
    if how == "exit":
        os._exit(3)
    if how == "raise":
        raise ValueError(f"job {k} refused")
    if how == "numba-interrupted":
        _numba_interrupted()
    if how == "swallowed":  # Ctrl-C reaches the job, which reports it as a failure of its own and
        try:  # returns (batch._run_seed catching numba's SystemError as a failed seed)
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(5)
        except KeyboardInterrupt:
            return k, "failed on its own", tempfile.gettempdir()
    if how == "sleep":
        try:
            Path(folder, "started").write_text(str(os.getpid()))
            time.sleep(60)
        finally:  # an interrupted job still cleans up
            Path(folder, "cleaned-up").write_text("yes")
    return k, os.getpid(), tempfile.gettempdir()


# Ctrl-C landing while numba loads a compiled function's constants: numba's C code raises a
# SystemError whose cause is a SystemError whose cause is the KeyboardInterrupt (checked against
# real numba by the test below, in a fresh process: numba's C side keeps its loader once called).
NUMBA_LOADS_AN_INTERRUPTED_FUNCTION = """
import numba, numpy as np
from numba.core import serialize

@numba.njit
def scaled(x):
    return np.ones(3) * x, (x, "a")  # the tuple's string is loaded through serialize

def interrupted(*args):  # what a SIGINT landing in the loader does
    raise KeyboardInterrupt

serialize._numba_unpickle = interrupted
try:
    scaled(1.0)
except SystemError as exc:
    chain = []
    while exc is not None:
        chain.append(type(exc).__name__)
        exc = exc.__cause__
    print(" <- ".join(chain))
"""


def _ctrl_c_swallowed_in_a_ctypes_callback():
    """What happens to a Ctrl-C that lands while numba compiles on a cold cache: LLVM calls back into
    Python through ctypes, and ctypes prints and drops the callback's KeyboardInterrupt."""
    def callback():
        os.kill(os.getpid(), signal.SIGINT)
        sum(range(1000))  # the handler runs at the next bytecode check, inside the callback

    ctypes.CFUNCTYPE(None)(callback)()


def _numba_interrupted():
    """Raise the chain that numba raises (see NUMBA_LOADS_AN_INTERRUPTED_FUNCTION)."""
    try:
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as interrupt:
            raise SystemError("<function _numba_unpickle> returned a result with an exception set") from interrupt
    except SystemError as loader:
        raise SystemError("CPUDispatcher(<function scaled>) returned a result with an exception set") from loader


@pytest.fixture
def scratch_root(tmp_path, monkeypatch):
    root = tmp_path / "tmp"
    root.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(root))
    return root


def test_a_dead_worker_costs_only_its_job(tmp_path, scratch_root):
    hows = ["ok", "ok", "sigkill", "ok", "raise", "ok", "exit", "ok", "ok"]
    jobs = [(k, how, str(tmp_path)) for k, how in enumerate(hows)]
    started = {}
    results = dict(run_jobs(_job, jobs, 2, on_start=lambda i, pid: started.setdefault(i, pid)))
    assert sorted(results) == list(range(len(jobs)))
    assert sorted(started) == list(range(len(jobs)))
    assert results[2] == JobFailed("worker process died (signal 9: SIGKILL)")
    assert results[6] == JobFailed("worker process died (exit code 3)")
    assert isinstance(results[4], JobFailed) and results[4].cause.startswith("ValueError: job 4 refused")
    ok = {k: v for k, v in results.items() if hows[k] in ("ok",)}
    assert all(v[0] == k for k, v in ok.items())
    # the workers that ran the later jobs replaced the dead ones; never more than 2 at a time alive
    assert started[2] not in {v[1] for k, v in ok.items() if k > 2}
    # jobs write temporary files into their worker's scratch folder, removed with the worker
    assert all(Path(v[2]).parent == scratch_root for v in ok.values())
    assert list(scratch_root.glob("vcfusion-worker-*")) == []


def test_ctrl_c_stops_the_pool_and_busy_jobs_clean_up(tmp_path, scratch_root):
    pids = {}

    def press_ctrl_c_once_started():  # SIGINT to this process only, as `kill -INT` would
        deadline = time.monotonic() + 60
        while not (tmp_path / "started").exists() and time.monotonic() < deadline:
            time.sleep(0.02)
        os.kill(os.getpid(), signal.SIGINT)

    threading.Thread(target=press_ctrl_c_once_started, daemon=True).start()
    with pytest.raises(KeyboardInterrupt):
        list(run_jobs(_job, [(0, "sleep", str(tmp_path))], 1, on_start=lambda i, pid: pids.setdefault(i, pid)))
    # the pool passed the interrupt on to its busy worker: the job cleaned up, the worker is gone
    assert (tmp_path / "cleaned-up").read_text() == "yes"
    with pytest.raises(ProcessLookupError):
        os.kill(pids[0], 0)
    assert list(scratch_root.glob("vcfusion-worker-*")) == []


def test_numba_raises_a_system_error_caused_by_the_interrupt():
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", NUMBA_LOADS_AN_INTERRUPTED_FUNCTION], capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["SystemError", "<-", "SystemError", "<-", "KeyboardInterrupt"]
    with pytest.raises(SystemError) as raised:
        _numba_interrupted()
    assert is_interrupt(raised.value)
    assert not is_interrupt(SystemError("a bug in an extension")) and not is_interrupt(ValueError("bad input"))


def test_ctrl_c_inside_numba_in_a_worker_stops_the_worker_not_fails_the_job(tmp_path, scratch_root):
    # the worker exits as after SIGINT (a batch's parent, which got the SIGINT too, then stops the pool)
    results = dict(run_jobs(_job, [(0, "numba-interrupted", str(tmp_path)), (1, "ok", str(tmp_path))], 1))
    assert results[0] == JobFailed("worker process interrupted (SIGINT)")
    assert results[1][0] == 1  # a fresh worker ran the next job


def test_a_worker_whose_job_swallowed_ctrl_c_stops_and_runs_no_other_job(tmp_path, scratch_root):
    """A SIGINT to one worker that its job caught and reported as a failure of its own: the seed was
    recorded as failed for another reason, and the worker went on with the interrupt recorded, so
    its next seed, never interrupted, died at its first tick."""
    pids = {}
    jobs = [(0, "swallowed", str(tmp_path)), (1, "ok", str(tmp_path))]
    results = dict(run_jobs(_job, jobs, 1, on_start=lambda i, pid: pids.setdefault(i, pid)))
    assert results[0] == JobFailed("worker process interrupted (SIGINT)")
    assert results[1][0] == 1 and pids[1] != pids[0]  # a fresh worker ran the next job


def test_ctrl_c_inside_numba_in_a_command_exits_130_with_the_hint(tmp_path, monkeypatch, capsys):
    from vcfusion.commands import main, simulation

    monkeypatch.setattr(simulation, "cmd_run", lambda args: _numba_interrupted())
    assert main(["run", str(tmp_path / "any.yaml")]) == 130
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        "interrupted: no run folder was written; run the same command again to redo the run")


def test_ctrl_c_swallowed_on_its_way_up_still_exits_130(tmp_path, monkeypatch, capsys):
    from vcfusion.commands import main, simulation

    def swallowed_then_failed(args):  # as numba, whose cache then has no compiled object
        _ctrl_c_swallowed_in_a_ctypes_callback()
        raise RuntimeError("no compiled object yet")

    monkeypatch.setattr(simulation, "cmd_run", swallowed_then_failed)
    assert main(["run", str(tmp_path / "any.yaml")]) == 130
    assert capsys.readouterr().err.strip().splitlines()[-1].startswith("interrupted: no run folder was written")
    # the record is the command's: the next command in this process starts afresh
    assert not interrupts.is_interrupt(RuntimeError("no compiled object yet"))
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_a_run_stops_at_the_next_tick_after_a_swallowed_ctrl_c(tmp_path):
    from scenario_files import write_scenario
    from vcfusion.cosim import CoSimulation
    from vcfusion.scenario import load_scenario

    scenario = load_scenario(write_scenario(tmp_path, """
name: busy
network: NET_DIR/highway.net.xml
vehicle_types: NET_DIR/vtypes.add.xml
simulation: {step_s: 0.1, max_time_s: 60}
vehicles:
  - {name: cars, count: 10, lanes: [0, 1, 2], pos_m: [10, 600], speed_mps: 15, min_spacing_m: 40}
"""))
    ticks = []

    def swallows_ctrl_c_once(twins, store):
        ticks.append(len(twins))
        if len(ticks) == 3:
            _ctrl_c_swallowed_in_a_ctypes_callback()
        return {}

    with interrupts.recorded(), pytest.raises(KeyboardInterrupt):
        CoSimulation(scenario, 0, process_models=[("swallows", swallows_ctrl_c_once)]).run()
    assert len(ticks) == 3  # not the run's 600 ticks


def _threads_of_this_worker():
    import cv2
    import torch

    return torch.get_num_threads(), cv2.getNumThreads(), os.environ.get("OMP_NUM_THREADS")


def _rasteriser_threads_of_this_worker():
    # one frame through OSMesa, as a run's camera renders: llvmpipe starts its threads with the context
    import numpy as np
    import trimesh

    import vcfusion.render  # noqa: F401  (PYOPENGL_PLATFORM)
    import pyrender

    scene = pyrender.Scene()
    scene.add(pyrender.Mesh.from_trimesh(trimesh.creation.box()))
    pose = np.eye(4)
    pose[2, 3] = 3.0
    scene.add(pyrender.PerspectiveCamera(yfov=1.0), pose=pose)
    renderer = pyrender.OffscreenRenderer(32, 24)
    try:
        renderer.render(scene)
        names = [Path(f"/proc/self/task/{t}/comm").read_text().strip() for t in os.listdir("/proc/self/task")]
    finally:
        renderer.delete()
    return sum(name.startswith("llvmpipe") for name in names)


def test_workers_share_the_cores_for_torch_and_opencv(scratch_root):
    """Each worker took every core for torch and OpenCV: W workers ran W x cores threads."""
    from vcfusion.workers import worker_threads

    cores = os.cpu_count() or 1
    assert worker_threads(1) == cores and worker_threads(cores) == 1 and worker_threads(2 * cores) == 1
    results = dict(run_jobs(_threads_of_this_worker, [()] * cores, cores))  # a job per worker
    assert set(results.values()) == {(1, 1, "1")}


@pytest.mark.skipif(os.environ.get("PYOPENGL_PLATFORM", "osmesa" if not os.path.exists("/dev/nvidiactl") else "egl")
                    != "osmesa", reason="llvmpipe is OSMesa's rasteriser; with EGL the GPU renders")
def test_workers_share_the_cores_for_the_software_rasteriser(scratch_root):
    """OSMesa's llvmpipe started a thread per core in every worker rendering a camera."""
    cores = os.cpu_count() or 1
    results = dict(run_jobs(_rasteriser_threads_of_this_worker, [()] * cores, cores))  # a job per worker
    assert set(results.values()) == {1}


def test_death_cause_names_the_signal():
    assert death_cause(-signal.SIGSEGV) == "worker process died (signal 11: SIGSEGV)"
    assert death_cause(1) == "worker process died (exit code 1)"


def test_ctrl_c_while_a_worker_starts_leaves_no_scratch_folder(tmp_path, scratch_root, monkeypatch):
    # a fresh fork server takes ~1 s to start the first worker, so a Ctrl-C often lands inside
    # Process.start(), before the worker is in the pool that the clean-up walks
    from multiprocessing.process import BaseProcess

    started = []
    real_start = BaseProcess.start

    def start_then_ctrl_c(process):
        real_start(process)
        started.append(process)
        raise KeyboardInterrupt

    monkeypatch.setattr(BaseProcess, "start", start_then_ctrl_c)
    with pytest.raises(KeyboardInterrupt):
        list(run_jobs(_job, [(0, "ok", str(tmp_path))], 1))
    assert len(started) == 1 and not started[0].is_alive()
    assert list(scratch_root.glob("vcfusion-worker-*")) == []


def test_fewer_jobs_than_workers_leave_the_cores_to_fewer_processes(scratch_root):
    """Each worker's thread share counted the workers asked for, not those that run: one job with
    two workers asked ran in one process on half the cores."""
    cores = os.cpu_count() or 1
    results = dict(run_jobs(_threads_of_this_worker, [()], 2 * cores))
    assert results == {0: (cores, cores, str(cores))}
