#!/usr/bin/env bash
# Issue #22's comparison: residual policies over always-full-throttle (3 training seeds) and one plain
# policy, all trained from scratch behind the shield on the task reward, then evaluated behind the
# shield on main-job scenarios against AIM, always-full-throttle + shield and the shipped planner.
#   bash experiments/shielded_training/shielded_training.sh STEPS SCENARIOS   (run with 50000 10; the plain policy
#   was stopped at its 40,000-step checkpoint)
# The trainings run in parallel, one torch thread each. Stop one early with `kill` and this script
# exports its latest checkpoint instead of a final model.
set -euo pipefail
steps=${1:-50000}
scenarios=${2:-10}
runs=${RUNS:-runs/issue22}
export OMP_NUM_THREADS=1
mkdir -p "$runs"
for s in 0 1 2; do
  sb3-graph train --config zoo_configs/td3_residual.yml --env CoopIntersection4Way-v0 --out "$runs/residual_s$s" \
    --n-timesteps "$steps" --seed "$s" --no-progress > "$runs/residual_s$s.log" 2>&1 &
done
sb3-graph train --config zoo_configs/td3_shield.yml --env CoopIntersection4Way-v0 --out "$runs/shield_s0" \
  --n-timesteps "$steps" --seed 0 --no-progress > "$runs/shield_s0.log" 2>&1 &
wait || true
latest() { ls "$1"/final_model.zip 2>/dev/null || ls -v "$1"/checkpoints/model_*_steps.zip | tail -n 1; }
for run in residual_s0 residual_s1 residual_s2 shield_s0; do
  mkdir -p "$runs/planners/$run"
  config=()
  case $run in residual*) config=(--planner-config '{"residual_base": "fullthrottle", "residual_scale": 2.0}');; esac
  sb3-graph export "$(latest "$runs/$run")" "$runs/planners/$run/final_model.safetensors" "${config[@]}"
done
P=$runs/planners
sb3-graph evaluate --planner aim --planner envs/planners/adversarial.py:FullThrottle+shield \
  --planner "$P/residual_s0/final_model.safetensors+shield" --planner "$P/residual_s1/final_model.safetensors+shield" \
  --planner "$P/residual_s2/final_model.safetensors+shield" --planner "$P/shield_s0/final_model.safetensors+shield" \
  --planner envs/pretrained/coop_4way_fair/best_model.safetensors+shield \
  --scenarios "$scenarios" --seed 0 --duration 100 --jobs 2 --trust-planner-files --out "$runs/eval"
sb3-graph aggregate "$runs/eval" --seed-pattern 'residual_s(\d+)' --out "$runs/aggregate"
