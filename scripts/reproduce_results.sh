#!/usr/bin/env bash
# Regenerate the numbers and plots in docs/results.md from the shipped policies (the time of the last run is on
# the page). The equal-terms table comes from the training runs instead: scripts/equal_terms.py (docs/results.md).
# Usage: bash scripts/reproduce_results.sh [OUT_DIR]   (default: results/)
# The variant policies' evaluations are in experiments/reproduce_variants.sh.
# Every run uses the defaults (the paper's own-lane safety mask, feasible entries, every other car on the shipped
# IDAS) unless it says otherwise.
set -euo pipefail
out=${1:-results}
ev() { idas-sumo evaluate --force --no-progress "$@"; }
# The headline: the paper's protocol on the seed declared for it (experiments/diary.md), every method as the ego.
ev --baseline all --scenarios 100 --seed 2030 --out "$out/headline-2030/paper-methods" --plots
for method in idas_paper idas_v_paper idas_direct_paper warm_start fsm_idm_smooth; do
  ev --baseline "$method" --scenarios 100 --seed 2030 --out "$out/headline-2030/$method"
done
python scripts/margins.py "$out"/headline-2030/*/ --methods idas idm fsm_idm warm_start idas_paper \
  --out "$out/headline-2030/margins.csv"
# Every car on one method: the method drives the ego and, as --others, every other car.
for method in idas idas_v idas_direct idas_paper warm_start idm fsm_idm fsm_idm_smooth; do
  ev --baseline "$method" --others "$method" --scenarios 100 --seed 2019 --out "$out/every-car/$method"
done
# Ablation: our merge-aware shield instead of the paper's mask.
ev --baseline all --scenarios 100 --seed 2019 --safety-mask merge_aware --out "$out/merge-aware"
# Geometries the policies never saw (issue #17): six generated merges and the on-ramp sample net.
ev --baseline all --suite geometry --scenarios 100 --seed 2019 --workers 2 --out "$out/geometry"
ev --baseline all --suite representative --seed 2019 --out "$out/representative" --trajectories --plots
ev --baseline all --suite driver-types --seed 2019 --out "$out/driver-types" --trajectories --plots
# The same sweep in the paper's Fig. 6 set-up: the main car at b_type -1 (L301, L358).
python scripts/driver_types_fig6.py --force --no-progress --baseline idas --seed 2019 --out "$out/driver-types-fig6"
# IDAS trained on many merges (issue #17), every other car on it; these tables were drawn with later entries as
# drawn before issue 36 and keep that generator, so they are reproduced unchanged.
ev_as_drawn() { ev --config scenarios/eval_paper_as_drawn.toml "$@"; }
for method in idas_geometry idm fsm_idm; do
  ev_as_drawn --baseline "$method" --others idas_geometry --suite geometry --scenarios 100 --seed 2019 --workers 2 \
    --out "$out/geometry-trained/$method"
  ev_as_drawn --baseline "$method" --others idas_geometry --scenarios 100 --seed 2019 --workers 2 \
    --out "$out/geometry-trained/tjunction-2019/$method"
  # the declared second evaluation seed of the held-out geometries
  ev_as_drawn --baseline "$method" --others idas_geometry --suite geometry --scenarios 100 --seed 2024 --workers 2 \
    --out "$out/geometry-trained-2024/$method"
done
