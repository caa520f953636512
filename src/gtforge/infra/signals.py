"""Ctrl-C held back over a few milliseconds of work that must finish once begun (a landing's renames and the record
that lists them): the interrupt is raised when the block ends, so a stop leaves the earlier state or the finished
one, never half of it."""
from __future__ import annotations

import contextlib
import signal
import threading


@contextlib.contextmanager
def interrupt_deferred():
    """Run the block with SIGINT recorded instead of raised; raise it (the handler that was in place) on exit."""
    if threading.current_thread() is not threading.main_thread():  # only the main thread handles signals
        yield
        return
    received = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: received.append((signum, frame)))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
    if received:
        if callable(previous):
            previous(*received[0])
        elif previous == signal.SIG_DFL:
            raise KeyboardInterrupt
