"""Worker processes for batch runs, datasets and studies.

libsumo holds one simulation per process, so parallel runs are processes. On platforms with a
fork server, workers are forked from it: it is started once per parent process, runs no
simulation and no threads of ours, and has already imported the run code and loaded the
compiled per-tick kernels (`vcfusion.worker_preload`), so a worker starts in milliseconds
instead of paying ~2 s of imports and numba initialisation per process. Elsewhere workers are
spawned fresh. Either way no SUMO state is ever inherited.
"""

from __future__ import annotations

import multiprocessing


def worker_context():
    """The multiprocessing context for worker processes."""
    if "forkserver" not in multiprocessing.get_all_start_methods():
        return multiprocessing.get_context("spawn")
    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload(["vcfusion.worker_preload"])
    return ctx
