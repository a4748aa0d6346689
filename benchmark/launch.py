"""One launcher for every study: a grid of runs of one script (or a named preset), on this machine or on a Slurm cluster.

    python benchmark/launch.py --list-presets                      # every preset (each study of docs/, each paper figure)
    python benchmark/launch.py --preset mnist                      # a study of docs/, two runs at a time
    python benchmark/launch.py --preset mnist --seeds 4 5 6        # the same study, other seeds (a preset's axes change)
    python benchmark/launch.py --script dgrl_ris.py --env-ids AntU AntMaze --groups 0 16 -- --total-timesteps 40000
                                                                   # any grid; the flags after a bare -- go to every run
    python benchmark/launch.py --preset hrac-paper --backend slurm --partition gpu --gpus-per-task 1 --runs-per-task 4
                                                                   # the paper's HRAC grid as one Slurm job array

Each run of the grid runs in its own folder, `sweeps/{name}/{run_id}/` (its log.txt, status.json and the script's
runs/), locally `--workers` at a time with a table of the runs, or as one job array through submitit (slurm_backend.py,
imported only with `--backend slurm`). A stopped run (Ctrl-C, a time limit, a preemption) resumes exactly from its
resume file; relaunching a sweep skips what is done. The studies are data (presets.py); what a script prints and how it
exits is protocol.py. docs/launch.md is the manual.
"""

from __future__ import annotations

import ctypes
import fcntl
import functools
import importlib.util
import json
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import protocol
from presets import PRESETS, Arm, Plot, Preset

ROOT = Path(__file__).resolve().parents[1]
STATUS_FILE = "status.json"
LOG_FILE = "log.txt"
DEFAULT_TAIL = 25  # log lines shown for a failed run


@dataclass
class Run:
    """One run of a sweep: `python {script} {argv}`, run in `folder` (which holds its log, status and runs/)."""

    run_id: str
    script: str
    argv: list[str]
    folder: Path

    def run_dir(self) -> Path | None:
        """The script's runs/{run_name} folder, once the run has made it."""
        made = sorted((self.folder / "runs").glob("*/")) if (self.folder / "runs").is_dir() else []
        return made[-1] if made else None

    def status(self) -> dict:
        try:
            return json.loads((self.folder / STATUS_FILE).read_text())
        except (OSError, ValueError):
            return {}


def slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9.=+-]+", "-", text).strip("-")


def expand(arms: tuple[Arm, ...], name: str, sweep_dir: Path, threads: int) -> list[Run]:
    """Every run of the arms, in order (seed outermost, so that an early stop leaves whole seeds). A run is named
    `{script}__{env}__{tag}__G{groups}__s{seed}` (the parts it has); its --exp-name is the sweep's name (the plots
    group runs by the script's run name, which holds the env, groups, the exp name and what else the script puts
    there, such as goal-DQN's K)."""
    runs, seen = [], {}
    for arm in arms:
        flags = shlex.split(arm.flags)
        for seed in arm.seeds:
            for env in arm.env_ids or (None,):
                for groups in arm.groups:
                    argv = ([] if env is None else ["--env-id", env]) + ["--groups", str(groups), "--seed", str(seed)]
                    argv += [*flags, "--exp-name", name, "--threads", str(threads)]
                    parts = [Path(arm.script).stem.removeprefix("dgrl_"), env or "", arm.tag, f"G{groups}", f"s{seed}"]
                    run_id = "__".join(part for part in parts if part)
                    if run_id in seen:
                        if seen[run_id] != (arm.script, argv):
                            raise ValueError(f"two arms make run {run_id} with other flags: give them tags")
                        continue
                    seen[run_id] = (arm.script, argv)
                    runs.append(Run(run_id, arm.script, argv, sweep_dir / run_id))
    return runs


# --- One run: start it (resuming if it can), watch it, record how it ended ----------------------------------------------


@dataclass
class Attempt:
    run: Run
    process: subprocess.Popen
    log_start: int  # byte offset of this attempt in log.txt
    started: float
    signalled: bool = False


def command_of(run: Run, python: str) -> list[str]:
    """The run's command line, with `--resume runs/{run_name}` when an earlier attempt left a resume file."""
    command = [python, str(ROOT / run.script), *run.argv]
    run_dir = run.run_dir()
    if run_dir is not None and (run_dir / protocol.RESUME_FILE).is_file():
        command += ["--resume", f"runs/{run_dir.name}"]
    return command


LIBC = ctypes.CDLL(None, use_errno=True) if sys.platform.startswith("linux") else None  # for prctl
PR_SET_PDEATHSIG = 1


def stop_with_launcher(launcher_pid: int) -> None:
    """Run in the run's process before its script starts: on Linux, the kernel sends it SIGTERM when the launcher ends,
    however it ends (kill -9, the out-of-memory killer, a closed terminal), so that it stops after its step and writes
    its resume file, as on Ctrl-C, instead of training on as an orphan that a relaunch would race. (Elsewhere there is
    no such signal: an orphan trains on, and a relaunch waits for it, as for any run whose folder is locked.)"""
    LIBC.prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
    if os.getppid() != launcher_pid:  # the launcher ended before the line above: no signal will come
        os.kill(os.getpid(), signal.SIGTERM)


STOPPED_BY = (-signal.SIGTERM, -signal.SIGUSR1)  # the launcher's stop signals, as exit statuses of an unhandled one


def start(run: Run, python: str, threads: int) -> Attempt:
    """Start the run in its folder, its output appended to log.txt. A run with no resume file starts afresh: whatever
    an earlier attempt left in runs/ is removed, so that every run has one run folder."""
    run.folder.mkdir(parents=True, exist_ok=True)
    command = command_of(run, python)
    if "--resume" not in command and (run.folder / "runs").exists():
        shutil.rmtree(run.folder / "runs")
    status = run.status()
    attempts = status.get("attempts", 0) + 1
    log = open(run.folder / LOG_FILE, "ab")
    log_start = log.tell()
    log.write(f"=== attempt {attempts} at {time.strftime('%Y-%m-%d %H:%M:%S')}: {shlex.join(command)}\n".encode())
    log.flush()
    env = dict(os.environ, OMP_NUM_THREADS=str(threads), PYTHONUNBUFFERED="1")
    env.setdefault("MUJOCO_GL", "egl")
    ends_with_us = functools.partial(stop_with_launcher, os.getpid()) if LIBC else None
    options = {"cwd": run.folder, "stdout": log, "stderr": subprocess.STDOUT, "env": env, "preexec_fn": ends_with_us}
    process = subprocess.Popen(command, start_new_session=True, **options)
    log.close()
    write_status(
        run,
        {
            "state": "running",
            "attempts": attempts,
            "command": command,
            "host": os.uname().nodename,
            "pid": process.pid,
            "parent_pid": os.getpid(),
            "slurm_job": os.environ.get("SLURM_ARRAY_JOB_ID", os.environ.get("SLURM_JOB_ID")),
            "seconds": status.get("seconds", 0),  # over every attempt
        },
    )
    return Attempt(run, process, log_start, time.time())


def write_status(run: Run, status: dict) -> None:
    path = run.folder / STATUS_FILE
    run.folder.mkdir(parents=True, exist_ok=True)  # a Slurm job that died before its run started made no folder
    temporary = path.with_name(f"{STATUS_FILE}.{os.getpid()}.tmp")  # the launcher and a job may write at once
    temporary.write_text(json.dumps(status, indent=1) + "\n")
    os.replace(temporary, path)


def finish(attempt: Attempt) -> dict:
    """Record how the ended attempt ended: done (exit 0 and the script's `done:` line), stopped (exit 0 after a stop
    signal, or killed by the stop signal this launcher sent before the script could handle it, in its first seconds:
    it resumes, or starts again, on the next launch or requeue) or failed (any other exit)."""
    rc = attempt.process.returncode
    with open(attempt.run.folder / LOG_FILE, "rb") as log:
        log.seek(attempt.log_start)
        lines = log.read().decode(errors="replace").splitlines()
    state = protocol.ending(lines, rc) or ("stopped" if attempt.signalled and rc in STOPPED_BY else "failed")
    status = attempt.run.status()
    status.update(state=state, rc=rc, seconds=status.get("seconds", 0) + round(time.time() - attempt.started, 1))
    status["tail"] = lines[-DEFAULT_TAIL:] if state == "failed" else []
    write_status(attempt.run, status)
    return status


def last_ending(run: Run) -> str | None:
    """How the run's latest attempt ended by its log ("done", "stopped" or None): for a run that ended while no launcher
    watched it (an orphan of a killed launcher, on a system without the parent-death signal)."""
    try:
        text = (run.folder / LOG_FILE).read_text(errors="replace")
    except OSError:
        return None
    return protocol.ending(text.rsplit("\n=== attempt ", 1)[-1].splitlines(), 0)


def progress_of(run: Run) -> dict:
    """The latest progress line of the run's log: step, total, figures, SPS, and the seconds left at the rate since the
    line before, less the time since the log was last written (so the figure keeps counting down between lines)."""
    try:
        with open(run.folder / LOG_FILE, "rb") as log:
            log.seek(max(0, log.seek(0, os.SEEK_END) - 8192))
            lines = log.read().decode(errors="replace").splitlines()
            written = os.fstat(log.fileno()).st_mtime
    except OSError:
        return {}
    for line in reversed(lines):
        progress = protocol.read_progress(line)
        if progress is not None:
            if progress["left"] is not None:
                progress["left"] = max(progress["left"] - max(time.time() - written, 0), 0)
            return progress
    return {}


def reaped(attempt: Attempt) -> int | None:
    """The run's exit status once it has ended, else None. Reaps the process itself, with the stop signals held back
    meanwhile, so that submitit's signal handler (which waits on the runs too) never finds it half-reaped, nor blocked
    on a lock of Popen.wait that the interrupted main loop holds."""
    if attempt.process.returncode is None:
        held = signal.pthread_sigmask(signal.SIG_BLOCK, protocol.STOP_SIGNALS)
        try:
            pid, wait_status = os.waitpid(attempt.process.pid, os.WNOHANG)
            if pid:
                attempt.process.returncode = os.waitstatus_to_exitcode(wait_status)
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, held)
    return attempt.process.returncode


def stop_attempt(attempt: Attempt, number: int = signal.SIGTERM) -> None:
    """Ask the run to stop after its current step (once: a second signal of the same kind stops it at once)."""
    if not attempt.signalled and reaped(attempt) is None:
        attempt.process.send_signal(number)
        attempt.signalled = True


# --- The table of runs ----------------------------------------------------------------------------------------------------


def clock(seconds: float | None) -> str:
    if seconds is None:
        return "-"
    seconds = int(seconds)
    return f"{seconds // 3600}:{seconds // 60 % 60:02d}:{seconds % 60:02d}"


def table(runs: list[Run], states: dict[str, str]) -> str:
    """One line per run: state, step/total, the latest figures the script printed, SPS and time left."""
    width = max(len(run.run_id) for run in runs)
    lines = [f"{'run':<{width}}  {'state':<9} {'step':>21}  {'SPS':>6}  {'left':>8}  latest"]
    for run in runs:
        state = states.get(run.run_id, "queued")
        progress = progress_of(run) if state not in ("queued", "skipped") else {}
        step = f"{progress['step']}/{progress['total']}" if progress else "-"
        sps = str(progress.get("sps", "-"))
        left = clock(progress.get("left")) if state == "running" else "-"
        figures = progress.get("figures", "")[:60]
        lines.append(f"{run.run_id:<{width}}  {state:<9} {step:>21}  {sps:>6}  {left:>8}  {figures}")
    counts = {state: list(states.values()).count(state) for state in dict.fromkeys(states.values())}
    queued = len(runs) - len(states)
    summary = ", ".join(f"{count} {state}" for state, count in counts.items()) + (f", {queued} queued" if queued else "")
    return "\n".join(lines) + f"\n[{time.strftime('%H:%M:%S')}] {len(runs)} runs: {summary}"


def failure_report(run: Run) -> str:
    status = run.status()
    tail = "\n".join(f"    {line}" for line in status.get("tail", []))
    return f"FAILED {run.run_id}: exit code {status.get('rc')}; log {run.folder / LOG_FILE}; its last lines:\n{tail}"


# --- Local backend: a pool of processes on this machine ---------------------------------------------------------------


def run_local(runs: list[Run], workers: int, python: str, threads: int, table_every: float) -> dict[str, str]:
    """Run every run, `workers` at a time; Ctrl-C or SIGTERM stops them cleanly (each writes its resume file). A run
    whose folder another process holds (a killed launcher's run, still stopping or training) is waited for, then
    resumed (or recorded as done), never started beside it."""
    states: dict[str, str] = {}
    pending, active, elsewhere = list(runs), [], []  # elsewhere: (run, the lock's holder), a worker's place each
    stop = []
    previous = {number: signal.signal(number, lambda n, f: stop.append(n)) for number in (signal.SIGINT, signal.SIGTERM)}
    last_table = time.time()  # the first table after --table-every seconds, when the runs have something to show
    try:
        while pending or active or elsewhere:
            if stop:  # the first Ctrl-C or SIGTERM stops the runs cleanly, a second one at once
                pending.clear()
                for run, holder in elsewhere:
                    print(f"left alone {run.run_id}: still running elsewhere ({holder})", flush=True)
                elsewhere.clear()
                for attempt in active:
                    if len(stop) > 1 and attempt.process.poll() is None:
                        attempt.process.send_signal(signal.SIGTERM)
                    stop_attempt(attempt)
            for run, holder in list(elsewhere):
                if protocol.lock_holder(run.run_dir()) is None:  # it has ended: record it, or resume it next
                    elsewhere.remove((run, holder))
                    if last_ending(run) == "done":
                        write_status(run, {**run.status(), "state": "done", "rc": 0})
                        states[run.run_id] = "done"
                        print(f"done {run.run_id} (ended elsewhere)", flush=True)
                    else:
                        pending.insert(0, run)
            while pending and len(active) + len(elsewhere) < workers:
                run = pending.pop(0)
                holder = protocol.lock_holder(run.run_dir())
                if holder is not None:
                    elsewhere.append((run, holder))
                    states[run.run_id] = "elsewhere"
                    print(f"running elsewhere {run.run_id} ({holder}): waiting for it to end, not starting it", flush=True)
                    continue
                active.append(start(run, python, threads))
                states[run.run_id] = "running"
                print(f"started {run.run_id}", flush=True)
            for attempt in [a for a in active if a.process.poll() is not None]:  # poll() sets returncode
                active.remove(attempt)
                status = finish(attempt)
                states[attempt.run.run_id] = status["state"]
                print(
                    f"{status['state']} {attempt.run.run_id} (exit {status['rc']}, {clock(time.time() - attempt.started)})",
                    flush=True,
                )
                if status["state"] == "failed":
                    print(failure_report(attempt.run), flush=True)
            if time.time() - last_table >= table_every and (pending or active or elsewhere):
                print(table(runs, states), flush=True)
                last_table = time.time()
            time.sleep(0.5)
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)
    return states


# --- The command line ------------------------------------------------------------------------------------------------


@dataclass
class Args:
    preset: str | None = None
    """a named study (--list-presets shows them); --script, --env-ids, --groups, --seeds and --flags change it"""
    script: str | None = None
    """the script of every run (e.g. dgrl_ris.py), for a sweep without a preset"""
    env_ids: list[str] = field(default_factory=list)
    """env ids of the grid (empty: each arm's own, or the script's default)"""
    groups: list[int] = field(default_factory=list)
    """values of --groups of the grid (0 is the baseline; empty: the preset's, or 0 and 16)"""
    seeds: list[int] = field(default_factory=list)
    """seeds of the grid (empty: the preset's, or 1 2 3)"""
    flags: str = ""
    """extra flags for every run, in one string (after the preset's own, so they win); or give them after a bare --"""
    name: str | None = None
    """the sweep's name: its folder sweeps/NAME and the runs' --exp-name (default: the preset's or the script's name)"""
    sweeps_dir: str = "sweeps"
    """folder holding one folder per sweep"""
    backend: Literal["local", "slurm"] = "local"
    """local: a pool of processes on this machine; slurm: one job array through submitit"""
    workers: int | None = None
    """local backend: runs at a time (default: the preset's, or 2)"""
    threads: int = 1
    """torch threads per run (--threads of the scripts; OMP_NUM_THREADS too)"""
    retry: bool = False
    """run again the runs that failed in an earlier launch (from their resume file when they wrote one)"""
    dry_run: bool = False
    """print the runs and their commands, run nothing"""
    plot: bool = True
    """write the preset's curves and tables to the sweep's folder once every run is done"""
    plot_tags: list[str] = field(default_factory=list)
    """scalar tags for one more figure and table of all the sweep's runs, sweeps/NAME/NAME.png and .md"""
    table_every: float = 60.0
    """seconds between two tables of the runs"""
    python: str = sys.executable
    """the Python that runs the scripts (on a cluster: one every node can reach)"""
    list_presets: bool = False
    """list the presets and exit"""
    partition: str | None = None
    """slurm: the partition (default: the cluster's default one)"""
    time_min: int = 240
    """slurm: the time limit of one job, in minutes; a run that needs longer continues in the requeued job"""
    cpus_per_task: int = 1
    """slurm: CPUs of one array task"""
    gpus_per_task: int = 0
    """slurm: GPUs of one array task (its runs share them)"""
    runs_per_task: int = 1
    """slurm: runs packed in one array task, side by side (e.g. 4 runs on one GPU)"""
    mem_gb: float | None = None
    """slurm: memory of one array task in GB (default: the cluster's)"""
    array_parallelism: int = 256
    """slurm: array tasks running at once"""
    signal_delay_s: int = 120
    """slurm: seconds between the stop signal and the time limit (time for the runs to write their resume files)"""
    max_requeues: int = 20
    """slurm: how many times a job may requeue on its time limit (preemptions do not count)"""
    sbatch: list[str] = field(default_factory=list)
    """slurm: extra sbatch options, KEY=VALUE each (e.g. account=myproject qos=low constraint=a100)"""
    setup: list[str] = field(default_factory=list)
    """slurm: shell lines the job runs first (e.g. "module load cuda")"""


def exit_on_errors(errors: list[str]) -> None:
    if errors:
        for error in errors:
            print(f"launch.py: {error}", file=sys.stderr)
        raise SystemExit(2)


def arms_of(args: Args) -> tuple[tuple[Arm, ...], Preset | None]:
    """The sweep's arms: the preset's (or one arm of --script), each axis replaced by the flag given for it."""
    preset = PRESETS.get(args.preset) if args.preset else None
    arms = preset.arms if preset else (Arm(args.script or ""),)
    changed = []
    for arm in arms:
        changed.append(
            Arm(
                args.script or arm.script,
                tuple(args.env_ids) or arm.env_ids,
                tuple(args.groups) or arm.groups,
                tuple(args.seeds) or arm.seeds,
                f"{arm.flags} {args.flags}".strip(),
                arm.tag,
            )
        )
    return tuple(changed), preset


def check(args: Args) -> list[str]:
    """Every problem with the flags, before anything runs."""
    errors = []
    if args.preset is not None and args.preset not in PRESETS:
        errors.append(f"--preset {args.preset}: no such preset; the presets: {', '.join(PRESETS)}")
    if args.preset is None and args.script is None:
        errors.append("pass --preset NAME or --script SCRIPT (--list-presets shows the presets)")
    if args.script is not None and not (ROOT / args.script).is_file():
        scripts = sorted(path.name for path in ROOT.glob("dgrl_*.py"))
        errors.append(f"--script {args.script}: no such script; the scripts: {', '.join(scripts)}")
    for flag in ("threads", "cpus_per_task", "runs_per_task", "array_parallelism", "time_min", "workers"):
        if getattr(args, flag) is not None and getattr(args, flag) < 1:  # (--workers: None is the preset's own)
            errors.append(f"--{flag.replace('_', '-')} must be >= 1, got {getattr(args, flag)}")
    for flag in ("gpus_per_task", "signal_delay_s", "max_requeues"):
        if getattr(args, flag) < 0:
            errors.append(f"--{flag.replace('_', '-')} must be >= 0, got {getattr(args, flag)}")
    for flag in ("table_every", "mem_gb"):
        if getattr(args, flag) is not None and getattr(args, flag) <= 0:  # (--mem-gb: None is the cluster's own)
            errors.append(f"--{flag.replace('_', '-')} must be > 0, got {getattr(args, flag)}")
    errors += [f"--sbatch {option}: give KEY=VALUE (e.g. account=myproject)" for option in args.sbatch if "=" not in option]
    if any(seed < 0 for seed in args.seeds):
        errors.append(f"--seeds must be >= 0, got {args.seeds}")
    if args.name is not None and (not args.name or slug(args.name) != args.name or "__" in args.name):
        errors.append(f"--name {args.name!r}: use letters, digits, '.', '=', '+' and '-' (single '_' too), no spaces")
    try:
        shlex.split(args.flags)
    except ValueError as error:
        errors.append(f"--flags {args.flags!r}: {error}")
    if args.backend == "slurm":
        if importlib.util.find_spec("submitit") is None:
            errors.append("--backend slurm needs submitit: pip install -r requirements.txt")
        if shutil.which("sbatch") is None:
            errors.append("--backend slurm: no sbatch on PATH (run the launcher on a machine of the cluster)")
    elif args.runs_per_task != 1 or args.gpus_per_task or args.partition or args.sbatch or args.setup:
        errors.append("--partition, --gpus-per-task, --runs-per-task, --sbatch and --setup are for --backend slurm")
    return errors


def hold_lock(folder: Path):
    """An exclusive lock on the sweep's folder for as long as this launcher runs (the kernel drops it when the process
    ends, however it ends), so that two launchers never run the same runs at once."""
    handle = open(folder / "launch.lock", "a+")  # kept open: closing it would drop the lock
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        handle.seek(0)
        exit_on_errors(
            [
                f"{folder} is in use by another launcher ({handle.read().strip() or 'pid unknown'}): wait for it "
                "to end, or stop it with Ctrl-C, before launching this sweep again"
            ]
        )
    handle.truncate(0)
    handle.write(f"pid {os.getpid()} on {os.uname().nodename}\n")
    handle.flush()
    return handle


def describe_presets() -> str:
    lines = []
    for name, preset in PRESETS.items():
        count = len(expand(preset.arms, name, Path("."), 1))
        lines.append(f"{name:<17} {count:>3} runs  {preset.description}")
    return "\n".join(lines)


def write_plots(plots: tuple[Plot, ...], folder: Path, runs: list[Run]) -> None:
    """The figures and tables of `plots` from the sweep's runs, by benchmark/analysis/plot.py."""
    sys.path.insert(0, str(ROOT / "benchmark" / "analysis"))
    import plot

    run_dirs = [run.run_dir() for run in runs]
    for spec in plots:
        out = folder / spec.out
        plot.plot_study(
            [d for d in run_dirs if d is not None], list(spec.tags), str(out), spec.match, spec.panel_by, spec.title, spec.bins
        )


def main(args: Args) -> int:
    if args.list_presets:
        print(describe_presets())
        return 0
    exit_on_errors(check(args))
    arms, preset = arms_of(args)
    name = args.name or args.preset or Path(arms[0].script).stem
    args.name = name
    folder = Path(args.sweeps_dir).resolve() / name
    runs = expand(arms, name, folder, args.threads)
    todo = [run for run in runs if run.status().get("state") != "done"]
    exit_on_errors(protocol.flag_errors(todo, args.python, args.backend, ROOT))
    if args.dry_run:
        for run in runs:
            print(f"{run.run_id}: cd {run.folder} && {shlex.join(command_of(run, args.python))}")
        return 0
    folder.mkdir(parents=True, exist_ok=True)
    lock = hold_lock(folder)  # noqa: F841 (held until the launcher exits)
    described = [{"id": run.run_id, "script": run.script, "argv": run.argv} for run in runs]
    (folder / "sweep.json").write_text(json.dumps({"name": name, "preset": args.preset, "runs": described}, indent=1) + "\n")
    states, todo = {}, []
    for run in runs:
        state = run.status().get("state")
        if state == "done":
            states[run.run_id] = "skipped"
        elif state == "failed" and not args.retry:
            states[run.run_id] = "failed"
        else:
            todo.append(run)
    skipped = sum(state == "skipped" for state in states.values())
    failed_before = [run for run in runs if states.get(run.run_id) == "failed"]
    resuming = sum("--resume" in command_of(run, args.python) for run in todo)
    busy = sum(protocol.lock_holder(run.run_dir()) is not None for run in todo)
    print(
        f"sweep {name}: {len(runs)} runs in {folder}; {skipped} done before, {len(failed_before)} failed before "
        f"(--retry runs them again), {len(todo)} to run ({resuming} resuming)"
        + (f", {busy} of them still running elsewhere (waited for, never started twice)" if busy else ""),
        flush=True,
    )
    if todo:
        if args.backend == "local":
            workers = args.workers or (preset.workers if preset else 2)
            states.update(run_local(todo, workers, args.python, args.threads, args.table_every))
        else:
            from slurm_backend import run_slurm  # submitit and its imports, only for a Slurm sweep

            states.update(run_slurm(todo, args, folder))
    print(table(runs, {run.run_id: run.status().get("state", "queued") for run in runs}), flush=True)
    failed = [run for run in runs if run.status().get("state") == "failed"]
    unfinished = [run for run in runs if run.status().get("state") != "done"]
    for run in failed:
        print(failure_report(run), flush=True)
    if unfinished:
        print(
            f"{len(unfinished)} of {len(runs)} runs are not done ({len(failed)} failed): launch the same command again "
            f"to resume the stopped ones{' and --retry to rerun the failed ones' if failed else ''}",
            flush=True,
        )
        return 1
    plots = (preset.plots if preset else ()) + ((Plot(name, tuple(args.plot_tags), name),) if args.plot_tags else ())
    if args.plot and plots:
        write_plots(plots, folder, runs)
    if preset and preset.note:
        print(f"\n{preset.note}")
    return 0


def cli(argv: list[str]) -> Args:
    """The launcher's flags; whatever follows a bare `--` is added to --flags (extra flags for every run)."""
    import tyro

    extra = []
    if "--" in argv:
        argv, extra = argv[: argv.index("--")], argv[argv.index("--") + 1 :]
    args = tyro.cli(Args, args=argv, description=__doc__)
    args.flags = f"{args.flags} {shlex.join(extra)}".strip()
    given = {word.split("=", 1)[0] for word in argv}
    lists = [name for name, value in vars(args).items() if isinstance(value, list)]
    empty = [
        f"--{name.replace('_', '-')}" for name in lists if f"--{name.replace('_', '-')}" in given and not getattr(args, name)
    ]
    exit_on_errors([f"{flag} was given no value: give at least one, or leave it out for the preset's own" for flag in empty])
    return args


if __name__ == "__main__":
    import launch  # this file as a module: Slurm jobs unpickle its classes as launch.*, which they can import, not __main__.*

    sys.exit(launch.main(launch.cli(sys.argv[1:])))
