"""The seeded outputs of every script, baseline and DGRL: proof that a refactor changed no number.

    python benchmark/analysis/seeded_runs.py --out /tmp/after.pt                 # the 14 runs of the working tree
    python benchmark/analysis/seeded_runs.py --rev HEAD~1 --out /tmp/before.pt   # the same runs at another commit
    python benchmark/analysis/seeded_runs.py --compare /tmp/before.pt /tmp/after.pt
    python benchmark/analysis/seeded_runs.py --scripts dgrl_ris.py --out ris.pt  # some scripts only (also with --compare)

Each of the seven scripts runs twice, with `--groups 0` and with its DGRL default, on a small seeded budget that still
reaches every phase of its loop (the updates, an evaluation, the codebook's updates), with `--save-model`, one thread
and the eager update. What is kept of each run: every TensorBoard scalar, step by step (charts/SPS, which measures
time, left out), and every tensor of the final checkpoint. `--rev` runs the scripts of a commit from a temporary git
worktree, with this interpreter. `--compare A B` prints, per run, the tags and tensors that differ (or IDENTICAL) and
exits 1 when any run differs; equality is exact (bit for bit, NaN equal to NaN).
"""

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tests"))
# tests/conftest.py: what the resume tests compare, compared here the same way
from conftest import WALL_CLOCK_TAGS, checkpoint_tensors, tensorboard_scalars  # noqa: E402

# (script, DGRL's groups, the small seeded budget): the smoke budgets of tests/, grown where a phase was not reached.
RUNS = {
    "dgrl_mnist.py": (2, "--epochs 1 --train-size 1000 --classifier-epochs 1 --n-swap-pairs 200 --hidden-dim 64"),
    "dgrl_goal_dqn.py": (
        4,
        "--total-timesteps 400 --learning-starts 100 --rep-steps 5 --rep-transitions 500 --eval-frequency 200 "
        "--batch-size 16 --buffer-size 1000 --max-episode-steps 30",
    ),
    "dgrl_hrac.py": (
        16,
        "--total-timesteps 60 --ctrl-updates 4 --man-updates 2 --batch-size 8 --eval-episodes 1 --adj-frequency 20 "
        "--adj-epochs 1 --hidden-dim 32",
    ),
    "dgrl_hrac_keychest.py": (
        16,
        "--total-timesteps 3000 --num-envs 4 --max-episode-steps 100 --adj-init-steps 800 --adj-init-epochs 1 "
        "--adj-frequency 1200 --adj-epochs 1 --man-buffer-size 200 --eval-frequency 400 --log-frequency 400 "
        "--eval-episodes 4 --hidden-dim 32 --ae-init-steps 5",
    ),
    "dgrl_ris.py": (
        16,
        "--env-id AntU --total-timesteps 1200 --start-timesteps 100 --batch-size 32 --eval-frequency 600 "
        "--eval-episodes 2 --max-episode-steps 50 --buffer-size 10000 --hidden-dim 32",
    ),
    "dgrl_ris_sawyer.py": (
        16,
        "--total-timesteps 300 --start-timesteps 100 --batch-size 16 --eval-frequency 300 --eval-episodes 2 "
        "--buffer-size 1000",
    ),
    "dgrl_amigo.py": (
        16,
        "--env-id MiniGrid-DoorKey-5x5-v0 --num-envs 10 --batch-envs 1 --num-steps 8 --total-timesteps 2400 "
        "--progress-frequency 80 --teacher-batch-size 1",
    ),
}


def run_outputs(source: Path, script: str, groups: int, budget: str, workdir: Path) -> dict:
    """Run one script from `source` in `workdir` and return its scalars and checkpoint tensors."""
    flags = [*budget.split(), "--groups", str(groups), "--seed", "1", "--threads", "1", "--save-model", "--exp-name", "seeded"]
    env = {"PATH": os.environ["PATH"], "PYTHONPATH": str(source), "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg"}
    env |= {key: os.environ[key] for key in ("MUJOCO_GL", "HOME") if key in os.environ}
    result = subprocess.run(
        [sys.executable, str(source / script), *flags], cwd=workdir, env=env, capture_output=True, text=True
    )
    if result.returncode != 0:
        raise SystemExit(f"{script} --groups {groups} failed (exit {result.returncode}):\n{result.stderr[-3000:]}")
    (run_dir,) = (workdir / "runs").iterdir()
    scalars = {tag: points for tag, points in tensorboard_scalars(run_dir).items() if tag not in WALL_CLOCK_TAGS}
    (checkpoint,) = run_dir.glob("*.cleanrl_model")
    return {"scalars": scalars, "tensors": checkpoint_tensors(checkpoint)}


def collect(source: Path, scripts: list[str]) -> dict:
    outputs = {}
    for script in scripts:
        dgrl_groups, budget = RUNS[script]
        for groups in (0, dgrl_groups):
            with tempfile.TemporaryDirectory() as workdir:
                outputs[f"{script} --groups {groups}"] = run_outputs(source, script, groups, budget, Path(workdir))
            print(f"{script} --groups {groups}: {len(outputs[f'{script} --groups {groups}']['scalars'])} tags", flush=True)
    return outputs


def same_tensor(a: torch.Tensor, b: torch.Tensor) -> bool:
    """Bit for bit, NaN equal to NaN."""
    if a.shape != b.shape or a.dtype != b.dtype:
        return False
    if not a.is_floating_point():
        return torch.equal(a, b)
    return bool(((a == b) | (a.isnan() & b.isnan())).all())


def differences(before: dict, after: dict) -> list[str]:
    """What differs between two runs' outputs, one line each."""
    problems = []
    for kind in ("scalars", "tensors"):
        for name in sorted(set(before[kind]) | set(after[kind])):
            if name not in before[kind] or name not in after[kind]:
                problems.append(f"{kind[:-1]} {name} only {'after' if name in after[kind] else 'before'}")
            elif kind == "scalars" and before[kind][name] != after[kind][name]:
                problems.append(f"scalar {name} differs: {before[kind][name][:3]}... against {after[kind][name][:3]}...")
            elif kind == "tensors" and not same_tensor(before[kind][name], after[kind][name]):
                problems.append(f"tensor {name} differs")
    return problems


def compare(before_path: str, after_path: str, scripts: list[str] | None = None) -> int:
    """Print each run's verdict; 1 when a run differs or is in one file only (of `scripts`' runs, if given), else 0."""
    before, after = torch.load(before_path, weights_only=False), torch.load(after_path, weights_only=False)
    failed = False
    for run in sorted(set(before) | set(after)):
        if scripts is not None and run.split()[0] not in scripts:
            continue
        if run not in before or run not in after:
            print(f"{run}: only in {before_path if run in before else after_path}")
            failed = True
            continue
        problems = differences(before[run], after[run])
        counts = f"{len(after[run]['scalars'])} tags, {len(after[run]['tensors'])} tensors"
        print(f"{run}: " + ("IDENTICAL" if not problems else "DIFFERENT") + f" ({counts})")
        for problem in problems[:10]:
            print(f"    {problem}")
        failed |= bool(problems)
    return 1 if failed else 0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", help="where to write the outputs (a torch file)")
    parser.add_argument("--rev", help="run the scripts of this commit (a temporary git worktree) instead of the tree's")
    parser.add_argument("--scripts", nargs="+", choices=list(RUNS), metavar="SCRIPT", help="these scripts only (default: all)")
    parser.add_argument("--compare", nargs=2, metavar=("BEFORE", "AFTER"), help="compare two --out files")
    args = parser.parse_args()
    if args.compare:
        missing = [path for path in args.compare if not os.path.isfile(path)]
        if missing:
            parser.error(f"--compare: no such file: {', '.join(missing)} (write it with --out first)")
        raise SystemExit(compare(*args.compare, args.scripts))
    if not args.out:
        parser.error("--out is needed to run the scripts (or --compare BEFORE AFTER)")
    os.environ.setdefault("MUJOCO_GL", "egl")
    if args.rev is None:
        outputs = collect(ROOT, args.scripts or list(RUNS))
    else:
        with tempfile.TemporaryDirectory() as folder:
            tree = Path(folder) / "tree"
            subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(tree), args.rev], check=True)
            try:
                outputs = collect(tree, args.scripts or list(RUNS))
            finally:
                subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(tree)], check=True)
    torch.save(outputs, args.out)
    print(f"{len(outputs)} runs written to {args.out}")


if __name__ == "__main__":
    main()
