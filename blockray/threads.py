"""The host's threads: how many cores the compiled kernels (numba ``prange``) use.

A render uses every core by default (numba's default: one thread per core); ``--threads N`` /
``render(threads=N)`` / :func:`using` choose fewer. Results never depend on the count: every
parallel loop writes only its own block's or ray's output.

Threading layer: numba's default (OpenMP when present) spins in its barriers. On this shared,
oversubscribed 2-core VM, 50 cornell shots with every batch on the pool took 8.0 s wall with
OpenMP against 0.78 s with the ``workqueue`` layer (docs/measurements.md), so ``workqueue`` is
the default here. It runs one parallel kernel at a time per process: callers that launch
kernels from several Python threads at once (e.g. a multi-threaded Dask worker) must set
``NUMBA_THREADING_LAYER=omp`` (or ``tbb``) in the environment, which always wins, or use one
thread per worker process.
"""

import os
import types
from contextlib import contextmanager

import numba

from .errors import ParameterError, option

__all__ = ["available", "get", "set_threads", "using", "parallel", "twins", "PARALLEL_MIN_RAYS"]

if "NUMBA_THREADING_LAYER" not in os.environ:
    numba.config.THREADING_LAYER = "workqueue"


#: a batch of fewer rays runs on the calling thread: starting the thread pool costs more than it
#: saves (and, on a loaded machine, waits for a descheduled worker)
PARALLEL_MIN_RAYS = 1 << 14


def parallel(rays):
    """Should a kernel run a batch of ``rays`` rays on the thread pool?"""
    return get() > 1 and rays >= PARALLEL_MIN_RAYS


def twins(loop):
    """``(on the pool, on the calling thread)``: the kernel ``loop`` (a ``prange`` loop over
    independent chunks) compiled twice from its one definition, with ``parallel=True`` and
    without (where ``prange`` is a plain range). :func:`parallel` picks one per batch. numba keys
    its on-disk cache by a function's name and line, not by its options (numba issue 6845), so the
    serial one is compiled from a copy of ``loop`` named ``<name>_serial``."""
    serial = types.FunctionType(loop.__code__, loop.__globals__, loop.__name__ + "_serial", loop.__defaults__,
                                loop.__closure__)
    serial.__qualname__ = loop.__qualname__ + "_serial"
    return numba.njit(cache=True, parallel=True)(loop), numba.njit(cache=True)(serial)


def available():
    """The most threads a kernel can use (the machine's cores, or NUMBA_NUM_THREADS)."""
    return int(numba.config.NUMBA_NUM_THREADS)


def get():
    """Threads the kernels use now (in the calling thread)."""
    return int(numba.get_num_threads())


def set_threads(n):
    """Use ``n`` threads (1 .. :func:`available`) in the kernels called from this thread."""
    if isinstance(n, bool) or not isinstance(n, int) or not 1 <= n <= available():
        raise ParameterError(f"{option('threads')} must be an integer from 1 to {available()} (this machine's cores), "
                             f"not {n!r}", parameter="threads")
    numba.set_num_threads(n)


@contextmanager
def using(n):
    """Run the body with ``n`` threads (None: leave the count as it is), then restore it."""
    if n is None:
        yield
        return
    previous = get()
    set_threads(n)
    try:
        yield
    finally:
        numba.set_num_threads(previous)
