"""A gtforge process leaves without the interpreter's teardown collection over numba's, LLVM's and pydantic's objects
(0.1-0.2 s a process: benchmarks/RESULTS.md, "Round 6"): the command (``gtforge.cli.main``) and the local pool's fork
server (``infra.pool_preload``) freeze the garbage collector's objects at exit, after every other exit handler."""
from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

# registered before the code under test, so it runs after that code's exit handlers (atexit runs them last-in first-out)
PROBE = "import atexit, gc\natexit.register(lambda: print('frozen at exit:', gc.get_freeze_count() > 0))\n"


@pytest.mark.parametrize("code, frozen", [
    ("import gtforge.cli", False),  # importing the command changes nothing: only running it does
    ("import sys\nfrom gtforge.cli import main\nsys.argv = ['gtforge', '--help']\nmain()", True),
    ("import sys\nfrom gtforge.cli import main\nsys.argv = ['gtforge', 'verify', '/nonexistent']\nmain()", True),
    ("import gtforge.infra.pool_preload", True),  # what the fork server imports before it forks any worker
], ids=["import only", "a command", "a command's one-line error", "the fork server's preload"])
def test_processes_leave_frozen(code, frozen):
    r = subprocess.run([sys.executable, "-c", PROBE + textwrap.dedent(code)], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode in (0, 2), r.stderr[-2000:]
    assert r.stdout.strip().splitlines()[-1] == f"frozen at exit: {frozen}"
