#!/usr/bin/env bash
# The goal-DQN study behind docs/dgrl_goal_dqn.md: LoopWorld trained on K = 4 and 8 goals, SpiralWorld trained on
# K = 8 and 16 goals (and tested on 4 novel goals); G in {0 = continuous baseline, 4, 8, 16}; seeds 1, 2, 3.
# 48 runs of the default budget, two at a time on one thread each. Curves and tables go to docs/img/.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-.venv/bin/python}
export OMP_NUM_THREADS=1 PYTHON
tag="study$(date +%Y%m%d%H%M%S)"
mkdir -p "logs/$tag"
start=$(date +%s)
for seed in 1 2 3; do
  for setting in "LoopWorld 4" "LoopWorld 8" "SpiralWorld 8" "SpiralWorld 16"; do
    for groups in 0 4 8 16; do
      echo "$setting $groups $seed"
    done
  done
done | xargs -P 2 -L 1 sh -c \
  '"$PYTHON" dgrl_goal_dqn.py --env-id $0 --n-train-goals $1 --groups $2 --seed $3 --exp-name '"$tag"' \
     > logs/'"$tag"'/$0_K$1_G$2_s$3.log 2>&1 && tail -n 1 logs/'"$tag"'/$0_K$1_G$2_s$3.log | cut -c1-150'
echo "study: 48 runs in $(( $(date +%s) - start )) s of wall-clock"
"$PYTHON" benchmark/plot.py --runs-dir runs --match "^LoopWorld.*__${tag}__" --panel-by '^(LoopWorld__K\d+)' \
  --tags eval/train_success_rate eval/train_total_steps --out docs/img/goal_dqn_loopworld \
  --title "LoopWorld: greedy success and total steps on the K training goals (3 seeds)"
"$PYTHON" benchmark/plot.py --runs-dir runs --match "^SpiralWorld.*__${tag}__" --panel-by '^(SpiralWorld__K\d+)' \
  --tags eval/novel_success_rate eval/novel_total_steps eval/train_success_rate --out docs/img/goal_dqn_spiralworld \
  --title "SpiralWorld: 4 novel goals after training on K goals (3 seeds)"
"$PYTHON" benchmark/plot.py --runs-dir runs --match "__${tag}__" --panel-by '^([A-Za-z]+World__K\d+)' \
  --tags charts/bonus_distance_corr charts/bonus_step_closer charts/SPS --out docs/img/goal_dqn_bonus_and_speed \
  --title "Bonus quality after pre-training, and env steps/s"
