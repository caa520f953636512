#!/usr/bin/env bash
# Regenerates calib_data_examples/session with gtforge's own synthetic generator (deterministic by seed).
# GTFORGE: the gtforge command to use (default: the repository's .venv).
set -euo pipefail
cd "$(dirname "$0")"
GTFORGE=${GTFORGE:-../.venv/bin/gtforge}
rm -rf session
$GTFORGE synth session --boards 5 --scenes 3 --scale 0.25 --seed 3 --depth-noise-mm 0.03
du -sh session
