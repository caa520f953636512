"""The ``gtforge`` command's entry point (``main``); the commands themselves are in ``gtforge.cli.commands``.

Kept small on purpose: a command that runs scenes on the local pool (build-dataset, verify) starts the pool's fork
server here, before Typer, Rich and the commands are imported (0.1 s), so that the server's imports (numba, the stage,
about 0.6 s) start as early as they can; and each pool worker, which runs the console script again when it starts,
imports only this module.
"""
from __future__ import annotations

import atexit
import gc
import signal
import sys

from gtforge.errors import InputError, Interrupted

# the commands whose scenes run on the local pool, and the module of their tasks (the fork server preloads it)
POOL_COMMANDS = {"build-dataset": "gtforge.build_dataset", "verify": "gtforge.verify"}


def _raise_interrupted(signum, frame) -> None:
    # a stage that catches it says what is complete; this text is what the user sees otherwise
    raise Interrupted("interrupted: every file already written is complete (gtforge writes each one whole); rerun "
                      "the same command to finish")


def pool_module_of(argv: list[str]) -> str | None:
    """The task module of the local pool the command line ``argv`` (``sys.argv``) will run scenes on, judged before
    its options are parsed: only a pool command with the default workers (no ``--workers``, ``--scheduler`` or
    ``--help``); None otherwise (the command then starts its pool, if any, once its options are parsed)."""
    words = [a for a in argv[1:] if not a.startswith("-")]
    if not words or words[0] not in POOL_COMMANDS:
        return None
    if any(a in ("--help", "-h") or a.startswith(("--workers", "--scheduler")) for a in argv[1:]):
        return None
    return POOL_COMMANDS[words[0]]


def main() -> None:
    # At exit the interpreter's teardown would garbage-collect every object numba, LLVM and pydantic made: 0.1-0.2 s
    # of every command that loaded them (benchmarks/RESULTS.md, "The exit"). Frozen, they are left to the OS; by then
    # every file gtforge writes is complete and closed (the atexit handlers registered later, multiprocessing's
    # included, run first).
    atexit.register(gc.freeze)
    # Ctrl-C raises Interrupted (not KeyboardInterrupt, which Click turns into "Aborted!" and exit 1):
    # stages clean up, say what is complete, and the command exits with 130 like any interrupted program.
    signal.signal(signal.SIGINT, _raise_interrupted)
    try:
        module = pool_module_of(sys.argv)
        if module is not None:
            from gtforge.infra.scheduling import prestart_pool

            prestart_pool(module, warm_up_later=True)  # the command hands the server its warm-up once parsed
        from gtforge.cli.commands import app

        app(standalone_mode=True)
    except InputError as exc:
        from rich.text import Text

        from gtforge.cli.commands import console

        console.print(Text.assemble(("error: ", "bold red"), str(exc)), highlight=False, soft_wrap=True)
        sys.exit(2)
    except Interrupted as exc:
        print(str(exc), file=sys.stderr)
        sys.exit(130)


if __name__ == "__main__":
    main()
