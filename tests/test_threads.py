import numpy as np  # noqa: F401  (loads the BLAS library the limit applies to)
from threadpoolctl import threadpool_info

from vcfusion.threads import one_blas_thread


def _blas_threads():
    return [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]


def test_one_blas_thread_nests_and_restores_only_at_the_outermost_exit():
    outside = _blas_threads()
    with one_blas_thread():
        assert set(_blas_threads()) == {1}
        with one_blas_thread():
            assert set(_blas_threads()) == {1}
        assert set(_blas_threads()) == {1}  # the inner exit must not restore the limit
    assert _blas_threads() == outside
