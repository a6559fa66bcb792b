#!/usr/bin/env bash
# Issue #22, stops: fine-tune the residual + feature planners of experiments/shielded_training/feature_training.sh (stored
# action fixed, experiments/shielded_training/features_proposal_s*) behind the shield with a new stop
# charged 10 s of delay instead of 2 s (reward_weights.stop 1.0), each vertex's exploration noise kept
# with its vehicle (VertexNoiseCallback), and the actor held for the first WARMUP steps while the
# critics learn the new reward. Then exported and evaluated behind the shield over demand.
#   bash experiments/shielded_training/stop_training.sh STEPS SCENARIOS SEED...   (the run in docs/training.md: 30000 10 0 1)
set -euo pipefail
steps=${1:-30000}
scenarios=${2:-10}
shift 2 || true
seeds=("${@:-0 1}")
runs=${RUNS:-runs/issue22_stops}
warmup=${WARMUP:-3000}
stop=${STOP_WEIGHT:-1.0}
export OMP_NUM_THREADS=1
mkdir -p "$runs"
callbacks="[{sb3_graph.callbacks.ActorWarmupCallback: {steps: $warmup, zero_output: false}},
 sb3_graph.callbacks.VertexNoiseCallback,
 {sb3_graph.callbacks.InfoLoggerCallback: {keys: [reward_terms, crossed, stopped, collided, waiting, shield_intervention_rate]}}]"
for s in ${seeds[@]}; do
  sb3-graph train --config zoo_configs/td3_residual_features.yml --env CoopIntersection4Way-v0 \
    --out "$runs/stops_s$s" --n-timesteps "$steps" --seed "$s" --no-progress \
    --init-weights "experiments/shielded_training/features_proposal_s$s/final_model.safetensors" \
    --env-kwargs "{\"config\": {\"reward_weights\": {\"stop\": $stop}}}" \
    --hyperparams "learning_starts:1000" "callback:$callbacks" > "$runs/stops_s$s.log" 2>&1 &
done
wait || true
source "$(dirname "$0")/residual_export.sh"
sweep_residual "$runs" stops fullthrottle "$scenarios" ${seeds[@]}
