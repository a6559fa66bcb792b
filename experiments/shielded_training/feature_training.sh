#!/usr/bin/env bash
# Issue #22's feature comparison: the residual policy of experiments/shielded_training/shielded_training.sh (a correction of
# always-full-throttle behind the shield, task reward) with the observation features of
# zoo_configs/td3_residual_features.yml, 3 training seeds from scratch, then evaluated behind the
# shield on the main job's scenarios beside the residual policies without them, AIM and
# always-full-throttle + shield.
#   bash experiments/shielded_training/feature_training.sh STEPS SCENARIOS   (the run in docs/training.md: 50000 10)
# The trainings run in parallel, one torch thread each; a killed one is exported from its latest checkpoint.
set -euo pipefail
steps=${1:-50000}
scenarios=${2:-10}
runs=${RUNS:-runs/issue22_features}
export OMP_NUM_THREADS=1
mkdir -p "$runs"
for s in 0 1 2; do
  sb3-graph train --config zoo_configs/td3_residual_features.yml --env CoopIntersection4Way-v0 \
    --out "$runs/features_s$s" --n-timesteps "$steps" --seed "$s" --no-progress > "$runs/features_s$s.log" 2>&1 &
done
wait || true
latest() { ls "$1"/final_model.zip 2>/dev/null || ls -v "$1"/checkpoints/model_*_steps.zip | tail -n 1; }
config='{"residual_base": "fullthrottle", "residual_scale": 2.0, "vertex_features": ["maneuver", "priority",
 "limit", "line", "zone", "committed"], "edge_features": ["zone_receiver", "zone_sender"]}'
for s in 0 1 2; do
  mkdir -p "$runs/planners/features_s$s"
  sb3-graph export "$(latest "$runs/features_s$s")" "$runs/planners/features_s$s/final_model.safetensors" \
    --planner-config "$config"
done
P=$runs/planners
E=experiments/shielded_training
sb3-graph evaluate --planner aim --planner envs/planners/adversarial.py:FullThrottle+shield \
  --planner "$P/features_s0/final_model.safetensors+shield" --planner "$P/features_s1/final_model.safetensors+shield" \
  --planner "$P/features_s2/final_model.safetensors+shield" \
  --planner "$E/residual_s0/final_model.safetensors+shield" --planner "$E/residual_s1/final_model.safetensors+shield" \
  --planner "$E/residual_s2/final_model.safetensors+shield" \
  --scenarios "$scenarios" --seed 0 --duration 100 --jobs 2 --out "$runs/eval"
sb3-graph aggregate "$runs/eval" --seed-pattern '_s(\d+)' --out "$runs/aggregate"
