"""Batch runs: many seeds of one scenario, one process per simulation, locally or on Dask.

libsumo holds one simulation per process, so seeds run in worker processes (forked from a
warm fork server or spawned, never inheriting SUMO state: vcfusion.workers). A seed's run
folder is OUT/seed_NNNN; a seed whose folder is complete is skipped, so a re-run resumes.
A failing seed is recorded in OUT/failures.json with its cause and the others go on: a seed
that raised, or whose worker process died running it (killed by the out-of-memory killer, a
crash): the worker is replaced. While a seed runs, OUT/running/seed_NNNN.pid names its worker
process. On Dask a seed whose worker is lost is run again, up to `lost_worker_retries` times.
"""

from __future__ import annotations

import shutil
import traceback
from dataclasses import dataclass
from pathlib import Path

import pandas as pd
from tqdm import tqdm

from vcfusion.errors import UsageError
from vcfusion.metrics.run_metrics import batch_row, metrics_settings
from vcfusion.runio import (atomic_write, differing_keys, discard_partial_folder, is_complete_run, write_json,
                            write_table)
from vcfusion.workers import JobFailed, run_jobs

# On Dask: how many times a seed is run again after the worker running it was lost (Dask's
# scheduler setting distributed.scheduler.allowed-failures, applied to the clusters we start).
LOST_WORKER_RETRIES = 2


def seed_folder(out: Path, seed: int) -> Path:
    return Path(out) / f"seed_{seed:04d}"


def complete_seeds(out: Path) -> list[int]:
    """The seeds whose run folder in `out` is complete."""
    numbers = (p.name.removeprefix("seed_") for p in Path(out).glob("seed_*"))
    return sorted(int(n) for n in numbers if n.isdigit() and is_complete_run(seed_folder(out, int(n))))


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
    `lost_worker_retries`: on a local Dask cluster, how many times a seed is run again after the
    worker running it died (a cluster at `dask_scheduler` applies its own
    distributed.scheduler.allowed-failures, Dask's default 3).
    """

    workers: int = 1
    dask_scheduler: str | None = None
    dask_local: int | None = None
    lost_worker_retries: int = LOST_WORKER_RETRIES

    @property
    def kind(self) -> str:
        return "dask" if self.dask_scheduler or self.dask_local else "processes"


def _pool_outcomes(executor: Executor, task, jobs: list[tuple], out: Path):
    running = out / "running"  # seed_NNNN.pid while a worker runs the seed (which pid, for the user)
    shutil.rmtree(running, ignore_errors=True)  # left by a batch that was killed itself

    def started(index: int, pid: int) -> None:
        running.mkdir(exist_ok=True)
        # written under another name and renamed: a reader never sees an empty pid file
        pid_file = running / f"seed_{jobs[index][1]:04d}.pid"
        pid_file.with_suffix(".pid-writing").write_text(f"{pid}\n")
        pid_file.with_suffix(".pid-writing").replace(pid_file)

    try:
        for index, result in run_jobs(task, jobs, executor.workers, on_start=started):
            seed = jobs[index][1]
            (running / f"seed_{seed:04d}.pid").unlink(missing_ok=True)
            if isinstance(result, JobFailed):  # its worker died (or the task itself broke)
                discard_partial_folder(seed_folder(out, seed))
                result = SeedOutcome(seed, False, None, result.cause)
            yield result
    finally:
        shutil.rmtree(running, ignore_errors=True)


def _dask_outcomes(executor: Executor, task, jobs: list[tuple], out: Path):
    import dask
    from distributed import Client, KilledWorker, LocalCluster
    from distributed import as_completed as dask_as_completed

    cluster = None
    if executor.dask_scheduler:
        client = Client(executor.dask_scheduler)
    else:
        # Dask runs a task again when the worker running it dies, up to allowed-failures times
        # (its `retries=` only covers tasks that raise; ours catch their errors themselves). A
        # worker holds only the seed it runs (worker-saturation 1.0; Dask's 1.1 hands a one-thread
        # worker a second, queued seed, and a lost worker then counts against both: under load a
        # seed that lost its worker once was recorded as failed twice)
        with dask.config.set({"distributed.scheduler.allowed-failures": executor.lost_worker_retries,
                              "distributed.scheduler.worker-saturation": 1.0}):
            cluster = LocalCluster(n_workers=executor.dask_local, threads_per_worker=1, processes=True,
                                   host="127.0.0.1", dashboard_address=None)
        client = Client(cluster)
    try:
        # pure=False: a seed job writes files, it is not a cacheable function of its arguments.
        futures = client.map(task, *zip(*jobs), pure=False)
        seed_of = {fut.key: job[1] for fut, job in zip(futures, jobs)}
        for fut in dask_as_completed(futures):
            try:
                yield fut.result()
            except KilledWorker as exc:
                seed = seed_of[fut.key]
                discard_partial_folder(seed_folder(out, seed))
                tries = exc.allowed_failures + 1
                yield SeedOutcome(seed, False, None, f"worker process died ({tries} Dask worker"
                                                     f"{'s' * (tries > 1)} lost running it)\n{exc}")
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
    check_kept_runs(scenario_path, seeds, out)
    skipped = len(seeds) - len(todo)
    outcomes: list[SeedOutcome] = []
    bar = tqdm(total=len(todo), unit="run", desc=f"batch {Path(scenario_path).stem}", disable=not progress)
    if todo:
        jobs = [(str(Path(scenario_path).resolve()), s, str(out)) for s in todo]
        source = _dask_outcomes if executor.kind == "dask" else _pool_outcomes
        stream = source(executor, task, jobs, out)
        try:
            for outcome in stream:
                outcomes.append(outcome)
                bar.update(1)
                if not outcome.ok:
                    bar.write(f"seed {outcome.seed} failed: {outcome.error.splitlines()[0]}")
        except KeyboardInterrupt:
            stream.close()  # stops the workers; their seeds remove what they had written
            # What a worker killed in the middle of writing left is removed here. On a cluster
            # of one's own, seeds may still be running there: they write whole folders or none.
            if not executor.dask_scheduler:
                for seed in todo:
                    discard_partial_folder(seed_folder(out, seed))
            raise
        finally:
            stream.close()
            bar.close()
    failed = sorted((o for o in outcomes if not o.ok), key=lambda o: o.seed)
    _write_index(out, seeds, failed)
    return {"done": len(todo) - len(failed), "skipped": skipped, "failed": [(o.seed, o.error) for o in failed]}


def check_kept_runs(scenario_path: Path, seeds: list[int], out: Path) -> None:
    """UsageError unless every complete run folder of these seeds in `out` (those a batch would keep)
    is this scenario's run of its seed: a re-run into a folder of another (or an edited) scenario
    would mix its old runs into the batch's summary."""
    import json

    from vcfusion.run import manifest_for
    from vcfusion.scenario import load_scenario

    seeds = [s for s in seeds if is_complete_run(seed_folder(out, s))]
    if not seeds:
        return
    scenario = load_scenario(scenario_path)
    expected_manifest = manifest_for(scenario, 0)
    expected = expected_manifest["scenario"]
    # `vcfusion metrics --scenario` recomputes a run's metrics with another block than its manifest's
    settings = metrics_settings(scenario.metrics) if scenario.metrics.enabled else None
    for seed in seeds:
        folder = seed_folder(out, seed)
        try:
            manifest = json.loads((folder / "manifest.json").read_text())
        except (OSError, ValueError):
            manifest = {}
        if not isinstance(manifest, dict):
            manifest = {}
        kept = manifest.get("scenario") if isinstance(manifest.get("scenario"), dict) else {}
        differs = differing_keys(expected, kept)
        # the files by content (a folder written before a file's digest was recorded: by name only)
        digests = manifest.get("files_sha256") if isinstance(manifest.get("files_sha256"), dict) else None
        if digests is not None:
            differs += [f"{k} file (its content)" for k, v in expected_manifest["files_sha256"].items()
                        if k in digests and digests[k] != v]
        if manifest.get("seed") != seed:
            differs.insert(0, "seed")
        if differs:
            what = ", ".join(differs[:4]) + (" ..." if len(differs) > 4 else "")
            raise UsageError(f"{folder}: holds a run that is not this scenario's run of seed {seed} (it differs in: "
                             f"{what}); a batch resumes only its own runs: choose another output folder, or "
                             "remove that one")
        if settings is not None:
            try:
                kept_settings = json.loads((folder / "summary.json").read_text())["metrics"]["settings"]
            except (OSError, ValueError, KeyError, TypeError):
                kept_settings = {}
            other = differing_keys(settings, kept_settings)
            if other:
                raise UsageError(f"{folder}: its metrics were recomputed with another metrics: block than this "
                                 f"scenario's (they differ in: {', '.join(other)}); a batch pools runs of one "
                                 f"definition: recompute them with this scenario's (vcfusion metrics {out} "
                                 f"--scenario {scenario_path}), or choose another output folder")


def _write_index(out: Path, seeds: list[int], failed: list[SeedOutcome]) -> None:
    """batch_summary.parquet: one row per complete seed of this batch; failures.json: the rest."""
    import json

    rows = []
    for s in seeds:
        folder = seed_folder(out, s)
        if is_complete_run(folder):
            summary = json.loads((folder / "summary.json").read_text())
            rows.append(batch_row(summary))
    # each file whole or not at all, and none left from an earlier batch into this folder: a summary
    # of other seeds next to this batch's failures was reported as this batch's metrics
    summary_file = out / "batch_summary.parquet"
    if rows:
        atomic_write(summary_file, lambda tmp: write_table(tmp, pd.DataFrame(rows).sort_values("seed")))
    else:
        summary_file.unlink(missing_ok=True)
    failures_file = out / "failures.json"
    if failed:
        atomic_write(failures_file, lambda tmp: write_json(tmp, {str(o.seed): o.error for o in failed}))
    else:
        failures_file.unlink(missing_ok=True)
