"""What the local pool's fork server (``gtforge.infra.scheduling``) loads before it forks the first worker, so that \
every
worker starts with it: numba's typing and lowering registries, which numba loads on a process's first compiled call
(with SciPy's BLAS, which numba checks for then): otherwise part of each worker's start, done once here through one tiny
function from numba's cache. The task's own module is preloaded by name beside this one.

Then the caller's warm-up, where ``prestart_pool`` was given one (``POOL_WARM_UP_ENV``: ``"module:function"`` and its
arguments, as JSON): what every worker would otherwise compute for its first task (build-dataset: the calibration,
the opened session, the depth camera's ray grid). A warm-up that fails leaves the workers to do it themselves (and to
report the error where there is one): the server must start whatever the inputs hold. It must not start threads that
do not survive a fork (GNU OpenMP: numba's parallel kernels; ``lens.undistort`` runs its serial compilation here)."""
from __future__ import annotations

import importlib
import json
import logging
import os
import warnings

import numba

from gtforge.infra.scheduling import POOL_WARM_UP_ENV


@numba.njit(cache=True)
def _first_compiled_call(x):
    return x + 1


def warm_up() -> bool:
    """Run the warm-up ``POOL_WARM_UP_ENV`` names, if any. Returns whether one ran and succeeded."""
    spec = os.environ.pop(POOL_WARM_UP_ENV, None)  # (popped: the workers, forked from here, do not see it)
    if not spec:
        return False
    logging.disable(logging.WARNING)  # the caller reports what the inputs hold, once (not the server too)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            target, args = json.loads(spec)
            module, name = target.split(":")
            getattr(importlib.import_module(module), name)(*args)
    except Exception:  # noqa: BLE001 (see the module's docstring: the workers do it, and report it, themselves)
        return False
    finally:
        logging.disable(logging.NOTSET)
    return True


_first_compiled_call(1)
warm_up()
