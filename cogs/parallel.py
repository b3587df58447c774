"""Run a nogil numba function over chunks of an index range on a small thread pool.

Why not numba's ``parallel=True``: its OpenMP workers spin while they wait for work, and
with the default wait policy a parallel region on a machine where another process competes
for the cores ran 5-7x slower than one thread (measured on the 2-core development
machines: 180 ms instead of 25 ms per 20k-Gaussian step). The policy cannot be changed
once torch has initialised OpenMP (`import cogs` sets it to PASSIVE when it comes first,
see cogs/__init__.py, but a library cannot count on that). Python threads calling ``nogil`` kernels block in the
kernel, never spin, and hand out chunks dynamically, so a thread that gets less CPU simply
takes fewer chunks. Each chunk writes disjoint outputs, so results do not depend on which
thread ran what.

The pool is process-wide (like numba's own) and sized by ``numba.get_num_threads()``, so
``NUMBA_NUM_THREADS`` / ``numba.set_num_threads`` control it as before.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

import numba

_lock = threading.Lock()
_pool: ThreadPoolExecutor | None = None
_pool_key: tuple[int, int] = (0, 0)  # (pid, size): a forked child needs its own threads


def _executor(n_threads: int) -> ThreadPoolExecutor:
    global _pool, _pool_key
    key = (os.getpid(), n_threads)
    with _lock:
        if _pool is None or _pool_key != key:
            if _pool is not None and _pool_key[0] == key[0]:
                _pool.shutdown(wait=False)
            _pool = ThreadPoolExecutor(max_workers=n_threads, thread_name_prefix="cogs-kernels")
            _pool_key = key
        return _pool


def parallel_for(fn, n: int, *args, min_chunk: int = 1, chunks_per_thread: int = 4) -> None:
    """Call ``fn(lo, hi, *args)`` over [0, n) split into chunks, on up to
    ``numba.get_num_threads()`` threads; serially when that is 1 or ``n`` is small."""
    n_threads = numba.get_num_threads()
    if n <= 0:
        return
    n_chunks = min(n_threads * chunks_per_thread, max(1, n // max(min_chunk, 1)))
    if n_threads <= 1 or n_chunks <= 1:
        fn(0, n, *args)
        return
    bounds = [(n * i) // n_chunks for i in range(n_chunks + 1)]
    pool = _executor(n_threads)
    futures = [pool.submit(fn, bounds[i], bounds[i + 1], *args) for i in range(n_chunks)]
    for f in futures:
        f.result()
