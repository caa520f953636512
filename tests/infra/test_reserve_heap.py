"""``scheduling.reserve_heap``: a pool worker's heap faulted in before its first task, so that the task's arrays land
on pages that are already there (one ``madvise`` call a piece instead of a page fault a page)."""
from __future__ import annotations

import json
import platform
import subprocess
import sys
import textwrap

import pytest

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux") or platform.libc_ver()[0] != "glibc",
                                reason="glibc's malloc on Linux (elsewhere reserve_heap does nothing)")

# a fresh process (a clean heap): reserve, then write a 24 MB block from malloc and count the page faults it took
PROBE = textwrap.dedent('''
    import ctypes, json, resource, sys
    from gtforge.infra.scheduling import reserve_heap, reuse_freed_memory
    libc = ctypes.CDLL("libc.so.6")
    libc.malloc.restype, libc.malloc.argtypes = ctypes.c_void_p, [ctypes.c_size_t]
    libc.memset.argtypes, libc.free.argtypes = [ctypes.c_void_p, ctypes.c_int, ctypes.c_size_t], [ctypes.c_void_p]
    applied = reuse_freed_memory()
    reserved = reserve_heap(int(sys.argv[1]))
    n = 24 << 20
    f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    p = libc.malloc(n)
    libc.memset(p, 1, n)
    f1 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    libc.free(p)
    print(json.dumps({"applied": applied, "reserved": reserved, "faults": f1 - f0}))
''')


def _probe(n_bytes: int) -> dict:
    r = subprocess.run([sys.executable, "-c", PROBE, str(n_bytes)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr[-2000:]
    return json.loads(r.stdout.strip().splitlines()[-1])


def test_a_reserved_heap_takes_the_next_arrays_without_page_faults():
    pages = (24 << 20) // 4096
    without = _probe(0)
    assert without["applied"] and not without["reserved"]
    if without["faults"] < pages // 4:
        pytest.skip(f"this kernel faults the heap in large pages ({without['faults']} faults for {pages} pages): "
                    "nothing for a reservation to save")
    assert without["faults"] >= pages * 0.9  # a page fault a 4 kB page
    with_reserve = _probe(40 << 20)
    if not with_reserve["reserved"]:
        pytest.skip("madvise(MADV_POPULATE_WRITE) needs Linux 5.14 or later")
    assert with_reserve["faults"] < pages // 20, with_reserve


def test_nothing_is_reserved_for_no_bytes():
    from gtforge.infra.scheduling import reserve_heap

    assert reserve_heap(0) is False and reserve_heap(-5) is False
