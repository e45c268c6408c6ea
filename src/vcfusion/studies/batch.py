"""Batch runs: many seeds of one scenario, one process per simulation, locally or on Dask.

libsumo holds one simulation per process, so seeds run in worker processes (forked from a
warm fork server or spawned, never inheriting SUMO state: vcfusion.workers). A seed's run
folder is OUT/seed_NNNN; a seed whose folder is
complete is skipped, so a re-run resumes. A failing seed is recorded in OUT/failures.json
and the others go on.
"""

from __future__ import annotations

import traceback
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path

import pandas as pd
from tqdm import tqdm

from vcfusion.errors import UsageError
from vcfusion.metrics.run_metrics import batch_row
from vcfusion.runio import is_complete_run, write_json, write_table
from vcfusion.workers import worker_context


def parse_seeds(text: str) -> list[int]:
    """'0-99', '3', '1,4,7-9' -> sorted unique seeds."""
    seeds: set[int] = set()
    try:
        for part in text.split(","):
            part = part.strip()
            if "-" in part:
                lo, hi = (int(x) for x in part.split("-", 1))
                if lo > hi or lo < 0:
                    raise ValueError
                seeds.update(range(lo, hi + 1))
            else:
                seed = int(part)
                if seed < 0:
                    raise ValueError
                seeds.add(seed)
    except ValueError:
        raise UsageError(f"--seeds: expected non-negative seeds like '0-99' or '1,4,7-9', got {text!r}") from None
    return sorted(seeds)


def seed_folder(out: Path, seed: int) -> Path:
    return Path(out) / f"seed_{seed:04d}"


@dataclass(frozen=True)
class SeedOutcome:
    seed: int
    ok: bool
    summary: dict | None
    error: str | None


def _run_seed(scenario_path: str, seed: int, out: str) -> SeedOutcome:
    # Imported here (already loaded in a worker forked from the warm fork server).
    from vcfusion.run import execute_run
    from vcfusion.scenario import load_scenario

    try:
        scenario = load_scenario(scenario_path)
        result = execute_run(scenario, seed, seed_folder(Path(out), seed))
        return SeedOutcome(seed, True, result.summary, None)
    except Exception as exc:  # isolate the failure of one seed from the others
        detail = traceback.format_exc(limit=3)
        return SeedOutcome(seed, False, None, f"{type(exc).__name__}: {exc}\n{detail}")


@dataclass(frozen=True)
class Executor:
    """Where seed jobs run: the local process pool (default) or a Dask cluster.

    `dask_scheduler` is the address of a running Dask scheduler (tcp://HOST:PORT); its workers
    must see the same file system as this process (the run folders are written by the workers).
    `dask_local` starts a local Dask cluster of that many single-threaded worker processes.
    Either way each worker process runs one simulation at a time (libsumo: one per process).
    """

    workers: int = 1
    dask_scheduler: str | None = None
    dask_local: int | None = None

    @property
    def kind(self) -> str:
        return "dask" if self.dask_scheduler or self.dask_local else "processes"


def _pool_outcomes(executor: Executor, task, jobs: list[tuple]):
    with ProcessPoolExecutor(max_workers=max(1, executor.workers), mp_context=worker_context()) as pool:
        futures = [pool.submit(task, *job) for job in jobs]
        for fut in as_completed(futures):
            yield fut.result()


def _dask_outcomes(executor: Executor, task, jobs: list[tuple]):
    from distributed import Client, LocalCluster
    from distributed import as_completed as dask_as_completed

    cluster = None
    if executor.dask_scheduler:
        client = Client(executor.dask_scheduler)
    else:
        cluster = LocalCluster(n_workers=executor.dask_local, threads_per_worker=1, processes=True,
                               host="127.0.0.1", dashboard_address=None)
        client = Client(cluster)
    try:
        # pure=False: a seed job writes files, it is not a cacheable function of its arguments.
        futures = client.map(task, *zip(*jobs), pure=False)
        for fut in dask_as_completed(futures):
            yield fut.result()
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def run_batch(scenario_path: Path, seeds: list[int], out: Path, workers: int = 1, progress: bool = True,
              task=_run_seed, executor: Executor | None = None) -> dict:
    """Run every seed not yet complete; returns {'done', 'skipped', 'failed'}."""
    out = Path(out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    executor = executor or Executor(workers=workers)
    todo = [s for s in seeds if not is_complete_run(seed_folder(out, s))]
    skipped = len(seeds) - len(todo)
    outcomes: list[SeedOutcome] = []
    bar = tqdm(total=len(todo), unit="run", desc=f"batch {Path(scenario_path).stem}", disable=not progress)
    if todo:
        jobs = [(str(Path(scenario_path).resolve()), s, str(out)) for s in todo]
        source = _dask_outcomes if executor.kind == "dask" else _pool_outcomes
        for outcome in source(executor, task, jobs):
            outcomes.append(outcome)
            bar.update(1)
            if not outcome.ok:
                bar.write(f"seed {outcome.seed} failed: {outcome.error.splitlines()[0]}")
    bar.close()
    failed = sorted((o for o in outcomes if not o.ok), key=lambda o: o.seed)
    _write_index(out, seeds, failed)
    return {"done": len(todo) - len(failed), "skipped": skipped, "failed": [(o.seed, o.error) for o in failed]}


def _write_index(out: Path, seeds: list[int], failed: list[SeedOutcome]) -> None:
    """batch_summary.parquet: one row per complete seed of this batch; failures.json: the rest."""
    import json

    rows = []
    for s in seeds:
        folder = seed_folder(out, s)
        if is_complete_run(folder):
            summary = json.loads((folder / "summary.json").read_text())
            rows.append(batch_row(summary))
    if rows:
        write_table(out / "batch_summary.parquet", pd.DataFrame(rows).sort_values("seed"))
    failures_file = out / "failures.json"
    if failed:
        write_json(failures_file, {str(o.seed): o.error for o in failed})
    elif failures_file.exists():
        failures_file.unlink()
