"""The run folder: Parquet tables, manifest and summary, written atomically.

Everything is written into a temporary sibling folder which is renamed to the run folder
once complete, so a run folder either is whole or does not exist.
"""

from __future__ import annotations

import glob
import json
import math
import os
import platform
import shutil
from collections.abc import Callable, Mapping
from contextlib import contextmanager
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.compute as pc
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


def package_code_sha256() -> str:
    """sha256 over the package's own Python source (each file's path inside the package, then its
    bytes, in path order): two installs give the same digest exactly when their code is the same,
    a source tree with uncommitted edits included (package data such as weights is hashed where a
    record names it: `run.input_files`)."""
    import hashlib

    root = Path(__file__).resolve().parent
    digest = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        digest.update(path.relative_to(root).as_posix().encode() + b"\0")
        digest.update(path.read_bytes())
    return digest.hexdigest()


def write_json(path: Path, data: dict) -> None:
    path.write_text(json.dumps(data, indent=2, sort_keys=True, default=str) + "\n")


def differing_keys(a: dict, b: dict) -> list[str]:
    """The keys (sorted) whose values differ between two records (a key missing from one differs)."""
    return sorted(k for k in a.keys() | b.keys() if a.get(k) != b.get(k))


def json_null_for_nan(data):
    """`data` with every NaN or infinite float as None (JSON null: NaN is no JSON, and strict readers refuse it)."""
    if isinstance(data, dict):
        return {k: json_null_for_nan(v) for k, v in data.items()}
    if isinstance(data, (list, tuple)):
        return [json_null_for_nan(v) for v in data]
    if isinstance(data, float) and not math.isfinite(data):
        return None
    return data


def write_table(path: Path, frame: pd.DataFrame) -> None:
    # Fixed writer settings so that the same table gives the same bytes.
    frame.reset_index(drop=True).to_parquet(path, engine="pyarrow", index=False, compression="zstd")


def _new_temporary_file(path: Path) -> Path:
    """An empty file of our own beside `path`, named .NAME.PID.RANDOM.SUFFIX, created with the
    permissions a plain write of a new file gets (0o666 less the umask; tempfile.mkstemp's 0o600
    would make a model or table written this way unreadable to the user's group)."""
    for _ in range(100):
        tmp = path.parent / f".{path.name}.{os.getpid()}.{os.urandom(4).hex()}{path.suffix}"
        try:
            os.close(os.open(tmp, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o666))
            return tmp
        except FileExistsError:
            continue
    raise FileExistsError(f"{path}: no free temporary name beside it")


def _fsync(path: Path) -> None:
    """Flush a file's (or a folder's: its entries') data to the disk."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def atomic_write(path: Path, write: Callable[[Path], None]) -> None:
    """`write(tmp)` into a temporary file of its own beside `path` (same suffix: writers that go by
    it still do), renamed over `path` when complete: a kill in the middle leaves the previous file
    whole instead of a truncated one under the final name."""
    path = Path(path)
    # its folder made, as atomic_folder makes a folder's parent (into a missing folder the error named
    # the temporary file: "nodir/.x.onnx.14945.14b5d359.onnx: No such file or directory")
    path.parent.mkdir(parents=True, exist_ok=True)
    # what killed writers of this file left (SIGKILL: no clean-up ran), named after their pid
    for left in path.parent.glob(glob.escape(f".{path.name}.") + "*"):
        pid = left.name[len(path.name) + 2:].split(".", 1)[0]
        if pid.isdigit() and left.is_file() and not _writer_alive(pid):
            left.unlink(missing_ok=True)
    tmp = _new_temporary_file(path)
    try:
        write(tmp)
        if path.exists():  # as an overwrite in place would: the file keeps its permissions
            shutil.copymode(path, tmp)
        _fsync(tmp)  # the content on disk before the name points at it: a power cut leaves old or new
        os.replace(tmp, path)
        if os.name == "posix":  # and the rename itself (a folder cannot be opened for it elsewhere)
            try:
                _fsync(path.parent)
            except OSError:  # some file systems refuse a folder's fsync; the file is in place all the same
                pass
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


class TableSink:
    """A table that grows during a run, written to Parquet in row groups as it grows.

    Appended chunks are kept as they are and concatenated per column every `flush_rows` rows
    (np.concatenate's dtype promotion: longer strings, ints into floats), so a long run's memory
    does not grow with simulated time. Flushing at fixed row counts keeps the bytes of the file
    a function of its content (runs stay byte-identical). A table that never reaches
    `flush_rows` never touches the disk: :meth:`close` hands it back in memory, and it is
    written (with the same bytes as one row group) only if the run folder is.

    The sink keeps the arrays it is given, without a copy: a caller must not change them after
    :meth:`append` (the tick loop's records are immutable). A tick appends ~10 rows; one
    concatenation of a row group's chunks costs ~3 us a chunk against ~12 us for copying each
    chunk into growing buffers (12 columns, measured).
    """

    def __init__(self, path: Path, flush_rows: int = 65_536):
        self.path = Path(path)
        self.flush_rows = flush_rows
        self._chunks: list[dict[str, np.ndarray]] = []  # appended since the last flush
        self._names: tuple[str, ...] | None = None  # the columns, from the first chunk with rows
        self._name_set: frozenset[str] = frozenset()
        self._buffered = 0
        self._writer: pq.ParquetWriter | None = None
        self._schema: pa.Schema | None = None
        self.rows = 0

    def append(self, columns: dict[str, np.ndarray]) -> None:
        n = len(next(iter(columns.values()))) if columns else 0
        if n == 0:
            return
        if self._names is None:
            self._names, self._name_set = tuple(columns), frozenset(columns)
        elif columns.keys() != self._name_set:
            raise KeyError(f"{self.path.name}: columns {sorted(columns)}; expected those of the earlier rows, "
                           f"{sorted(self._names)}")
        self._chunks.append(columns)
        self._buffered += n
        self.rows += n
        if self._buffered >= self.flush_rows:
            self._flush()

    def append_rows(self, rows: list[dict]) -> None:
        if rows:
            self.append({k: np.array([r[k] for r in rows]) for k in rows[0]})

    def _drain(self) -> pa.Table:
        """The rows appended since the last flush as one Arrow table; the sink starts anew."""
        chunks, self._chunks, self._buffered = self._chunks, [], 0
        arrays = {}
        for name in self._names:
            v = np.concatenate([c[name] for c in chunks])
            arrays[name] = pa.array(v.astype(str) if v.dtype == object else v)
        if self._schema is None:
            self._schema = pa.schema([(k, a.type) for k, a in arrays.items()])
        return pa.Table.from_arrays([arrays[f.name].cast(f.type) for f in self._schema], schema=self._schema)

    def _flush(self) -> None:
        if not self._buffered:
            return
        table = self._drain()
        if self._writer is None:
            self._writer = pq.ParquetWriter(self.path, self._schema, compression="zstd")
        self._writer.write_table(table)  # one row group per flush

    def close(self) -> Path | pa.Table | None:
        """The table: its Parquet file once it was flushed, else in memory (None when empty)."""
        if self._writer is None:
            return self._drain() if self._buffered else None
        self._flush()
        self._writer.close()
        self._writer = None
        return self.path


class RunTables(Mapping):
    """A run's tables by name: DataFrames, in-memory Arrow tables (converted on access) and
    streamed ones read from Parquet on access."""

    def __init__(self, frames: dict[str, pd.DataFrame], stored: dict[str, Path | pa.Table], keepalive=None):
        self._frames = dict(frames)
        self._stored = dict(stored)
        self._cache: dict[str, pd.DataFrame] = {}
        self._keepalive = keepalive  # e.g. the TemporaryDirectory holding the files

    def __getitem__(self, name: str) -> pd.DataFrame:
        if name in self._frames:
            return self._frames[name]
        if name not in self._cache:
            src = self._stored[name]
            self._cache[name] = src.to_pandas() if isinstance(src, pa.Table) else pd.read_parquet(src)
        return self._cache[name]

    def arrow(self, name: str, columns: list[str]) -> pa.Table:
        """Some columns of a table as Arrow (no pandas conversion; e.g. for end-of-run summaries)."""
        if name in self._frames or name in self._cache:
            return pa.Table.from_pandas(self[name][columns], preserve_index=False)
        src = self._stored[name]
        return src.select(columns) if isinstance(src, pa.Table) else pq.read_table(src, columns=columns)

    def column_names(self, name: str) -> list[str]:
        if name in self._frames or name in self._cache:
            return list(self[name].columns)
        src = self._stored[name]
        return src.schema.names if isinstance(src, pa.Table) else pq.read_schema(src).names

    def __iter__(self):
        return iter(list(self._frames) + [k for k in self._stored if k not in self._frames])

    def __len__(self) -> int:
        return len(set(self._frames) | set(self._stored))

    def __setitem__(self, name: str, frame: pd.DataFrame) -> None:
        self._frames[name] = frame

    def update(self, other: dict[str, pd.DataFrame]) -> None:
        self._frames.update(other)

    def add_arrow(self, name: str, table: pa.Table) -> None:
        """A table made as Arrow (converted to pandas only if someone reads it)."""
        self._stored[name] = table

    def sources(self) -> dict[str, pd.DataFrame | pa.Table | Path]:
        """Each table as a DataFrame, an Arrow table or its already-written Parquet file."""
        return {**self._stored, **self._frames}

    def relocate(self, folder: Path) -> None:
        """The tables were written into `folder` (same names): read them from there from now on."""
        self._stored = {k: Path(folder) / f"{k}.parquet" for k in self._stored if k not in self._frames}


def vehicle_tracks(table: pa.Table, vehicle_ids, columns: list[str]) -> dict[str, dict[str, np.ndarray]]:
    """For each of `vehicle_ids` found in `table` (which has a vehicle_id column): its rows'
    values of `columns` as NumPy arrays by column name, in table order (time order for the run's
    tables)."""
    if not vehicle_ids or table.num_rows == 0:
        return {}
    vid_column = table.column("vehicle_id")
    wanted = pa.array(sorted(vehicle_ids), type=vid_column.type)
    rows = table.filter(pc.is_in(vid_column, value_set=wanted))
    # group by vehicle with one stable sort (a per-vehicle scan would be rows x vehicles)
    encoded = pc.dictionary_encode(rows.column("vehicle_id").combine_chunks())
    codes = encoded.indices.to_numpy(zero_copy_only=False)
    order = np.argsort(codes, kind="stable")
    ends = np.cumsum(np.bincount(codes, minlength=len(encoded.dictionary)))
    values = {c: rows.column(c).to_numpy()[order] for c in columns}
    return {vid: {c: v[start:end] for c, v in values.items()}
            for vid, start, end in zip(encoded.dictionary.to_pylist(), np.r_[0, ends[:-1]], ends)}


def write_run_folder(out_dir: Path, tables: Mapping[str, pd.DataFrame | Path], manifest: dict, summary: dict,
                     extra_files: dict[str, Path] | None = None) -> Path:
    """Write a complete run folder at out_dir (which must not exist yet).

    A table given as a Path is an already-written Parquet file and is moved in, and so are
    `extra_files` (name in the folder -> file or folder, e.g. the AR video and its frames).
    summary.json gets the list of the folder's files.
    """
    if isinstance(tables, RunTables):
        tables = tables.sources()
    with atomic_folder(out_dir, "run folder") as tmp:
        for name, frame in tables.items():
            if isinstance(frame, Path):
                shutil.move(str(frame), tmp / f"{name}.parquet")
            elif isinstance(frame, pa.Table):
                pq.write_table(frame, tmp / f"{name}.parquet", compression="zstd")  # as TableSink writes
            else:
                write_table(tmp / f"{name}.parquet", frame)
        for name, src in (extra_files or {}).items():
            shutil.move(str(src), tmp / name)
        # what the folder holds (a folder's name ends in '/'), these two JSON files included
        files = sorted([p.name + "/" * p.is_dir() for p in tmp.iterdir()] + [SUMMARY, MANIFEST])
        write_json(tmp / SUMMARY, {**summary, "files": files})
        write_json(tmp / MANIFEST, manifest)  # last: its presence marks a complete run
    return Path(out_dir)


PARTIAL_SUFFIX = ".tmp-writing"  # what a writer writes into before the rename that completes it


def _partial(out: Path) -> Path:
    # one per writing process: a second writer of the same folder (the same command started twice)
    # must not delete or fill the first one's
    return Path(out).with_name(f"{Path(out).name}{PARTIAL_SUFFIX}-{os.getpid()}")


def video_staging_prefix(out: Path) -> str:
    """Name prefix of the folder beside `out` where this process stages its AR video before moving it in."""
    return f".{Path(out).name}.video-{os.getpid()}-"


def _writer_alive(pid: str) -> bool:
    """Whether the process that named a partial folder after itself still runs (so may still write it).
    A dead writer's pid taken by another process keeps its folder until that process ends."""
    if not pid.isdigit() or int(pid) == os.getpid():  # no pid (older layout), or this process's own leftover
        return False
    try:
        os.kill(int(pid), 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's live process
        return True
    return True


def discard_partial_folder(out: Path) -> None:
    """Remove what writers of `out` killed before they completed (SIGKILL) left behind: their partial
    folders and their AR videos' staging folders (their frames stayed forever before). A writer that
    still runs keeps its own."""
    out = Path(out)
    partial = out.name + PARTIAL_SUFFIX
    staging = f".{out.name}.video-"
    for path in out.parent.glob(glob.escape(partial) + "*"):
        if path.name == partial or (path.name[len(partial)] == "-" and not _writer_alive(path.name[len(partial) + 1:])):
            shutil.rmtree(path, ignore_errors=True)
    for path in out.parent.glob(glob.escape(staging) + "*"):
        pid = path.name[len(staging):].split("-", 1)[0]
        # this process's staging holds the video that the run folder being written moves in
        if pid != str(os.getpid()) and not _writer_alive(pid):
            shutil.rmtree(path, ignore_errors=True)


@contextmanager
def atomic_folder(out: Path, kind: str = "folder"):
    """Yield a temporary sibling folder that becomes `out` only if the block completes."""
    out = Path(out)
    if out.exists():
        raise FileExistsError(f"{out}: {kind} already exists")
    out.parent.mkdir(parents=True, exist_ok=True)
    discard_partial_folder(out)  # what killed writers of `out` left (a rerun of the command clears it)
    tmp = _partial(out)
    tmp.mkdir()
    try:
        yield tmp
        try:
            tmp.rename(out)
        except OSError:
            if out.exists():  # another writer completed it meanwhile: theirs stays
                raise FileExistsError(f"{out}: {kind} already exists (written by another process meanwhile)") from None
            raise
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def is_complete_run(folder: Path) -> bool:
    # a writer killed between its manifest and the rename leaves SEED.tmp-writing-PID with a manifest:
    # that folder matches seed_* but is no run
    return PARTIAL_SUFFIX not in Path(folder).name and (Path(folder) / MANIFEST).is_file()
