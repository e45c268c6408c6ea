import numpy as np
import pandas as pd
import pytest

from vcfusion.runio import RunTables, TableSink, is_complete_run, write_run_folder


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
    assert tables.columns("big", ["x"]).x.tolist() == [0, 1, 2, 3, 4]
    out = write_run_folder(tmp_path / "run", tables, {"seed": 0}, {})
    tables.relocate(out)
    assert is_complete_run(out) and not (tmp_path / "big.parquet").exists()
    assert tables["big"].x.sum() == 10
    with pytest.raises(FileExistsError):
        write_run_folder(out, tables, {}, {})
