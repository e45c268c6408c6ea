import numpy as np
import pandas as pd
import pytest

from vcfusion.runio import RunTables, TableSink, is_complete_run, vehicle_tracks, write_run_folder


def test_table_sink_streams_in_row_groups_and_round_trips(tmp_path):
    sink = TableSink(tmp_path / "t.parquet", flush_rows=10)
    expected = []
    for k in range(7):
        chunk = {"time": np.full(4, k * 0.1), "vehicle_id": np.array([f"v{i}" for i in range(4)], dtype=object),
                 "lane": np.arange(4, dtype=np.int16)}
        sink.append(chunk)
        expected.append(pd.DataFrame(chunk))
    sink.append({"time": np.array([]), "vehicle_id": np.array([], dtype=object), "lane": np.array([], np.int16)})
    path = sink.close()
    import pyarrow.parquet as pq

    assert pq.ParquetFile(path).num_row_groups == 3  # flushed at 12 and 24 rows, then the rest
    got = pd.read_parquet(path)
    pd.testing.assert_frame_equal(got, pd.concat(expected, ignore_index=True), check_dtype=False)
    assert got["lane"].dtype == np.int16
    assert TableSink(tmp_path / "empty.parquet").close() is None


def test_run_tables_lazy_and_moved_into_run_folder(tmp_path):
    sink = TableSink(tmp_path / "big.parquet")
    sink.append({"x": np.arange(5.0)})
    tables = RunTables({"small": pd.DataFrame({"a": [1]})}, {"big": sink.close()})
    assert sorted(tables) == ["big", "small"]
    assert tables.arrow("big", ["x"]).column("x").to_pylist() == [0, 1, 2, 3, 4]
    out = write_run_folder(tmp_path / "run", tables, {"seed": 0}, {})
    tables.relocate(out)
    assert is_complete_run(out) and not (tmp_path / "big.parquet").exists()
    assert tables["big"].x.sum() == 10
    with pytest.raises(FileExistsError):
        write_run_folder(out, tables, {}, {})


def test_table_sink_equals_concatenating_the_chunks_across_growth_and_promotion(tmp_path):
    """Buffers grow past their first size and promote dtypes exactly as np.concatenate would
    (longer strings later, an int column that becomes float)."""
    rng = np.random.default_rng(3)
    chunks = []
    for k in range(400):  # 400 x 1..12 rows: past the first buffer size
        n = int(rng.integers(1, 13))
        chunks.append({"time": np.full(n, round(k * 0.1, 6)),
                       "vehicle_id": np.array([f"veh{'x' * (k // 100)}{i}" for i in range(n)], dtype=object),
                       "leader": np.array([("a" * (1 + k % 7)) for _ in range(n)]),
                       "value": np.arange(n, dtype=np.int64) if k < 200 else rng.normal(size=n),
                       "lane": rng.integers(0, 3, n).astype(np.int16)})
    sink = TableSink(tmp_path / "t.parquet")
    for c in chunks:
        sink.append(c)
    got = sink.close().to_pandas()
    for name in chunks[0]:
        want = np.concatenate([c[name] for c in chunks])
        np.testing.assert_array_equal(got[name].to_numpy(), want.astype(str) if want.dtype.kind in "OU" else want)
    assert got["value"].dtype == np.float64 and got["lane"].dtype == np.int16


@pytest.mark.parametrize("stored", ["memory", "parquet"])
def test_vehicle_tracks_per_vehicle_in_table_order(tmp_path, stored):
    sink = TableSink(tmp_path / "traj.parquet", flush_rows=4 if stored == "parquet" else 65_536)
    for t in range(5):
        ids = ["b", "a", "c"] if t % 2 else ["a", "b"]
        sink.append({"vehicle_id": np.array(ids, dtype=object), "time": np.full(len(ids), t * 0.1),
                     "s": np.arange(len(ids)) + 10.0 * t})
    tables = RunTables({}, {"traj": sink.close()})
    tracks = vehicle_tracks(tables.arrow("traj", ["vehicle_id", "time", "s"]), {"a", "c", "zzz"}, ["time", "s"])
    assert sorted(tracks) == ["a", "c"]
    np.testing.assert_allclose(tracks["a"]["time"], [0.0, 0.1, 0.2, 0.3, 0.4])
    np.testing.assert_allclose(tracks["a"]["s"], [0.0, 11.0, 20.0, 31.0, 40.0])
    np.testing.assert_allclose(tracks["c"]["s"], [12.0, 32.0])
    assert vehicle_tracks(tables.arrow("traj", ["vehicle_id", "time"]), set(), ["time"]) == {}


def test_run_folder_moves_extra_files_in_and_its_summary_lists_them(tmp_path):
    import json

    staging = tmp_path / "staging"
    (staging / "frames").mkdir(parents=True)
    (staging / "frames" / "000000.png").write_bytes(b"png")
    (staging / "overlay.mp4").write_bytes(b"mp4")
    out = write_run_folder(tmp_path / "run", {"ego": pd.DataFrame({"t": [0.0, 0.1]})}, {"seed": 1}, {"seed": 1},
                           extra_files={"overlay.mp4": staging / "overlay.mp4", "frames": staging / "frames"})
    summary = json.loads((out / "summary.json").read_text())
    assert summary["files"] == ["ego.parquet", "frames/", "manifest.json", "overlay.mp4", "summary.json"]
    assert summary["files"] == sorted(p.name + "/" * p.is_dir() for p in out.iterdir())
    assert (out / "frames" / "000000.png").read_bytes() == b"png" and not list(staging.iterdir())
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run", "staging"]  # no temporary folder left


def test_a_writer_killed_before_its_rename_leaves_no_run(tmp_path):
    """A worker killed (OOM, SIGKILL) between writing its manifest and the rename that completes the
    folder leaves seed_0001.tmp-writing with a manifest: it matches seed_*, and `vcfusion metrics`
    counted it as a run of the batch."""
    from vcfusion.errors import UsageError
    from vcfusion.metrics.folders import run_folders

    batch = tmp_path / "batch"
    write_run_folder(batch / "seed_0000", {"vehicles": pd.DataFrame({"a": [1]})}, {"seed": 0}, {"seed": 0})
    write_run_folder(batch / "seed_0001", {"vehicles": pd.DataFrame({"a": [1]})}, {"seed": 1}, {"seed": 1})
    (batch / "seed_0001").rename(batch / "seed_0001.tmp-writing")  # as the killed writer left it
    assert (batch / "seed_0001.tmp-writing" / "manifest.json").is_file()
    assert not is_complete_run(batch / "seed_0001.tmp-writing")
    assert [p.name for p in run_folders(batch)[0]] == ["seed_0000"]
    (batch / "seed_0000").rename(batch / "seed_0000.tmp-writing")
    with pytest.raises(UsageError, match="complete seed_NNNN run folders"):
        run_folders(batch)


def test_a_file_replaced_through_a_temporary_one_survives_a_failed_write(tmp_path):
    from vcfusion.runio import atomic_write, write_table

    path = tmp_path / "batch_summary.parquet"
    write_table(path, pd.DataFrame({"seed": [0, 1]}))

    def killed(tmp):
        tmp.write_bytes(b"PAR1")  # a truncated Parquet file
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        atomic_write(path, killed)
    assert pd.read_parquet(path)["seed"].tolist() == [0, 1]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["batch_summary.parquet"]
    atomic_write(path, lambda tmp: write_table(tmp, pd.DataFrame({"seed": [5]})))
    assert pd.read_parquet(path)["seed"].tolist() == [5]


def test_a_file_written_through_a_temporary_one_gets_a_plain_writes_permissions(tmp_path):
    """A new file: 0o666 less the umask (the temporary file was 0o600, so a shipped model or a
    study's table was unreadable to the user's group); an existing file keeps its own."""
    import os
    import stat

    from vcfusion.runio import atomic_write

    old = os.umask(0o022)
    try:
        atomic_write(tmp_path / "model.npz", lambda tmp: tmp.write_bytes(b"model"))
        assert stat.S_IMODE((tmp_path / "model.npz").stat().st_mode) == 0o644
        os.chmod(tmp_path / "model.npz", 0o640)
        atomic_write(tmp_path / "model.npz", lambda tmp: tmp.write_bytes(b"model 2"))
        assert stat.S_IMODE((tmp_path / "model.npz").stat().st_mode) == 0o640
        assert (tmp_path / "model.npz").read_bytes() == b"model 2"
    finally:
        os.umask(old)


def test_a_file_written_through_a_temporary_one_is_on_disk_before_its_name(tmp_path, monkeypatch):
    """The temporary file's data is flushed before the rename and the folder's entry after it: a
    power cut after the rename cannot leave the name pointing at an empty file."""
    import os

    import vcfusion.runio as runio

    events = []
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(fd):
        events.append(("fsync", os.readlink(f"/proc/self/fd/{fd}")))
        real_fsync(fd)

    def replace(src, dst):
        events.append(("replace", str(dst)))
        real_replace(src, dst)

    monkeypatch.setattr(runio.os, "fsync", fsync)
    monkeypatch.setattr(runio.os, "replace", replace)
    runio.atomic_write(tmp_path / "model.npz", lambda tmp: tmp.write_bytes(b"model"))
    assert [e[0] for e in events] == ["fsync", "replace", "fsync"]
    folder = os.path.realpath(tmp_path)
    assert events[0][1].startswith(os.path.join(folder, ".model.npz."))  # the temporary file, before
    assert events[2][1] == folder  # the folder, after

    # a file system that refuses a folder's fsync: the write still succeeds
    def no_folder_fsync(fd):
        if os.path.isdir(os.readlink(f"/proc/self/fd/{fd}")):
            raise OSError(22, "Invalid argument")
        real_fsync(fd)

    monkeypatch.setattr(runio.os, "fsync", no_folder_fsync)
    runio.atomic_write(tmp_path / "model.npz", lambda tmp: tmp.write_bytes(b"model 2"))
    assert (tmp_path / "model.npz").read_bytes() == b"model 2"


def test_what_a_killed_writer_left_goes_but_nothing_else(tmp_path):
    """A run killed mid-way left its partial folder and, with the AR video on, the staging folder of
    its frames beside it: only the first was ever removed."""
    import subprocess
    import sys

    from vcfusion.runio import discard_partial_folder, video_staging_prefix

    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    out = tmp_path / "seed_0001"
    left = [tmp_path / "seed_0001.tmp-writing", tmp_path / f"seed_0001.tmp-writing-{dead.pid}",
            tmp_path / f".seed_0001.video-{dead.pid}-k3j2"]
    # this process's own staging folder holds the video its run folder is about to take in
    kept = [tmp_path / "seed_00011.tmp-writing", tmp_path / (video_staging_prefix(tmp_path / "seed_00011") + "x"),
            tmp_path / "seed_0002", tmp_path / (video_staging_prefix(out) + "own")]
    for folder in left + kept:
        (folder / "frames").mkdir(parents=True)
    discard_partial_folder(out)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(p.name for p in kept)


def test_a_writer_that_still_runs_keeps_its_partial_folder(tmp_path):
    """The same command started twice writes the same folder: the second may clear what a killed writer
    left, but not the folder (or the AR video staging) of a writer that is still running."""
    import subprocess
    import sys

    from vcfusion.runio import discard_partial_folder

    live = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    try:
        out = tmp_path / "seed_0001"
        kept = [tmp_path / f"seed_0001.tmp-writing-{live.pid}", tmp_path / f".seed_0001.video-{live.pid}-ab12"]
        gone = [tmp_path / f"seed_0001.tmp-writing-{dead.pid}", tmp_path / f".seed_0001.video-{dead.pid}-cd34"]
        for folder in kept + gone:
            (folder / "frames").mkdir(parents=True)
        discard_partial_folder(out)
        assert sorted(p.name for p in tmp_path.iterdir()) == sorted(p.name for p in kept)
    finally:
        live.kill()
        live.wait()


def test_two_writers_of_one_folder_the_later_one_is_refused_and_the_first_stays(tmp_path):
    from vcfusion.runio import atomic_folder

    out = tmp_path / "data"
    with pytest.raises(FileExistsError, match="written by another process meanwhile"):
        with atomic_folder(out, "dataset folder") as tmp:
            (tmp / "mine.txt").write_text("second")
            out.mkdir()  # the other writer's rename lands first
            (out / "theirs.txt").write_text("first")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data"]
    assert [p.name for p in out.iterdir()] == ["theirs.txt"]


def test_a_rerun_clears_what_a_killed_writer_of_the_folder_left(tmp_path):
    """The partial folder is named after its writer's pid, so a rerun (another pid) does not write
    over it: the rerun removes what the killed command left, or it would stay beside the new one."""
    import subprocess
    import sys

    from vcfusion.runio import atomic_folder

    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    (tmp_path / f"data.tmp-writing-{dead.pid}" / "rgb").mkdir(parents=True)
    with atomic_folder(tmp_path / "data", "dataset folder") as tmp:
        (tmp / "annotations.json").write_text("{}")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data"]


def test_a_file_write_clears_what_killed_writers_of_that_file_left(tmp_path):
    """atomic_write's temporary files carry the writer's pid: the next write of the file removes a
    killed writer's (SIGKILL runs no clean-up), and leaves a live writer's and other files alone."""
    import subprocess
    import sys

    from vcfusion.runio import atomic_write

    live = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    try:
        for name in (f".m.npz.{dead.pid}.x1.npz", f".m.npz.{live.pid}.y2.npz", ".m.npz.backup", "other.npz"):
            (tmp_path / name).write_bytes(b"x")
        atomic_write(tmp_path / "m.npz", lambda tmp: tmp.write_bytes(b"model"))
        assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
            ["m.npz", f".m.npz.{live.pid}.y2.npz", ".m.npz.backup", "other.npz"])
        assert (tmp_path / "m.npz").read_bytes() == b"model"
    finally:
        live.kill()
        live.wait()


def test_atomic_write_makes_the_folder_it_writes_into(tmp_path):
    # as atomic_folder does for a folder's parent; the error named the temporary file before
    from vcfusion.runio import atomic_write

    atomic_write(tmp_path / "a" / "b" / "model.onnx", lambda tmp: tmp.write_bytes(b"onnx"))
    assert (tmp_path / "a" / "b" / "model.onnx").read_bytes() == b"onnx"
    assert [p.name for p in (tmp_path / "a" / "b").iterdir()] == ["model.onnx"]


def test_json_null_for_nan_leaves_numbers_and_nulls_non_finite_floats():
    from vcfusion.runio import json_null_for_nan

    data = {"a": float("nan"), "b": [1.5, float("inf"), {"c": -float("inf"), "d": "NaN"}], "e": (2, None), "f": 0}
    assert json_null_for_nan(data) == {"a": None, "b": [1.5, None, {"c": None, "d": "NaN"}], "e": [2, None], "f": 0}


def test_table_sink_with_narrower_types_later_equals_concatenating(tmp_path):
    """A chunk of a type the earlier ones hold (a shorter string after a longer one, ints into a
    float column) and a wider one after it: the table is np.concatenate's."""
    chunks = [{"id": np.array(["abcdef", "b"]), "x": np.array([0.5, 1.5])},
              {"id": np.array(["c"]), "x": np.array([3], dtype=np.int64)},
              {"id": np.array(["dd", "eee"]), "x": np.array([7, 8], dtype=np.int16)},
              {"id": np.array(["abcdefghij"]), "x": np.array([2.25])}]
    sink = TableSink(tmp_path / "t.parquet")
    for c in chunks:
        sink.append(c)
    got = sink.close().to_pandas()
    for name in ("id", "x"):
        want = np.concatenate([c[name] for c in chunks])
        np.testing.assert_array_equal(got[name].to_numpy(), want.astype(str) if want.dtype.kind == "U" else want)
    assert got["x"].dtype == np.float64


def test_table_sink_refuses_a_chunk_with_other_columns_and_keeps_the_earlier_rows(tmp_path):
    sink = TableSink(tmp_path / "t.parquet")
    sink.append({"a": np.arange(2), "b": np.arange(2.0)})
    for other in ({"a": np.arange(1)}, {"a": np.arange(1), "b": np.arange(1.0), "c": np.arange(1)},
                  {"a": np.arange(1), "c": np.arange(1.0)}):
        with pytest.raises(KeyError, match="expected those of the earlier rows"):
            sink.append(other)
    got = sink.close().to_pandas()
    assert got["a"].tolist() == [0, 1] and got["b"].tolist() == [0.0, 1.0]
