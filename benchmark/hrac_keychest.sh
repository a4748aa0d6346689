#!/usr/bin/env bash
# The Key-Chest study (docs/dgrl_hrac_keychest.md): HRAC (--groups 0) against DGRL with G = 4, 8, 16, each seed at the
# paper's 2M frames, JOBS runs at a time (one torch thread each), then curves and a table from the TensorBoard logs.
#   bash benchmark/hrac_keychest.sh                                   # the whole study: 12 runs (about 2.5 h on 2 cores)
#   SEEDS=1 GROUPS_LIST="0 16" TAG=cpu bash benchmark/hrac_keychest.sh  # the CPU runs of the docs (about 30 min)
#   JOBS=12 TAG=devstudy bash benchmark/hrac_keychest.sh              # all 12 at once on a 16-core machine
# Every run evaluates every 25,000 frames (--eval-frequency, the published 50 full-length episodes of 8 envs); the docs
# say which commit and machine made each published arm.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-.venv/bin/python}
FRAMES=${FRAMES:-2000000}
SEEDS=${SEEDS:-"1 2 3"}
GROUPS_LIST=${GROUPS_LIST:-"0 4 8 16"}
JOBS=${JOBS:-2}
TAG=${TAG:-study}
export OMP_NUM_THREADS=1 PYTHONUNBUFFERED=1  # one thread a run; logs readable while a run goes
mkdir -p logs
for seed in $SEEDS; do
  for groups in $GROUPS_LIST; do
    echo "$groups $seed"
  done
done | xargs -P "$JOBS" -L 1 bash -c 'log="logs/hrac_keychest_$3_G$4_s$5.log"
  "$1" dgrl_hrac_keychest.py --groups "$4" --seed "$5" --total-timesteps "$2" --threads 1 --save-model \
    --exp-name "$3" > "$log" 2>&1
  tail -n 1 "$log"' _ "$PYTHON" "$FRAMES" "$TAG"
"$PYTHON" benchmark/plot.py --runs-dir runs --match "__${TAG}__" --out "results/hrac_keychest_${TAG}" \
  --bins 20 --tags eval/return eval/return_random_subgoals eval/subgoal_reach_rate eval/subgoal_distance charts/adjacency_accuracy \
  --title "Key-Chest: HRAC (G0) vs HRAC+DGRL (G4, G8, G16), ${FRAMES} frames"
