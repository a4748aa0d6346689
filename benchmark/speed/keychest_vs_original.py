"""Speed of dgrl_hrac_keychest.py against the original HRAC code's Key-Chest ("discrete") experiment, side by side.

    python benchmark/speed/keychest_vs_original.py --original /tmp/hrac_orig/discrete --seconds 900
    python benchmark/speed/keychest_vs_original.py --original /tmp/hrac_orig/discrete --seconds 900 --fast eager compile

Starts the original and ours (one run per --groups x --fast choice) at the same time, as subprocesses with one thread
each (OMP_NUM_THREADS=1 and MKL_NUM_THREADS=1; ours also gets `--threads 1` from the preset), lets them run --seconds,
stops them, and prints each one's frames per CPU-second and ours / original. Running them together gives them the same
machine load; counting CPU seconds (utime + stime of each process tree, from /proc, reaped children included: the
compile workers of --fast compile count too) rather than wall time makes the figures hold on a shared machine.

Our command is the Key-Chest preset's per-run command (`benchmark/launch.py --preset keychest --dry-run`, read from it
for the chosen --groups and --seed) plus `--fast`. The original runs `python -u main.py --env_name KeyChest --seed S`
at its defaults. Each process runs in its own folder under --workdir (the original writes output/, ours runs/), and its
output goes to a log there.

Phases. Both spend their first 50k frames exploring with uniform random subgoals (no learning), then train the
adjacency network (50 epochs), then act with uniform random subgoals until the high level's replay holds 10k of its 20k
k-step transitions (about 100k more frames): both levels train from about 150k frames on, in both. The rate is taken
between two progress points, each process's first one at or after --start-frames (default 200k: past that warm-up and
past the first updates, where --fast compile compiles) and its last one before the stop: frames done / CPU seconds
spent between them. Progress points are the original's per-episode "Frames N" lines and our progress lines (one per
evaluation, every 25k frames; one a minute otherwise). Both retrain the adjacency network every 50k frames and evaluate
on their own cadence (the original 50 episodes every 50 training episodes, ours 2 x 50 every 25k frames); those costs are
part of each one's rate. A second figure uses the common frame window (from --start-frames to the frames the slower one
reached), so both are measured over the same stretch of training. --pretrain-epochs shortens the warm-up (the first
adjacency training) of both alike; it is outside the measured window.

Getting the original: the HRAC repository, https://github.com/trzhang0116/HRAC (Zhang et al., NeurIPS 2020), folder
`discrete/` (main.py, solver.py, agent.py, env.py, memory.py, metric.py, model.py, utils.py); keep it outside this
project. To run on today's stack (torch 2.x CPU, NumPy 2, gymnasium, no CUDA) it needs three small patches:
- agent.py: the device is hard-coded to `cuda:{gid}`; use the CPU when CUDA is not available.
- agent.py: `import pandas` at the top (used only to write the final CSV); import it where it is used, or install pandas.
- env.py: `from gym import spaces` -> `from gymnasium import spaces` (old gym does not install), and `np.Inf` ->
  `np.inf` (removed in NumPy 2).
Nothing else changes; its hyper-parameters are the defaults of its main.py (the Key-Chest ones).
"""

from __future__ import annotations

import argparse
import os
import re
import shlex
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
CLOCK_TICKS = os.sysconf("SC_CLK_TCK")
ORIGINAL_PROGRESS = re.compile(r"^\s*Frames (\d+), Episode #")  # the original's log_train, after every episode
OURS_PROGRESS = re.compile(r"^frame\s+(\d+)/\d+")  # Progress.line (heartbeats too)


def process_tree_cpu_seconds(root_pid: int) -> float:
    """utime + stime of `root_pid` and its live descendants, plus the cutime + cstime of each (children they reaped)."""
    parents, times = {}, {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            stat = Path(f"/proc/{entry}/stat").read_text()
        except OSError:  # gone meanwhile
            continue
        fields = stat[stat.rindex(")") + 2 :].split()  # after "pid (comm) ": state, ppid, ... (man 5 proc)
        parents[int(entry)] = int(fields[1])
        times[int(entry)] = sum(int(value) for value in fields[11:15])  # utime stime cutime cstime
    tree, frontier = {root_pid}, [root_pid]
    while frontier:
        parent = frontier.pop()
        children = [pid for pid, ppid in parents.items() if ppid == parent and pid not in tree]
        tree.update(children)
        frontier.extend(children)
    return sum(times.get(pid, 0) for pid in tree) / CLOCK_TICKS


@dataclass
class Run:
    """One training process: its command, its progress points (frames, CPU seconds of its tree, wall seconds)."""

    name: str
    command: list[str]
    folder: Path
    progress: re.Pattern
    points: list[tuple[int, float, float]] = field(default_factory=list)
    process: subprocess.Popen | None = None
    final_cpu: float = 0.0

    def start(self, env: dict, start_time: float) -> None:
        self.folder.mkdir(parents=True, exist_ok=True)
        log = open(self.folder / "log.txt", "w", buffering=1)  # line by line; closed by the reader thread
        log.write(shlex.join(self.command) + "\n")
        self.process = subprocess.Popen(
            self.command,
            cwd=self.folder,
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            bufsize=1,
            start_new_session=True,  # its own process group, stopped as a whole
        )
        threading.Thread(target=self._read, args=(log, start_time), daemon=True).start()

    def _read(self, log, start_time: float) -> None:
        for line in self.process.stdout:
            log.write(line)
            match = self.progress.match(line)
            if match:
                cpu = process_tree_cpu_seconds(self.process.pid)
                self.points.append((int(match.group(1)), cpu, time.time() - start_time))
        log.close()

    def stop(self) -> None:
        self.final_cpu = process_tree_cpu_seconds(self.process.pid)
        if self.process.poll() is None:
            os.killpg(self.process.pid, signal.SIGTERM)  # ours saves its resume file and exits
            try:
                self.process.wait(30)
            except subprocess.TimeoutExpired:
                os.killpg(self.process.pid, signal.SIGKILL)
                self.process.wait()

    def rate(self, first_frame: int, last_frame: int | None = None) -> tuple[float, int, int, float] | None:
        """Frames per CPU second between the first point at or after `first_frame` and the last point at or before
        `last_frame` (or the last point): (rate, frame from, frame to, CPU seconds); None without two such points."""
        inside = [p for p in self.points if p[0] >= first_frame and (last_frame is None or p[0] <= last_frame)]
        if len(inside) < 2 or inside[-1][1] <= inside[0][1]:
            return None
        (frame_a, cpu_a, _), (frame_b, cpu_b, _) = inside[0], inside[-1]
        return (frame_b - frame_a) / (cpu_b - cpu_a), frame_a, frame_b, cpu_b - cpu_a


def preset_command(groups: int, seed: int) -> list[str]:
    """Our per-run command of the Key-Chest preset, as benchmark/launch.py --preset keychest --dry-run prints it."""
    dry_run = subprocess.run(
        [sys.executable, str(ROOT / "benchmark" / "launch.py"), "--preset", "keychest", "--dry-run"],
        capture_output=True,
        text=True,
        check=True,
        cwd=ROOT,
    ).stdout
    for line in dry_run.splitlines():
        run_id, _, shell = line.partition(": ")
        if run_id.endswith(f"__G{groups}__s{seed}"):
            return shlex.split(shell.split(" && ", 1)[1])  # without its `cd` into the sweep folder
    raise SystemExit(f"no run G{groups} seed {seed} in the keychest preset; its runs:\n{dry_run}")


def describe(run: Run, figure: tuple[float, int, int, float] | None) -> str:
    if figure is None:
        reached = run.points[-1][0] if run.points else 0
        return f"{run.name:<22} fewer than two progress points in the window (reached frame {reached})"
    rate, frame_a, frame_b, cpu = figure
    return f"{run.name:<22} {rate:7.0f} frames/CPU-s  (frames {frame_a}-{frame_b}, {cpu:.1f} CPU-s)"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    parser.add_argument("--original", type=Path, required=True, help="the original's discrete/ folder (patched)")
    parser.add_argument("--seconds", type=float, default=900, help="wall seconds to let them run")
    parser.add_argument("--fast", nargs="+", default=["eager"], choices=["eager", "compile"], help="our --fast path(s)")
    parser.add_argument("--groups", nargs="+", type=int, default=[0], help="our G (0: HRAC; the preset has 0 4 8 16)")
    parser.add_argument("--seed", type=int, default=1, help="seed of every run (the preset has 1 2 3)")
    parser.add_argument("--start-frames", type=int, default=200_000, help="measure from this frame on (after warm-ups)")
    parser.add_argument("--pretrain-epochs", type=int, default=None, help="first adjacency training's epochs, both")
    parser.add_argument("--python", default=sys.executable, help="the Python of both (torch, gymnasium, tensorboard)")
    parser.add_argument("--workdir", type=Path, default=None, help="folder of the runs (default: a new temporary one)")
    args = parser.parse_args()

    original_main = args.original.resolve() / "main.py"
    if not original_main.is_file():
        raise SystemExit(f"{original_main} not found: --original is the HRAC repository's discrete/ folder")
    workdir = args.workdir or Path(tempfile.mkdtemp(prefix="keychest_vs_original_"))
    original_command = [args.python, "-u", str(original_main), "--env_name", "KeyChest", "--seed", str(args.seed)]
    if args.pretrain_epochs is not None:
        original_command += ["--r_init_epochs", str(args.pretrain_epochs)]
    runs = [Run("original HRAC", original_command, workdir / "original", ORIGINAL_PROGRESS)]
    for groups in args.groups:
        ours = preset_command(groups, args.seed)
        ours[0] = args.python
        if args.pretrain_epochs is not None:
            ours += ["--adj-init-epochs", str(args.pretrain_epochs)]
        for fast in args.fast:
            command = [*ours, "--fast", fast]
            runs.append(Run(f"ours G{groups} --fast {fast}", command, workdir / f"ours_G{groups}_{fast}", OURS_PROGRESS))

    env = os.environ | {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
    print(f"{len(runs)} runs at once for {args.seconds:.0f} s, one thread each; logs in {workdir}")
    for run in runs:
        print(f"  {run.name}: {shlex.join(run.command)}")
    start_time = time.time()
    for run in runs:
        run.start(env, start_time)
    try:
        while time.time() - start_time < args.seconds and any(run.process.poll() is None for run in runs):
            time.sleep(5)
    finally:
        for run in runs:
            run.stop()
    wall = time.time() - start_time
    for run in runs:  # every progress point, for a closer look (e.g. which window holds an adjacency retraining)
        rows = [f"{frames},{cpu:.2f},{seconds:.1f}" for frames, cpu, seconds in run.points]
        (run.folder / "points.csv").write_text("\n".join(["frames,cpu_seconds,wall_seconds", *rows]) + "\n")

    print(f"\nafter {wall:.0f} s wall (whole run, warm-up included: frames / CPU-s of the process tree)")
    for run in runs:
        frames = run.points[-1][0] if run.points else 0
        print(f"  {run.name:<22} frame {frames:>8}, {run.final_cpu:7.1f} CPU-s, {frames / max(run.final_cpu, 1e-9):6.0f}")

    print(f"\neach one's window: its first progress point at or after frame {args.start_frames} to its last one")
    figures = [run.rate(args.start_frames) for run in runs]
    for run, figure in zip(runs, figures, strict=True):
        print("  " + describe(run, figure))

    common_end = min((run.points[-1][0] if run.points else 0) for run in runs)
    print(f"\ncommon window: frames {args.start_frames} to {common_end} (the point nearest inside, for each)")
    common = [run.rate(args.start_frames, common_end) for run in runs]
    for run, figure in zip(runs, common, strict=True):
        print("  " + describe(run, figure))

    print("\nours / original, frames per CPU-second (each one's window; common window)")
    for label, rates in (("each", figures), ("common", common)):
        for run, figure in zip(runs[1:], rates[1:], strict=True):
            if rates[0] is not None and figure is not None:
                print(f"  {run.name:<22} {label:<6} {figure[0] / rates[0][0]:5.2f}x")
            else:
                print(f"  {run.name:<22} {label:<6}   n/a (a window without two progress points)")


if __name__ == "__main__":
    main()
