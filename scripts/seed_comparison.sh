#!/bin/bash
# Tuned reward weights against Table I's over training seeds (issue #15; docs/tuning.md, "The comparison
# that was run"). Trains each set from scratch under the protocol of the study's trials, evaluates the
# final models on the main job's held-out scenarios, with and without the shield, and aggregates.
#
#   bash scripts/seed_comparison.sh [STEPS] [SEED ...]      (default: 54000 steps, seeds 0 1 2)
#
# Two trainings run at once, one per core. Existing run folders and reports are refused, never
# overwritten (sb3-graph's own checks).
set -euo pipefail
cd "$(dirname "$0")/.."
STEPS=${1:-54000}
SEEDS=(0 1 2)
if [ $# -gt 1 ]; then SEEDS=("${@:2}"); fi
PRESET='"duration": 20.0, "max_vehicles": 16, "max_edges": 192'
# The study's best weights: examples/weight_study/best_params.yml (trial 0 of weights_fair).
TUNED=$(python -c "
import json, yaml
entry = yaml.safe_load(open('examples/weight_study/best_params.yml'))['CoopIntersection4Way-v0']
print(json.dumps(entry['env_kwargs']['config']['reward_weights']))")

train() { # CFG SEED
  local kw="{\"config\": {$PRESET}}"
  [ "$1" = tuned ] && kw="{\"config\": {$PRESET, \"reward_weights\": $TUNED}}"
  sb3-graph train --config zoo_configs/td3_tune.yml --env CoopIntersection4Way-v0 --out "runs/cmp/$1/seed_$2" \
    --seed "$2" --n-timesteps "$STEPS" --hyperparams n_envs:2 --env-kwargs "$kw" \
    --eval-freq 18000 --eval-episodes 4 --threads 1 --no-progress
}

for seed in "${SEEDS[@]}"; do
  train table1 "$seed" & train tuned "$seed" & wait
done

for cfg in table1 tuned; do
  planners=()
  for seed in "${SEEDS[@]}"; do
    wide="runs/cmp_wide/$cfg/seed_$seed"
    mkdir -p "$wide"
    # trained on graphs of <= 16 vehicles; the same weights for the full environment's 64
    sb3-graph export "runs/cmp/$cfg/seed_$seed/final_model.zip" "$wide/final_model.safetensors" \
      --max-nodes 64 --max-edges 1024
    planners+=(--planner "$wide/final_model.safetensors" --planner "$wide/final_model.safetensors+shield")
  done
  sb3-graph evaluate "${planners[@]}" --scenarios 20 --duration 100 --seed 0 --jobs 2 --no-progress \
    --out "reports/cmp_$cfg"
done
sb3-graph aggregate table1=reports/cmp_table1 tuned=reports/cmp_tuned --out reports/cmp_aggregate
python benchmarks/bench_eval_rank.py --model table1=runs/cmp/table1 --model tuned=runs/cmp/tuned \
  --report reports/cmp_table1 --report reports/cmp_tuned
