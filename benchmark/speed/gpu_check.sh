#!/usr/bin/env bash
# The GPU check: one command, at most 8 minutes on one GPU, nothing downloaded.
#
#     bash benchmark/speed/gpu_check.sh                 # from the repository root, on a machine with a CUDA GPU
#     WHEELS=wheels/ bash benchmark/speed/gpu_check.sh  # install missing packages from local wheel files first (offline)
#
# It needs the machine's python3 (PYTHON) with a CUDA build of torch, plus gymnasium, mujoco, minigrid, tyro and
# tensorboard (requirements.txt's versions). Where some are missing, `bash benchmark/speed/gpu_wheels.sh wheels/` on a
# networked machine downloads their wheels (and their dependencies'), for Python 3.12; pass that folder as WHEELS:
# they are installed with `pip --no-index --no-deps` into a temporary folder put on PYTHONPATH, and every requirement
# they declare is checked against what they and the machine have, before any measurement. Everything the check writes
# outside the repository (those packages, torch's compilation caches, the runs' folders) lies in that temporary folder,
# removed at the end; in the repository it writes its figures to gpu_check.txt (LOG).
#
# Part 1 (about 3 min), per-update time (median of 5 blocks, compilation and capture done first) at the paper's batch
# sizes through each speed path: --fast eager, compile (torch.compile, one graph) and cudagraphs (that graph replayed as
# one CUDA graph): RIS's update at batch 2048 (Ant sizes, G 0 and 16) and goal-DQN's TD update, each benchmark stopped
# after BENCH_SECONDS (default 180). The other scripts' benchmark/speed/bench_*.py take the same --fast choices where they
# take --device. Part 2 (about 5 min), training steps/s of each paper-setting command over SECONDS_PER_RUN (default
# 45) of wall clock, after its first SKIP (default 25) seconds (start-up, warm-up, compilation), stopped by SIGINT
# (killed if it has not stopped STOP_WAIT, default 30, seconds later):
# `python dgrl_ris.py --env-id AntMaze --groups 16` with eager and with cudagraphs, the other scripts' paper commands
# (each first run of its paper preset in benchmark/presets.py, with DGRL) with cudagraphs. The whole check keeps inside
# LIMIT_SECONDS (default 450; 0: no limit): a step is shortened to the time left, or skipped with a line saying so.
# Every line it prints is a figure for the docs' speed tables. DEVICE=cpu tries it out on a machine without a GPU;
# there the probes see mostly warm-up and compilation, so its figures mean nothing. Tried out on the 2-core CPU
# (docs/launch.md, "The GPU check on an offline GPU machine", has the commands and times): with the project's
# Python 3.11 venv and torch 2.13.0, and with Python 3.12 and torch 2.11.0 alone plus the wheels of gpu_wheels.sh.
set -uo pipefail
cd "$(dirname "$0")/../.."
SECONDS_PER_RUN=${SECONDS_PER_RUN:-45}
SKIP=${SKIP:-25}
PYTHON=${PYTHON:-python3}
LOG=${LOG:-gpu_check.txt}
DEVICE=${DEVICE:-cuda}  # DEVICE=cpu tries the script out on a machine without a GPU (eager and compile only)
BENCH_SECONDS=${BENCH_SECONDS:-180}
STOP_WAIT=${STOP_WAIT:-30}
LIMIT_SECONDS=${LIMIT_SECONDS:-450}
[ "$DEVICE" = cuda ] || [ "$DEVICE" = cpu ] || { echo "gpu_check: DEVICE=$DEVICE: cuda or cpu"; exit 2; }
for name in SECONDS_PER_RUN SKIP BENCH_SECONDS STOP_WAIT LIMIT_SECONDS; do
    [[ "${!name}" =~ ^[0-9]+$ ]] || { echo "gpu_check: $name=${!name}: a whole number of seconds"; exit 2; }
done
PATHS="eager compile cudagraphs"
[ "$DEVICE" = cpu ] && PATHS="eager compile"
BEST=cudagraphs
[ "$DEVICE" = cpu ] && BEST=compile
GL_CHOSEN=${MUJOCO_GL:+yes}  # a MUJOCO_GL of the caller's is kept as it is
export MUJOCO_GL=${MUJOCO_GL:-egl} PYTHONUNBUFFERED=1 OMP_NUM_THREADS=1
: >"$LOG"
say() { echo "$@" | tee -a "$LOG"; }
started=$(date +%s)

# Everything this check writes outside the repository goes into one temporary folder, removed at the end: the machine
# is left as it was. TMPDIR too: torch keeps its precompiled C++ headers in the temporary folder whatever
# TORCHINDUCTOR_CACHE_DIR says. Triton's home (~/.triton) and CUDA's kernel cache (~/.nv) are moved there as well.
SCRATCH=$(mktemp -d "${TMPDIR:-/tmp}/dgrl-gpu-check.XXXXXX") || exit 1
trap 'rm -rf "$SCRATCH"' EXIT
mkdir -p "$SCRATCH/tmp"
export TMPDIR=$SCRATCH/tmp
export TORCHINDUCTOR_CACHE_DIR=${TORCHINDUCTOR_CACHE_DIR:-$SCRATCH/inductor}
export TRITON_HOME=${TRITON_HOME:-$SCRATCH} TRITON_CACHE_DIR=${TRITON_CACHE_DIR:-$SCRATCH/triton}
export CUDA_CACHE_PATH=${CUDA_CACHE_PATH:-$SCRATCH/nv}
SITE=
if [ -n "${WHEELS:-}" ]; then
    wheels=("$WHEELS"/*.whl)
    [ -e "${wheels[0]}" ] || { echo "gpu_check: WHEELS=$WHEELS holds no wheels (benchmark/speed/gpu_wheels.sh makes them)"; exit 1; }
    SITE=$SCRATCH/site
    wheels_started=$(date +%s)
    "$PYTHON" -m pip install -q --disable-pip-version-check --no-cache-dir --no-index --no-deps --no-compile \
        --target "$SITE" "${wheels[@]}" || { echo "gpu_check: pip could not install the wheels of $WHEELS"; exit 1; }
    say "gpu_check: ${#wheels[@]} wheels of $WHEELS installed into $SITE in $(( $(date +%s) - wheels_started )) s"
    export PYTHONPATH=$SITE${PYTHONPATH:+:$PYTHONPATH}
fi
# A machine without the EGL library fails at `import mujoco` itself with MUJOCO_GL=egl (mujoco's EGL module raises an
# AttributeError from PyOpenGL, which mujoco does not catch): every MuJoCo script would crash. glfw imports without a
# display and steps MuJoCo; it cannot render, so the Sawyer probe (pixel observations) fails and says so.
if [ -z "$GL_CHOSEN" ] && ! "$PYTHON" -c "import mujoco" >/dev/null 2>&1 && MUJOCO_GL=glfw "$PYTHON" -c "import mujoco" 2>/dev/null; then
    export MUJOCO_GL=glfw
    say "gpu_check: import mujoco fails with MUJOCO_GL=egl (no EGL library?): MUJOCO_GL=glfw, which cannot render (no Sawyer figure)"
fi
DEVICE=$DEVICE SITE=$SITE "$PYTHON" - <<'EOF' | tee -a "$LOG" || exit 1
import importlib.metadata as metadata, importlib.util, os, sys
import torch
try:
    from packaging.requirements import Requirement
except ImportError:
    from pip._vendor.packaging.requirements import Requirement
needed = ("gymnasium", "mujoco", "minigrid", "tyro", "tensorboard")  # what the check's scripts import
missing = [name for name in needed if importlib.util.find_spec(name) is None]
if missing:
    sys.exit(f"gpu_check: missing packages {missing}: install them, or pass their wheels as WHEELS=folder")
if os.environ["SITE"]:  # every requirement of what the wheels installed, met by them or by the machine's packages
    # but those of requirements-nodeps.txt, which the project installs without their declared dependencies
    nodeps = {Requirement(line.strip()).name.lower() for line in open("requirements-nodeps.txt") if line[:1].isalnum()}
    installed = metadata.distributions(path=[os.environ["SITE"]])
    unmet, todo, done = set(), [(dist, "") for dist in installed if dist.metadata["Name"].lower() not in nodeps], set()
    while todo:
        dist, extra = todo.pop()
        for line in dist.requires or []:
            requirement = Requirement(line)
            if requirement.marker and not requirement.marker.evaluate({"extra": extra}):
                continue
            needs = f"{dist.metadata['Name']}{f'[{extra}]' if extra else ''} needs {requirement.name}{requirement.specifier}"
            try:
                found = metadata.distribution(requirement.name)
            except metadata.PackageNotFoundError:
                unmet.add(f"{needs}, which is not installed")
                continue
            if not requirement.specifier.contains(found.version, prereleases=True):
                unmet.add(f"{needs}, the machine has {found.version}")
            for wanted in requirement.extras:
                if (requirement.name, wanted) not in done:
                    done.add((requirement.name, wanted))
                    todo.append((found, wanted))
    if unmet:
        sys.exit("gpu_check: " + "; ".join(sorted(unmet)) + " (add its wheel: benchmark/speed/gpu_wheels.sh DIR NAME==VERSION)")
for name in needed:
    importlib.import_module(name)  # a broken package fails here, before any measurement
if os.environ["DEVICE"] == "cuda" and not torch.cuda.is_available():
    sys.exit(f"gpu_check: torch {torch.__version__} sees no CUDA device")
where = torch.cuda.get_device_name() if os.environ["DEVICE"] == "cuda" else "CPU"
versions = ", ".join(f"{name} {metadata.version(name)}" for name in needed)
print(f"gpu_check: Python {sys.version.split()[0]}, torch {torch.__version__}, {where}, CUDA {torch.version.cuda}; {versions}")
EOF
say "gpu_check: $(git rev-parse --short HEAD 2>/dev/null || echo 'no git') $(date -u +%FT%TZ)"

left() {  # seconds of LIMIT_SECONDS left, less $1 (a large number without a limit)
    [ "$LIMIT_SECONDS" = 0 ] && { echo 1000000; return; }
    echo $(( LIMIT_SECONDS - ($(date +%s) - started) - $1 ))
}
bench() {  # one benchmark script, its figures to the log; a failure or a time-out says so
    local limit=$BENCH_SECONDS rc
    [ "$(left 0)" -lt 30 ] && { say "gpu_check: skipped $1: less than 30 s of LIMIT_SECONDS=$LIMIT_SECONDS left"; return; }
    [ "$(left 0)" -lt "$limit" ] && limit=$(left 0)
    timeout "$limit" "$PYTHON" "$@" >"$SCRATCH/bench.txt" 2>&1
    rc=$?
    grep -E "^(update|learner|env|acting)" "$SCRATCH/bench.txt" | tee -a "$LOG"
    if [ $rc = 124 ]; then
        say "gpu_check: $1 stopped after $limit s (BENCH_SECONDS=$BENCH_SECONDS, LIMIT_SECONDS=$LIMIT_SECONDS)"
    elif [ $rc != 0 ]; then
        say "gpu_check: $1 failed with exit status $rc; its last lines:"
        tail -n 20 "$SCRATCH/bench.txt" | sed 's/^/  /' | tee -a "$LOG"
    fi
}
say "== part 1: one update, eager vs compile vs cudagraphs, paper batch sizes"
FAST="--fast $PATHS --device $DEVICE"
bench benchmark/speed/bench_ris.py $FAST --no-envs --batches 2048 --goals ant
bench benchmark/speed/bench_goal_dqn.py $FAST --only td

say "== part 2: steps/s of the paper commands, ${SECONDS_PER_RUN} s each"
probe() {
    local seconds=$SECONDS_PER_RUN room
    room=$(left $((STOP_WAIT + 5)))
    if [ "$room" -lt $((SKIP + 10)) ]; then
        say "gpu_check: skipped ${1##*/} ${*:2}: too little of LIMIT_SECONDS=$LIMIT_SECONDS left"
        return
    fi
    [ "$room" -lt "$seconds" ] && seconds=$room
    "$PYTHON" benchmark/speed/sps_probe.py --seconds "$seconds" --skip "$SKIP" --stop-wait "$STOP_WAIT" -- "$PYTHON" "$@" 2>&1 |
        tee -a "$LOG"
}
RIS_PAPER="--batch-size 2048 --start-timesteps 10000 --eval-frequency 1000 --eval-episodes 5"
probe "$PWD/dgrl_ris.py" --env-id AntMaze --groups 16 $RIS_PAPER --fast eager
probe "$PWD/dgrl_ris.py" --env-id AntMaze --groups 16 $RIS_PAPER --fast $BEST
probe "$PWD/dgrl_ris_sawyer.py" --groups 16 --eval-frequency 5000 --fast $BEST
probe "$PWD/dgrl_hrac.py" --env-id AntMazeSparse --groups 16 --fast $BEST
probe "$PWD/dgrl_hrac_keychest.py" --groups 16 --fast $BEST
probe "$PWD/dgrl_amigo.py" --env-id MiniGrid-KeyCorridorS3R3-v0 --groups 16 --progress-frequency 50000 --fast $BEST

say "gpu_check: $(( $(date +%s) - started )) s in all"
