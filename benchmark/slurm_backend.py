"""The Slurm backend of benchmark/launch.py: one job array per sweep through submitit, imported only with
`--backend slurm` (the local backend needs nothing beyond the standard library). docs/launch.md says what happens on a
time limit, a preemption, a requeue by Slurm itself and a job that dies; tests/test_launch.py's `slurm` tests check it
against a real cluster."""

from __future__ import annotations

import json
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import protocol
import submitit
from launch import (
    DEFAULT_TAIL,
    ROOT,
    STATUS_FILE,
    Args,
    Attempt,
    Run,
    exit_on_errors,
    failure_report,
    finish,
    reaped,
    start,
    stop_attempt,
    table,
    write_status,
)
from submitit.helpers import Checkpointable


class SlurmTask(Checkpointable):
    """One array task: its runs (several when packed on one GPU), side by side. On Slurm's signal before a time limit
    or on preemption, submitit calls `checkpoint`: every run is asked to stop after its current step, its resume file
    written, and the requeued task continues them with --resume. A run that fails makes the task raise, with its log's
    tail, so that the launcher shows the traceback."""

    def __init__(self, runs: list[Run], python: str, threads: int, stop_wait: float):
        self.runs, self.python, self.threads = runs, python, threads
        self.stop_wait = stop_wait  # seconds the runs get to stop (then they are killed): less than Slurm's grace
        self.attempts: list[Attempt] = []

    def __getstate__(self) -> dict:
        return {**self.__dict__, "attempts": []}

    def __call__(self) -> list[dict]:
        todo = [run for run in self.runs if run.status().get("state") != "done"]
        free = self.free(todo)
        self.attempts = [start(run, self.python, self.threads) for run in free]
        self.wait()
        statuses = [finish(attempt) for attempt in self.attempts]
        failed = [run for run, status in zip(free, statuses, strict=True) if status["state"] != "done"]
        failed += [run for run in todo if run not in free]
        if failed:
            raise RuntimeError("\n".join(failure_report(run) for run in failed))
        return statuses

    def free(self, runs: list[Run]) -> list[Run]:
        """The runs whose folder no process holds. A requeued task may start while the one before it still writes its
        resume files (its node slow to let go): each held run is waited for up to `stop_wait` seconds, then refused
        (recorded as failed, naming the holder), never started beside it."""
        end = time.time() + self.stop_wait
        held = {run.run_id: holder for run in runs if (holder := protocol.lock_holder(run.run_dir()))}
        while held and time.time() < end:
            time.sleep(1)
            held = {run.run_id: holder for run in runs if (holder := protocol.lock_holder(run.run_dir()))}
        for run in runs:
            if run.run_id in held:
                why = (
                    f"runs/{run.run_dir().name} is still held by {held[run.run_id]} after {self.stop_wait:.0f} s: the "
                    "task before this one has not let go of it; launch the sweep again with --retry once it has ended"
                )
                write_status(run, {**run.status(), "state": "failed", "rc": None, "tail": [why]})
        return [run for run in runs if run.run_id not in held]

    def wait(self, timeout: float | None = None) -> None:
        """Until every run has ended; after `timeout` seconds, the ones left are killed."""
        end = None if timeout is None else time.time() + timeout
        while any(reaped(attempt) is None for attempt in self.attempts):
            if end is not None and time.time() > end:
                for attempt in self.attempts:
                    if reaped(attempt) is None:
                        attempt.process.kill()
            time.sleep(0.2)

    def checkpoint(self) -> submitit.helpers.DelayedSubmission:
        # Slurm signals every process of the job: the runs have most likely had SIGTERM and/or SIGUSR2 already. SIGUSR1
        # is a kind they have not had, so sending it is harmless when they have and stops them when they have not.
        for attempt in self.attempts:
            stop_attempt(attempt, signal.SIGUSR1)
        self.wait(timeout=self.stop_wait)
        for attempt in self.attempts:
            finish(attempt)
        return submitit.helpers.DelayedSubmission(SlurmTask(self.runs, self.python, self.threads, self.stop_wait))


def slurm_executor(args: Args, folder: Path):
    executor = submitit.AutoExecutor(folder=folder / "slurm" / "%j", cluster="slurm", slurm_max_num_timeout=args.max_requeues)
    parameters = {
        "name": args.name,
        "timeout_min": args.time_min,
        "cpus_per_task": args.cpus_per_task,
        "slurm_array_parallelism": args.array_parallelism,
        "slurm_signal_delay_s": args.signal_delay_s,
        "slurm_setup": [f"export PYTHONPATH={shlex.quote(str(ROOT / 'benchmark'))}${{PYTHONPATH:+:$PYTHONPATH}}", *args.setup],
        "slurm_additional_parameters": dict(option.split("=", 1) for option in args.sbatch),
    }
    if args.partition:
        parameters["slurm_partition"] = args.partition
    if args.gpus_per_task:
        parameters["gpus_per_node"] = args.gpus_per_task
    if args.mem_gb:
        parameters["mem_gb"] = args.mem_gb
    executor.update_parameters(**parameters)
    return executor


def run_slurm(runs: list[Run], args: Args, folder: Path) -> dict[str, str]:
    """Submit one job array (`--runs-per-task` runs a task) and wait for it, with the table of runs; a job that ends
    without a result (killed, out of memory, cancelled) is reported as such, from Slurm's accounting."""
    jobs_file = folder / "slurm_jobs.json"
    if jobs_file.is_file():
        known = json.loads(jobs_file.read_text())
        active = [job for job in known if slurm_state(job) in ACTIVE_STATES]
        if active:
            exit_on_errors(
                [
                    f"this sweep already has jobs in the queue ({', '.join(active)}): wait for them or "
                    f"scancel them before launching it again"
                ]
            )
    chunks = [runs[i : i + args.runs_per_task] for i in range(0, len(runs), args.runs_per_task)]
    stop_wait = max(args.signal_delay_s - 15, 10)  # the time limit comes signal_delay_s after the stop signal
    executor = slurm_executor(args, folder)
    try:
        with executor.batch():
            jobs = [executor.submit(SlurmTask(chunk, args.python, args.threads, stop_wait)) for chunk in chunks]
    except (submitit.core.utils.UncompletedJobError, submitit.core.utils.FailedSubmissionError) as error:
        message = " ".join(str(error).split())  # sbatch's own words, e.g. an unknown partition or account
        exit_on_errors([f"sbatch refused the sweep's job array: {message[-600:]}"])
    submitted = time.time() - 1  # file times may be a little behind this clock
    jobs_file.write_text(json.dumps([job.job_id for job in jobs]) + "\n")
    print(
        f"submitted {len(jobs)} array tasks of job {jobs[0].job_id.split('_')[0]} ({len(runs)} runs); "
        f"submitit's files in {folder / 'slurm'}",
        flush=True,
    )
    states: dict[str, str] = {}
    waiting = dict(zip(jobs, chunks, strict=True))
    stop, requeued = [], set()
    previous = signal.signal(signal.SIGINT, lambda n, f: stop.append(n))
    last_table = time.time()
    try:
        while waiting and not stop:
            for job, chunk in list(waiting.items()):
                for run in chunk:  # a status written before this submission is an earlier launch's: still queued
                    status_file = run.folder / STATUS_FILE
                    if status_file.is_file() and status_file.stat().st_mtime >= submitted:
                        states[run.run_id] = run.status().get("state", "queued")
                if not job.done():
                    continue
                held = slurm_state(job.job_id)  # done() trusts the result file, which an earlier attempt may have left
                if held in ACTIVE_STATES and any(run.status().get("state") not in ("done", "failed") for run in chunk):
                    for run in chunk:  # Slurm requeued the task itself (scontrol requeue, preemption): it will run again
                        if states.get(run.run_id) == "stopped" and held != "COMPLETING":
                            states[run.run_id] = "requeued"
                            if (run.run_id, run.status().get("attempts")) not in requeued:
                                requeued.add((run.run_id, run.status().get("attempts")))
                                print(f"requeued {run.run_id} (job {job.job_id}, Slurm state {held})", flush=True)
                    continue
                del waiting[job]
                try:
                    job.result()
                except Exception as error:  # the runs' own status says which failed and why, unless the job died first
                    if isinstance(error, submitit.core.utils.UncompletedJobError):
                        why = f"job {job.job_id} ended without a result (Slurm state {slurm_state(job.job_id)})"
                    else:
                        why = f"job {job.job_id} failed"
                    for run in chunk:
                        if run.status().get("state") not in ("done", "failed", "stopped"):
                            write_status(
                                run,
                                {
                                    **run.status(),
                                    "state": "failed",
                                    "rc": None,
                                    "tail": [why, *str(error).splitlines()[-DEFAULT_TAIL:]],
                                },
                            )
                for run in chunk:
                    state = run.status().get("state", "failed")
                    states[run.run_id] = state
                    print(f"{state} {run.run_id} (job {job.job_id})", flush=True)
                    if state == "failed":
                        print(failure_report(run), flush=True)
            if time.time() - last_table >= args.table_every and waiting:
                print(table(runs, states), flush=True)
                last_table = time.time()
            time.sleep(2)
    finally:
        signal.signal(signal.SIGINT, previous)
    if stop:
        print(
            f"stopped waiting: the jobs go on in the queue ({jobs[0].job_id.split('_')[0]}); launch the sweep again once "
            "they are done to see its results, or scancel them",
            flush=True,
        )
        sys.exit(130)
    return states


ACTIVE_STATES = (
    "PENDING",
    "RUNNING",
    "REQUEUED",
    "CONFIGURING",
    "COMPLETING",
    "RESIZING",
    "SUSPENDED",
    "REQUEUE_HOLD",
    "REQUEUE_FED",
    "SIGNALING",
    "STAGE_OUT",
    "PREEMPTED",
)


def slurm_state(job_id: str) -> str:
    """A job's state from squeue, or else from sacct ("UNKNOWN" if neither knows it)."""
    for command in (["squeue", "-h", "-j", job_id, "-o", "%T"], ["sacct", "-n", "-X", "-P", "-j", job_id, "-o", "State"]):
        try:
            out = subprocess.run(command, capture_output=True, text=True, timeout=30).stdout.split()
        except (OSError, subprocess.TimeoutExpired):
            continue
        if out:
            return out[-1].split()[0]
    return "UNKNOWN"
