#!/usr/bin/env bash
# The HRAC study (docs/dgrl_hrac.md): HRAC (--groups 0) against HRAC+DGRL (--groups 16) on one HIRO Ant env, JOBS runs
# at a time (one torch thread each), then curves and a table from the TensorBoard logs. The default is the short CPU
# run on AntMaze; ENV, STEPS and THREADS select the others (the paper's budget is 5M steps, a GPU job).
#   bash benchmark/hrac.sh                                                   # AntMaze, 300k steps, seed 1, G0 and G16
#   ENV=AntPush STEPS=50000 bash benchmark/hrac.sh                           # a shorter AntPush run
#   STEPS=5000000 SEEDS="1 2 3" JOBS=6 TAG=paper bash benchmark/hrac.sh      # the paper's budget (GPU machine)
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-.venv/bin/python}
ENV=${ENV:-AntMaze}
STEPS=${STEPS:-300000}
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
done | xargs -P "$JOBS" -L 1 bash -c 'log="logs/hrac_$2_$4_G$5_s$6.log"
  "$1" dgrl_hrac.py --env-id "$2" --groups "$5" --seed "$6" --total-timesteps "$3" --exp-name "$4" --save-model \
    $EXTRA > "$log" 2>&1
  tail -n 1 "$log"' _ "$PYTHON" "$ENV" "$STEPS" "$TAG"
"$PYTHON" benchmark/plot.py --runs-dir runs --match "^${ENV}__G.*__${TAG}__" --out "results/hrac_${ENV}_${TAG}" \
  --tags eval/final_distance eval/success_rate charts/final_distance charts/subgoal_distance charts/controller_reward \
  --title "${ENV}: HRAC (G0) vs HRAC+DGRL (G16), ${STEPS} steps"
