"""Where per-scene work runs: in this process, on a local process pool, or on a Dask cluster.

Every task is an independent call ``fn(*args)`` that writes its own outputs atomically and returns a
small picklable result; the caller's ``on_result`` runs in this process, in completion order.

Local workers are forked from one fork server (``multiprocessing``'s ``forkserver``, where the platform has it; else
each is spawned): it imports the task's module, the main script and ``gtforge.infra.pool_preload`` once, instead of each
worker importing them: their CPU is spent once, not once a worker (benchmarks/RESULTS.md, "Figures from code comments").
``prestart_pool`` starts it before the caller's own set-up, so that its imports overlap that.

Threads x processes: each local worker process gets ``max(1, cores // workers)`` numba threads, so the
pool never runs more compute threads than cores (a parallel loop waits for its thread on a busy core). On a
Dask cluster each task gets ``max(1, cores // threads)``, where ``threads`` counts the task threads of
every worker on that host.

Ctrl-C (SIGINT): workers ignore it; this process cancels queued tasks, terminates the workers at once
(a scene being written stays a hidden temporary folder, never a visible scene) and re-raises
``KeyboardInterrupt`` for the CLI to report and exit with 130. On a Dask cluster the tasks are cancelled
on the scheduler; a task already running on a worker cannot be stopped and finishes there (its scene
lands complete, or not at all).

Dask (``scheduler="tcp://HOST:PORT"``, docs/cluster.md): ``fn`` and its arguments are pickled to the
workers, so every path in them must be absolute and valid on the workers (a shared filesystem). A task
whose worker process dies is run again on another worker by Dask; when
``distributed.scheduler.allowed-failures`` + 1 workers (default 3 + 1, set on the scheduler) have died
running it, Dask gives up with ``KilledWorker`` and the task is handed to ``lost_result`` (build-dataset
lists that scene as failed) instead of stopping the whole run. The cluster holds at most as many of the tasks as
its workers have threads (the next is submitted as one finishes): Dask counts a worker's death against every task
assigned to it, so tasks queued behind a scene that kills its worker would otherwise fail with it.
"""
from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import sys
import threading
from typing import TYPE_CHECKING, Any, Callable, Sequence

import gtforge
from gtforge.errors import InputError
from gtforge.infra.signals import interrupt_deferred

if TYPE_CHECKING:
    from concurrent.futures import ProcessPoolExecutor

    from distributed import Client


def cpu_count() -> int:
    """Cores this process may use (the affinity mask, not the machine's total)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def threads_per_worker(workers: int) -> int:
    return max(1, cpu_count() // max(1, workers))


def oversubscription_warning(asked: int | None, workers: int, cores: int) -> str | None:
    """What to tell a user whose ``--workers`` starts more processes than there are cores (a typo's 100000 would start
    one per task): they only share the cores, and each holds a task's arrays. None when the processes fit."""
    if asked is None or workers <= cores:
        return None
    return (f"--workers {asked}: {workers} processes on {cores} core{'s' if cores != 1 else ''} share them (no faster "
            f"than {cores}, and each holds a scene's arrays in memory); leave --workers out for one per core")


def _init_worker(n_threads: int, heap_bytes: int = 0) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent decides what Ctrl-C does
    # numba makes a named semaphore in a process whose start method has "fork" in its name (forkserver too) when its
    # threads start; a worker stopped on Ctrl-C (terminated) then leaves it to multiprocessing's resource tracker,
    # which warns of "leaked semaphore objects". The lock guards processes forked from this one, and a worker starts
    # none: with "spawn" as its default numba takes a no-op lock instead.
    import multiprocessing

    multiprocessing.set_start_method("spawn", force=True)
    limit_threads(n_threads)
    if reuse_freed_memory() and heap_bytes > 0:
        reserve_heap(heap_bytes)


# glibc's mallopt parameters (malloc.h) and their defaults
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
_GLIBC_DEFAULT_THRESHOLD = 128 * 1024
# madvise's advice that faults a range in, writable, in one call (Linux 5.14)
_MADV_POPULATE_WRITE = 23


def _glibc():
    """The C library, where it is glibc (mallopt, malloc_trim); None elsewhere."""
    import ctypes
    import platform

    if platform.libc_ver()[0] != "glibc":
        return None
    try:
        return ctypes.CDLL("libc.so.6")
    except OSError:
        return None


def reuse_freed_memory() -> bool:
    """Let glibc's malloc keep freed memory for the next array instead of returning it to the kernel.

    A scene allocates and frees dozens of full-image arrays (10-40 MB each). By default glibc maps each anew and
    the kernel zero-fills its pages on first touch: a page fault per page of every array, every scene
    (benchmarks/RESULTS.md, "Figures from code comments"). With these settings arrays up to 32 MB (glibc's upper
    limit) come from the heap and freed memory stays there, so a local pool worker keeps its peak footprint between
    scenes. On a Dask worker see ``_memory_kept_for_task``. Returns whether it applied (glibc only)."""
    libc = _glibc()
    return libc is not None and bool(libc.mallopt(_M_MMAP_THRESHOLD, 32 << 20)) \
        and bool(libc.mallopt(_M_TRIM_THRESHOLD, 1 << 30))


def reserve_heap(n_bytes: int, piece_bytes: int = 16 << 20) -> bool:
    """Fault ``n_bytes`` of glibc's heap in now, with one ``madvise(MADV_POPULATE_WRITE)`` call a piece, and leave
    them to malloc: after ``reuse_freed_memory``, arrays up to 32 MB come from the heap and freed memory stays there,
    so the next allocations use these pages without a page fault each.

    A pool worker's first task otherwise grows the heap a 4 kB page at a time: a full-resolution scene grows it by
    about 174 MB, some 36,000 page faults, 0.1-0.2 CPU s of system time on a VM, where populating the same memory
    takes 0.04 s (benchmarks/RESULTS.md, "Round 9 (issue 39)"). Later tasks reuse that memory either way. Returns
    whether the pages were faulted in (glibc on Linux 5.14 or later; elsewhere nothing happens)."""
    libc = _glibc()
    if libc is None or n_bytes <= 0:
        return False
    import ctypes
    import mmap

    page = mmap.PAGESIZE
    malloc, free, madvise = libc.malloc, libc.free, libc.madvise
    malloc.restype, malloc.argtypes = ctypes.c_void_p, [ctypes.c_size_t]
    free.restype, free.argtypes = None, [ctypes.c_void_p]
    madvise.restype, madvise.argtypes = ctypes.c_int, [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int]
    pieces, ok = [], True
    try:
        for _ in range(-(-n_bytes // piece_bytes)):
            p = malloc(piece_bytes)
            if not p:
                break
            pieces.append(p)
            start = -(-p // page) * page  # the whole pages inside the piece
            if madvise(start, (p + piece_bytes - start) // page * page, _MADV_POPULATE_WRITE) != 0:
                ok = False  # an older kernel (EINVAL): the memory is reserved, not faulted in; no harm
                break
    finally:
        for p in pieces:
            free(p)
    return ok and bool(pieces)


@contextlib.contextmanager
def _memory_kept_for_task():
    """``reuse_freed_memory`` for one task on a Dask worker, whose process is shared with other tasks and whose memory
    Dask watches: the worker's settings are put back afterwards and the freed memory is returned to the kernel
    (``malloc_trim``). Dask starts workers with MALLOC_TRIM_THRESHOLD_ = 64 kB, which returns every freed array at
    once, to be faulted in again by the next allocation (docs/design/performance.md). Another gtforge task running
    at the same time on the same worker may finish with the worker's settings (slower, not wrong)."""
    applied = reuse_freed_memory()
    try:
        yield
    finally:
        if applied:
            libc = _glibc()
            for param, env in ((_M_TRIM_THRESHOLD, "MALLOC_TRIM_THRESHOLD_"),
                               (_M_MMAP_THRESHOLD, "MALLOC_MMAP_THRESHOLD_")):
                try:
                    libc.mallopt(param, int(os.environ.get(env, _GLIBC_DEFAULT_THRESHOLD)))
                except ValueError:
                    libc.mallopt(param, _GLIBC_DEFAULT_THRESHOLD)
            libc.malloc_trim(0)


# the files of ``release_written_pages``'s last two calls, oldest first; the next call drops the first (per process)
_WRITTEN_GROUPS: list[list[str]] = []
_WRITTEN_LOCK = threading.Lock()


def _fadvise_dontneed(path: str) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
    except OSError:
        pass
    finally:
        os.close(fd)


def release_written_pages(paths: Sequence[str | os.PathLike]) -> None:
    """Give the page-cache pages of files this process just wrote back to the kernel once they are on disk,
    as a streaming writer does (``dd oflag=nocache``): a build writes about 56 MB a full-resolution scene,
    45 GB for 808 scenes, which would otherwise fill the page cache and push out everything else in it. (Its large
    files bypass the page cache where the filesystem allows, ``io.unbuffered``: this is for the rest, and for
    filesystems without ``O_DIRECT``.)

    ``POSIX_FADV_DONTNEED`` on ``paths`` starts their writeback (it drops only pages already clean); two calls
    later, two scenes on, the same advice drops their pages, written by then, and the following scenes' writes
    reuse them instead of growing the cache into memory never touched. Pages still dirty then stay cached and
    are written back by the kernel as usual; contents are never affected. On a VM, a page-cache page the guest has
    not touched before costs the host a fault and a reused one does not (benchmarks/RESULTS.md, "Figures from code
    comments"). No-op where ``posix_fadvise`` does not exist."""
    if not hasattr(os, "posix_fadvise"):
        return
    group = [os.fspath(p) for p in paths]
    with _WRITTEN_LOCK:  # (Dask runs several tasks in one process)
        older = _WRITTEN_GROUPS[:-1]  # the group before the last: its writeback started a scene ago
        del _WRITTEN_GROUPS[:-1]
        _WRITTEN_GROUPS.append(group)
    for p in (q for g in older for q in g):  # written back by now: dropped
        _fadvise_dontneed(p)
    for p in group:  # writeback started
        _fadvise_dontneed(p)


def _thread_environment(n_threads: int) -> dict[str, str]:
    """The environment that limits numba and OpenMP (OpenBLAS) to ``n_threads`` threads in a process that has not
    imported them yet."""
    return {"NUMBA_NUM_THREADS": str(n_threads), "OMP_NUM_THREADS": str(n_threads)}


def limit_threads(n_threads: int) -> None:
    """Cap numba's and OpenCV's thread pools in this process (before or after numba was imported).

    Once numba is imported, NUMBA_NUM_THREADS must keep the value numba read: numba re-reads the environment
    before each compilation and refuses a change once its threads run (a Dask worker imports numba with
    gtforge, before its first task). The cap is then ``numba.set_num_threads`` (per calling thread)."""
    import sys

    if "numba" in sys.modules:
        import numba

        numba.set_num_threads(min(n_threads, numba.config.NUMBA_NUM_THREADS))
    else:
        os.environ.update(_thread_environment(n_threads))
    try:
        import cv2

        cv2.setNumThreads(n_threads)
    except ImportError:
        pass


class SchedulerLost(InputError):
    """The Dask scheduler went away (stopped, restarted, its machine or the network lost) while a run's tasks were on
    it. One line, exit code 2 as for an unreachable scheduler. The tasks already finished are complete: the caller
    keeps them (build-dataset writes its manifest, verify its journal) and says so in ``done``."""

    def __init__(self, address: str, cause: str, done: str | None = None):
        self.address, self.cause = address, cause
        super().__init__(None, "--scheduler", f"the Dask scheduler at {address} for the whole run",
                         f"the connection lost ({cause})" + (f" after {done}" if done else ""),
                         "restart the scheduler and its workers (docs/cluster.md) and rerun the same command: it "
                         "resumes with the work not done")


LOST_REASON = "a worker process died while running it (out of memory? killed?); rerun to build it"


def run_tasks(fn: Callable[..., Any], arg_list: Sequence[tuple], on_result: Callable[[Any], None], *,
              workers: int | None = None, scheduler: str | None = None,
              lost_result: Callable[[tuple, str], Any] | None = None, heap_bytes: int = 0) -> None:
    """Run ``fn(*args)`` for every ``args`` in ``arg_list`` and pass each return value to ``on_result``.

    ``workers``: local processes (default: one per core); 1 runs in this process. ``scheduler``: the
    address of a Dask scheduler (``tcp://HOST:PORT``); the cluster's workers run the tasks (``workers``
    must then be None). ``lost_result(args, reason)``: the result to pass on for a task lost with its worker:
    one Dask gave up on because its workers kept dying, or one a local pool process took down when it died
    (without it, ``KilledWorker`` / ``BrokenProcessPool`` propagates). ``heap_bytes``: the memory a task
    allocates, about: each local worker process faults that much of its heap in before its first task
    (``reserve_heap``). An exception raised by ``fn`` or ``on_result`` cancels the remaining tasks and propagates.
    """
    if scheduler and workers is not None:
        raise InputError(None, "--workers", "no local worker count with --scheduler (the cluster's workers "
                         "run the tasks)", str(workers), "drop --workers, or drop --scheduler to run locally")
    if not arg_list:
        return
    if scheduler:
        client = connect_scheduler(scheduler)

        said_by_us = _DropReconnectFailure()
        client_log = logging.getLogger("distributed.client")
        client_log.addFilter(said_by_us)
        try:
            _run_on_cluster(client, fn, arg_list, on_result, lost_result, scheduler)
        finally:
            client.close(timeout=10)
            client_log.removeFilter(said_by_us)
        return
    asked, workers = workers, max(1, min(workers or cpu_count(), len(arg_list)))
    said = oversubscription_warning(asked, workers, cpu_count())
    if said:
        logging.getLogger(__name__).warning(said)
    if workers == 1:
        _stop_unused_fork_server()  # (started for more tasks than there are: its imports would take a core from these)
        for args in arg_list:
            on_result(fn(*args))
        return
    # (imported here: ``gtforge.cli`` imports this module before it starts the fork server, which waits for it)
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
    from concurrent.futures.process import BrokenProcessPool

    n_threads = threads_per_worker(workers)
    _FORK_SERVER["used"] = True  # (when the context is the server's: it is stopped at exit as usual, not killed)
    ex = ProcessPoolExecutor(max_workers=workers, mp_context=_pool_context(fn.__module__, n_threads),
                             initializer=_init_worker, initargs=(n_threads, heap_bytes))
    pending = set()
    futs: dict = {}
    any_broken = False
    try:
        # the first submits start the workers: a Ctrl-C while one starts would leave it unknown to the pool (never
        # stopped) and forked after this process had left, unpickling its queues' freed semaphores (a traceback on the
        # user's terminal); so it takes effect once every submit has returned
        with interrupt_deferred():
            for args in arg_list:
                futs[ex.submit(fn, *args)] = args
        pending = set(futs)
        while pending:
            done, pending = wait(pending, return_when=FIRST_COMPLETED)
            broken = False
            for f in sorted(done, key=lambda g: g.exception() is not None):
                if broken:
                    on_result(lost_result(futs[f], LOST_REASON))
                    continue
                try:
                    res = f.result()
                except BrokenProcessPool:
                    # a worker process died (killed, out of memory): the pool is gone with every task it still
                    # held; report those as failed (the caller lists them) rather than crash the run
                    if lost_result is None:
                        raise
                    broken = True
                    on_result(lost_result(futs[f], LOST_REASON))
                    continue
                on_result(res)
            if broken:
                any_broken = True
                for f in pending:
                    on_result(lost_result(futs[f], LOST_REASON))
                pending = set()
    except BaseException:
        for f in pending or futs:
            f.cancel()
        _terminate(ex)
        raise
    if any_broken:
        # the pool marks its tasks failed before it terminates its other workers: wait until they have exited, so
        # that none still holds a scene's lock when the caller tidies up
        ex.shutdown(wait=True)
        return
    # every task is done: the workers leave while the caller goes on (a worker's exit, the kernel unmapping its heap,
    # takes about 0.05 s); the interpreter waits for them when it exits (concurrent.futures joins its pools)
    ex.shutdown(wait=False)


# the environment variables that hand a warm-up to the fork server (``prestart_pool``, ``pool_preload.warm_up``): the
# warm-up itself, or the file it will be in when the server was started before the command knew it
POOL_WARM_UP_ENV = "GTFORGE_POOL_WARM_UP"
# the task's module, which the server imports after numba's registries (``pool_preload.preload``)
POOL_MODULE_ENV = "GTFORGE_POOL_MODULE"
POOL_WARM_UP_FILE_ENV = "GTFORGE_POOL_WARM_UP_FILE"
# this process's fork server, once started: the numba/OpenMP thread count its environment set, the module it preloaded
# and, when it was started with ``warm_up_later``, the file its warm-up goes to
_FORK_SERVER: dict[str, Any] = {}


def prestart_pool(module: str, workers: int | None = None, scheduler: str | None = None,
                  warm_up: tuple[str, tuple] | None = None, warm_up_later: bool = False) -> None:
    """Start the fork server that ``run_tasks`` will fork local workers from (``workers`` processes, tasks from
    ``module``) now, so that its imports overlap what this process does before it calls ``run_tasks``. Nothing when
    the tasks will run on a Dask cluster or in this process, or where there is no fork server. The server exits with
    this process, used or not.

    ``warm_up``: ``(function name in module, JSON-able arguments)``, called once in the server after its imports
    (``pool_preload.warm_up``): what each worker would otherwise compute for its first task, done once and inherited
    by every worker. Only when each worker gets one thread: the function must not start OpenMP, and with one thread
    gtforge's kernels do not (``lens.undistort``). When the server is already running, the warm-up reaches it only
    if it was started with ``warm_up_later`` (for ``module``, with as many threads): ``gtforge.cli.main`` starts it
    that way before the command's options are parsed, and the command's own call then hands the warm-up over, through
    a file the server reads once its imports are done (0.5 s later; if it is not there yet, each worker warms up
    itself, which gives the same results)."""
    if scheduler or (workers or cpu_count()) < 2:
        return
    n_threads = threads_per_worker(workers or cpu_count())
    warm_up = warm_up if n_threads == 1 else None
    started = _FORK_SERVER.get("n_threads")
    if started is not None:
        path = _FORK_SERVER.get("warm_up_file")
        if warm_up is not None and path and not _FORK_SERVER.get("warm_up_handed") and started == n_threads \
                and _FORK_SERVER.get("module") == module:
            _FORK_SERVER["warm_up_handed"] = True  # once
            _hand_over(path, _warm_up_spec(module, warm_up))
        return
    _pool_context(module, n_threads, warm_up, warm_up_later and n_threads == 1)


def _warm_up_spec(module: str, warm_up: tuple[str, tuple]) -> str:
    """The warm-up as the fork server reads it (``pool_preload.warm_up``): ``["module:function", [arguments]]``."""
    return json.dumps([f"{module}:{warm_up[0]}", list(warm_up[1])])


def _hand_over(path: str, text: str) -> None:
    """Write ``text`` to ``path`` whole (atomically): the fork server may look at any moment."""
    # (imported here: this module is imported before the fork server starts, when nothing may load numpy yet)
    from gtforge.infra.atomic import atomic_write_text

    try:
        atomic_write_text(path, text)
    except OSError:  # (the folder is this process's own; if it is gone, the workers warm up themselves)
        pass


def _pool_context(module: str, n_threads: int, warm_up: tuple[str, tuple] | None = None,
                  warm_up_later: bool = False):
    """The ``multiprocessing`` context local workers start with: this process's fork server, started here once with
    ``__main__``, ``gtforge.infra.pool_preload`` and ``module`` (the first tasks' module; a worker imports any other
    itself)
    preloaded and numba/OpenMP limited to ``n_threads`` threads, as ``_init_worker`` limits them in a spawned worker;
    ``spawn`` where the platform has no fork server, or for another thread count than the server was started with.
    ``warm_up`` / ``warm_up_later``: see ``prestart_pool``."""
    import multiprocessing as mp

    if "forkserver" not in mp.get_all_start_methods():
        return mp.get_context("spawn")
    started = _FORK_SERVER.get("n_threads")
    if started is not None:
        return mp.get_context("forkserver" if started == n_threads else "spawn")
    from multiprocessing import forkserver

    ctx = mp.get_context("forkserver")
    preload = ["__main__", "gtforge.infra.pool_preload", module]
    if "gtforge.cli" in sys.modules:
        # "__main__" does not reach the server when the main module is a script (CPython's forkserver is never handed
        # its path), so each worker runs the script itself before its first task: the gtforge command's imports
        # gtforge.cli, unless the server holds it already
        preload.insert(1, "gtforge.cli")
    ctx.set_forkserver_preload(preload)
    env = {**_thread_environment(n_threads), POOL_MODULE_ENV: module}
    if warm_up is not None:
        env[POOL_WARM_UP_ENV] = _warm_up_spec(module, warm_up)
    elif warm_up_later:
        import atexit
        import shutil
        import tempfile

        folder = tempfile.mkdtemp(prefix="gtforge-pool-")  # this user's only (0700), outside every session and output
        atexit.register(shutil.rmtree, folder, ignore_errors=True)
        env[POOL_WARM_UP_FILE_ENV] = _FORK_SERVER["warm_up_file"] = os.path.join(folder, "warm_up.json")
    saved = {k: os.environ.get(k) for k in env}
    os.environ.update(env)  # the server's environment is this process's when it starts (fork + exec, below)
    try:
        # ignored signals stay ignored across exec: the server starts immune to Ctrl-C (as it is once running), so a
        # Ctrl-C while it imports stops this process with no traceback from the server; workers ignore it too
        old_sigint = signal.signal(signal.SIGINT, signal.SIG_IGN)
    except ValueError:  # not the main thread: no signal handling here
        old_sigint = None
    try:
        forkserver.ensure_running()
    finally:
        if old_sigint is not None:
            signal.signal(signal.SIGINT, old_sigint)
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    _FORK_SERVER.update(n_threads=n_threads, module=module)
    import atexit

    atexit.register(_stop_unused_fork_server)
    return ctx


def _stop_unused_fork_server() -> None:
    """Kill this process's fork server if no pool forked from it: at exit (nothing to build, bad input found after it
    started) and when ``run_tasks`` runs the tasks here (one scene). Left alone, it finished its imports first (0.5 s
    of a core, beside this process's own scene) and kept this process's standard output and error open until then,
    so that a shell pipeline or a caller reading them waited for it. A server that forked workers exits as
    multiprocessing stops it (it is idle by then); a later pool starts a new one."""
    if _FORK_SERVER.get("n_threads") is None or _FORK_SERVER.get("used"):
        return
    from multiprocessing import forkserver

    server = getattr(forkserver, "_forkserver", None)
    pid = getattr(server, "_forkserver_pid", None)
    if pid is None or not hasattr(server, "_stop"):
        return
    with contextlib.suppress(OSError):
        os.kill(pid, signal.SIGKILL)
    with contextlib.suppress(OSError):
        server._stop()  # (reaps it and removes its socket)
    _FORK_SERVER.clear()


def _terminate(ex: ProcessPoolExecutor) -> None:
    """Stop a pool now: queued tasks are dropped and running workers killed (no waiting for them)."""
    procs = list(getattr(ex, "_processes", {}).values())  # the executor has no public kill
    manager = getattr(ex, "_executor_manager_thread", None)
    ex.shutdown(wait=False, cancel_futures=True)
    for p in procs:
        if p.is_alive():
            p.terminate()
    for p in procs:
        p.join(timeout=5)
    # the pool's manager thread sees its workers gone and closes its wake-up pipe; at exit the interpreter writes to
    # that pipe without the pool's lock (CPython 3.11's concurrent.futures._python_exit), and a close between its check
    # and its write printed "OSError: [Errno 9] Bad file descriptor" after the Ctrl-C message: wait for the thread
    if manager is not None and manager is not threading.current_thread():
        manager.join(timeout=5)


# ---- Dask --------------------------------------------------------------------------------------
def check_scheduler_address(address: str) -> None:
    """Fail fast, before anything is written or a client is made, on an address that cannot work: a TCP-like
    address without a port, or a host name that does not resolve (Dask would try for its whole timeout)."""
    try:
        from distributed.comm import parse_address
        from distributed.comm.addressing import parse_host_port
    except ImportError:
        raise InputError(None, "--scheduler", "dask.distributed installed", "it is not installed",
                         "pip install 'gtforge[dask]'") from None
    example = "a Dask scheduler address such as tcp://HOST:8786"
    try:
        scheme, loc = parse_address(address)
    except ValueError as exc:
        raise InputError(None, "--scheduler", example, repr(address), str(exc).splitlines()[0]) from None
    if scheme not in ("tcp", "tls", "ws", "wss"):
        return
    try:
        host, port = parse_host_port(loc)
    except ValueError:
        raise InputError(None, "--scheduler", example, repr(address), "the port is required (dask scheduler "
                         "prints the address to use, e.g. tcp://10.0.0.5:8786)") from None
    import socket

    try:
        socket.getaddrinfo(host, port)
    except (OSError, UnicodeError) as exc:
        raise InputError(None, "--scheduler", example + " whose host resolves", repr(address),
                         f"{host!r} is not a known host ({type(exc).__name__})") from None


def connect_scheduler(address: str, timeout_s: float | None = None) -> Client:
    """A ``distributed.Client`` on the scheduler at ``address`` with at least one worker running this
    gtforge version; one-line ``InputError`` otherwise (dask missing, unreachable, no or foreign workers).

    ``timeout_s`` (connecting, then waiting for a first worker): default Dask's
    ``distributed.comm.timeouts.connect`` (30 s; env ``DASK_DISTRIBUTED__COMM__TIMEOUTS__CONNECT=10s``)."""
    try:
        import dask
        from dask.utils import parse_timedelta
        from distributed import Client
    except ImportError:
        raise InputError(None, "--scheduler", "dask.distributed installed", "it is not installed",
                         "pip install 'gtforge[dask]'") from None

    check_scheduler_address(address)
    if timeout_s is None:
        timeout_s = parse_timedelta(dask.config.get("distributed.comm.timeouts.connect"), "s")
    hint = "start one with 'dask scheduler' and workers with 'dask worker ADDRESS' (docs/cluster.md)"
    try:
        client = Client(address, timeout=timeout_s, set_as_default=False)
    except (OSError, TimeoutError) as exc:
        raise InputError(None, "--scheduler", "a reachable Dask scheduler",
                         f"no connection to {address} within {timeout_s:g} s ({type(exc).__name__})", hint) from None
    except ValueError as exc:
        raise InputError(None, "--scheduler", "a Dask scheduler address such as tcp://HOST:8786", repr(address),
                         str(exc).splitlines()[0]) from None
    try:
        try:
            client.wait_for_workers(1, timeout=timeout_s)
        except TimeoutError:
            raise InputError(None, "--scheduler", f"at least one worker on the scheduler at {address}",
                             f"none within {timeout_s:g} s", hint) from None
        found = client.get_versions(check=False, packages=["gtforge"])["workers"]
        have = {w: v.get("packages", {}).get("gtforge") for w, v in found.items()}
        wrong = {w: v for w, v in have.items() if v != gtforge.__version__}
        if wrong:
            w, v = sorted(wrong.items())[0]
            raise InputError(None, "--scheduler", f"gtforge {gtforge.__version__} on every worker of {address}",
                             f"{'no gtforge' if v is None else 'gtforge ' + v} on {w} ({len(wrong)} of {len(found)} "
                             f"worker(s))", "install this gtforge (with the 'dask' extra) in the workers' Python")
    except BaseException:
        client.close(timeout=10)
        raise
    return client


class _DropReconnectFailure:
    """A logging filter for Dask's client: its "Failed to reconnect to scheduler after N seconds" (and the tracebacks of
    its own shutdown that follow it) went to the user's terminal beside ``SchedulerLost``'s one line, which says the
    same with what was built and what to do."""

    def filter(self, record) -> bool:
        import asyncio

        if str(record.msg).startswith("Failed to reconnect to scheduler"):
            return False
        exc = record.exc_info[1] if record.exc_info else None
        return not isinstance(exc, asyncio.CancelledError)  # (the client's own tasks cancelled as it closes)


def _run_on_cluster(client: Client, fn: Callable[..., Any], arg_list: Sequence[tuple],
                    on_result: Callable[[Any], None], lost_result: Callable[[tuple, str], Any] | None,
                    scheduler_address: str = "") -> None:
    from distributed import KilledWorker, as_completed
    from distributed.comm import get_address_host

    threads_by_host: dict[str, int] = {}
    for worker_address, n in client.nthreads().items():
        host = get_address_host(worker_address)
        threads_by_host[host] = threads_by_host.get(host, 0) + n
    import uuid

    token = uuid.uuid4().hex[:8]  # keys unique to this run (another client may run the same scenes)
    name = getattr(fn, "__name__", "task")
    todo = list(enumerate(arg_list))[::-1]  # popped from the end: submitted in order
    pending: dict = {}
    completed = as_completed(loop=client.loop)

    def submit_more() -> None:
        # only as many tasks on the cluster as its workers have threads (workers that join get work at the next
        # refill): Dask counts a worker's death against every task assigned to it, so a scene that kills its worker
        # must not hold others queued there (they would be listed as failed with it)
        slots = max(1, sum(client.nthreads().values()))
        while todo and len(pending) < slots:
            i, args = todo.pop()
            f = client.submit(_run_on_worker, fn, args, threads_by_host, key=f"gtforge-{name}-{i}-{token}",
                              pure=False)
            pending[f] = args
            completed.add(f)

    try:
        submit_more()
        for f in completed:
            args = pending.pop(f)
            submit_more()
            if f.status == "error" and lost_result is not None:
                exc = f.exception()
                if isinstance(exc, KilledWorker):
                    last = getattr(exc.last_worker, "address", exc.last_worker)
                    on_result(lost_result(args, f"the Dask worker running it died, {exc.allowed_failures + 1} "
                                                f"time(s) on different workers (KilledWorker; last {last}): out of "
                                                f"memory? see the workers' logs"))
                    continue
            elif f.status == "cancelled" and lost_result is not None:
                if client.status != "running":  # the client gave up on the scheduler: every other task goes too
                    raise SchedulerLost(scheduler_address or str(client.scheduler.address), f"client {client.status}")
                on_result(lost_result(args, "cancelled on the Dask cluster (scheduler restarted or connection lost)"))
                continue
            result = f.result()  # re-raises the task's own exception, with its remote traceback
            f.release()
            on_result(result)
    except BaseException as exc:
        lost = None
        if not isinstance(exc, (KeyboardInterrupt, SchedulerLost)) and (
                _is_comm_error(exc) or client.status != "running"):
            # (the scheduler gone: Dask's CommClosedError from the next call, or a cancelled future once the client
            # stopped reconnecting; a traceback of Dask's internals said nothing the user can act on)
            lost = SchedulerLost(scheduler_address or str(client.scheduler.address), type(exc).__name__)
        if pending:
            try:
                client.cancel(list(pending), force=True)
            except OSError:  # the scheduler is gone too (CommClosedError, timeout): nothing left to cancel
                pass
        if lost is not None:
            raise lost from None
        raise


def _is_comm_error(exc: BaseException) -> bool:
    """A failure to talk to the scheduler (not a task's own error, which Dask re-raises as the task raised it)."""
    from distributed.comm import CommClosedError

    return isinstance(exc, (CommClosedError, TimeoutError)) or (
        isinstance(exc, OSError) and type(exc).__module__.startswith(("distributed", "tornado")))


def _run_on_worker(fn: Callable[..., Any], args: tuple, threads_by_host: dict[str, int]) -> Any:
    """On a Dask worker: share the host's cores among the task threads of every worker on it, then run."""
    from distributed import get_worker
    from distributed.comm import get_address_host

    worker = get_worker()
    n_tasks = threads_by_host.get(get_address_host(worker.address), worker.state.nthreads)
    limit_threads(max(1, cpu_count() // n_tasks))
    with _memory_kept_for_task():
        return fn(*args)
