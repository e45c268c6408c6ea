"""The run folder: Parquet tables, manifest and summary, written atomically.

Everything is written into a temporary sibling folder which is renamed to the run folder
once complete, so a run folder either is whole or does not exist.
"""

from __future__ import annotations

import json
import platform
import shutil
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import pandas as pd

MANIFEST = "manifest.json"
SUMMARY = "summary.json"


def package_versions() -> dict[str, str]:
    out = {"python": platform.python_version()}
    for pkg in ("vcfusion", "libsumo", "numpy", "pandas", "pyarrow", "torch"):
        try:
            out[pkg] = version(pkg)
        except PackageNotFoundError:
            out[pkg] = "not installed"
    return out


def write_json(path: Path, data: dict) -> None:
    path.write_text(json.dumps(data, indent=2, sort_keys=True, default=str) + "\n")


def write_table(path: Path, frame: pd.DataFrame) -> None:
    # Fixed writer settings so that the same table gives the same bytes.
    frame.reset_index(drop=True).to_parquet(path, engine="pyarrow", index=False, compression="zstd")


def write_run_folder(out_dir: Path, tables: dict[str, pd.DataFrame], manifest: dict, summary: dict,
                     extra_files: dict[str, Path] | None = None) -> Path:
    """Write a complete run folder at out_dir (which must not exist yet)."""
    out_dir = Path(out_dir)
    if out_dir.exists():
        raise FileExistsError(f"{out_dir}: run folder already exists")
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = out_dir.with_name(out_dir.name + ".tmp-writing")
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir()
    try:
        for name, frame in tables.items():
            write_table(tmp / f"{name}.parquet", frame)
        for name, src in (extra_files or {}).items():
            shutil.move(str(src), tmp / name)
        write_json(tmp / SUMMARY, summary)
        write_json(tmp / MANIFEST, manifest)  # last: its presence marks a complete run
        tmp.rename(out_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out_dir


def is_complete_run(folder: Path) -> bool:
    return (Path(folder) / MANIFEST).is_file()
