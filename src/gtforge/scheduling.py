"""Where per-scene work runs: in this process, on a local process pool, or (later) on a Dask cluster.

Every task is an independent call ``fn(*args)`` that writes its own outputs atomically and returns a
small picklable result; the caller's ``on_result`` runs in this process, in completion order.

Threads x processes: each local worker process gets ``max(1, cores // workers)`` numba threads, so the
pool never runs more compute threads than cores (a busy core slows numba's parallel loops 2-3x).

Ctrl-C (SIGINT): workers ignore it; this process cancels queued tasks, terminates the workers at once
(a scene being written stays a hidden temporary folder, never a visible scene) and re-raises
``KeyboardInterrupt`` for the CLI to report and exit with 130.
"""
from __future__ import annotations

import os
import signal
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from typing import Any, Callable, Sequence


def cpu_count() -> int:
    """Cores this process may use (the affinity mask, not the machine's total)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def threads_per_worker(workers: int) -> int:
    return max(1, cpu_count() // max(1, workers))


def _init_worker(n_threads: int) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent decides what Ctrl-C does
    limit_threads(n_threads)


def limit_threads(n_threads: int) -> None:
    """Cap numba's and OpenCV's thread pools in this process (before or after numba was imported)."""
    import sys

    os.environ["NUMBA_NUM_THREADS"] = str(n_threads)
    os.environ["OMP_NUM_THREADS"] = str(n_threads)
    if "numba" in sys.modules:
        import numba

        numba.set_num_threads(min(n_threads, numba.config.NUMBA_NUM_THREADS))
    try:
        import cv2

        cv2.setNumThreads(n_threads)
    except ImportError:
        pass


def run_tasks(fn: Callable[..., Any], arg_list: Sequence[tuple], on_result: Callable[[Any], None], *,
              workers: int | None = None) -> None:
    """Run ``fn(*args)`` for every ``args`` in ``arg_list`` and pass each return value to ``on_result``.

    ``workers``: local processes (default: one per core); 1 runs in this process. An exception raised
    by ``on_result`` cancels the remaining tasks and propagates.
    """
    if not arg_list:
        return
    workers = max(1, min(workers or cpu_count(), len(arg_list)))
    if workers == 1:
        for args in arg_list:
            on_result(fn(*args))
        return
    import multiprocessing as mp

    ex = ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn"), initializer=_init_worker,
                             initargs=(threads_per_worker(workers),))
    pending = set()
    try:
        pending = {ex.submit(fn, *args) for args in arg_list}
        while pending:
            done, pending = wait(pending, return_when=FIRST_COMPLETED)
            for f in done:
                on_result(f.result())
    except BaseException:
        for f in pending:
            f.cancel()
        _terminate(ex)
        raise
    ex.shutdown(wait=True)


def _terminate(ex: ProcessPoolExecutor) -> None:
    """Stop a pool now: queued tasks are dropped and running workers killed (no waiting for them)."""
    procs = list(getattr(ex, "_processes", {}).values())  # the executor has no public kill
    ex.shutdown(wait=False, cancel_futures=True)
    for p in procs:
        if p.is_alive():
            p.terminate()
    for p in procs:
        p.join(timeout=5)
