"""Steps per second of a training command in steady state: run it for a while, then stop it cleanly.

    python benchmark/speed/sps_probe.py --seconds 90 -- python dgrl_ris.py --env-id AntMaze --groups 16

The command runs in a fresh temporary folder (its runs/ is thrown away). Every progress line a script prints
(`step N/TOTAL ...`, `frame N/TOTAL ...`, also the `(running)` heartbeat) is timed as it arrives. After `--seconds` the
probe sends SIGINT (the scripts stop after the current step) and prints one line:

    sps_probe: 1234 steps/s over the last 58 s (steps 61000 -> 132600); 90 s in all; dgrl_ris.py --env-id ...

The rate is taken between the first progress line after `--skip` seconds (start-up, the random warm-up phase and any
compilation fall before it) and the last line; with fewer than two such lines it falls back to the script's own
whole-run figure from its final line, and says so. With `--stop-wait S`, a command still running S seconds after the
SIGINT (a step that takes minutes, such as a first compilation on a slow machine) is killed, and the line says so: the
rate from the progress lines it printed still stands.
"""

import argparse
import os
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time

PROGRESS = re.compile(r"^(?:step|frame|image)\s+(\d+)/(\d+)")
FINAL = re.compile(r"^(?:done|stopped): (\d+) \w+.*?; (\d+)s;")


def probe(command: list[str], seconds: float, skip: float, stop_wait: float | None = None) -> str:
    lines: list[tuple[float, int]] = []
    final = None
    with tempfile.TemporaryDirectory(prefix="sps_probe_") as folder:
        process = subprocess.Popen(
            command, cwd=folder, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1,
            env=os.environ | {"PYTHONUNBUFFERED": "1"},
        )  # fmt: skip
        start = time.time()
        killed = []

        def kill():  # the command outlived its stop wait
            if process.poll() is None:
                process.kill()
                killed.append(True)

        timers = [threading.Timer(seconds, lambda: process.poll() is None and process.send_signal(signal.SIGINT))]
        if stop_wait is not None:
            timers.append(threading.Timer(seconds + stop_wait, kill))
        for timer in timers:
            timer.start()
        tail = []
        for line in process.stdout:
            now = time.time() - start
            tail = [*tail, line.rstrip()][-20:]
            if match := PROGRESS.match(line.strip()):
                lines.append((now, int(match.group(1))))
            elif match := FINAL.match(line.strip()):
                final = (int(match.group(1)), int(match.group(2)))
        process.wait()
        for timer in timers:
            timer.cancel()
    elapsed = time.time() - start
    name = " ".join(os.path.basename(part) if part.endswith(".py") else part for part in command[1:])
    name = " ".join(name.split())[:200]  # one line
    if killed:
        name = f"killed {stop_wait:.0f} s after its SIGINT; {name}"
    steady = [(at, step) for at, step in lines if at >= skip]
    if len(steady) >= 2 and steady[-1][1] > steady[0][1]:
        (t0, s0), (t1, s1) = steady[0], steady[-1]
        return (
            f"sps_probe: {(s1 - s0) / (t1 - t0):.0f} steps/s over the last {t1 - t0:.0f} s (steps {s0} -> {s1}); "
            f"{elapsed:.0f} s in all; {name}"
        )
    if final is not None and final[1] > 0:
        return f"sps_probe: {final[0] / final[1]:.0f} steps/s over the whole run (too few progress lines); {name}"
    return f"sps_probe: no rate (exit {process.returncode}); {name}; last output:\n  " + "\n  ".join(tail)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=90.0, help="how long the command runs before SIGINT")
    parser.add_argument("--skip", type=float, default=30.0, help="progress lines before this many seconds are ignored")
    parser.add_argument("--stop-wait", type=float, default=None, help="kill the command this long after its SIGINT")
    parser.add_argument("command", nargs=argparse.REMAINDER, help="the command, after --")
    options = parser.parse_args()
    command = options.command[1:] if options.command[:1] == ["--"] else options.command
    if not command:
        parser.error("give the command after --")
    print(probe(command, options.seconds, options.skip, options.stop_wait), flush=True)
    sys.exit(0)
