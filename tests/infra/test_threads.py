"""Per-capture work on threads (gtforge.infra.threads.ordered_map): the items' order, a bounded number in flight,
errors where their item is."""
from __future__ import annotations

import threading
import time

import pytest

from gtforge.infra.threads import ordered_map


def test_results_come_in_the_items_order_with_at_most_workers_in_flight():
    lock = threading.Lock()
    running, most, threads = [0], [0], set()

    def work(i):
        with lock:
            running[0] += 1
            most[0] = max(most[0], running[0])
            threads.add(threading.get_ident())
        time.sleep(0.03 + 0.02 * (-i % 3))  # later items often finish first
        with lock:
            running[0] -= 1
        return i * i

    assert list(ordered_map(work, range(12), workers=3)) == [i * i for i in range(12)]
    assert most[0] == 3 and len(threads) == 3
    assert threading.get_ident() not in threads


def test_one_worker_runs_in_the_calling_thread():
    idents = list(ordered_map(lambda _: threading.get_ident(), range(4), workers=1))
    assert idents == [threading.get_ident()] * 4


def test_an_error_is_raised_at_its_item_and_no_later_item_is_started():
    started = []

    def work(i):
        started.append(i)
        if i == 2:
            raise ValueError("capture 2 is broken")
        return i

    got = []
    with pytest.raises(ValueError, match="capture 2"):
        for r in ordered_map(work, range(10), workers=2):
            got.append(r)
    assert got == [0, 1]
    # items 0-3 may have been started (2 in flight while 0 and 1 were consumed); none after the window
    assert max(started) <= 3 and sorted(started) == list(range(len(started)))

