"""Error types. See docs/conventions.md ("Errors")."""
from __future__ import annotations

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
        where = self.file or "<input>"
        if field:
            where += f" [{field}]"
        msg = f"{where}: expected {expected}, got {actual}"
        if hint:
            msg += f" (hint: {hint})"
        super().__init__(msg.replace("\n", " "))

