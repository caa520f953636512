"""Ctrl-C held back over short work that must finish once begun (a landing's renames and the record that lists them;
a local pool's start of its workers, at most the fork server's start): the interrupt is raised when the block ends,
so a stop leaves the earlier state or the finished one, never half of it."""
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
    finally:  # (None: a handler not set from Python; the default's is the closest)
        signal.signal(signal.SIGINT, signal.SIG_DFL if previous is None else previous)
    if received:
        if callable(previous):
            previous(*received[0])
        elif previous in (signal.SIG_DFL, None):
            raise KeyboardInterrupt
