#!/usr/bin/env bash
# Regenerate the co-simulation study in docs/cosim.md: both nets' grids (demand x penetration x seed, IDAS as the
# automated cars' policy), their flows.png, and the time-space diagram of one mixed run on the T-junction.
# Usage: bash scripts/cosim_study.sh [OUT_DIR] [WORKERS]   (defaults: results/, 2 worker processes).
# Resumable: run it again after an interruption and each study skips the runs its flows.csv already holds
# (results do not depend on WORKERS). Copy the PNGs into docs/img/ by hand after checking them.
set -euo pipefail
out=${1:-results}
workers=${2:-2}
grid=(--penetration 0,0.25,0.5,1 --policy idas --duration-s 900 --bin-s 300 --warmup-s 300 --seeds 0-2
  --workers "$workers")
# The shipped T-junction: three demand levels up to the merge road's capacity.
idas-sumo cosim --demand main=600,merge=200 --demand main=900,merge=300 --demand main=1200,merge=400 \
  "${grid[@]}" --out "$out/cosim_tjunction"
# The on-ramp sample: a two-lane highway and an acceleration lane, at higher demand.
[ -f "$out/onramp.net.xml" ] || idas-sumo nets sample onramp --out "$out/onramp.net.xml"
idas-sumo cosim --net "$out/onramp.net.xml" --demand main=1600,merge=400 --demand main=2400,merge=600 \
  --demand main=3200,merge=800 "${grid[@]}" --out "$out/cosim_onramp"
# One mixed run's time-space diagram (5 minutes at the T-junction's highest level, half the cars automated).
idas-sumo cosim --demand main=1200,merge=400 --penetration 0.5 --policy idas --duration-s 300 --seeds 0 \
  --trajectories --out "$out/cosim_tjunction_trajectories"
idas-sumo plot "$out/cosim_tjunction_trajectories"
echo "plots: $out/cosim_tjunction/flows.png $out/cosim_onramp/flows.png $out/cosim_tjunction_trajectories/trajectories/*.png"
