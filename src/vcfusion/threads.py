"""One BLAS thread for the per-tick work.

The tick loop's arrays are small (tens to hundreds of rows): a multi-threaded OpenBLAS gains
nothing there, and on a busy machine its thread hand-off made one MLP call take ~16 ms instead
of ~50 us (measured with `vcfusion bench-predict`). The co-simulation holds this for its whole
tick loop; the MLP also takes it per call when used on its own. Re-entrant: inside an outer
hold it costs nothing (setting the limit was 6 library calls per tick, ~20 us).
"""

from __future__ import annotations

import contextlib

_BLAS_LIBS = None
_DEPTH = 0  # nesting level of one_blas_thread: only the outermost sets and restores the limit


@contextlib.contextmanager
def one_blas_thread():
    global _BLAS_LIBS, _DEPTH
    if _BLAS_LIBS is None:
        # found once: threadpoolctl's own limit() context re-inspects the libraries every call
        from threadpoolctl import ThreadpoolController

        _BLAS_LIBS = ThreadpoolController().select(user_api="blas").lib_controllers
    before = [lib.get_num_threads() for lib in _BLAS_LIBS] if _DEPTH == 0 else []
    for lib, n in zip(_BLAS_LIBS, before):
        if n != 1:
            lib.set_num_threads(1)
    _DEPTH += 1
    try:
        yield
    finally:
        _DEPTH -= 1
        for lib, n in zip(_BLAS_LIBS, before):
            if n != 1:
                lib.set_num_threads(n)
