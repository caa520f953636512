"""What the local pool's fork server (``gtforge.infra.scheduling``) loads before it forks the first worker, so that
every worker starts with it: numba's typing and lowering registries, which numba loads on a process's first compiled
call (``load_registries``: without the SciPy BLAS check numba runs then): otherwise part of each worker's start, done
once here through one tiny function from numba's cache; then the task's own module (``POOL_MODULE_ENV``).

Then the caller's warm-up, where ``prestart_pool`` was given one (``POOL_WARM_UP_ENV``: ``"module:function"`` and its
arguments, as JSON; or ``POOL_WARM_UP_FILE_ENV``: the file the command writes them to once it has parsed its options,
when it started the server before that): what every worker would otherwise compute for its first task (build-dataset:
the calibration, the opened session, the depth camera's ray grid). A warm-up that fails leaves the workers to do it
themselves (and to report the error where there is one): the server must start whatever the inputs hold. It must not
start threads that do not survive a fork (GNU OpenMP: numba's parallel kernels, ``lens.undistort`` runs its serial
compilation here; OpenCV's pool: OpenCV runs serially here)."""
from __future__ import annotations

import gc

# The server's imports (numba, its registries, the task's module) make some 150,000 objects and next to no garbage,
# and the collector's passes over them while they load took 0.08 of the chain's 0.49 CPU s, on the critical path to
# the first scene (benchmarks/RESULTS.md, "Round 17 (issue 39)"). It is off until they and the warm-up are done; then
# they are frozen (no collection in a worker walks them) and it is on again for the workers (``preload``).
gc.disable()

import atexit  # noqa: E402
import importlib  # noqa: E402
import json  # noqa: E402
import logging  # noqa: E402
import os  # noqa: E402
import sys  # noqa: E402
import warnings  # noqa: E402

import numba  # noqa: E402

from gtforge.infra.scheduling import POOL_MODULE_ENV, POOL_WARM_UP_ENV, POOL_WARM_UP_FILE_ENV  # noqa: E402


@numba.njit(cache=True)
def _first_compiled_call(x):
    return x + 1


def warm_up() -> bool:
    """Run the warm-up ``POOL_WARM_UP_ENV`` names, if any. Returns whether one ran and succeeded."""
    spec = os.environ.pop(POOL_WARM_UP_ENV, None)  # (popped: the workers, forked from here, do not see them)
    path = os.environ.pop(POOL_WARM_UP_FILE_ENV, None)
    if not spec and path:
        try:
            with open(path, encoding="utf-8") as f:
                spec = f.read()
        except OSError:  # not written (yet): no warm-up, or the command is slower than these imports
            return False
    if not spec:
        return False
    # OpenCV's thread pool does not survive a fork either: a worker forked after a warm-up that started it (a raw
    # ZED session's rectification maps) hung for good in its first cv2.setNumThreads (_init_worker). OpenCV runs
    # serially here, starting no thread; each worker sets its own count.
    try:
        import cv2

        cv2.setNumThreads(0)
    except ImportError:
        pass
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


def load_registries() -> None:
    """Load numba's registries (its first compiled call) without SciPy's linear algebra.

    numba's ``np.arraymath`` asks, when imported, whether BLAS is there by importing ``scipy.linalg.cython_blas``,
    which imports all of ``scipy.linalg``: 0.27 CPU s of the server's start (benchmarks/RESULTS.md, "Round 4 (issue
    39)"), for an answer known here (SciPy is one of gtforge's dependencies). So the import fails on purpose while the
    registries load, and the answer is set as the check would have set it: numba then behaves as with the check
    (``np.dot`` and friends import SciPy's BLAS when compiled; ``np.convolve`` / ``np.correlate`` take the BLAS path),
    and no gtforge kernel loaded from the cache needs ``scipy.linalg`` (the workers import it only where a stage's
    Python code does)."""
    name = "scipy.linalg.cython_blas"
    if name in sys.modules or "numba.np.arraymath" in sys.modules:
        _first_compiled_call(1)
        return
    sys.modules[name] = None  # an import of it raises ImportError
    try:
        _first_compiled_call(1)
    finally:
        del sys.modules[name]
    import numba.np.arraymath

    numba.np.arraymath._HAVE_BLAS = True


def preload() -> None:
    """What the server does once, before its first fork: numba's registries, the task's module
    (``POOL_MODULE_ENV``), the warm-up; then every object so far frozen and the collector on again."""
    try:
        load_registries()
        module = os.environ.pop(POOL_MODULE_ENV, None)
        if module:
            try:
                importlib.import_module(module)
            except ImportError:  # (as the server's own preload does: the workers import it, and report it, themselves)
                pass
        warm_up()
    finally:
        gc.freeze()
        gc.enable()


preload()
# the server's own exit (its workers leave with os._exit): no teardown collection over numba's objects (0.15-0.2 s),
# as in the command (gtforge.cli.main)
atexit.register(gc.freeze)
