#!/usr/bin/env bash
# The RIS study (docs/dgrl_ris.md): RIS (--groups 0) against RIS+DGRL (--groups 16; GROUPS_LIST picks others) on one
# env, JOBS runs at a time (one torch thread each on CPU), then curves and a table from the TensorBoard logs. The
# defaults are the CPU preset: ENV=PointMaze_UMaze-v3 STEPS=30000 BATCH=128 START=2000 EVAL_EVERY=2000 EVAL_EPISODES=10
# SEEDS=1; every variable below can be set on the command line. The runs of docs/dgrl_ris.md:
#   SEEDS="1 2 3" bash benchmark/ris.sh                                # the CPU preset, 3 seeds (the docs' table)
#   GROUPS_LIST="4 8" SEEDS=1 bash benchmark/ris.sh                    # G = 4 and G = 8, one seed
#   ENV=AntU STEPS=40000 BATCH=256 START=10000 EVAL_EVERY=5000 TAG=antu_cpu bash benchmark/ris.sh   # AntU on a CPU
# The paper's setting, one run at a time on a GPU (not run yet):
#   ENV=AntMaze STEPS=5000000 BATCH=2048 START=10000 EVAL_EVERY=1000 EVAL_EPISODES=5 JOBS=1 TAG=paper EXTRA=--cuda \
#     bash benchmark/ris.sh
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
  --title "${ENV}: RIS vs RIS+DGRL (G in ${GROUPS_LIST}), ${STEPS} steps, batch ${BATCH}"
