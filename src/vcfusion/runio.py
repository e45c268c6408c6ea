"""The run folder: Parquet tables, manifest and summary, written atomically.

Everything is written into a temporary sibling folder which is renamed to the run folder
once complete, so a run folder either is whole or does not exist.
"""

from __future__ import annotations

import json
import platform
import shutil
from collections.abc import Mapping
from contextlib import contextmanager
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

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


class TableSink:
    """A table that grows during a run, written to Parquet in row groups as it grows.

    Rows are buffered as column chunks and flushed every `flush_rows` rows, so a long run's
    memory does not grow with simulated time. Flushing at fixed row counts keeps the bytes of
    the file a function of its content (runs stay byte-identical).
    """

    def __init__(self, path: Path, flush_rows: int = 65_536):
        self.path = Path(path)
        self.flush_rows = flush_rows
        self._chunks: list[dict[str, np.ndarray]] = []
        self._buffered = 0
        self._writer: pq.ParquetWriter | None = None
        self._schema: pa.Schema | None = None
        self.rows = 0

    def append(self, columns: dict[str, np.ndarray]) -> None:
        n = len(next(iter(columns.values()))) if columns else 0
        if n == 0:
            return
        self._chunks.append(columns)
        self._buffered += n
        self.rows += n
        if self._buffered >= self.flush_rows:
            self._flush()

    def append_rows(self, rows: list[dict]) -> None:
        if rows:
            self.append({k: np.array([r[k] for r in rows]) for k in rows[0]})

    def _flush(self) -> None:
        if not self._chunks:
            return
        names = list(self._chunks[0])
        data = {k: np.concatenate([c[k] for c in self._chunks]) for k in names}
        arrays = {k: pa.array(v.astype(str) if v.dtype == object else v) for k, v in data.items()}
        if self._schema is None:
            self._schema = pa.schema([(k, a.type) for k, a in arrays.items()])
            self._writer = pq.ParquetWriter(self.path, self._schema, compression="zstd")
        table = pa.Table.from_arrays([arrays[f.name].cast(f.type) for f in self._schema], schema=self._schema)
        self._writer.write_table(table)  # one row group per flush
        self._chunks, self._buffered = [], 0

    def close(self) -> Path | None:
        """Flush and close; the file's path, or None when the table stayed empty."""
        self._flush()
        if self._writer is not None:
            self._writer.close()
            self._writer = None
            return self.path
        return None


class RunTables(Mapping):
    """A run's tables by name: small ones in memory, streamed ones read from Parquet on access."""

    def __init__(self, frames: dict[str, pd.DataFrame], files: dict[str, Path], keepalive=None):
        self._frames = dict(frames)
        self._files = dict(files)
        self._cache: dict[str, pd.DataFrame] = {}
        self._keepalive = keepalive  # e.g. the TemporaryDirectory holding the files

    def __getitem__(self, name: str) -> pd.DataFrame:
        if name in self._frames:
            return self._frames[name]
        if name not in self._cache:
            self._cache[name] = pd.read_parquet(self._files[name])
        return self._cache[name]

    def columns(self, name: str, columns: list[str]) -> pd.DataFrame:
        """Some columns of a table, without loading the rest."""
        if name in self._frames or name in self._cache:
            return self[name][columns]
        return pd.read_parquet(self._files[name], columns=columns)

    def column_names(self, name: str) -> list[str]:
        if name in self._frames or name in self._cache:
            return list(self[name].columns)
        return pq.read_schema(self._files[name]).names

    def __iter__(self):
        return iter(list(self._frames) + [k for k in self._files if k not in self._frames])

    def __len__(self) -> int:
        return len(set(self._frames) | set(self._files))

    def __setitem__(self, name: str, frame: pd.DataFrame) -> None:
        self._frames[name] = frame

    def update(self, other: dict[str, pd.DataFrame]) -> None:
        self._frames.update(other)

    def sources(self) -> dict[str, pd.DataFrame | Path]:
        """Each table as a DataFrame or as its already-written Parquet file."""
        return {**self._files, **self._frames}

    def relocate(self, folder: Path) -> None:
        """The streamed files were moved into `folder` (same names)."""
        self._files = {k: Path(folder) / p.name for k, p in self._files.items()}


def write_run_folder(out_dir: Path, tables: Mapping[str, pd.DataFrame | Path], manifest: dict, summary: dict,
                     extra_files: dict[str, Path] | None = None) -> Path:
    """Write a complete run folder at out_dir (which must not exist yet).

    A table given as a Path is an already-written Parquet file and is moved in.
    """
    if isinstance(tables, RunTables):
        tables = tables.sources()
    with atomic_folder(out_dir, "run folder") as tmp:
        for name, frame in tables.items():
            if isinstance(frame, Path):
                shutil.move(str(frame), tmp / f"{name}.parquet")
            else:
                write_table(tmp / f"{name}.parquet", frame)
        for name, src in (extra_files or {}).items():
            shutil.move(str(src), tmp / name)
        write_json(tmp / SUMMARY, summary)
        write_json(tmp / MANIFEST, manifest)  # last: its presence marks a complete run
    return Path(out_dir)


@contextmanager
def atomic_folder(out: Path, kind: str = "folder"):
    """Yield a temporary sibling folder that becomes `out` only if the block completes."""
    out = Path(out)
    if out.exists():
        raise FileExistsError(f"{out}: {kind} already exists")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".tmp-writing")
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir()
    try:
        yield tmp
        tmp.rename(out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def is_complete_run(folder: Path) -> bool:
    return (Path(folder) / MANIFEST).is_file()
