#!/usr/bin/env bash
# The vision RIS study (docs/dgrl_ris_sawyer.md): RIS (--groups 0) against RIS+DGRL (--groups 16) on the Sawyer
# push-and-reach task from pixels, JOBS runs at a time (one torch thread each), then curves and a table from the
# TensorBoard logs. The default is the CPU preset (batch 32, 2k random steps, 10 test episodes every 2k steps); the
# paper's setting (batch 256, 10k random steps, 20 test episodes) is a GPU job: PRESET=paper.
#   bash benchmark/ris_sawyer.sh                                               # CPU preset, 30k steps, seed 1, G0 and G16
#   PRESET=paper STEPS=1000000 SEEDS="1 2 3" JOBS=6 TAG=paper bash benchmark/ris_sawyer.sh   # a GPU machine
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-.venv/bin/python}
STEPS=${STEPS:-30000}
SEEDS=${SEEDS:-1}
GROUPS_LIST=${GROUPS_LIST:-"0 16"}
JOBS=${JOBS:-2}
TAG=${TAG:-cpu}
PRESET=${PRESET:-cpu}
EXTRA=${EXTRA:-}
case "$PRESET" in
  cpu) PRESET_FLAGS="--batch-size 32 --start-timesteps 2000 --eval-frequency 2000 --eval-episodes 10" ;;
  paper) PRESET_FLAGS="--eval-frequency 5000" ;;
  *) echo "PRESET must be cpu or paper; got $PRESET" >&2; exit 2 ;;
esac
export OMP_NUM_THREADS=1 PYTHONUNBUFFERED=1 MUJOCO_GL=${MUJOCO_GL:-egl}  # one thread a run; headless rendering
mkdir -p logs
for seed in $SEEDS; do
  for groups in $GROUPS_LIST; do
    echo "$groups $seed"
  done
done | xargs -P "$JOBS" -L 1 bash -c 'log="logs/ris_sawyer_$3_G$5_s$6.log"
  "$1" dgrl_ris_sawyer.py --groups "$5" --seed "$6" --total-timesteps "$2" --exp-name "$3" --save-model $4 \
    $EXTRA > "$log" 2>&1
  tail -n 1 "$log"' _ "$PYTHON" "$STEPS" "$TAG" "$PRESET_FLAGS"
"$PYTHON" benchmark/plot.py --runs-dir runs --match "^SawyerPushAndReach__G.*__${TAG}__" --out "results/ris_sawyer_${TAG}" \
  --tags eval/hand_success_rate eval/success_rate eval/final_hand_distance eval/final_puck_distance losses/q_values \
  --title "Sawyer push-and-reach from pixels: RIS (G0) vs RIS+DGRL (G16), ${STEPS} steps"
