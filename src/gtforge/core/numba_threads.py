"""How many numba threads the kernels may use in this process: numba's own count, or one in a child forked from a
process whose numba had loaded the OpenMP threading layer. GNU OpenMP is not fork-safe, and numba stops such a child
(SIGTERM, "Terminating: fork() called from a process already using GNU OpenMP") at its first parallel loop. A
researcher's own ``multiprocessing`` pool, which forks by default on Linux, would lose every worker that reprojects
after the parent did. Such a child runs the one-thread kernels instead, which give the same values."""
from __future__ import annotations

import os

import numba

_forked_after_openmp = False


def _openmp_loaded() -> bool:
    try:
        return numba.threading_layer() == "omp"
    except ValueError:  # no threading layer loaded yet: no parallel loop has run in this process
        return False


def _after_fork_in_child() -> None:
    global _forked_after_openmp
    _forked_after_openmp = _forked_after_openmp or _openmp_loaded()


os.register_at_fork(after_in_child=_after_fork_in_child)


def parallel_allowed() -> bool:
    """Whether this process may run numba's parallel loops: not in a child forked after OpenMP was loaded."""
    return not _forked_after_openmp


def usable_threads() -> int:
    """numba's thread count for this process's kernels (``numba.get_num_threads()``), 1 where ``parallel_allowed`` is
    not."""
    return numba.get_num_threads() if parallel_allowed() else 1
