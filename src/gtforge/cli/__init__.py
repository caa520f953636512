"""The ``gtforge`` command's entry point (``main``); the commands themselves are in ``gtforge.cli.commands``.

Kept small on purpose: a command that runs scenes on the local pool (build-dataset, verify) starts the pool's fork
server here, before Typer, Rich and the commands are imported (0.1 s), so that the server's imports (numba, the stage,
about 0.6 s) start as early as they can; and each pool worker, which runs the console script again when it starts,
imports only this module.
"""
from __future__ import annotations

import atexit
import errno
import gc
import importlib
import os
import signal
import sys

from gtforge.errors import INTERRUPTED, InputError, Interrupted

# OpenBLAS's idle threads wait for work by spinning before they sleep: 2**28 cycles by default (about 0.1 s), set
# when the library loads. numpy and OpenCV each load their own OpenBLAS, so importing them burnt 0.2 CPU s on two
# spinning threads, beside the pool's fork server starting on the other core (benchmarks/RESULTS.md, "Round 10 (issue
# 39)"). 2**20 cycles (about 0.4 ms) still bridges the gap between one BLAS call and the next in a loop (2**4 made a
# threaded 128 x 128 product 45 % slower, the threads woken every call). The same threads, the same results.
OPENBLAS_SPIN_ENV = {"OPENBLAS_THREAD_TIMEOUT": "20"}

# the commands whose scenes run on the local pool, and the module of their tasks (the fork server preloads it)
POOL_COMMANDS = {"build-dataset": "gtforge.build_dataset", "verify": "gtforge.verify"}


def _raise_interrupted(signum, frame) -> None:
    # a stage that catches it says what is complete; this text is what the user sees otherwise
    raise Interrupted(INTERRUPTED)


def pool_of(argv: list[str]) -> tuple[str, int | None] | None:
    """The local pool the command line ``argv`` (``sys.argv``) will run scenes on, judged before its options are
    parsed: ``(task module, workers)`` for a pool command, ``workers`` None for the default (every core) or the count
    ``--workers N`` / ``--workers=N`` gives; None for any other command line, and where ``--scheduler`` or ``--help``
    is given or ``--workers`` is not a positive whole number (the command then starts its pool, if any, once its
    options are parsed, and reports a bad value itself)."""
    args = argv[1:]
    workers = None
    for i, a in enumerate(args):
        if a in ("--help", "-h") or a.startswith("--scheduler"):
            return None
        if a.startswith("--workers"):
            value = a.partition("=")[2] if "=" in a else (args[i + 1] if i + 1 < len(args) else "")
            if not value.isdigit() or int(value) < 1:
                return None
            workers = int(value)
    words = [a for i, a in enumerate(args) if not a.startswith("-") and (i == 0 or args[i - 1] != "--workers")]
    if not words or words[0] not in POOL_COMMANDS:
        return None
    return POOL_COMMANDS[words[0]], workers


def _click_exceptions():
    """The exceptions module of the Click that Typer runs on: its own copy since Typer 0.2x, else Click's."""
    try:
        from typer._click import exceptions
    except ImportError:
        from click import exceptions
    return exceptions


def _print_error(message: str) -> None:
    """``error: MESSAGE``, one line on stderr (the shape of every error the command reports itself)."""
    from rich.text import Text

    from gtforge.cli.commands import console

    console.print(Text.assemble(("error: ", "bold red"), message), highlight=False, soft_wrap=True)


def _usage_error(exc) -> None:
    """Print Click's usage error ``exc`` (an unknown option, a value out of range, a missing argument) as one line
    naming the command, and exit with its code (2)."""
    names, ctx = [], exc.ctx
    while ctx is not None and ctx.parent is not None:  # the subcommand's name (the root's is how Python was started)
        names.insert(0, ctx.info_name)
        ctx = ctx.parent
    command = " ".join(["gtforge", *names])
    message = " ".join(exc.format_message().split())
    _print_error(f"{command}: {message} (hint: {command} --help)")
    sys.exit(exc.exit_code)


class _ClosedPipeTolerant:
    """``sys.stdout`` / ``sys.stderr`` for a command whose reader may go away (``gtforge ... | head``): once the pipe is
    closed, what the command still prints goes to /dev/null and its work goes on to its end, with its own exit code.
    Without it the next print raised BrokenPipeError and Click ended the command there with exit code 1 and no word:
    a build stopped between its last scene and its manifest."""

    def __init__(self, stream):
        self._stream = stream

    def write(self, text):
        try:
            return self._stream.write(text)
        except BrokenPipeError:
            self._to_devnull()
            return len(text)

    def writelines(self, lines):
        for line in lines:
            self.write(line)

    def flush(self):
        try:
            self._stream.flush()
        except BrokenPipeError:
            self._to_devnull()

    def _to_devnull(self):
        fd = os.open(os.devnull, os.O_WRONLY)
        try:
            os.dup2(fd, self._stream.fileno())
        finally:
            os.close(fd)
        try:  # what the stream still holds goes to /dev/null, so that the interpreter's flush at exit finds nothing
            self._stream.flush()
        except OSError:
            pass

    def __getattr__(self, name):
        return getattr(self._stream, name)


def main() -> None:
    # At exit the interpreter's teardown would garbage-collect every object numba, LLVM and pydantic made: 0.1-0.2 s
    # of every command that loaded them (benchmarks/RESULTS.md, "The exit"). Frozen, they are left to the OS; by then
    # every file gtforge writes is complete and closed (the atexit handlers registered later, multiprocessing's
    # included, run first).
    atexit.register(gc.freeze)
    for name, value in OPENBLAS_SPIN_ENV.items():  # before numpy is imported; a user's own setting stands
        os.environ.setdefault(name, value)
    # Ctrl-C raises Interrupted (not KeyboardInterrupt, which Click turns into "Aborted!" and exit 1):
    # stages clean up, say what is complete, and the command exits with 130 like any interrupted program. A Ctrl-C
    # the command inherited as ignored (started with `&` by a script, or under a launcher that ignores it) stays
    # ignored, as Python itself keeps it: the terminal's Ctrl-C is then meant for the script, not this run.
    if signal.getsignal(signal.SIGINT) != signal.SIG_IGN:
        signal.signal(signal.SIGINT, _raise_interrupted)
    streams = sys.stdout, sys.stderr
    sys.stdout, sys.stderr = (s if s is None or isinstance(s, _ClosedPipeTolerant) else _ClosedPipeTolerant(s)
                              for s in streams)
    try:
        pool = pool_of(sys.argv)
        if pool is not None:
            from gtforge.infra.scheduling import prestart_pool

            # the command hands the server its warm-up once its options are parsed
            prestart_pool(pool[0], workers=pool[1], warm_up_later=True)
        # the imports make some 100,000 objects and next to no garbage: no collection walks them while they load (0.035
        # CPU s of a build's 0.39 s of imports) nor after (frozen), as in the pool's server (infra.pool_preload)
        gc.disable()
        try:
            import typer

            from gtforge.cli.commands import app

            if pool is not None:
                importlib.import_module(pool[0])  # (what the command imports first; the server preloads it too)
        finally:
            gc.freeze()
            gc.enable()

        click_errors = _click_exceptions()
        no_args = getattr(click_errors, "NoArgsIsHelpError", ())
        try:
            code = app(standalone_mode=False)
        except no_args as exc:  # `gtforge` alone: Typer has printed the help
            sys.exit(exc.exit_code)
        except click_errors.UsageError as exc:
            # a bad option or argument gets one line, as bad input does (Typer's own is a boxed usage block)
            _usage_error(exc)
        except click_errors.ClickException as exc:
            exc.show()
            sys.exit(exc.exit_code)
        except typer.Abort:
            print("Aborted!", file=sys.stderr)
            sys.exit(1)
        sys.exit(code if isinstance(code, int) else 0)
    except InputError as exc:
        _print_error(str(exc))
        sys.exit(2)
    except Interrupted as exc:
        print(str(exc), file=sys.stderr)
        sys.exit(130)
    except OSError as exc:
        if exc.errno not in _PLACE_ERRNOS or os.environ.get("GTFORGE_DEBUG"):
            raise  # (a bug, or something no user input explains: its traceback is wanted)
        name = _destination(exc.filename or exc.filename2)
        _print_error(f"{name + ': ' if name else ''}could not be written or read ({exc.strerror}) (hint: check the "
                     "path, its permissions and the free space; every file already written is complete; "
                     "GTFORGE_DEBUG=1 shows where)")
        sys.exit(2)
    finally:
        for wrapped in (sys.stdout, sys.stderr):
            if isinstance(wrapped, _ClosedPipeTolerant):
                wrapped.flush()
        sys.stdout, sys.stderr = streams


# what a place refuses once a stage runs, whatever gtforge does (most is checked before it starts): read-only, not
# permitted, full. (A file where a folder goes, or the reverse, is checked before; at a write it would be a bug.)
_PLACE_ERRNOS = {errno.EROFS, errno.EACCES, errno.EPERM, errno.ENOSPC, errno.EDQUOT}


def _destination(name) -> str:
    """The file a user knows for ``name``: an atomic write's temporary ``.STEM.XXXX.tmp.SUFFIX`` is ``STEM.SUFFIX``
    (``gtforge.infra.atomic``)."""
    if not name:
        return ""
    import re

    p = str(name)
    m = re.match(r"^(.*/)?\.(.+)\.[^./]+\.tmp(\.[^./]+)?$", p)
    return f"{m.group(1) or ''}{m.group(2)}{m.group(3) or ''}" if m else p


if __name__ == "__main__":
    main()
