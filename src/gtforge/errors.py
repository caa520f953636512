"""Error types. See docs/conventions.md ("Errors")."""
from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # (gtforge.cli imports this module before it starts the fork server: nothing more than it needs)
    from pathlib import Path


class InputError(ValueError):
    """Bad user input: one line naming the file and field, expected vs actual, and a hint.

    The CLI prints ``str(err)`` and exits with code 2 without a traceback.
    """

    def __init__(self, file: str | Path | None, field: str | None, expected: str, actual: str,
                 hint: str | None = None):
        self.file = str(file) if file is not None else None
        self.field = field
        self.expected = expected
        self.actual = actual
        self.hint = hint
        where = self.file or ""
        if field:
            where = f"{where} [{field}]" if where else field
        msg = f"{where}: expected {expected}, got {actual}" if where else f"expected {expected}, got {actual}"
        if hint:
            msg += f" (hint: {hint})"
        super().__init__(msg.replace("\n", " "))


class MissingFileError(InputError):
    """A file (or every candidate name of one) that should be there is not. The stages that read many captures
    skip a capture that raises it (a capture that did not complete) and stop on any other ``InputError``."""

    def __init__(self, file: str | Path | None, field: str | None, expected: str, actual: str = "no such file",
                 hint: str | None = None):
        super().__init__(file, field, expected, actual, hint)


class Interrupted(BaseException):
    """Ctrl-C, as the ``gtforge`` command raises it (its SIGINT handler) and as a stage re-raises it after
    stopping cleanly, with ``str()`` saying what is complete. The CLI prints it and exits with code 130.
    Library callers get the usual ``KeyboardInterrupt``; stages treat both alike. A ``BaseException``, as
    ``KeyboardInterrupt`` is: an ``except Exception`` that turns a reader's error into an ``InputError`` (a bag's
    message, an image's bytes) lets it through, so Ctrl-C is never reported as bad input (exit 2).

    ``detail``: what the stage that stopped says is complete, where it says more than ``INTERRUPTED`` (build-dataset:
    the scenes built), for a caller that words its own message (``gtforge run``)."""

    def __init__(self, message: str, detail: str | None = None):
        super().__init__(message)
        self.detail = detail


# what the user sees of a Ctrl-C no stage words itself
INTERRUPTED = ("interrupted: every file already written is complete (gtforge writes each one whole); rerun the same "
               "command to finish")


def first_of(items, n: int = 8, sep: str = ", ") -> str:
    """The first ``n`` of ``items`` (strings), joined, and how many more there are: how a message lists ids."""
    items = list(items)
    return sep.join(items[:n]) + (f" (+{len(items) - n} more)" if len(items) > n else "")
