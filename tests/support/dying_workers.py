"""Ways for a test to end a real worker process in the middle of its job (as the out-of-memory
killer does: SIGKILL), for the fault tests of the worker pools."""

from __future__ import annotations

import multiprocessing
import os
import signal
import time
from pathlib import Path

import numpy as np


def _first_to_claim(marker: Path) -> bool:
    try:
        os.close(os.open(marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY))
        return True
    except FileExistsError:
        return False


def dies_once(scenario):
    """A process-model factory (`--process-model support.dying_workers:dies_once`): the first
    worker process that builds it kills itself with SIGKILL; later ones, and the parent's
    fail-fast load, get a model that adds a constant column. The marker lives beside the scenario."""
    in_worker = multiprocessing.parent_process() is not None
    if in_worker and _first_to_claim(Path(scenario.source).parent / "killed-once"):
        os.kill(os.getpid(), signal.SIGKILL)
    return lambda twins, store: {"dies_once_survived": np.ones(len(twins))}


def run_seed_or_die(scenario_path: str, seed: int, out: str, deaths: dict[int, int]):
    """A batch task: the batch's own seed task, except that a seed in `deaths` kills its worker
    process with SIGKILL on its first deaths[seed] attempts (counted in files in the batch folder)."""
    from vcfusion.studies.batch import _run_seed

    if seed in deaths:
        for attempt in range(deaths[seed]):
            if _first_to_claim(Path(out) / f"death-{seed}-{attempt}"):
                time.sleep(0.2)  # die in the middle of the job, not at its very start
                os.kill(os.getpid(), signal.SIGKILL)
    return _run_seed(scenario_path, seed, out)


def wait_for(path: Path, timeout_s: float = 120.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not path.exists():
        if time.monotonic() > deadline:
            raise TimeoutError(f"{path} did not appear in {timeout_s} s")
        time.sleep(0.01)
