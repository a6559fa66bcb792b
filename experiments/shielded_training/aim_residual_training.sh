#!/usr/bin/env bash
# Issue #22 item 5 with AIM as the base: the residual + feature policy of experiments/shielded_training/feature_training.sh
# (zoo_configs/td3_residual_features.yml) correcting AIM instead of always-full-throttle, from scratch
# (a zero actor is AIM; the critics learn AIM's value for the first 10,000 steps), then evaluated
# behind the shield over demand beside AIM and full throttle + shield.
#   bash experiments/shielded_training/aim_residual_training.sh STEPS SCENARIOS SEED...   (the run in docs/training.md: 30000 10 0 1)
set -euo pipefail
steps=${1:-30000}
scenarios=${2:-10}
shift 2 || true
seeds=("${@:-0 1}")
runs=${RUNS:-runs/issue22_aim}
export OMP_NUM_THREADS=1
mkdir -p "$runs"
for s in ${seeds[@]}; do
  sb3-graph train --config zoo_configs/td3_residual_features.yml --env CoopIntersection4Way-v0 \
    --out "$runs/aim_s$s" --n-timesteps "$steps" --seed "$s" --no-progress \
    --env-kwargs '{"config": {"residual_base": "aim"}}' > "$runs/aim_s$s.log" 2>&1 &
done
wait || true
source "$(dirname "$0")/residual_export.sh"
sweep_residual "$runs" aim aim "$scenarios" ${seeds[@]}
