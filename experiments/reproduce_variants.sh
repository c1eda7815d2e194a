#!/usr/bin/env bash
# The evaluations of the variant policies in experiments/policies/ that --policy reproduces exactly: the ego on the
# variant, every other car on the shipped IDAS (experiments/README.md). Those with every other car on a variant
# (--others idas_brakes and the like, results/{brakes,manoeuvre,explored10,cooperative/paper-2024}/ in the diary)
# need commit 6499494: git checkout 6499494 && bash scripts/reproduce_results.sh.
# Usage, from the repository root: bash experiments/reproduce_variants.sh [OUT_DIR]   (default: results/)
set -euo pipefail
out=${1:-results}
here=$(cd "$(dirname "$0")" && pwd)
# The generator these were drawn with (the default is now "feasible").
ev() { idas-sumo evaluate --force --no-progress --config scenarios/eval_paper_as_drawn.toml "$@"; }
# The labelled hypothesis idas_cooperative (r_finish falling in b_type): the driver-type sweep (diary, "Declared: a
# reward that makes cooperativeness explicit"; docs/results.md, "Driver types").
ev --baseline idas --policy "$here/policies/idas_cooperative.pt" --suite driver-types --seed 2019 \
  --out "$out/cooperative/driver-types" --trajectories
# The labelled variant idas_anchored (stage 2 with the actor anchored to IDAS-V; diary, "Declared: stage 2 anchored
# to its warm start"): the paper protocol on the declared seed and 2019, and the driver-type sweep.
for seed in 2024 2019; do
  ev --baseline idas --policy "$here/policies/idas_anchored.pt" --scenarios 100 --seed "$seed" --workers 2 \
    --out "$out/anchored/paper-$seed"
done
ev --baseline idas --policy "$here/policies/idas_anchored.pt" --suite driver-types --seed 2019 \
  --out "$out/anchored/driver-types" --trajectories
