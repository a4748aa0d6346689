#!/usr/bin/env bash
# The GPU check: one command, at most 9 minutes on one GPU, nothing downloaded.
#
#     bash benchmark/speed/gpu_check.sh                 # from the repository root, on a machine with a CUDA GPU
#     WHEELS=wheels/ GL_DEBS=debs/ bash benchmark/speed/gpu_check.sh   # offline: packages from local files first
#
# It needs the machine's python3 (PYTHON) with a CUDA build of torch, plus gymnasium, mujoco, minigrid, tyro and
# tensorboard (requirements.txt's versions). Where some are missing, `bash benchmark/speed/gpu_wheels.sh wheels/` on a
# networked machine downloads their wheels (and their dependencies'), for Python 3.12; pass that folder as WHEELS:
# they are installed with `pip --no-index --no-deps` into a temporary folder put on PYTHONPATH, and every requirement
# they declare is checked against what they and the machine have, before any measurement. A machine image without the
# EGL library (MuJoCo's headless rendering, which Sawyer's pixels need) takes Debian's libegl1, libglvnd0, libopengl0,
# libgl1, libglx0 and libgles2 packages as GL_DEBS=folder: they are unpacked into / (`dpkg -x`, then `ldconfig`; only
# with GL_DEBS: on a machine of your own install them with its package manager instead), and the NVIDIA driver's EGL
# vendor file is named if the loader does not find it. Everything else the check writes outside the repository (the
# wheels' packages, torch's compilation caches, the runs' folders) lies in a temporary folder removed at the end; in
# the repository it writes its figures to gpu_check.txt (LOG).
#
# Part 1 (BENCH_SECONDS, default 150): benchmark/speed/gpu_updates.py, training updates at their paper batch through
# --fast eager, compile and cudagraphs: milliseconds per update, the ratio to eager, and the largest relative difference
# of every parameter and optimizer state after 10 updates against eager on the GPU and against eager on the CPU. By
# default RIS's (batch 2048) and HRAC's two levels, with and without DGRL; UPDATE_CASES names others
# (`python benchmark/speed/gpu_updates.py --help` lists the 21), for a second run of the check. Part 2 (the rest),
# training steps/s of each paper command over SECONDS_PER_RUN (default 25) of wall clock after its first SKIP (default
# 20) seconds (start-up, warm-up, compilation), one command at a time, stopped by SIGINT (killed if it has not stopped STOP_WAIT, default 20, seconds
# later): RIS AntMaze G = 16 eager and cudagraphs and G = 0, Sawyer G = 16 (pixels through EGL), HRAC AntMazeSparse
# G = 16 and G = 0, Key-Chest and AMIGo KeyCorridorS3R3 (G = 16), with cudagraphs. The whole check keeps inside
# LIMIT_SECONDS (default 510; 0: no limit): a step is shortened to the time left, or skipped with a line saying so.
# It ends with one table of every figure. DEVICE=cpu tries it out on a machine without a GPU (eager and compile only);
# there the probes see mostly warm-up and compilation, so its figures mean nothing.
set -uo pipefail
cd "$(dirname "$0")/../.."
SECONDS_PER_RUN=${SECONDS_PER_RUN:-25}
SKIP=${SKIP:-20}
PYTHON=${PYTHON:-python3}
case $PYTHON in */*) PYTHON=$(cd "$(dirname "$PYTHON")" && pwd)/$(basename "$PYTHON") ;; esac  # the probes run elsewhere
LOG=${LOG:-gpu_check.txt}
DEVICE=${DEVICE:-cuda}  # DEVICE=cpu tries the script out on a machine without a GPU (eager and compile only)
BENCH_SECONDS=${BENCH_SECONDS:-150}
UPDATE_CASES=${UPDATE_CASES:-ris_G0 ris_G16 hrac_controller_G0 hrac_controller_G16 hrac_manager_G0 hrac_manager_G16}
STOP_WAIT=${STOP_WAIT:-20}
LIMIT_SECONDS=${LIMIT_SECONDS:-510}
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
trap 'rm -rf "$SCRATCH" 2>/dev/null || { sleep 2; rm -rf "$SCRATCH"; }' EXIT  # (a killed probe's child may still write)
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
if [ -n "${GL_DEBS:-}" ]; then  # the EGL and GL libraries, unpacked into / (a bare machine image lacks them)
    debs=("$GL_DEBS"/*.deb)
    [ -e "${debs[0]}" ] || { echo "gpu_check: GL_DEBS=$GL_DEBS holds no .deb packages"; exit 1; }
    for deb in "${debs[@]}"; do dpkg -x "$deb" / || { echo "gpu_check: dpkg -x $deb failed"; exit 1; }; done
    ldconfig
    vendor=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
    if [ -z "${__EGL_VENDOR_LIBRARY_FILENAMES:-}" ] && [ -e "$vendor" ] && ! ls /usr/share/glvnd/egl_vendor.d/*nvidia* >/dev/null 2>&1; then
        export __EGL_VENDOR_LIBRARY_FILENAMES=$vendor
    fi
    say "gpu_check: ${#debs[@]} packages of $GL_DEBS unpacked (EGL vendor file: ${__EGL_VENDOR_LIBRARY_FILENAMES:-found by the loader})"
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
# shellcheck disable=SC2086  # the case names are words
bench benchmark/speed/gpu_updates.py --device "$DEVICE" --paths $PATHS --out "$SCRATCH/updates.txt" --cases $UPDATE_CASES

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
probe "$PWD/dgrl_ris.py" --env-id AntMaze --groups 0 $RIS_PAPER --fast $BEST
probe "$PWD/dgrl_hrac.py" --env-id AntMazeSparse --groups 16 --fast $BEST
probe "$PWD/dgrl_hrac.py" --env-id AntMazeSparse --groups 0 --fast $BEST
probe "$PWD/dgrl_ris_sawyer.py" --groups 16 --eval-frequency 5000 --fast $BEST
probe "$PWD/dgrl_hrac_keychest.py" --groups 16 --fast $BEST
probe "$PWD/dgrl_amigo.py" --env-id MiniGrid-KeyCorridorS3R3-v0 --groups 16 --progress-frequency 50000 --fast $BEST

say "== table: every figure of this check (LOG=$LOG)"
"$PYTHON" - "$LOG" <<'TABLE' | tee -a "$LOG.table"
import re, sys
lines = open(sys.argv[1]).read().splitlines()
rows = [line for line in lines if line.startswith(("update ", "sps_probe:", "gpu_check: Python"))]
for line in rows:
    match = re.match(r"sps_probe: (\d+) steps/s .*?; \d+ s in all; (.*)", line)
    print(f"{match.group(1):>8} steps/s  {match.group(2)}" if match else line)
TABLE
cat "$LOG.table" >>"$LOG" && rm -f "$LOG.table"

say "gpu_check: $(( $(date +%s) - started )) s in all"
