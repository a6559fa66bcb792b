#!/bin/bash
# Tuned reward weights against Table I's over training seeds (issue #15; docs/tuning.md, "The comparison
# that was run"). Trains each set from scratch under the protocol of the study's trials, evaluates the
# final models on the main job's held-out scenarios, with and without the shield, and aggregates.
#
#   bash experiments/weight_study/seed_comparison.sh [STEPS] [SEED ...]      (default: 54000 steps, seeds 0 1 2)
#
# Two trainings run at once, one per core. Existing run folders and reports are refused, never
# overwritten (sb3-graph's own checks).
set -euo pipefail
cd "$(dirname "$0")/../.."
STEPS=${1:-54000}
SEEDS=(0 1 2)
if [ $# -gt 1 ]; then SEEDS=("${@:2}"); fi
# The tuning preset (envs.evaluation.tuning.TUNING_PRESET), the study's best weights (experiments/weight_study,
# trial 0 of weights_fair) and the full environment's graph sizes, read where they are defined.
read -r PRESET TUNED FULL_NODES FULL_EDGES < <(python -c "
import json, yaml
from envs.simulation.env import CoopIntersectionEnv
from envs.evaluation.tuning import TUNING_PRESET
entry = yaml.safe_load(open('experiments/weight_study/best_params.yml'))['CoopIntersection4Way-v0']
full = CoopIntersectionEnv.default_config()
print(json.dumps(TUNING_PRESET, separators=(',', ':'))[1:-1],
      json.dumps(entry['env_kwargs']['config']['reward_weights'], separators=(',', ':')),
      full['max_vehicles'], full['max_edges'])")
[ -n "${FULL_EDGES:-}" ] || { echo "seed_comparison.sh: cannot read the preset and the weights" >&2; exit 1; }

train() { # CFG SEED
  local kw="{\"config\": {$PRESET}}"
  [ "$1" = tuned ] && kw="{\"config\": {$PRESET, \"reward_weights\": $TUNED}}"
  sb3-graph train --config zoo_configs/td3_tune.yml --env CoopIntersection4Way-v0 --out "runs/cmp/$1/seed_$2" \
    --seed "$2" --n-timesteps "$STEPS" --hyperparams n_envs:2 --env-kwargs "$kw" \
    --eval-freq 18000 --eval-episodes 4 --threads 1 --no-progress
}

for seed in "${SEEDS[@]}"; do
  train table1 "$seed" & first=$!
  train tuned "$seed" & second=$!
  status=0
  wait "$first" || status=$?
  wait "$second" || status=$?
  [ "$status" -eq 0 ] || { echo "seed_comparison.sh: a training of seed $seed failed" >&2; exit "$status"; }
done

for cfg in table1 tuned; do
  planners=()
  for seed in "${SEEDS[@]}"; do
    wide="runs/cmp_wide/$cfg/seed_$seed"
    mkdir -p "$wide"
    # trained on the preset's small graphs; the same weights for the full environment's
    sb3-graph export "runs/cmp/$cfg/seed_$seed/final_model.zip" "$wide/final_model.safetensors" \
      --max-nodes "$FULL_NODES" --max-edges "$FULL_EDGES"
    planners+=(--planner "$wide/final_model.safetensors" --planner "$wide/final_model.safetensors+shield")
  done
  sb3-graph evaluate "${planners[@]}" --scenarios 20 --duration 100 --seed 0 --jobs 2 --no-progress \
    --out "reports/cmp_$cfg"
done
sb3-graph aggregate table1=reports/cmp_table1 tuned=reports/cmp_tuned --out reports/cmp_aggregate
python benchmarks/bench_eval_rank.py --model table1=runs/cmp/table1 --model tuned=runs/cmp/tuned \
  --report reports/cmp_table1 --report reports/cmp_tuned
