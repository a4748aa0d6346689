"""One seeded run under the CPU's floating-point paths: is a run reproducible on another machine?

    python benchmark/analysis/float_paths.py
    python benchmark/analysis/float_paths.py --tag eval/novel_success_rate -- dgrl_goal_dqn.py --env-id SpiralWorld \\
        --groups 16 --seed 2 --n-train-goals 8

Runs the same seeded command (default: goal-DQN, LoopWorld, 4 training goals, G = 0, seed 1, one thread: one run of
the `goal-dqn` study, about a minute) three times, each in a fresh folder: as this machine runs it; with torch's own
kernels held to AVX2 (`ATEN_CPU_CAPABILITY=avx2`, what torch picks on a CPU without AVX-512); and with MKL's and
oneDNN's held to AVX2 as well (`MKL_ENABLE_INSTRUCTIONS`, `ONEDNN_MAX_CPU_ISA`). The code, the seed and the flags are
the same; only the order in which floating-point sums are taken differs, by a last bit here and there. It prints each
path's curve of TAG and its mean. On a machine with AVX-512 the three differ when a run amplifies its rounding (a
DQN's argmax, a replay drawn from what the policy did): a seeded run reproduces bit for bit only on a machine that
takes the same paths, and two studies of the same seeds on two kinds of machine are two draws of that noise.
"""

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from plot import load_runs, run_folders  # benchmark/analysis/plot.py

ROOT = Path(__file__).resolve().parents[2]
DEFAULT = ["dgrl_goal_dqn.py", "--env-id", "LoopWorld", "--groups", "0", "--seed", "1", "--n-train-goals", "4"]
PATHS = {
    "this machine's": {},
    "torch at AVX2": {"ATEN_CPU_CAPABILITY": "avx2"},
    "torch, MKL and oneDNN at AVX2": {
        "ATEN_CPU_CAPABILITY": "avx2",
        "MKL_ENABLE_INSTRUCTIONS": "AVX2",
        "ONEDNN_MAX_CPU_ISA": "AVX2",
    },
}


def curve(command: list[str], environment: dict[str, str], tag: str) -> list[float]:
    """Run the script's command in a fresh folder under the extra environment and return its curve of `tag`."""
    with tempfile.TemporaryDirectory() as folder:
        script, *flags = command
        argv = [sys.executable, str(ROOT / script), *flags, "--exp-name", "float-paths", "--threads", "1"]
        done = subprocess.run(argv, cwd=folder, env=dict(os.environ, **environment), capture_output=True, text=True)
        if done.returncode != 0:
            raise SystemExit(f"{' '.join(argv)} failed:\n{done.stderr[-2000:]}")
        runs = load_runs(run_folders(Path(folder) / "runs"), "", [tag])
        (seeds,) = runs.values()
        steps_values = seeds[0][tag]
        return [float(x) for x in steps_values[1]]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tag", default="eval/train_success_rate")
    parser.add_argument("command", nargs="*", help="the script and its flags (default: one goal-DQN run)")
    options = parser.parse_args()
    command = options.command or DEFAULT
    print(f"{' '.join(command)}; torch {torch.__version__}, CPU capability {torch.backends.cpu.get_cpu_capability()}")
    for name, environment in PATHS.items():
        values = curve(command, environment, options.tag)
        shown = ", ".join(f"{v:.3g}" for v in values)
        print(f"{name:>30}: mean {sum(values) / len(values):.4f} over {len(values)} evaluations; {shown}")


if __name__ == "__main__":
    main()
