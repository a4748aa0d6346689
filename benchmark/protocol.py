"""The protocol between a DGRL script and benchmark/launch.py, in one place: how a script reports, stops and exits, and
how the launcher reads it. The scripts import nothing from here (each one stands alone): their side is the `Progress`
class and the signal handling of the run-management block they share. tests/test_launch.py runs every script's
`Progress` and reads what it prints with this module, so that neither side can drift.

A script, run as `python dgrl_x.py FLAGS` in a run folder:
- refuses bad flags before any work, with a message on stderr naming each flag, and exit status 2 (its `validate`);
- prints progress lines: `{unit} {step:>9}/{total}  {figures}  SPS {sps}  {s}s elapsed, {s}s left` (or `time left
  unknown`), the time left at the rate since the line before; after a silent minute, the same line ending in
  ` (running)` (a heartbeat);
- on SIGTERM, SIGUSR1, SIGUSR2 or Ctrl-C, stops after its current step, writes `runs/{run_name}/resume.pt` and
  its checkpoint, prints `stopped: {summary}; {s}s; logs in runs/{run_name}` and exits with status 0 (a second
  signal of the same kind stops it at once);
- after a full run prints `done: {summary}; {s}s; logs in runs/{run_name}` and exits with status 0;
- continues a stopped run exactly with `--resume runs/{run_name}`, from the run folder;
- holds an exclusive lock (flock) on `runs/{run_name}/run.lock` for as long as it writes the run folder, with `pid N on
  HOST` in it: a second process on the folder exits 2 naming that holder; the kernel drops the lock when the holder
  ends, however it ends. The launcher reads the lock (`lock_holder`) to tell a run still alive from a stopped one.
"""

from __future__ import annotations

import fcntl
import json
import os
import re
import shlex
import signal
import subprocess
import tempfile
from pathlib import Path

EXIT_BAD_FLAGS = 2
STOP_SIGNALS = (signal.SIGTERM, signal.SIGUSR1, signal.SIGUSR2)  # each means "stop after this step" to a script
RESUME_FILE = "resume.pt"  # in runs/{run_name}/ (the scripts' RESUME_FILE)
LOCK_FILE = "run.lock"  # in runs/{run_name}/, held by the process that writes the run (the scripts' LOCK_FILE)
DONE, STOPPED = "done: ", "stopped: "  # how the last line of a finished or stopped run starts
PROGRESS = re.compile(r"^\S+\s+(\d+)/(\d+)\s+(.*?)\s+SPS (\d+)\s+\d+s elapsed, (?:(\d+)s left|time left unknown)")


def read_progress(line: str) -> dict | None:
    """A progress or heartbeat line's step, total, figures, SPS and seconds left (None when unknown); else None."""
    found = PROGRESS.match(line)
    if found is None:
        return None
    step, total, figures, sps, left = found.groups()
    return {"step": int(step), "total": int(total), "figures": figures, "sps": int(sps), "left": left and int(left)}


def lock_holder(run_dir: Path | None) -> str | None:
    """Who holds a run folder's lock ("pid N on HOST"), while a process does; None when none does (or no folder)."""
    if run_dir is None or not (run_dir / LOCK_FILE).is_file():
        return None
    with open(run_dir / LOCK_FILE) as lock:
        try:
            fcntl.flock(lock, fcntl.LOCK_SH | fcntl.LOCK_NB)  # granted only while no process holds it exclusively
        except BlockingIOError:
            return lock.read().strip() or "a run that is starting"
    return None  # (closing the file released the probe)


def ending(lines: list[str], rc: int) -> str | None:
    """ "done" or "stopped" when a run's output and exit status say so, as the protocol has it; else None."""
    if rc == 0 and any(line.startswith(DONE) for line in lines):
        return "done"
    if rc == 0 and any(line.startswith(STOPPED) for line in lines):
        return "stopped"
    return None


# The script's own parser and validate(), on each run's flags, in a child process (it imports torch), from an empty
# folder: a run of the sweep would refuse the same flags with the same message, after queueing and starting.
FLAG_CHECK = """
import importlib.util, json, sys, tyro
path, on_slurm, runs = sys.argv[1], sys.argv[2] == "slurm", json.load(sys.stdin)
spec = importlib.util.spec_from_file_location("checked_script", path)
script = sys.modules[spec.name] = importlib.util.module_from_spec(spec)
spec.loader.exec_module(script)
for run_id, argv in runs:
    print(run_id, flush=True)
    args = tyro.cli(script.Args, args=argv, prog=spec.origin.rsplit("/", 1)[-1])
    if on_slurm:
        args.fast = "eager"  # what --fast needs (CUDA, a compiler) is the node's, not this machine's
    script.validate(args)
"""


def flag_errors(runs: list, python: str, backend: str, root: Path) -> list[str]:
    """The flags of `runs` (launch.Run: run_id, script, argv) as their scripts see them, checked once before a sweep
    starts: one error per refusing script, with the script's own message."""
    errors = []
    for script in dict.fromkeys(run.script for run in runs):
        source = (root / script).read_text()
        if "\nclass Args" not in source or "\ndef validate(" not in source:
            continue  # not a script of this project (a stand-in of the tests): it has no validate to ask
        argvs = [(run.run_id, run.argv) for run in runs if run.script == script]
        with tempfile.TemporaryDirectory() as folder:
            result = subprocess.run(
                [python, "-c", FLAG_CHECK, str(root / script), backend],
                input=json.dumps(argvs),
                capture_output=True,
                text=True,
                cwd=folder,
                env=dict(os.environ, PYTHONPATH=str(root)),
            )
        if result.returncode:
            run_id = (result.stdout.split() or ["(none)"])[-1]
            argv = dict(argvs).get(run_id, [])
            message = "\n".join(f"    {line}" for line in result.stderr.strip().splitlines()[-20:])
            errors.append(f"{script} refuses the flags of run {run_id} ({shlex.join(argv)}):\n{message}")
    return errors
