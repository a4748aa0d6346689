"""benchmark/launch.py: grids and presets, the local backend (a table, failures with their log, resume after a stop,
relaunches that skip what is done), and the Slurm backend against a real cluster (tests marked `slurm`: a sweep equal
to the local one, a preempted and a timed-out job that requeue and continue exactly, a failure's traceback, a killed
job reported). `.ci/slurm.sh` starts a single-node cluster; without one the slurm tests are skipped, with the reason."""

import json
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.conftest import HANG_TIMEOUT, assert_same_run

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmark"))
import launch  # noqa: E402
import presets  # noqa: E402
import protocol  # noqa: E402

# A goal-DQN run of about 5 s (1 ms a step after a 3 s start), with its checkpoint for assert_same_run.
GOAL_DQN = presets.SMOKE_GOAL_DQN.split()
PROGRESS = re.compile(r"^step +\d+/\d+  train", re.M)


def launcher(sweeps: Path, *argv: str, timeout: int = HANG_TIMEOUT, env: dict | None = None) -> subprocess.CompletedProcess:
    """Run benchmark/launch.py as a user would, its sweeps under `sweeps`."""
    command = [sys.executable, str(ROOT / "benchmark/launch.py"), "--sweeps-dir", str(sweeps), *argv]
    environment = dict(os.environ, PYTHONUNBUFFERED="1") | (env or {})
    return subprocess.run(command, capture_output=True, text=True, timeout=timeout, env=environment)


def popen_launcher(sweeps: Path, *argv: str) -> subprocess.Popen:
    command = [sys.executable, str(ROOT / "benchmark/launch.py"), "--sweeps-dir", str(sweeps), *argv]
    environment = dict(os.environ, PYTHONUNBUFFERED="1")
    return subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=environment)


def status(sweep: Path, run_id: str) -> dict:
    return json.loads((sweep / run_id / "status.json").read_text())


def run_dir(sweep: Path, run_id: str) -> Path:
    (found,) = (sweep / run_id / "runs").iterdir()
    return found


def wait_for(predicate, timeout: float, what: str) -> None:
    end = time.time() + timeout
    while not predicate():
        assert time.time() < end, f"timed out after {timeout} s waiting for {what}"
        time.sleep(0.5)


def log_has_progress(sweep: Path, run_id: str, pattern: re.Pattern = PROGRESS) -> bool:
    log = sweep / run_id / "log.txt"
    return log.is_file() and pattern.search(log.read_text()) is not None


FAILING_SCRIPT = """\
import sys
print("step 1/10  loss 0.5  SPS 100  1s elapsed, 9s left", flush=True)
raise ValueError("boom: this run fails on purpose")
"""

SLEEPING_SCRIPT = """\
import time
print("step 1/10  loss 0.5  SPS 100  1s elapsed, 9s left", flush=True)
time.sleep(600)
"""


# --- Grids, presets and flags --------------------------------------------------------------------------------------------


def test_a_grid_is_the_product_of_its_lists_with_readable_run_ids(tmp_path):
    arm = launch.Arm("dgrl_ris.py", ("AntU", "AntMaze"), (0, 16), (1, 2, 3), "--total-timesteps 40000")
    runs = launch.expand((arm,), "study", tmp_path, threads=1)
    assert len(runs) == 12 and len({run.run_id for run in runs}) == 12
    assert runs[0].run_id == "ris__AntU__G0__s1" and runs[-1].run_id == "ris__AntMaze__G16__s3"
    assert runs[0].folder == tmp_path / "ris__AntU__G0__s1"
    assert runs[0].argv == "--env-id AntU --groups 0 --seed 1 --total-timesteps 40000 --exp-name study --threads 1".split()
    # Seeds outermost: a sweep stopped early leaves whole seeds.
    assert [run.run_id.split("__")[-1] for run in runs[:4]] == ["s1"] * 4


def test_arms_of_one_script_and_env_need_tags(tmp_path):
    untagged = (
        launch.Arm("dgrl_amigo.py", ("E",), (0,), (1,), "--a 1"),
        launch.Arm("dgrl_amigo.py", ("E",), (0,), (1,), "--a 2"),
    )
    with pytest.raises(ValueError, match="give them tags"):
        launch.expand(untagged, "s", tmp_path, 1)
    tagged = (
        launch.Arm("dgrl_amigo.py", ("E",), (0,), (1,), "--a 1", "x"),
        launch.Arm("dgrl_amigo.py", ("E",), (0,), (1,), "", "y"),
    )
    runs = launch.expand(tagged, "s", tmp_path, 1)
    assert [run.run_id for run in runs] == ["amigo__E__x__G0__s1", "amigo__E__y__G0__s1"]
    assert runs[0].argv[runs[0].argv.index("--exp-name") + 1] == "s"


def test_the_command_line_replaces_a_presets_axes_and_appends_flags():
    args = launch.cli(["--preset", "ris-pointmaze", "--seeds", "4", "5", "--groups", "8", "--", "--batch-size", "64"])
    (arm,), preset = launch.arms_of(args)
    assert preset is launch.PRESETS["ris-pointmaze"]
    assert arm.seeds == (4, 5) and arm.groups == (8,) and arm.env_ids == ("PointMaze_UMaze-v3",)
    assert arm.flags.endswith("--save-model --batch-size 64")  # after the preset's --batch-size 128: the later one wins


@pytest.mark.parametrize("name", sorted(launch.PRESETS))
def test_every_preset_dry_runs_with_flags_its_scripts_accept_and_names_its_page(name, tmp_path, capsys):
    """--dry-run of the preset, in this process: every run's flags pass its script's own parser and validate (the
    launcher's check), one command per run is printed; the preset's page exists and gives its command."""
    preset = launch.PRESETS[name]
    assert launch.main(launch.cli(["--sweeps-dir", str(tmp_path), "--preset", name, "--dry-run"])) == 0
    runs = launch.expand(preset.arms, name, tmp_path, 1)
    printed = capsys.readouterr().out.splitlines()
    assert [line.split(":")[0] for line in printed] == [run.run_id for run in runs] and runs and preset.description
    assert not (tmp_path / name).exists()
    assert f"--preset {name}" in (ROOT / preset.page).read_text(), preset.page

    def value(run, flag, default):
        return run.argv[run.argv.index(flag) + 1] if flag in run.argv else default

    names = []  # the run names the scripts will give these runs: {env}[__K{k}]__G{groups}__{exp_name}__{seed}__{time}
    for run in runs:
        k = f"__K{value(run, '--n-train-goals', 8)}" if run.script == "dgrl_goal_dqn.py" else ""
        env = value(run, "--env-id", "ENV")
        names.append(f"{env}{k}__G{value(run, '--groups', 0)}__{value(run, '--exp-name', '')}__{value(run, '--seed', 1)}__0")
    for plot in preset.plots:  # every plot selects some of the preset's runs
        assert any(re.search(plot.match, name) for name in names), (name, plot.out, plot.match)


def test_the_studies_of_the_docs_are_presets_and_no_fan_out_is_left_in_benchmark():
    for name in (
        "quick",
        "goal-dqn",
        "mnist",
        "keychest",
        "ris-pointmaze",
        "ris-antu-cpu",
        "hrac-antmaze-cpu",
        "sawyer-cpu",
        "amigo-doorkey",
        "amigo-s3r1",
        "amigo-s3r1-3m",
        "amigo-nochannel",
        "amigo-paper",
        "hrac-paper",
        "ris-paper",
        "sawyer-paper",
    ):
        assert name in launch.PRESETS
    for path in (ROOT / "benchmark").rglob("*.sh"):
        text = path.read_text()
        assert "xargs" not in text and " & " not in text and "&\n" not in text, path


@pytest.mark.parametrize(
    ("preset", "channel"),
    [
        ("amigo-doorkey", {0: "on", 8: "on", 16: "on"}),  # run with the goal channel in both modes
        ("amigo-s3r1", {0: "on", 8: "on", 16: "on"}),
        ("amigo-s3r1-3m", {0: "on", 16: "on"}),
        ("amigo-nochannel", {0: "off", 16: "off"}),  # without it in both
        ("amigo-paper", {0: "on", 8: "off", 16: "off"}),  # the script's default, the paper's wiring
    ],
)
def test_the_amigo_presets_keep_the_goal_channel_their_documented_runs_had(preset, channel):
    import dgrl_amigo

    for run in launch.expand(launch.PRESETS[preset].arms, preset, Path("/nonexistent"), 1):
        argv = run.argv
        given = argv[argv.index("--goal-channel") + 1] if "--goal-channel" in argv else "auto"
        groups = int(argv[argv.index("--groups") + 1])
        assert dgrl_amigo.resolve_goal_channel(given, groups) == channel[groups], (run.run_id, argv)
    assert ("--goal-channel" in launch.PRESETS[preset].arms[0].flags) == (preset != "amigo-paper")


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--preset", "nope"], "--preset nope: no such preset; the presets: smoke, quick"),
        (["--script", "nope.py"], "--script nope.py: no such script; the scripts: dgrl_amigo.py"),
        ([], "pass --preset NAME or --script SCRIPT"),
        (["--preset", "smoke", "--workers", "0"], "--workers must be >= 1, got 0"),
        (["--preset", "smoke", "--partition", "gpu"], "are for --backend slurm"),
        (["--preset", "smoke", "--backend", "slurm", "--sbatch", "account"], "--sbatch account: give KEY=VALUE"),
        (["--preset", "smoke", "--name", "my sweep"], "--name 'my sweep': use letters"),
        (["--preset", "smoke", "--flags", "'unclosed"], '--flags "\'unclosed": No closing quotation'),
        (["--preset", "smoke", "--seeds", "--dry-run"], "--seeds was given no value: give at least one"),
        (
            ["--script", "dgrl_goal_dqn.py", "--groups", "0", "--seeds", "1", "--dry-run", "--", "--bogus-flag", "3"],
            "dgrl_goal_dqn.py refuses the flags of run goal_dqn__G0__s1 (--groups 0 --seed 1 --bogus-flag 3",
        ),
        (
            ["--preset", "smoke", "--groups", "3", "--dry-run"],
            "--groups must be 0 (baseline) or divide --embed-dim 64",
        ),
    ],
)
def test_bad_flags_exit_2_with_a_message_before_anything_runs(flags, message, tmp_path):
    result = launcher(tmp_path / "sweeps", *flags)
    assert result.returncode == 2, result.stdout + result.stderr
    assert message in result.stderr and "Traceback" not in result.stderr
    assert not (tmp_path / "sweeps").exists()


def test_the_flag_check_leaves_what_fast_needs_to_the_slurm_node():
    """Checked on the launching machine (no CUDA here), --fast cudagraphs is refused for a local sweep and left to the
    node for a Slurm one; an out-of-range flag is refused for both."""
    runs = launch.expand((launch.Arm("dgrl_mnist.py", (), (0,), (1,), "--fast cudagraphs"),), "check", Path("/nowhere"), 1)
    (local,) = protocol.flag_errors(runs, sys.executable, "local", ROOT)
    assert "dgrl_mnist.py refuses the flags of run mnist__G0__s1" in local and "--fast cudagraphs needs a CUDA" in local
    assert protocol.flag_errors(runs, sys.executable, "slurm", ROOT) == []
    runs = launch.expand((launch.Arm("dgrl_mnist.py", (), (0,), (1,), "--epochs 0"),), "check", Path("/nowhere"), 1)
    assert all("--epochs must be >= 1" in error for error in protocol.flag_errors(runs, sys.executable, "slurm", ROOT))


def test_the_table_counts_a_runs_time_left_down_between_its_progress_lines(tmp_path):
    run = launch.Run("r", "dgrl_goal_dqn.py", [], tmp_path)
    (tmp_path / "log.txt").write_text("step       500/3000  train 0.00 success  SPS 292  20s elapsed, 400s left\n")
    assert 399 <= launch.progress_of(run)["left"] <= 400
    os.utime(tmp_path / "log.txt", (time.time() - 100, time.time() - 100))  # 100 s without a line
    assert 299 <= launch.progress_of(run)["left"] <= 300 and launch.progress_of(run)["step"] == 500
    os.utime(tmp_path / "log.txt", (time.time() - 1000, time.time() - 1000))
    assert launch.progress_of(run)["left"] == 0
    assert re.search(r"^r +running +500/3000 +292 +0:00:00  train", launch.table([run], {"r": "running"}), re.M)


def test_every_tool_of_benchmark_answers_help():
    """`--help` of every tool in benchmark/'s folders (in one child process: they share their imports) exits 0 and
    prints its usage, so that each command of the docs at least starts."""
    tools = sorted(str(path) for path in (ROOT / "benchmark").glob("*/*.py") if path.name != "timing.py")
    code = (
        "import json, runpy, sys\n"
        "codes = {}\n"
        "for tool in json.loads(sys.argv[1]):\n"
        "    sys.argv, saved = [tool, '--help'], list(sys.path)\n"
        "    sys.path.insert(0, tool.rsplit('/', 1)[0])  # as `python TOOL` puts its folder first\n"
        "    try:\n"
        "        runpy.run_path(tool, run_name='__main__')\n"
        "        codes[tool] = 'returned'\n"
        "    except SystemExit as exit:\n"
        "        codes[tool] = exit.code\n"
        "    sys.path[:] = saved\n"
        "print('CODES', json.dumps(codes))\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", code, json.dumps(tools)], capture_output=True, text=True, timeout=HANG_TIMEOUT
    )
    assert result.returncode == 0, result.stderr[-3000:]
    codes = json.loads(result.stdout.rsplit("CODES ", 1)[1])
    assert len(codes) == len(tools) >= 20 and {tool: code for tool, code in codes.items() if code not in (0, None)} == {}
    assert result.stdout.count("usage:") >= len(tools), result.stdout[-3000:]


def test_dry_run_prints_every_command_and_runs_nothing(tmp_path):
    result = launcher(tmp_path, "--preset", "hrac-paper", "--dry-run")
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    assert len(lines) == 90 and "dgrl_hrac.py --env-id AntGather --groups 32 --seed 3 --total-timesteps 5000000" in lines[-1]
    assert not (tmp_path / "hrac-paper").exists()


@pytest.mark.parametrize("script", sorted(path.name for path in ROOT.glob("dgrl_*.py")))
def test_each_scripts_progress_lines_and_endings_read_as_the_protocol_says(script, capsys):
    """The script's own Progress prints; protocol.py, the launcher's reader, reads: a progress line, a heartbeat after a
    silent minute, and the done and stopped lines (each with exit status 0; any other status is a failure)."""
    import importlib

    module = importlib.import_module(script.removesuffix(".py"))
    progress = module.Progress(total=1000, unit="frame", start_step=100)
    progress.print_time -= 10
    progress.line(400, "eval return 0.50  loss 0.10")
    progress.print_time -= 61  # a silent minute
    progress.line(520, heartbeat=True)
    progress.finish(True, "KeyChest__G4__x__1__2", "520 frames")
    progress.finish(False, "KeyChest__G4__x__1__2", "1000 frames")
    line, heartbeat, stopped, done = capsys.readouterr().out.splitlines()
    read = protocol.read_progress(line)
    assert read["step"] == 400 and read["total"] == 1000 and read["figures"] == "eval return 0.50  loss 0.10"
    assert read["sps"] >= 0 and 0 < read["left"] < 10 * 600 / 300 + 1  # 600 frames left at 300 frames in about 10 s
    read = protocol.read_progress(heartbeat)
    assert heartbeat.endswith("(running)") and read["step"] == 520 and read["left"] is not None
    assert protocol.read_progress(stopped) is None and protocol.read_progress(done) is None
    assert protocol.ending([line, stopped], 0) == "stopped" and protocol.ending([line, done], 0) == "done"
    assert protocol.ending([line, done], 1) is None and protocol.ending([line], 0) is None
    source = (ROOT / script).read_text()
    assert all(f"signal.{number.name}" in source for number in protocol.STOP_SIGNALS)
    assert (module.RESUME_FILE, module.LOCK_FILE) == (protocol.RESUME_FILE, protocol.LOCK_FILE)


# --- The local backend ----------------------------------------------------------------------------------------------------


def test_a_local_sweep_runs_every_run_plots_it_and_a_relaunch_skips_it(tmp_path):
    result = launcher(tmp_path, "--preset", "smoke", "--table-every", "2")
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    sweep = tmp_path / "smoke"
    ids = [f"goal_dqn__SpiralWorld__G{g}__s{s}" for s in (1, 2) for g in (0, 4)] + [f"mnist__G2__s{s}" for s in (1, 2)]
    for run_id in ids:
        assert status(sweep, run_id)["state"] == "done" and status(sweep, run_id)["attempts"] == 1
        assert "done: " in (sweep / run_id / "log.txt").read_text()
    assert re.search(r"goal_dqn__SpiralWorld__G4__s2 +done +3000/3000 +\d+ ", result.stdout)  # the table
    assert "6 runs: 6 done" in result.stdout
    table = (sweep / "smoke_goal_dqn.md").read_text()
    assert "| SpiralWorld K8 G0 smoke | 2 |" in table and "| SpiralWorld K8 G4 smoke | 2 |" in table
    again = launcher(tmp_path, "--preset", "smoke")
    assert again.returncode == 0 and "6 done before, 0 failed before (--retry runs them again), 0 to run" in again.stdout
    assert "started" not in again.stdout and all(status(sweep, run_id)["attempts"] == 1 for run_id in ids)


def test_a_failed_run_is_reported_with_its_log_and_rerun_only_with_retry(tmp_path):
    script = tmp_path / "failing.py"
    script.write_text(FAILING_SCRIPT)
    result = launcher(tmp_path / "sweeps", "--script", str(script), "--groups", "0", "--seeds", "1")
    assert result.returncode == 1
    assert "FAILED failing__G0__s1: exit code 1;" in result.stdout
    assert "ValueError: boom: this run fails on purpose" in result.stdout  # the traceback's last line, from the log
    assert "1 of 1 runs are not done (1 failed)" in result.stdout
    sweep = tmp_path / "sweeps" / "failing"
    again = launcher(tmp_path / "sweeps", "--script", str(script), "--groups", "0", "--seeds", "1")
    assert again.returncode == 1 and "1 failed before" in again.stdout and status(sweep, "failing__G0__s1")["attempts"] == 1
    retried = launcher(tmp_path / "sweeps", "--script", str(script), "--groups", "0", "--seeds", "1", "--retry")
    assert retried.returncode == 1 and status(sweep, "failing__G0__s1")["attempts"] == 2


# The goal-DQN script as the launcher runs it, whose first attempt waits at its first progress line until the launcher
# stops it (tests/signal_at_line.py's hold): the stop comes mid-run however fast the machine finishes the run.
HOLD_AT_THE_FIRST_PROGRESS_LINE = """
import runpy, sys
script, holder = {script!r}, {holder!r}
sys.path[0] = {root!r}
if "--resume" in sys.argv:
    sys.argv[0] = script
    runpy.run_path(script, run_name="__main__")
else:
    sys.argv[:1] = [holder, "hold", {pattern!r}, script]
    runpy.run_path(holder, run_name="__main__")
"""


def held_goal_dqn(tmp_path: Path) -> Path:
    """The held goal-DQN script, under the name of the real one (so the same sweep and run names)."""
    held = tmp_path / "scripts" / "dgrl_goal_dqn.py"
    held.parent.mkdir()
    held.write_text(
        HOLD_AT_THE_FIRST_PROGRESS_LINE.format(
            script=str(ROOT / "dgrl_goal_dqn.py"), holder=str(ROOT / "tests" / "signal_at_line.py"), root=str(ROOT),
            pattern=PROGRESS.pattern,
        )
    )  # fmt: skip
    return held


def test_ctrl_c_stops_a_local_sweep_cleanly_and_a_relaunch_resumes_it_exactly(tmp_path):
    """A sweep interrupted by SIGINT mid-run (its run held at its first progress line until the launcher's stop reaches
    it), then launched again, ends with the curves and checkpoint of a sweep that ran straight through."""
    flags = ["--groups", "4", "--seeds", "1", "--", *GOAL_DQN]
    straight = popen_launcher(tmp_path / "straight", "--script", "dgrl_goal_dqn.py", *flags)
    flags = ["--script", str(held_goal_dqn(tmp_path)), *flags]
    stopped = popen_launcher(tmp_path / "stopped", *flags)
    sweep, run_id = tmp_path / "stopped" / "dgrl_goal_dqn", "goal_dqn__G4__s1"
    wait_for(lambda: log_has_progress(sweep, run_id), HANG_TIMEOUT, "the first progress line")
    stopped.send_signal(signal.SIGINT)
    output = stopped.communicate(timeout=HANG_TIMEOUT)[0]
    assert stopped.returncode == 1, output
    assert status(sweep, run_id)["state"] == "stopped" and "launch the same command again" in output
    assert (run_dir(sweep, run_id) / "resume.pt").is_file()
    resumed = launcher(tmp_path / "stopped", *flags)
    assert resumed.returncode == 0, resumed.stdout[-3000:]
    assert "1 to run (1 resuming)" in resumed.stdout and "resumed at" in (sweep / run_id / "log.txt").read_text()
    assert straight.wait(timeout=HANG_TIMEOUT) == 0
    assert status(sweep, run_id)["attempts"] == 2
    assert_same_run(run_dir(tmp_path / "straight" / "dgrl_goal_dqn", run_id), run_dir(sweep, run_id))


def test_a_second_launcher_of_a_running_sweep_is_refused(tmp_path):
    """Two launchers of one sweep would run the same runs twice: the second exits with status 2, naming the first."""
    script = tmp_path / "sleeping.py"
    script.write_text(SLEEPING_SCRIPT)
    flags = ["--script", str(script), "--groups", "0", "--seeds", "1"]
    first = popen_launcher(tmp_path / "sweeps", *flags)
    sweep = tmp_path / "sweeps" / "sleeping"
    wait_for(
        lambda: log_has_progress(sweep, "sleeping__G0__s1", re.compile("^step 1/10", re.M)), HANG_TIMEOUT, "the run's start"
    )
    second = launcher(tmp_path / "sweeps", *flags)
    assert second.returncode == 2 and "is in use by another launcher (pid" in second.stderr, second.stderr
    assert status(sweep, "sleeping__G0__s1")["attempts"] == 1
    first.send_signal(signal.SIGINT)  # the sleeping run has no stop handler: the launcher's SIGTERM ends it
    assert first.wait(timeout=HANG_TIMEOUT) == 1
    ended = status(sweep, "sleeping__G0__s1")  # stopped by the launcher, not failed: a relaunch runs it again
    assert ended["state"] == "stopped" and ended["rc"] == -signal.SIGTERM and ended["seconds"] > 0


def hold_lock(run_dir: Path, holder: str):
    """Take a run folder's lock as a live run holds it (flock, its holder written in), once no process holds it."""
    import fcntl

    wait_for(lambda: protocol.lock_holder(run_dir) is None, HANG_TIMEOUT, f"{run_dir.name}'s process to end")
    lock = open(run_dir / protocol.LOCK_FILE, "a+")
    fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    lock.truncate(0)
    lock.write(f"{holder}\n")
    lock.flush()
    return lock


def test_a_killed_launchers_runs_stop_with_it_and_a_relaunch_trains_each_once_exactly(tmp_path):
    """kill -9 of a launcher with two runs under way (each held at its first progress line): each run gets SIGTERM
    from the kernel as its launcher dies and stops with its resume file, as on Ctrl-C. The launch again finds one run
    still held by another process (the test takes its lock, as a run still stopping or an orphan training on would hold
    it): it says so, waits, never starts it beside the holder, and resumes it once free. Both runs end equal to a
    straight sweep's, each attempt starting only after the one before it has ended (one writer at a time)."""
    flags = ["--groups", "0", "4", "--seeds", "1", "--", *GOAL_DQN]
    straight = popen_launcher(tmp_path / "straight", "--script", "dgrl_goal_dqn.py", *flags)
    flags = ["--script", str(held_goal_dqn(tmp_path)), *flags]
    killed = popen_launcher(tmp_path / "killed", *flags)
    sweep, ids = tmp_path / "killed" / "dgrl_goal_dqn", ["goal_dqn__G0__s1", "goal_dqn__G4__s1"]
    for run_id in ids:
        wait_for(lambda run_id=run_id: log_has_progress(sweep, run_id), HANG_TIMEOUT, f"{run_id}'s first progress line")
    killed.kill()
    killed.communicate()
    for run_id in ids:  # the parent-death signal reached the held runs: they stop as on Ctrl-C
        wait_for(lambda run_id=run_id: "\nstopped: " in (sweep / run_id / "log.txt").read_text(), HANG_TIMEOUT, "a stop")
    lock = hold_lock(run_dir(sweep, ids[1]), "pid 4242 on elsewhere-host")
    relaunch = popen_launcher(tmp_path / "killed", *flags)
    seen = []
    for line in relaunch.stdout:
        seen.append(line)
        if line.startswith("running elsewhere "):
            break
    assert seen[-1].startswith(f"running elsewhere {ids[1]} (pid 4242 on elsewhere-host): waiting"), "".join(seen)
    assert "2 to run (2 resuming), 1 of them still running elsewhere" in "".join(seen)
    assert "=== attempt 2" not in (sweep / ids[1] / "log.txt").read_text() and status(sweep, ids[1])["attempts"] == 1
    lock.close()  # the holder ends: the run resumes
    output = "".join(seen) + relaunch.communicate(timeout=HANG_TIMEOUT)[0]
    assert relaunch.returncode == 0, output[-3000:]
    assert straight.wait(timeout=HANG_TIMEOUT) == 0
    for run_id in ids:
        log = (sweep / run_id / "log.txt").read_text()
        attempts = log.split("=== attempt ")[1:]
        assert len(attempts) == 2 and status(sweep, run_id)["state"] == "done", log[-3000:]
        assert "\nstopped: " in attempts[0] and "resumed at DQN step" in attempts[1] and "\ndone: " in attempts[1]
        assert log.count("\ndone: ") == 1 and protocol.lock_holder(run_dir(sweep, run_id)) is None
        assert_same_run(run_dir(tmp_path / "straight" / "dgrl_goal_dqn", run_id), run_dir(sweep, run_id))


def test_a_run_that_ended_while_no_launcher_watched_is_read_from_its_logs_last_attempt(tmp_path):
    """What a relaunch records for a run it waited for: the ending of the log's last attempt only."""
    run = launch.Run("r", "dgrl_goal_dqn.py", [], tmp_path)
    assert launch.last_ending(run) is None  # no log yet
    first = "=== attempt 1 at 2026-01-01 00:00:00: python x.py\nstep 1/10  a  SPS 1  1s elapsed, 9s left\n"
    first += "stopped: 1 step; 1s\n"
    (tmp_path / "log.txt").write_text(first)
    assert launch.last_ending(run) == "stopped"
    (tmp_path / "log.txt").write_text(first + "=== attempt 2 at 2026-01-01 00:01:00: python x.py --resume runs/a\n")
    assert launch.last_ending(run) is None  # the second attempt has not ended (or crashed): resumed, not recorded done
    (tmp_path / "log.txt").write_text(first + "=== attempt 2 at 2026-01-01 00:01:00: python x.py\ndone: 10 steps; 9s\n")
    assert launch.last_ending(run) == "done"


def test_a_slurm_task_waits_for_a_held_run_then_refuses_it_naming_the_holder(tmp_path):
    """A requeued Slurm task that finds a run's folder still held (the task before it not yet gone) does not start it
    beside the holder: after its bounded wait (none here) the run is recorded as failed, naming the holder."""
    from slurm_backend import SlurmTask

    run = launch.expand((launch.Arm("dgrl_goal_dqn.py", (), (4,), (1,), shlex.join(GOAL_DQN)),), "s", tmp_path, 1)[0]
    (run.folder / "runs" / "held_run").mkdir(parents=True)
    lock = hold_lock(run.folder / "runs" / "held_run", "pid 4242 on node-7")
    with pytest.raises(RuntimeError, match="FAILED goal_dqn__G4__s1"):
        SlurmTask([run], sys.executable, 1, stop_wait=0)()
    ended = run.status()
    assert ended["state"] == "failed" and "held by pid 4242 on node-7 after 0 s" in ended["tail"][0]
    assert not (run.folder / "log.txt").exists()  # never started
    lock.close()


# --- The Slurm backend, on a real cluster ------------------------------------------------------------------------------


def slurm_problem() -> str | None:
    """Why the slurm tests cannot run here, or None."""
    if shutil.which("sbatch") is None:
        return "no Slurm on this machine (sbatch not found): `bash .ci/slurm.sh` starts a single-node cluster, as root"
    for command in (["sinfo", "-h", "-o", "%T"], ["sacct", "-n", "-X", "-S", "now"]):
        try:
            result = subprocess.run(command, capture_output=True, text=True, timeout=120)
        except subprocess.TimeoutExpired:
            return f"`{shlex.join(command)}` timed out: is the cluster up? (`bash .ci/slurm.sh`)"
        if result.returncode != 0:
            return (
                f"`{shlex.join(command)}` failed ({result.stderr.strip()[:200]}): start the cluster with `bash .ci/slurm.sh`"
            )
    return None


PROBLEM = slurm_problem()
if PROBLEM and os.environ.get("DGRL_REQUIRE_SLURM"):
    raise RuntimeError(f"DGRL_REQUIRE_SLURM is set, but {PROBLEM}")
needs_slurm = pytest.mark.skipif(PROBLEM is not None, reason=PROBLEM or "")


def slurm_job(sweep: Path):
    """The submitit job of a one-run sweep (for submitit's own preemption and timeout signals)."""
    import submitit

    wait_for(lambda: (sweep / "slurm_jobs.json").is_file(), HANG_TIMEOUT, "the job's submission")
    (job_id,) = json.loads((sweep / "slurm_jobs.json").read_text())
    return submitit.SlurmJob(folder=sweep / "slurm" / "%j", job_id=job_id)


@pytest.mark.slurm
@needs_slurm
def test_a_slurm_sweep_of_two_scripts_equals_the_same_sweep_run_locally(tmp_path):
    local = popen_launcher(tmp_path / "local", "--preset", "smoke")
    result = launcher(tmp_path / "slurm", "--preset", "smoke", "--backend", "slurm", "--table-every", "10")
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-3000:]
    assert "submitted 6 array tasks of job" in result.stdout and "6 runs: 6 done" in result.stdout
    assert local.wait(timeout=HANG_TIMEOUT) == 0
    for run in launch.expand(launch.PRESETS["smoke"].arms, "smoke", Path("."), 1):
        on_slurm = status(tmp_path / "slurm" / "smoke", run.run_id)
        assert on_slurm["slurm_job"] and on_slurm["state"] == "done"
        assert_same_run(run_dir(tmp_path / "local" / "smoke", run.run_id), run_dir(tmp_path / "slurm" / "smoke", run.run_id))
    assert (tmp_path / "slurm" / "smoke" / "smoke_goal_dqn.md").read_text() == (
        tmp_path / "local" / "smoke" / "smoke_goal_dqn.md"
    ).read_text()


def interrupted_run_resumes_exactly(tmp_path: Path, slurm_flags: list[str], interrupt) -> tuple[str, str]:
    """A one-run goal-DQN sweep on Slurm, interrupted by `interrupt(job)` once training is under way (or by its time
    limit when `interrupt` is None), must requeue, resume and end equal to the same sweep run locally, the launcher
    waiting for it. Returns the run's log and the launcher's output.
    The first attempt holds at its first progress line until the stop signal reaches it, so that it is interrupted
    mid-run however fast the machine; the requeued attempt runs the plain script."""
    flags = ["--env-ids", "SpiralWorld", "--groups", "4", "--seeds", "1"]
    local = popen_launcher(tmp_path / "local", "--script", "dgrl_goal_dqn.py", *flags, "--", *GOAL_DQN)
    flags = ["--script", str(held_goal_dqn(tmp_path)), *flags]
    on_slurm = popen_launcher(
        tmp_path / "slurm", *flags, "--backend", "slurm", "--table-every", "10", *slurm_flags, "--", *GOAL_DQN
    )
    sweep, run_id = tmp_path / "slurm" / "dgrl_goal_dqn", "goal_dqn__SpiralWorld__G4__s1"
    if interrupt is not None:
        job = slurm_job(sweep)
        wait_for(lambda: log_has_progress(sweep, run_id), HANG_TIMEOUT, "the first progress line on Slurm")
        interrupt(job)
    output = on_slurm.communicate(timeout=HANG_TIMEOUT)[0]
    assert on_slurm.returncode == 0, output[-4000:]
    assert local.wait(timeout=HANG_TIMEOUT) == 0
    log = (sweep / run_id / "log.txt").read_text()
    assert status(sweep, run_id)["attempts"] >= 2 and "resumed at" in log, log[-3000:]
    assert_same_run(run_dir(tmp_path / "local" / "dgrl_goal_dqn", run_id), run_dir(sweep, run_id))
    assert f"done {run_id}" in output and "launch the same command again" not in output, output[-4000:]
    return log, output


@pytest.mark.slurm
@needs_slurm
def test_a_preempted_slurm_job_requeues_and_ends_equal_to_an_uninterrupted_run(tmp_path):
    """submitit's preemption path (SIGTERM, then its USR2): the run stops with its resume file, the job requeues."""
    log, _ = interrupted_run_resumes_exactly(tmp_path, [], lambda job: job._interrupt(timeout=False))
    assert re.search(r"^stopped: ", log, re.M)


@pytest.mark.slurm
@needs_slurm
def test_a_task_that_slurm_requeues_itself_is_followed_to_its_end(tmp_path):
    """`scontrol requeue`, as an administrator or a preempting partition does it: Slurm's SIGTERM stops the run with its
    resume file and Slurm restarts the task by itself. The launcher shows the run requeued and waits for it; it never
    asks for a relaunch while Slurm still holds the job."""
    log, output = interrupted_run_resumes_exactly(
        tmp_path, [], lambda job: subprocess.run(["scontrol", "requeue", job.job_id], check=True, timeout=60)
    )
    assert re.search(r"^stopped: ", log, re.M)
    assert re.search(r"^requeued goal_dqn__SpiralWorld__G4__s1 \(job \d+(_0)?, Slurm state [A-Z_]+\)$", output, re.M), output


@pytest.mark.slurm
@needs_slurm
def test_a_slurm_job_at_its_time_limit_requeues_and_ends_equal_to_an_uninterrupted_run(tmp_path):
    """A 2-minute limit with the stop signal 60 s before it: the run, held at its first progress line, is stopped by it
    and requeued. The signal kills a job still starting Python, so it comes late enough for a loaded machine."""
    log, _ = interrupted_run_resumes_exactly(tmp_path, ["--time-min", "2", "--signal-delay-s", "60"], None)
    assert re.search(r"^stopped: ", log, re.M)


@pytest.mark.slurm
@needs_slurm
def test_a_job_array_that_sbatch_refuses_exits_2_with_sbatchs_message(tmp_path):
    result = launcher(tmp_path, "--preset", "smoke", "--backend", "slurm", "--partition", "no-such-partition")
    assert result.returncode == 2, result.stdout[-2000:] + result.stderr[-2000:]
    assert "sbatch refused the sweep's job array" in result.stderr and "invalid partition" in result.stderr.lower()
    assert "Traceback" not in result.stderr


@pytest.mark.slurm
@needs_slurm
def test_a_failing_run_on_slurm_surfaces_its_traceback(tmp_path):
    script = tmp_path / "failing.py"
    script.write_text(FAILING_SCRIPT)
    result = launcher(
        tmp_path / "sweeps",
        "--script",
        str(script),
        "--groups",
        "0",
        "--seeds",
        "1",
        "--backend",
        "slurm",
        timeout=HANG_TIMEOUT,
    )
    assert result.returncode == 1, result.stdout[-3000:]
    assert "FAILED failing__G0__s1: exit code 1;" in result.stdout
    assert "ValueError: boom: this run fails on purpose" in result.stdout


@pytest.mark.slurm
@needs_slurm
def test_a_sweep_whose_jobs_are_still_queued_is_not_submitted_again(tmp_path):
    """Ctrl-C on the launcher leaves the job running; launching the sweep again then refuses, naming the job."""
    script = tmp_path / "sleeping.py"
    script.write_text(SLEEPING_SCRIPT)
    flags = ["--script", str(script), "--groups", "0", "--seeds", "1", "--backend", "slurm"]
    first = popen_launcher(tmp_path / "sweeps", *flags)
    sweep = tmp_path / "sweeps" / "sleeping"
    job = slurm_job(sweep)
    try:
        wait_for(
            lambda: log_has_progress(sweep, "sleeping__G0__s1", re.compile("^step 1/10", re.M)),
            HANG_TIMEOUT,
            "the run's start",
        )
        first.send_signal(signal.SIGINT)
        output = first.communicate(timeout=HANG_TIMEOUT)[0]
        assert first.returncode == 130 and "stopped waiting: the jobs go on in the queue" in output, output
        again = launcher(tmp_path / "sweeps", *flags)
        assert again.returncode == 2 and f"this sweep already has jobs in the queue ({job.job_id})" in again.stderr
    finally:
        subprocess.run(["scancel", job.job_id.split("_")[0]], check=False)


@pytest.mark.slurm
@needs_slurm
def test_a_killed_slurm_job_is_reported_not_waited_on(tmp_path):
    """SIGKILL to every process of the job (the run and submitit's own, as the kernel's out-of-memory killer would): no
    result is ever written; Slurm's accounting tells the launcher that the job is over."""
    script = tmp_path / "sleeping.py"
    script.write_text(SLEEPING_SCRIPT)
    sweeps = tmp_path / "sweeps"
    process = popen_launcher(sweeps, "--script", str(script), "--groups", "0", "--seeds", "1", "--backend", "slurm")
    sweep = sweeps / "sleeping"
    job = slurm_job(sweep)
    wait_for(
        lambda: log_has_progress(sweep, "sleeping__G0__s1", re.compile("^step 1/10", re.M)), HANG_TIMEOUT, "the run's start"
    )
    running = status(sweep, "sleeping__G0__s1")
    assert running["slurm_job"] == job.job_id.split("_")[0]
    for pid in (running["parent_pid"], running["pid"]):  # submitit's process in the job, then the run
        os.kill(pid, signal.SIGKILL)
    output = process.communicate(timeout=HANG_TIMEOUT)[0]
    assert process.returncode == 1, output[-3000:]
    assert "FAILED sleeping__G0__s1" in output and "ended without a result" in output
