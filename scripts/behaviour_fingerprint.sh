#!/usr/bin/env bash
# A fingerprint of what the code computes, for refactors that must not change behaviour: the paper evaluation's
# CSVs (five methods, 100 scenarios, seed 2019) and two short training runs (the curriculum from random weights;
# the shipped IDAS's stage-2 settings from IDAS-V), hashed without wall-clock columns.
# Usage: bash scripts/behaviour_fingerprint.sh OUT_DIR   (prints one "sha256  name" line per artefact; ~5 min)
set -euo pipefail
out=${1:?usage: behaviour_fingerprint.sh OUT_DIR}
mkdir -p "$out"
policies=$(python -c "from idas_sumo.resources import POLICY_DIR; print(POLICY_DIR)")
idas-sumo evaluate --force --no-progress --baseline all --suite paper --scenarios 100 --seed 2019 \
  --out "$out/paper" > /dev/null
cat > "$out/curriculum.toml" <<TOML
stage = "curriculum"
robot_episodes = 48
intelligent_episodes = 48
episodes_per_update = 16
checkpoint_every = 48
max_episode_s = 30.0
validate_every = 48
validation_scenarios = 8
TOML
cat > "$out/stage2.toml" <<TOML
stage = "intelligent"
intelligent_episodes = 64
episodes_per_update = 16
checkpoint_every = 64
max_episode_s = 40.0
init_from = "$policies/idas_v.pt"
validate_every = 32
validation_scenarios = 8
validation_criterion = "success_then_return"
[learner]
lr_actor = 3e-5
gamma = 0.99
gae_lambda = 0.95
q_lambda = 0.95
normalize_advantages = true
entropy_coef = 0.05
anchor_coef = 0.5
TOML
for run in curriculum stage2; do
  idas-sumo train --config "$out/$run.toml" --seed 3 --workers 1 --out "$out/$run" --force --no-progress > /dev/null
done
python - "$out" <<'PY'
import hashlib, sys
from pathlib import Path
import pandas as pd
import torch
out = Path(sys.argv[1])
def digest(b: bytes) -> str:
    return hashlib.sha256(b).hexdigest()[:16]
for csv in sorted(out.rglob("*.csv")):
    frame = pd.read_csv(csv)
    frame = frame[[c for c in frame.columns if "wall" not in c]]
    print(digest(frame.to_csv(index=False).encode()), csv.relative_to(out))
for pt in sorted(out.rglob("*.pt")):
    ckpt = torch.load(pt, weights_only=True, map_location="cpu")
    h = hashlib.sha256()
    def walk(x, key=""):
        if isinstance(x, torch.Tensor):
            h.update(key.encode()); h.update(x.contiguous().numpy().tobytes())
        elif isinstance(x, dict):
            for k in sorted(x, key=str):
                walk(x[k], f"{key}/{k}")
        elif isinstance(x, list | tuple):
            for i, v in enumerate(x):
                walk(v, f"{key}/{i}")
    walk(ckpt.get("learner", {}), "learner")  # the networks and optimisers, not the run's wall times
    print(h.hexdigest()[:16], pt.relative_to(out))
PY
