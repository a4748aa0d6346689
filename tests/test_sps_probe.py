"""benchmark/speed/sps_probe.py: the steady-state steps/s of a command from its progress lines, and its clean stop."""

import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmark" / "speed"))

import sps_probe  # noqa: E402
from conftest import HANG_TIMEOUT  # noqa: E402

# A stand-in for a training script: the run-management block's progress lines every 0.1 s at 10,000 steps per second of
# its own clock (however late a loaded machine ends its sleeps), a SIGINT handler that prints the end-of-run line as the
# scripts do.
FAKE = """
import signal, sys, time
stop = []
signal.signal(signal.SIGINT, lambda *_: stop.append(1))
step, start = 0, time.time()
while not stop and step < 10**6:
    time.sleep(0.1)
    step = int((time.time() - start) * 10_000)
    print(f"step {step:>9}/1000000  eval success  10%  SPS 1  1s elapsed, 9s left", flush=True)
print(f"stopped: {step} steps, 3 updates, last eval success 0%; {time.time() - start:.0f}s; logs in runs/x", flush=True)
"""


def test_progress_and_final_lines_of_the_scripts_parse():
    assert sps_probe.PROGRESS.match("step      1500/3000  eval success  0%  SPS 12").group(1) == "1500"
    assert sps_probe.PROGRESS.match("frame     25000/2000000  train return 0.10  SPS 900  (running)").group(1) == "25000"
    assert sps_probe.PROGRESS.match("pre-training step 10/100") is None  # the goal-DQN's representation phase
    final = sps_probe.FINAL.match("done: 150 steps, 51 updates, last eval success 0%; 12s; logs in runs/a")
    assert final.groups() == ("150", "12")


def test_probe_measures_the_rate_after_the_skip_and_stops_the_command():
    line = sps_probe.probe([sys.executable, "-c", FAKE], seconds=3.0, skip=1.0)
    rate = float(line.split()[1])
    assert 7000 < rate < 13000, line  # 10,000 steps/s, give or take the lines' delivery to the probe
    assert "over the last" in line, line  # the progress lines, not the fallback to the final line
    assert int(re.search(r"(\d+) s in all", line).group(1)) >= 3, line  # stopped by the SIGINT at 3 s, not before


def test_probe_kills_a_command_that_outlasts_its_stop_wait():
    deaf = FAKE.replace("lambda *_: stop.append(1)", "lambda *_: None")  # a command whose step outlasts the stop wait
    line = sps_probe.probe([sys.executable, "-c", deaf], seconds=2.0, skip=0.5, stop_wait=1.0)
    assert "killed 1 s after its SIGINT" in line, line
    assert "over the last" in line, line  # the progress lines before the kill still give the rate
    assert 7000 < float(line.split()[1]) < 13000, line


def test_probe_script_prints_one_line():
    command = [sys.executable, str(ROOT / "benchmark" / "speed" / "sps_probe.py"), "--seconds", "2", "--skip", "0.5", "--"]
    result = subprocess.run([*command, sys.executable, "-c", FAKE], capture_output=True, text=True, timeout=HANG_TIMEOUT)
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith("sps_probe: ") and result.stdout.count("\n") == 1, result.stdout
