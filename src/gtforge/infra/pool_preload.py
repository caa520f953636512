"""What the local pool's fork server (``gtforge.infra.scheduling``) loads before it forks the first worker, so that \
every
worker starts with it: numba's typing and lowering registries, which numba loads on a process's first compiled call
(with SciPy's BLAS, which numba checks for then): otherwise part of each worker's start, done once here through one tiny
function from numba's cache. The task's own module is preloaded by name beside this one."""
from __future__ import annotations

import numba


@numba.njit(cache=True)
def _first_compiled_call(x):
    return x + 1


_first_compiled_call(1)
