#!/usr/bin/env bash
# Regenerate the numbers and plots in docs/results.md (about 3-4 minutes on a 2-core laptop; measured 3 min 14 s).
# Usage: bash scripts/reproduce_results.sh [OUT_DIR]   (default: results/)
set -euo pipefail
out=${1:-results}
idas-sumo evaluate --baseline all --suite paper --scenarios 100 --seed 2019 --out "$out/paper" --force --plots
idas-sumo evaluate --baseline all --suite representative --seed 2019 --out "$out/representative" --force --trajectories --plots
idas-sumo evaluate --baseline all --suite driver-types --seed 2019 --out "$out/driver-types" --force --trajectories --plots
# Every car on one method: the method drives the ego and, as --others, every other car.
for method in idas idas_v idm fsm_idm; do
  idas-sumo evaluate --baseline "$method" --others "$method" --scenarios 40 --seed 456 \
    --config scenarios/eval_intelligent.toml --out "$out/every-car/intelligent/$method" --force --no-progress
  idas-sumo evaluate --baseline "$method" --others "$method" --scenarios 100 --seed 2019 \
    --out "$out/every-car/paper/$method" --force --no-progress
done
