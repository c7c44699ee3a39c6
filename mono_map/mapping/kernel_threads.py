"""The compiled kernels' second thread and their per-thread buffers (:mod:`mono_map.mapping.raycast_c`,
``distribution_c``, ``mirror_c``).

A large kernel call runs in two halves, one on the calling thread and one on a helper thread shared by the
whole process (ctypes releases the GIL). The buffers reused across frames (the visited bitmap over a
frame's box of keys, the float32 update accumulators) belong to the calling thread, so maps built in
several threads at once never share one.
"""

from __future__ import annotations

import os
import threading

import numpy as np

PARALLEL_MIN_RAYS = 4096   # smaller calls run on the calling thread alone
_POOL = None
_POOL_LOCK = threading.Lock()
_BUFFERS = threading.local()   # per calling thread: maps built in different threads never share a buffer


def threads() -> int:
    """Threads for the kernel: ``$MONO_MAP_RAY_THREADS`` (1 or 2), else 2 when the process may use 2 CPUs."""
    env = os.environ.get("MONO_MAP_RAY_THREADS")
    if env:
        return max(1, min(2, int(env)))
    try:
        return min(2, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return min(2, os.cpu_count() or 1)


def helper_pool():
    """The process's one helper thread for the second halves of kernel calls."""
    global _POOL
    with _POOL_LOCK:   # builds in several threads share the one helper thread (each waits for its own half)
        if _POOL is None:
            from concurrent.futures import ThreadPoolExecutor

            _POOL = ThreadPoolExecutor(max_workers=1, thread_name_prefix="mm-dda")
    return _POOL


def use_two_threads(n: int) -> bool:
    """Whether a kernel call over ``n`` rays (rows, cells) runs in two halves: n ≥ PARALLEL_MIN_RAYS and
    :func:`threads` is 2."""
    return n >= PARALLEL_MIN_RAYS and threads() >= 2


def settle(future) -> None:
    """Wait until the other thread's kernel call is over (its result or error is not wanted any more)."""
    import concurrent.futures

    concurrent.futures.wait([future])


def on_two_threads(rows, n: int) -> None:
    """rows(a, b) over 0..n: in two halves on two threads for large n (ctypes releases the GIL), else at once."""
    if not use_two_threads(n):
        rows(0, n)
        return
    half = n // 2
    future = helper_pool().submit(rows, half, n)
    rows(0, half)
    future.result()


def _buffers():
    """This thread's per-frame buffers: the visited bitmap ``mark`` and the two accumulators ``acc``."""
    b = _BUFFERS
    if not hasattr(b, "mark"):
        b.mark = np.zeros(0, dtype=np.uint8)
        b.acc = [np.zeros(0, dtype=np.float32), np.zeros(0, dtype=np.float32)]
    return b


def zeroed_accumulator(slot: int, size: int) -> np.ndarray:
    """Zeroed float32 buffer ``slot`` (one per kernel thread) of at least ``size`` cells, reused across
    frames (allocating and faulting in hundreds of MB per frame would cost more than the rays); callers zero
    what they touched."""
    acc = _buffers().acc
    if len(acc[slot]) < size:
        acc[slot] = np.zeros(max(size, int(len(acc[slot]) * 1.25)), dtype=np.float32)
    return acc[slot]


def release_buffers() -> None:
    """Free this thread's per-frame buffers kept between frames (visited bitmap, accumulators): at the end
    of a build."""
    vars(_BUFFERS).clear()   # the next _buffers() call starts this thread's buffers empty


def zeroed_bitmap(size: int) -> np.ndarray:
    """A zeroed uint8 bitmap of ``size`` cells, this thread's, reused across frames (as the accumulators);
    the caller zeroes the cells it marked before the next frame."""
    b = _buffers()
    if len(b.mark) < size:
        b.mark = np.zeros(max(size, int(len(b.mark) * 1.25)), dtype=np.uint8)
    return b.mark[:size]
