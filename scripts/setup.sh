#!/usr/bin/env bash
# Set up gtforge from scratch: the system libraries Open3D needs (libusb-1.0-0, libgomp1), a virtual environment,
# the package, with its numba kernels compiled.
# Usage: scripts/setup.sh [VENV_DIR]   (default .venv). Idempotent.
set -euo pipefail
VENV="${1:-.venv}"
PY="${PYTHON:-python3}"

need_libs=()
ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0' || need_libs+=(libusb-1.0-0)
ldconfig -p 2>/dev/null | grep -q 'libgomp.so.1' || need_libs+=(libgomp1)
if [ ${#need_libs[@]} -gt 0 ]; then
  if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null; then
    echo "setup: installing system packages: ${need_libs[*]}"
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq >/dev/null && apt-get install -y -qq "${need_libs[@]}" >/dev/null
  else
    echo "setup: Open3D needs the system packages ${need_libs[*]}; install them (e.g. 'sudo apt-get install ${need_libs[*]}') and run again" >&2
    exit 1
  fi
fi

"$PY" -c 'import sys; sys.exit(0 if sys.version_info >= (3, 10) else 1)' || {
  echo "setup: Python >= 3.10 needed, found $("$PY" --version 2>&1)" >&2; exit 1; }
if [ ! -x "$VENV/bin/python" ]; then
  "$PY" -m venv "$VENV"
fi
"$VENV/bin/python" -m pip install -q --upgrade pip
"$VENV/bin/python" -m pip install -q -e ".[test]"
# numba compiles each kernel on its first call after an install and caches it: do it once here, not in every worker
# of the first build (gtforge/precompile.py)
"$VENV/bin/python" -m gtforge.precompile
"$VENV/bin/python" -c "import open3d, cv2, numba, gtforge; print('setup: ok (gtforge', gtforge.__version__, ', OpenCV', cv2.__version__, ', Open3D', open3d.__version__ + ')')"
