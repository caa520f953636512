#!/usr/bin/env bash
# Regenerates calib_data_examples/session with gtforge's own synthetic generator (deterministic by seed).
set -euo pipefail
cd "$(dirname "$0")"
rm -rf session
../.venv/bin/gtforge synth session --boards 5 --scenes 2 --scale 0.25 --seed 3 --depth-noise-mm 0.03
du -sh session
