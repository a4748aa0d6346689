#!/usr/bin/env bash
# The AMIGo study (docs/dgrl_amigo.md): AMIGo (--groups 0) against AMIGo+DGRL (G = 8, 16) on one MiniGrid env, JOBS runs
# at a time (one torch thread each), then curves and a table from the TensorBoard logs. The default is the scaled-down
# CPU study's DoorKey-5x5 arm; ENV and FRAMES select the others.
#   bash benchmark/amigo.sh                                                       # DoorKey-5x5, 1M frames, 3 seeds
#   ENV=MiniGrid-KeyCorridorS3R1-v0 bash benchmark/amigo.sh                      # KeyCorridorS3R1, 1M frames, 3 seeds
#   ENV=MiniGrid-KeyCorridorS3R1-v0 FRAMES=3000000 GROUPS_LIST="0 16" TAG=cpu3m bash benchmark/amigo.sh   # 3M frames
#   TAG=nochannel EXTRA=--no-goal-channel GROUPS_LIST="0 16" bash benchmark/amigo.sh   # the goal only through the encoder
#   ENV=MiniGrid-KeyCorridorS3R3-v0 FRAMES=30000000 JOBS=6 TAG=paper bash benchmark/amigo.sh   # KCmedium, the paper's budget
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-.venv/bin/python}
ENV=${ENV:-MiniGrid-DoorKey-5x5-v0}
FRAMES=${FRAMES:-1000000}
SEEDS=${SEEDS:-"1 2 3"}
GROUPS_LIST=${GROUPS_LIST:-"0 8 16"}
JOBS=${JOBS:-2}
TAG=${TAG:-cpu}
EXTRA=${EXTRA:-}
export OMP_NUM_THREADS=1 PYTHONUNBUFFERED=1  # one thread a run; logs readable while a run goes
mkdir -p logs
for seed in $SEEDS; do
  for groups in $GROUPS_LIST; do
    echo "$groups $seed"
  done
done | xargs -P "$JOBS" -L 1 bash -c 'log="logs/amigo_$2_$4_G$5_s$6.log"
  "$1" dgrl_amigo.py --env-id "$2" --groups "$5" --seed "$6" --total-timesteps "$3" --progress-frequency 50000 \
    --exp-name "$4" --save-model $EXTRA > "$log" 2>&1
  tail -n 1 "$log"' _ "$PYTHON" "$ENV" "$FRAMES" "$TAG"
"$PYTHON" benchmark/plot.py --runs-dir runs --match "${ENV}__G.*__${TAG}__" --out "results/amigo_${ENV}_${TAG}" \
  --bins 20 --tags charts/episodic_return charts/success_rate charts/goal_reach_rate teacher/t_star \
  --title "${ENV}: AMIGo (G0) vs AMIGo+DGRL (G8, G16), ${FRAMES} frames"
