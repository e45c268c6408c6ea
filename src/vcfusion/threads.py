"""One BLAS thread for the per-tick work.

The tick loop's arrays are small (tens to hundreds of rows): a multi-threaded OpenBLAS gains
nothing there, and on a busy machine its thread hand-off made one MLP call take ~16 ms instead
of ~50 us (measured with `vcfusion bench-predict`). The co-simulation holds this for its whole
tick loop; the MLP also takes it per call when used on its own. Re-entrant: inside an outer
hold entering costs a counter increment (it is entered on every tick; a generator-based context
manager alone cost ~3 us per entry, and setting the limit was 6 library calls, ~20 us).
"""

from __future__ import annotations


class _OneBlasThread:
    def __init__(self):
        self._libs = None  # found once: threadpoolctl's own limit() re-inspects the libraries every call
        self._depth = 0  # nesting level: only the outermost entry sets and restores the limit
        self._before: list[int] = []

    def __enter__(self):
        if self._depth == 0:
            if self._libs is None:
                from threadpoolctl import ThreadpoolController

                self._libs = ThreadpoolController().select(user_api="blas").lib_controllers
            self._before = [lib.get_num_threads() for lib in self._libs]
            for lib, n in zip(self._libs, self._before):
                if n != 1:
                    lib.set_num_threads(1)
        self._depth += 1
        return self

    def __exit__(self, *exc) -> None:
        self._depth -= 1
        if self._depth == 0:
            for lib, n in zip(self._libs, self._before):
                if n != 1:
                    lib.set_num_threads(n)


_ONE_BLAS_THREAD = _OneBlasThread()


def one_blas_thread() -> _OneBlasThread:
    """Context manager: at most one BLAS thread inside (re-entrant)."""
    return _ONE_BLAS_THREAD
