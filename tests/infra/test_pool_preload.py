"""What the local pool's fork server loads (``infra.pool_preload``): numba's registries without SciPy's linear
algebra, and numba then behaving as its own BLAS check would have it."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import pytest

SCRIPT = textwrap.dedent('''
    import json, sys
    import numpy as np
    import gtforge.infra.pool_preload
    import numba
    import numba.np.arraymath

    out = {"scipy_linalg_after_preload": "scipy.linalg" in sys.modules,
           "have_blas_set": numba.np.arraymath._HAVE_BLAS}

    @numba.njit
    def dot_and_convolve(a, b):
        return np.dot(a, b), np.convolve(a, b)

    a, b = np.array([0.1, 0.7, -2.3, 1e-3]), np.array([3.3, -0.2, 0.9, 4.1])
    d, c = dot_and_convolve(a, b)
    out["dot_same"] = bool(d == np.dot(a, b))
    out["convolve_same"] = c.tobytes() == np.convolve(a, b).tobytes()
    out["numba_check"] = numba.np.arraymath._check_blas()  # numba's own answer (imports SciPy's BLAS now)
    print(json.dumps(out))
''')


@pytest.mark.slow  # a child Python imports numba and compiles np.dot and np.convolve
def test_registries_load_without_scipy_linalg_and_numba_keeps_blas():
    env = {**os.environ, "NUMBA_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
    env.pop("GTFORGE_POOL_WARM_UP", None)
    r = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, env=env, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out == {"scipy_linalg_after_preload": False, "have_blas_set": True, "dot_same": True,
                   "convolve_same": True, "numba_check": True}
