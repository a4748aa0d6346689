#!/usr/bin/env bash
# The GPU check: one command, at most 8 minutes on one GPU, nothing downloaded.
#
#     bash benchmark/gpu_check.sh                 # from the repository root, on a machine with a CUDA GPU
#     WHEELS=wheels/ bash benchmark/gpu_check.sh  # install missing packages from local wheel files first (offline)
#
# It needs the machine's python3 with a CUDA build of torch, plus gymnasium, gymnasium-robotics, mujoco, minigrid, tyro
# and tensorboard (requirements.txt's versions). Where some are missing, put their wheels (and their dependencies') in
# a folder and pass it as WHEELS: they are installed with `pip --no-index` into a temporary folder, nothing else changes.
#
# Part 1 (about 3 min), per-update time (median of 5 blocks, compilation and capture done first) at the paper's batch
# sizes through each speed path: --fast eager, compile (torch.compile, one graph) and cudagraphs (that graph replayed as
# one CUDA graph): RIS's update at batch 2048 (Ant sizes, G 0 and 16) and goal-DQN's TD update. The other scripts'
# benchmark/bench_*.py take the same --fast choices where they take --device. Part 2 (about 5 min), training steps/s of
# each paper-setting command over SECONDS_PER_RUN (default 45) of wall clock, after its first SKIP (default 25) seconds
# (start-up, warm-up, compilation), stopped cleanly by SIGINT:
# `python dgrl_ris.py --env-id AntMaze --groups 16` with eager and with cudagraphs, the other scripts' paper commands
# (each first run of its paper preset in benchmark/launch.py, with DGRL) with cudagraphs. Every line it prints is a
# figure for the docs' speed tables; it also writes them to gpu_check.txt. Tried out on the 2-core CPU with
# `PYTHON=.venv/bin/python DEVICE=cpu SECONDS_PER_RUN=40 SKIP=20 bash benchmark/gpu_check.sh`: it ran end to end in
# 466 s (on a CPU the probes see mostly warm-up and compilation, so its figures there mean nothing).
set -uo pipefail
cd "$(dirname "$0")/.."
SECONDS_PER_RUN=${SECONDS_PER_RUN:-45}
SKIP=${SKIP:-25}
PYTHON=${PYTHON:-python3}
LOG=${LOG:-gpu_check.txt}
DEVICE=${DEVICE:-cuda}  # DEVICE=cpu tries the script out on a machine without a GPU (eager and compile only)
PATHS="eager compile cudagraphs"
[ "$DEVICE" = cpu ] && PATHS="eager compile"
BEST=cudagraphs
[ "$DEVICE" = cpu ] && BEST=compile
export MUJOCO_GL=${MUJOCO_GL:-egl} PYTHONUNBUFFERED=1 OMP_NUM_THREADS=1
: >"$LOG"
say() { echo "$@" | tee -a "$LOG"; }
started=$(date +%s)

if [ -n "${WHEELS:-}" ]; then
    "$PYTHON" -m pip install -q --no-index --no-deps --no-compile --target /tmp/dgrl-gpu-site "$WHEELS"/*.whl || exit 1
    export PYTHONPATH=/tmp/dgrl-gpu-site${PYTHONPATH:+:$PYTHONPATH}
fi
DEVICE=$DEVICE "$PYTHON" - <<'EOF' || exit 1
import importlib.util, os, sys
import torch
missing = [name for name in ("gymnasium", "gymnasium_robotics", "mujoco", "minigrid", "tyro", "tensorboard")
           if importlib.util.find_spec(name) is None]
if missing:
    sys.exit(f"gpu_check: missing packages {missing}: install them, or pass their wheels as WHEELS=folder")
if os.environ["DEVICE"] == "cuda" and not torch.cuda.is_available():
    sys.exit(f"gpu_check: torch {torch.__version__} sees no CUDA device")
where = torch.cuda.get_device_name() if os.environ["DEVICE"] == "cuda" else "CPU"
print(f"gpu_check: torch {torch.__version__}, {where}, CUDA {torch.version.cuda}")
EOF
say "gpu_check: $(git rev-parse --short HEAD 2>/dev/null || echo 'no git') $(date -u +%FT%TZ)"

bench() {  # one benchmark script, its lines to the log
    timeout 180 "$PYTHON" "$@" 2>&1 | grep -E "^(update|learner|env|acting)" | tee -a "$LOG"
}
say "== part 1: one update, eager vs compile vs cudagraphs, paper batch sizes"
FAST="--fast $PATHS --device $DEVICE"
bench benchmark/bench_ris.py $FAST --no-envs --batches 2048 --goals ant
bench benchmark/bench_goal_dqn.py $FAST --only td

say "== part 2: steps/s of the paper commands, ${SECONDS_PER_RUN} s each"
probe() {
    "$PYTHON" benchmark/sps_probe.py --seconds "$SECONDS_PER_RUN" --skip "$SKIP" -- "$PYTHON" "$@" 2>&1 | tee -a "$LOG"
}
RIS_PAPER="--batch-size 2048 --start-timesteps 10000 --eval-frequency 1000 --eval-episodes 5"
probe "$PWD/dgrl_ris.py" --env-id AntMaze --groups 16 $RIS_PAPER --fast eager
probe "$PWD/dgrl_ris.py" --env-id AntMaze --groups 16 $RIS_PAPER --fast $BEST
probe "$PWD/dgrl_ris_sawyer.py" --groups 16 --eval-frequency 5000 --fast $BEST
probe "$PWD/dgrl_hrac.py" --env-id AntMazeSparse --groups 16 --fast $BEST
probe "$PWD/dgrl_hrac_keychest.py" --groups 16 --fast $BEST
probe "$PWD/dgrl_amigo.py" --env-id MiniGrid-KeyCorridorS3R3-v0 --groups 16 --progress-frequency 50000 --fast $BEST

say "gpu_check: $(( $(date +%s) - started )) s in all"
