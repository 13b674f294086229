"""The worker threads that share one image's work: the stages split their batches (views of
the pre-filter, jobs of the matching, poses of the refinement) into one chunk per worker.

Threads, not processes: the chunks are OpenCV calls, large array operations and compiled
numba kernels (``kernels``, ``matching``), which release the GIL, and a process pool would
copy every chunk's arrays (../shared/ROS2_ON_PIP.md measured a 2-process pool 2x slower
than one thread). The calling
thread works on the first chunk itself, so ``workers`` threads compute with ``workers - 1``
pool threads.
"""
from __future__ import annotations

import ctypes
import itertools
import os
from concurrent.futures import ThreadPoolExecutor, wait
from typing import Callable, Sequence, TypeVar

import numpy as np

T = TypeVar("T")
R = TypeVar("R")


def cpu_count() -> int:
    """CPU cores this process may run on (its affinity, not the machine's count)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def resolve_workers(workers: int) -> int:
    """``matching.workers`` as a thread count: 0 means one per CPU core."""
    return cpu_count() if workers == 0 else max(1, workers)


#: glibc ``mallopt`` options (malloc.h)
_M_TRIM_THRESHOLD, _M_TOP_PAD, _M_MMAP_THRESHOLD = -1, -2, -3
#: arrays up to this size come from the heap rather than their own mapping (glibc's most)
HEAP_ARRAYS_MB = 32
#: freed heap memory kept for the next image rather than handed back to the kernel
RETAINED_MB = 256


def keep_freed_memory() -> bool:
    """Ask glibc's malloc to keep the memory of an image's freed maps for the next image.

    An image builds up to 15-35 MB of evidence maps (``scoring.EdgeEvidence.bin_jobs``); by
    default glibc maps each such array afresh and unmaps it when freed, so the next image's
    pages fault in one by one, under a lock the worker threads share: 8-10 ms of a clean
    image on two threads (docs/results/latency.md). Process-wide and idempotent; at most
    ``RETAINED_MB`` stays mapped. False where there is no glibc (nothing changed)."""
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    # every option set even where one is refused (a list, not all()'s short circuit)
    accepted = [mallopt(option, value) == 1 for option, value in (
        (_M_MMAP_THRESHOLD, HEAP_ARRAYS_MB << 20), (_M_TRIM_THRESHOLD, RETAINED_MB << 20),
        (_M_TOP_PAD, HEAP_ARRAYS_MB << 20))]
    return all(accepted)


class WorkerPool:
    """``size`` threads (the caller and ``size - 1`` pool threads) running chunks of one image.

    ``map`` may be called from one thread at a time per pool (an Estimator's ``estimate``
    is not re-entrant); estimators in parallel threads each own their pool.
    """

    def __init__(self, workers: int):
        self.size = resolve_workers(workers)
        self._pool = (ThreadPoolExecutor(max_workers=self.size - 1, thread_name_prefix="brepose-worker")
                      if self.size > 1 else None)

    def map(self, function: Callable[[T], R], chunks: Sequence[T]) -> list[R]:
        """``[function(c) for c in chunks]``: the caller and the pool threads each take the
        next chunk not yet taken until none is left (more chunks than threads balance)."""
        if self._pool is None or len(chunks) < 2:
            return [function(c) for c in chunks]
        results: list = [None] * len(chunks)
        taken = itertools.count()  # next() on it is atomic: each chunk is taken once

        def drain() -> None:
            while (i := next(taken)) < len(chunks):
                results[i] = function(chunks[i])

        helpers = [self._pool.submit(drain) for _ in range(min(self.size, len(chunks)) - 1)]
        try:
            drain()
        finally:  # no chunk of this call outlives it, even when one raised
            wait(helpers)
        for helper in helpers:
            helper.result()  # re-raises a chunk's exception
        return results

    def split(self, count: int, minimum: int = 1) -> list[slice]:
        """``range(count)`` as at most ``size`` contiguous slices of near-equal length, each
        at least ``minimum`` long (a chunk shorter than that costs more to hand over than it
        saves). ``count`` 0 gives one empty slice."""
        chunks = max(1, min(self.size, count // max(minimum, 1)))
        bounds = [count * k // chunks for k in range(chunks + 1)]
        return [slice(lo, hi) for lo, hi in zip(bounds[:-1], bounds[1:])]

    def deal(self, count: int) -> list[slice]:
        """``range(count)`` dealt like cards into at most ``size`` strided slices (``count`` 0
        gives one empty slice): where neighbours in a batch cost alike (the refinement's poses
        come the whole image's first, then by score), each thread gets its share of every kind,
        which contiguous chunks (``split``) do not."""
        chunks = max(1, min(self.size, count))
        return [slice(k, count, chunks) for k in range(chunks)]

    def map_dealt(self, function: Callable[[slice], tuple[np.ndarray, ...]], count: int) -> tuple[np.ndarray, ...]:
        """``range(count)`` dealt between the threads (``deal``), ``function`` of each slice
        giving a tuple of float arrays whose first axis runs over the slice; the tuple's arrays
        whole, in the order of ``range(count)``."""
        chunks = self.deal(count)
        parts = self.map(function, chunks)
        out = tuple(np.empty((count,) + np.shape(piece)[1:]) for piece in parts[0])
        for which, part in zip(chunks, parts):
            for whole, piece in zip(out, part):
                whole[which] = piece
        return out

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True)


#: no threads: the stages' default when no pool is given
SERIAL = WorkerPool(1)
