"""tools/loop_hashes.py: the hash of a run table changes with any value, dtype or column name."""

import importlib.util

import numpy as np
import pandas as pd

from scenario_files import REPO


def _tool():
    spec = importlib.util.spec_from_file_location("loop_hashes_tool", REPO / "tools" / "loop_hashes.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_a_tables_hash_changes_with_one_ulp_a_dtype_a_nan_or_a_name_and_only_then():
    table_hash = _tool().table_hash
    frame = pd.DataFrame({"time": [0.1, 0.2], "vehicle_id": ["a", "b"], "lane": np.array([0, 1], np.int16)})
    same = pd.DataFrame({"time": [0.1, 0.2], "vehicle_id": ["a", "b"], "lane": np.array([0, 1], np.int16)})
    assert table_hash(frame) == table_hash(same)
    ulp = same.assign(time=[0.1, np.nextafter(0.2, 1.0)])
    wider = same.assign(lane=np.array([0, 1], np.int32))
    nan = same.assign(time=[0.1, np.nan])
    renamed = same.rename(columns={"lane": "track"})
    hashes = {table_hash(f) for f in (frame, ulp, wider, nan, renamed)}
    assert len(hashes) == 5
