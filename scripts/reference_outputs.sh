#!/usr/bin/env bash
# The outputs scripts/compare_outputs.py compares between two versions of gtforge (docs/architecture.md):
#   PYTHONPATH=<checkout>/src bash scripts/reference_outputs.sh OUT
# OUT/demo: `gtforge demo` (calibrate, validate, refine, build-dataset, evaluate on its synthetic session).
# OUT/chain: a second synthetic session with a longer baseline, a turned right camera and gauge objects, through
# calibrate, calibrate-scale, validate (gauges included), build-dataset (one worker) and verify.
set -euo pipefail
OUT=${1:?usage: reference_outputs.sh OUT}
PY=${PY:-python}
gt() { "$PY" -c "from gtforge.cli import main; main()" "$@"; }
mkdir -p "$OUT"
gt demo "$OUT/demo" > "$OUT/demo.log"
C="$OUT/chain"
gt synth "$C/session" --boards 6 --scenes 3 --scale 0.3 --seed 3 --gauges --baseline-error-pct 0.25 \
  --right-yaw-deg 0.05 > "$C.log"
gt calibrate "$C/session" --output "$C/calibration.yaml" >> "$C.log"
gt calibrate-scale "$C/session" --calibration "$C/calibration.yaml" --output "$C/scaled.yaml" >> "$C.log"
gt validate "$C/session" --calibration "$C/scaled.yaml" --output "$C/validation" >> "$C.log" || true  # exit 1: FAIL
gt build-dataset "$C/session" --calibration "$C/scaled.yaml" --output "$C/dataset" --workers 1 >> "$C.log"
gt verify "$C/dataset" >> "$C.log" || true  # exit 1: a scene flagged
echo "outputs in $OUT"
