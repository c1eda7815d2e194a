#!/usr/bin/env bash
# The paper's recipe as printed (issue 36 item 3; idas_sumo/scenarios/train_paper.toml): three seeds of IDAS
# (curriculum: 20,000 robot-world + 50,000 intelligent-world episodes from random weights; its stage 1 gives
# IDAS-V) and three of IDAS-direct (70,000 from random weights), then the declared pick.
#
#   bash scripts/paper_recipe.sh [OUT_ROOT] [EPISODES]     # default runs/paper, the recipe's budgets
#
# Every run continues with --resume where a checkpoint exists, so the script can be stopped (Ctrl-C saves a
# checkpoint) and started again in another session; a finished run is left as it is. EPISODES (per stage)
# shortens every run, for a smoke test: `bash scripts/paper_recipe.sh /tmp/paper_smoke 100`. SEEDS="0" runs
# fewer seeds; WORKERS=1 leaves the machine's other cores free. All six runs: about 15-30 h on 2 cores
# (seed 0's curriculum ran 20,000 episodes in ~13 min, then stage 2 at ~16 episodes/s with one worker).
# RECIPE names another recipe run the same way (our recipe: RECIPE=idas_sumo/scenarios/train_ours.toml SUFFIX=
# bash scripts/paper_recipe.sh runs/ours); KINDS="direct" runs one kind only, e.g. one kind per core.
set -euo pipefail
out=${1:-runs/paper}
recipe=${RECIPE:-idas_sumo/scenarios/train_paper.toml}
kinds=${KINDS:-curriculum direct}
suffix=${SUFFIX-_paper}
episodes=${2:-}
seeds=${SEEDS:-0 1 2}
budget=()
if [[ -n "$episodes" ]]; then budget=(--episodes "$episodes"); fi
if [[ -n "${WORKERS:-}" ]]; then budget+=(--workers "$WORKERS"); fi

train() { # STAGE SEED
  local dir="$out/$1_seed$2"
  if [[ -f "$dir/checkpoint.pt" ]]; then
    idas-sumo train --out "$dir" --resume --no-progress "${budget[@]}"
  else
    # Nothing to continue: a run stopped before its first checkpoint starts over (--force).
    idas-sumo train --config "$recipe" --stage "$1" --seed "$2" --out "$dir" --force \
      --no-progress "${budget[@]}"
  fi
}

for kind in $kinds; do
  for seed in $seeds; do train "$kind" "$seed"; done
done
# The pick over every seed that has run (paper_pick.py skips a seed without runs), not only this call's SEEDS.
python "$(dirname "$0")/paper_pick.py" "$out" --suffix "$suffix"
