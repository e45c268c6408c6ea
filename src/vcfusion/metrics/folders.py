"""Run folders and batch folders as the metrics commands read them: find the run folders of a path,
recompute a folder's metric tables from its own tables, rebuild a batch's seeds table."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pandas as pd

from vcfusion.errors import UsageError

BATCH_SUMMARY = "batch_summary.parquet"


def run_folders(path: Path) -> tuple[list[Path], bool]:
    """The run folders of a run folder or a batch folder (seed_NNNN), and whether it is a batch."""
    from vcfusion.runio import is_complete_run

    path = Path(path)
    if is_complete_run(path):
        return [path], False
    seeds = sorted(p for p in path.glob("seed_*") if is_complete_run(p)) if path.is_dir() else []
    if not seeds:
        raise UsageError(f"{path}: expected a run folder (with manifest.json) or a batch folder "
                         "(with complete seed_NNNN run folders)")
    return seeds, True


def _settings(folder: Path, scenario_file: str | None):
    """(metrics config, simulation config): the metrics block of --scenario, else the run's own
    (a run written before the block existed gets the defaults); the sampling is always the run's."""
    from vcfusion.scenario import MetricsConfig, SimulationConfig, load_scenario

    recorded = json.loads((folder / "manifest.json").read_text())["scenario"]
    simulation = SimulationConfig.model_validate(recorded["simulation"])
    if scenario_file:
        return load_scenario(scenario_file).metrics, simulation
    return MetricsConfig.model_validate(recorded.get("metrics", {})), simulation


def recompute_folder(folder: Path, scenario_file: str | None = None) -> bool:
    """Rewrite a run folder's metric tables and the metrics block of its summary.json from its
    tables; returns whether SUMO's emission totals were there."""
    import pyarrow.parquet as pq

    from vcfusion.metrics.run_metrics import METRIC_TABLES, folder_metrics, write_summary_metrics

    for name in ("trajectories.parquet", "vehicles.parquet", "summary.json"):
        if not (folder / name).is_file():
            raise UsageError(f"{folder}: {name} is missing; expected a complete run folder")
    cfg, simulation = _settings(folder, scenario_file)
    result, block, has_sumo = folder_metrics(folder, cfg, simulation)
    written = []
    try:  # every table first to a temporary name: a failure leaves the folder as it was
        for name, table in zip(METRIC_TABLES, (result.vehicles, result.conflicts, result.histograms)):
            tmp = folder / f"{name}.parquet.tmp"
            pq.write_table(table, tmp, compression="zstd")  # as the run folder writer writes Arrow tables
            written.append((tmp, folder / f"{name}.parquet"))
    except BaseException:
        for tmp, _ in written:
            tmp.unlink(missing_ok=True)
        raise
    for tmp, final in written:
        os.replace(tmp, final)
    write_summary_metrics(folder, block)
    return has_sumo


def batch_seed_folders(batch: Path, folders: list[Path]) -> list[Path]:
    """The run folders a batch's figures cover: the seeds its batch_summary.parquet lists (those of
    the last `vcfusion batch` into it), else every complete one."""
    from vcfusion.studies.batch import seed_folder

    path = batch / BATCH_SUMMARY
    if not path.is_file():
        return folders
    listed = {seed_folder(batch, int(s)).name for s in pd.read_parquet(path, columns=["seed"])["seed"]}
    return [f for f in folders if f.name in listed]


def rebuild_batch_summary(batch: Path, folders: list[Path]) -> pd.DataFrame:
    """batch_summary.parquet from its seeds' summaries (the seeds it listed, else every complete one)."""
    from vcfusion.metrics.run_metrics import batch_row
    from vcfusion.runio import atomic_write, write_table

    path = batch / BATCH_SUMMARY
    rows = [batch_row(json.loads((folder / "summary.json").read_text())) for folder in batch_seed_folders(batch, folders)]
    frame = pd.DataFrame(rows).sort_values("seed")
    atomic_write(path, lambda tmp: write_table(tmp, frame))
    return frame


def print_batch_metrics(batch: Path) -> None:
    """The metrics of a batch over its seeds (end of `vcfusion batch` and `vcfusion metrics`)."""
    from vcfusion.metrics.batch_table import format_seed_statistics, seed_statistics

    path = Path(batch) / BATCH_SUMMARY
    if not path.is_file():
        return
    stats = seed_statistics(pd.read_parquet(path))
    if len(stats):
        print("metrics over the seeds (mean, t-based 95% confidence interval of the mean, spread of the seeds):")
        print(format_seed_statistics(stats))
