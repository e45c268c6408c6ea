"""Worker processes for batch runs, datasets and studies, and the pool that survives their death.

libsumo holds one simulation per process, so parallel runs are processes. On platforms with a
fork server, workers are forked from it: it is started once per parent process, runs no
simulation and no threads of ours, and has already imported the run code and loaded the
compiled per-tick kernels (`vcfusion.worker_preload`), so a worker starts in milliseconds
instead of paying ~2 s of imports and numba initialisation per process. Elsewhere workers are
spawned fresh. Either way no SUMO state is ever inherited.

`run_jobs` is the one pool every command uses. Each worker has its own pipe and runs one job at
a time, so the parent always knows which job a worker holds: when a worker dies (SIGKILL from
the out-of-memory killer, a crash in native code, any abrupt exit) only that job fails, with the
exit signal as its cause, a fresh worker takes the dead one's place and the other jobs go on.
(A concurrent.futures pool cannot do this: one dead worker breaks the pool and fails every
pending future, running or merely queued.)
"""

from __future__ import annotations

import multiprocessing
import os
import shutil
import signal
import sys
import tempfile
import threading
import time
import traceback
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from multiprocessing.connection import wait

from vcfusion import interrupts

# A worker still busy this long after being asked to stop (Ctrl-C) is killed.
STOP_GRACE_S = 10.0
INTERRUPTED_EXIT = 130  # a worker's exit status after SIGINT, as a shell's


def worker_context():
    """The multiprocessing context for worker processes."""
    if "forkserver" not in multiprocessing.get_all_start_methods():
        return multiprocessing.get_context("spawn")
    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload(["vcfusion.worker_preload"])
    return ctx


@dataclass(frozen=True)
class JobFailed:
    """A job that gave no result: its task raised, or its worker process died running it."""

    cause: str  # first line for the user, then details (the task's traceback)


def death_cause(exitcode: int | None) -> str:
    """'worker process died (signal 9: SIGKILL)' from a multiprocessing exit code."""
    if exitcode is not None and exitcode < 0:
        try:
            name = signal.Signals(-exitcode).name
        except ValueError:
            name = "unknown signal"
        return f"worker process died (signal {-exitcode}: {name})"
    if exitcode == INTERRUPTED_EXIT:
        return "worker process interrupted (SIGINT)"
    return f"worker process died (exit code {exitcode})"


def _interrupt_once(signum, frame):
    # The first SIGINT (the terminal's Ctrl-C, or the parent stopping the pool) or SIGTERM (sent to
    # the whole process group) interrupts the job; a second one must not interrupt the clean-up
    # that follows (partial folders removed).
    for stop in interrupts.STOP_SIGNALS:
        signal.signal(stop, signal.SIG_IGN)
    interrupts.note_received()
    raise KeyboardInterrupt


def worker_threads(workers: int) -> int:
    """Threads each of `workers` worker processes may use for torch and OpenCV: their share of the
    cores. Each took every core before, so W workers ran W x cores threads (the CNN of a fusion
    batch, the renderer's image work) and contended on every tick."""
    return max(1, (os.cpu_count() or 1) // max(1, workers))


def _limit_threads(threads: int) -> None:
    import cv2  # its thread pool ignores the variables below: set here (a fast import)

    cv2.setNumThreads(threads)
    # torch when the fork server loaded it; the variables cover it and the BLAS libraries when a
    # job loads them later (OpenMP reads them when it starts)
    # LP_NUM_THREADS: OSMesa's llvmpipe rasteriser, read when a worker creates its GL context
    for name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "LP_NUM_THREADS"):
        os.environ[name] = str(threads)
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(threads)


def _serve(task: Callable, conn, scratch: str, threads: int | None = None) -> None:
    """A worker: run task(*job) for each job received until the parent closes the pipe, with at
    most `threads` threads for torch and OpenCV (None: as they come)."""
    if signal.getsignal(signal.SIGINT) is not signal.SIG_IGN:  # as the parent's (a background job ignores it)
        signal.signal(signal.SIGINT, _interrupt_once)
    if signal.getsignal(signal.SIGTERM) is not signal.SIG_IGN:
        signal.signal(signal.SIGTERM, _interrupt_once)
    # Temporary files of the jobs go to a folder the parent removes, even after a SIGKILL here.
    tempfile.tempdir = scratch
    os.environ["TMPDIR"] = scratch
    if threads is not None:
        _limit_threads(threads)
    # tqdm's default lock is a multiprocessing semaphore, which a killed worker would leak (and
    # the resource tracker warn about at exit); a worker's bars are its own: a thread lock does.
    from tqdm import tqdm

    tqdm.set_lock(threading.RLock())
    with interrupts.recorded():  # a SIGINT that numba swallows still stops the job (vcfusion.interrupts)
        try:
            while True:
                job = conn.recv()
                try:
                    result = task(*job)
                    # a SIGINT that the job caught (a seed reported failed for numba's SystemError)
                    # still stops the worker: it is recorded, and the next job would die of it
                    interrupts.raise_if_received()
                except Exception as exc:  # the job fails, the worker goes on
                    if interrupts.is_interrupt(exc):  # SIGINT mangled on its way up (numba): the worker stops
                        raise KeyboardInterrupt from exc
                    result = JobFailed(f"{type(exc).__name__}: {exc}\n{traceback.format_exc(limit=3)}")
                try:
                    conn.send(result)
                except (EOFError, OSError):
                    raise
                except Exception as exc:  # a result that cannot be pickled (nothing was sent yet)
                    conn.send(JobFailed(f"the job's result could not be sent back: {type(exc).__name__}: {exc}"))
        except (EOFError, OSError):
            pass  # the parent closed the pipe or went away: exit quietly
        except KeyboardInterrupt:
            sys.exit(INTERRUPTED_EXIT)  # quietly, and telling the parent why


class _Worker:
    def __init__(self, ctx, task: Callable, threads: int | None = None):
        self.scratch = tempfile.mkdtemp(prefix="vcfusion-worker-")
        self.conn, child_end = ctx.Pipe()
        # not daemonic, as a concurrent.futures worker: a job may start processes of its own
        self.process = ctx.Process(target=_serve, args=(task, child_end, self.scratch, threads))
        try:
            self.process.start()  # ~1 s when the fork server starts: a Ctrl-C often lands here
        except BaseException:
            # not in the pool yet, so _stop would not see it: a started worker reads the end of
            # its pipe and exits; its scratch folder goes now
            self.conn.close()
            if self.process.pid is not None:
                self.process.kill()
                self.process.join()
            shutil.rmtree(self.scratch, ignore_errors=True)
            raise
        finally:
            child_end.close()
        self.job: int | None = None  # index of the job it runs
        self.pipe_closed = False  # the worker's end is gone: it died (its exit code follows)


def run_jobs(task: Callable, jobs: Sequence[tuple], workers: int,
             on_start: Callable[[int, int], None] | None = None) -> Iterator[tuple[int, object]]:
    """Run task(*job) for every job in at most `workers` worker processes.

    Yields (index of the job, its result) as jobs end, in completion order. The result is the
    task's return value, or a JobFailed when the task raised or its worker died. `on_start(index,
    pid)` is called when a job is handed to worker `pid`. Closing the iterator early, or an
    exception (Ctrl-C) in the caller, stops the pool: busy workers get SIGINT so that their jobs
    clean up, and are killed after STOP_GRACE_S.
    """
    ctx = worker_context()
    pending = deque(range(len(jobs)))
    pool: list[_Worker] = []
    # the workers that will run: fewer jobs than workers leave the cores to fewer processes
    workers = max(1, min(workers, len(jobs)))
    try:
        while pending or any(w.job is not None for w in pool):
            for w in [w for w in pool if w.job is None]:
                if pending:
                    _hand_over(w, pending, jobs, on_start)
            while pending and len(pool) < workers:
                w = _Worker(ctx, task, worker_threads(workers))
                pool.append(w)
                _hand_over(w, pending, jobs, on_start)
            wait([w.conn for w in pool if not w.pipe_closed] + [w.process.sentinel for w in pool])
            for w in list(pool):
                result = _collect(w)
                if result is not None:
                    # the next job goes out before the caller handles this result: the worker
                    # does not idle while the parent writes and reports (short seeds)
                    if pending:
                        _hand_over(w, pending, jobs, on_start)
                    index, value = result
                    yield index, value
                elif not w.process.is_alive():  # died, busy or idle: a fresh one replaces it
                    w.process.join()
                    pool.remove(w)
                    _discard(w)
                    if w.job is not None:
                        yield w.job, JobFailed(death_cause(w.process.exitcode))
    finally:
        _stop(pool)


def _hand_over(w: _Worker, pending: deque, jobs: Sequence[tuple], on_start) -> None:
    index = pending.popleft()
    try:
        w.conn.send(jobs[index])
    except OSError:  # the worker died while idle: the job waits for the next one
        pending.appendleft(index)
        return
    w.job = index
    if on_start is not None:
        on_start(index, w.process.pid)


def _collect(w: _Worker) -> tuple[int, object] | None:
    """(job, result) when worker `w` sent one, else None (nothing yet, or the pipe closed: an
    idle worker sends nothing, so a readable pipe of one means it died)."""
    if w.pipe_closed or not w.conn.poll():
        return None
    try:
        value = w.conn.recv()
    except (EOFError, OSError):
        w.pipe_closed = True  # the worker died: its sentinel tells when its exit code is known
        return None
    index, w.job = w.job, None
    return index, value


def results_in_order(task: Callable, jobs: Sequence[tuple], workers: int, what: Callable[[int], str],
                     on_result: Callable[[int], None] | None = None) -> list:
    """The results of task(*job) for every job, in the jobs' order, from `workers` processes; the
    first job that fails raises JobError naming it (`what(index)`) and stops the pool. For work
    whose parts must all succeed (a dataset folder written whole); `on_result(index)` as each ends."""
    from vcfusion.errors import JobError

    done = {}
    for index, result in run_jobs(task, jobs, workers):
        if isinstance(result, JobFailed):
            raise JobError(what(index), result.cause)
        done[index] = result
        if on_result is not None:
            on_result(index)
    return [done[index] for index in range(len(jobs))]


def _discard(w: _Worker) -> None:
    w.conn.close()
    shutil.rmtree(w.scratch, ignore_errors=True)


@contextmanager
def _stop_signals_ignored():
    """While stopping the pool, a second Ctrl-C (or SIGTERM) must not abandon its workers."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {stop: signal.signal(stop, signal.SIG_IGN) for stop in interrupts.STOP_SIGNALS}
    try:
        yield
    finally:
        for stop, handler in previous.items():
            signal.signal(stop, handler)


def _stop(pool: list[_Worker]) -> None:
    with _stop_signals_ignored():
        for w in pool:
            if w.job is not None and w.process.is_alive():
                try:
                    os.kill(w.process.pid, signal.SIGINT)  # its job removes its partial outputs
                except ProcessLookupError:
                    pass  # it has just ended
            w.conn.close()  # an idle worker reads the end of its pipe and exits
        deadline = time.monotonic() + STOP_GRACE_S
        for w in pool:
            w.process.join(max(0.0, deadline - time.monotonic()))
            if w.process.is_alive():
                w.process.kill()
                w.process.join()
            shutil.rmtree(w.scratch, ignore_errors=True)
