#!/usr/bin/env bash
# The main job: set up the environment (first run only), train the default agent on
# heml_gym/TissueRetraction-v1 for a short budget, evaluate it, and record a rollout.
set -euo pipefail
cd "$(dirname "$0")/.."
HEML_EXTRAS="${HEML_EXTRAS:-train,viz}" source scripts/setup_env.sh
set -euo pipefail
seed=0  # the run folder follows --seed (bash scripts/main.sh --seed 3 -> runs/quick-seed3)
args=("$@")
for i in "${!args[@]}"; do
  case "${args[$i]}" in
    --seed) seed="${args[$((i + 1))]:-0}" ;;
    --seed=*) seed="${args[$i]#--seed=}" ;;
  esac
done
run="${RUN_DIR:-runs/quick-seed$seed}"
heml-gym train configs/quick.yaml --run-dir "$run" "$@"
heml-gym eval "$run" --episodes 20 --seed 20000 --out "$run/eval.json"  # episodes training never evaluated on
heml-gym rollout --policy "$run" --episodes 2 --rrd "$run/rollout.rrd"
echo
echo "everything is in $run/: model.zip, checkpoints/, tb/ (tensorboard --logdir $run/tb),"
echo "evaluations.json (success during training), eval.json, rollout.rrd (rerun $run/rollout.rrd)"
