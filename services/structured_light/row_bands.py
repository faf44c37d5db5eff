"""Images processed in bands of rows on a small thread pool.

numpy and OpenCV release the GIL on large arrays, so bands run in parallel; and a band's temporaries
(about 100 kB each) stay in the CPU cache and are reused by the allocator, where whole-image temporaries
of several MB are each fetched fresh from the kernel, page by page.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from functools import lru_cache
from typing import TypeVar

BAND_PIXELS = 1 << 16

_Result = TypeVar("_Result")


_thread_limit: int | None = None


def thread_count() -> int:
    """Threads of the pool: one per CPU this process may run on, at most 8 (or :func:`limit_threads`)."""
    cpus = max(1, min(8, len(os.sched_getaffinity(0))))
    return cpus if _thread_limit is None else min(cpus, _thread_limit)


def limit_threads(count: int) -> None:
    """Use at most ``count`` threads from now on (a worker process sharing the cores with other replicas)."""
    global _thread_limit
    if count < 1:
        raise ValueError(f"The thread limit must be at least 1; got {count}.")
    _thread_limit = count
    _pool.cache_clear()


@lru_cache(maxsize=1)
def _pool() -> ThreadPoolExecutor:
    return ThreadPoolExecutor(max_workers=thread_count(), thread_name_prefix="row-band")


os.register_at_fork(after_in_child=_pool.cache_clear)  # a forked child has none of the parent's threads


def row_bands(height: int, width: int, band_pixels: int = BAND_PIXELS) -> list[slice]:
    """Consecutive slices of rows of an image, each of about ``band_pixels`` pixels (at least one row)."""
    rows = max(1, band_pixels // max(1, width))
    return [slice(first, min(height, first + rows)) for first in range(0, height, rows)]


def map_row_bands(function: Callable[[slice], _Result], height: int, width: int,
                  band_pixels: int = BAND_PIXELS) -> list[_Result]:
    """``function(rows)`` for each of :func:`row_bands`, on the process's pool of one thread per CPU;
    the results in band order. ``function`` must only write rows of its own band."""
    return map_bands(function, row_bands(height, width, band_pixels))


def map_bands(function: Callable[[slice], _Result], bands: list[slice]) -> list[_Result]:
    """``function(rows)`` for each band of rows, on the pool; the results in band order."""
    if len(bands) == 1 or thread_count() == 1:
        return [function(rows) for rows in bands]
    return list(_pool().map(function, bands))
