#!/usr/bin/env bash
# Regenerate every number and plot in docs/results.md (about 5-10 minutes on a 2-core laptop).
# Usage: bash scripts/reproduce_results.sh [OUT_DIR]   (default: results/)
set -euo pipefail
out=${1:-results}
idas-sumo evaluate --baseline all --suite paper --scenarios 100 --seed 2019 --out "$out/paper" --force --plots
idas-sumo evaluate --baseline all --suite representative --seed 2019 --out "$out/representative" --force --trajectories --plots
idas-sumo evaluate --baseline all --suite driver-types --seed 2019 --out "$out/driver-types" --force --trajectories --plots
