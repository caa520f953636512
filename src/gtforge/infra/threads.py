"""Per-capture work of the calibration stages on threads, results in the captures' order.

What the stages run per capture (PNG decoding, OpenCV's board detectors, SIFT, optical flow) releases the GIL, so two
captures on two threads use two cores; the results are the same as one after the other (each call sees only its own
capture), and the caller consumes them in order, so its reports, warnings and progress read as before. At most
``workers`` captures are in flight (each holds its images): memory stays that of ``workers`` captures.
"""
from __future__ import annotations

from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Callable, Iterable, Iterator, TypeVar

from gtforge.infra.scheduling import cpu_count

T = TypeVar("T")
R = TypeVar("R")


def capture_threads() -> int:
    """Threads for per-capture work: the cores this process may use, at most 4 (OpenCV's own threads share them)."""
    return min(4, cpu_count())


def ordered_map(fn: Callable[[T], R], items: Iterable[T], workers: int | None = None) -> Iterator[R]:
    """``fn(item)`` for every item, on up to ``workers`` threads (default ``capture_threads()``), yielded in the
    items' order. An exception of ``fn`` is raised where its item's result would have been yielded; the items after
    it that were already started finish, the others are never started. With one worker everything runs in the
    calling thread, one item at a time."""
    workers = capture_threads() if workers is None else max(1, int(workers))
    if workers == 1:
        for item in items:
            yield fn(item)
        return
    it = iter(items)
    pending: deque[Future] = deque()
    ex = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="gtforge-capture")
    try:
        for item in it:
            pending.append(ex.submit(fn, item))
            if len(pending) >= workers:
                break
        while pending:
            result = pending.popleft().result()
            for item in it:  # keep ``workers`` in flight
                pending.append(ex.submit(fn, item))
                break
            yield result
    finally:
        for f in pending:
            f.cancel()
        ex.shutdown(wait=True, cancel_futures=True)
