# Sourced by issue #22's training scripts: export a residual + feature run (zoo_configs/
# td3_residual_features.yml) as a planner file whose header names its base and features.
latest() { ls "$1"/final_model.zip 2>/dev/null || ls -v "$1"/checkpoints/model_*_steps.zip | tail -n 1; }
export_residual() {  # RUN_FOLDER OUT_FILE BASE: the run's final model, else its latest checkpoint
  local config="{\"residual_base\": \"$3\", \"residual_scale\": 2.0, \"vertex_features\": [\"maneuver\",
 \"priority\", \"limit\", \"line\", \"zone\", \"committed\"], \"edge_features\": [\"zone_receiver\", \"zone_sender\"]}"
  mkdir -p "$(dirname "$2")"
  sb3-graph export "$(latest "$1")" "$2" --planner-config "$config"
}
sweep_residual() {  # RUNS NAME BASE SCENARIOS SEED...: export RUNS/NAME_s<SEED>, sweep them behind the shield
  local runs=$1 name=$2 base=$3 scenarios=$4 s
  shift 4
  local planners=()
  for s in "$@"; do
    export_residual "$runs/${name}_s$s" "$runs/planners/${name}_s$s/final_model.safetensors" "$base"
    planners+=(--planner "$runs/planners/${name}_s$s/final_model.safetensors+shield")
  done
  sb3-graph sweep --planner aim --planner fullthrottle+shield "${planners[@]}" \
    --demand 0.05 0.1 0.2 0.3 0.4 0.6 --scenarios "$scenarios" --jobs 2 --out "$runs/sweep"
}
