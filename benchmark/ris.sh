#!/usr/bin/env bash
# The RIS study (docs/dgrl_ris.md): RIS (--groups 0) against RIS+DGRL (--groups 16) on one env, JOBS runs at a time (one
# torch thread each on CPU), then curves and a table from the TensorBoard logs. The default is the CPU preset on
# PointMaze_UMaze-v3; ENV, STEPS, BATCH and EXTRA select other settings.
#   bash benchmark/ris.sh                                              # CPU preset: PointMaze U, 2 modes x 1 seed
#   SEEDS="1 2 3" bash benchmark/ris.sh                                # the same with 3 seeds
#   ENV=AntU STEPS=60000 BATCH=256 START=10000 EVAL_EVERY=5000 TAG=antu_cpu bash benchmark/ris.sh   # AntU on a CPU
#   ENV=AntMaze STEPS=5000000 BATCH=2048 START=10000 EVAL_EVERY=1000 EVAL_EPISODES=5 JOBS=1 TAG=paper EXTRA=--cuda \
#     bash benchmark/ris.sh                                            # the paper's setting, one run at a time on a GPU
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-.venv/bin/python}
ENV=${ENV:-PointMaze_UMaze-v3}
STEPS=${STEPS:-30000}
BATCH=${BATCH:-128}
START=${START:-2000}
EVAL_EVERY=${EVAL_EVERY:-2000}
EVAL_EPISODES=${EVAL_EPISODES:-10}
SEEDS=${SEEDS:-1}
GROUPS_LIST=${GROUPS_LIST:-"0 16"}
JOBS=${JOBS:-2}
TAG=${TAG:-cpu}
EXTRA=${EXTRA:-}
export OMP_NUM_THREADS=1 PYTHONUNBUFFERED=1  # one thread a run; logs readable while a run goes
mkdir -p logs
for seed in $SEEDS; do
  for groups in $GROUPS_LIST; do
    echo "$groups $seed"
  done
done | xargs -P "$JOBS" -L 1 bash -c 'log="logs/ris_$2_$3_G$9_s${10}.log"
  "$1" dgrl_ris.py --env-id "$2" --groups "$9" --seed "${10}" --total-timesteps "$4" --batch-size "$5" \
    --start-timesteps "$6" --eval-frequency "$7" --eval-episodes "$8" --exp-name "$3" --save-model $EXTRA > "$log" 2>&1
  tail -n 1 "$log"' _ "$PYTHON" "$ENV" "$TAG" "$STEPS" "$BATCH" "$START" "$EVAL_EVERY" "$EVAL_EPISODES"
"$PYTHON" benchmark/plot.py --runs-dir runs --match "${ENV}__G.*__${TAG}__" --out "results/ris_${ENV}_${TAG}" \
  --bins 15 --tags eval/success_rate eval/final_distance charts/success_rate charts/subgoal_distance \
  --title "${ENV}: RIS (G0) vs RIS+DGRL (G16), ${STEPS} steps, batch ${BATCH}"
