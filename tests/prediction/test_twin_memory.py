"""TwinMemory: each twin's row of the last tick, whether the tick's ids come as the last tick's
tuple (the run-time path, no lookup) or in any other form and order."""

import numpy as np

from vcfusion.prediction.memory import TwinMemory


def test_rows_of_the_last_tick_for_the_same_tuple_a_new_order_and_new_twins():
    memory = TwinMemory(1)
    assert memory.previous_rows(("a", "b")).tolist() == [-1, -1]
    memory.keep(("a", "b"), np.array([[1.0], [2.0]]))
    assert memory.previous_rows(("a", "b")).tolist() == [0, 1]  # the same twins, the same order
    memory.keep(("a", "b"), np.array([[3.0], [4.0]]))
    assert memory.previous_rows(("b", "a")).tolist() == [1, 0]
    assert memory.previous_rows(["a", "c"]).tolist() == [0, -1]
    assert memory.previous_rows(np.array(["b", "a"])).tolist() == [1, 0]
    memory.keep(("b", "c"), np.array([[5.0], [6.0]]))  # a leaves, c comes
    assert memory.previous_rows(("a", "b", "c")).tolist() == [-1, 0, 1]
    assert memory.previous_rows(("b", "c")).tolist() == [0, 1]
    memory.keep(["c"], np.array([[7.0]]))  # a list: the tuple of the tick before no longer holds
    assert memory.previous_rows(("b", "c")).tolist() == [-1, 0]
