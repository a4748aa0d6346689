"""benchmark/analysis/plot.py: settings grouped over seeds, mean and std on the common steps, table and figure written."""

import subprocess
import sys
from pathlib import Path

from conftest import HANG_TIMEOUT
from torch.utils.tensorboard import SummaryWriter

ROOT = Path(__file__).resolve().parents[1]
PLOT_FLAGS = ["--tags", "eval/novel_success_rate", "--out"]


def write_run(runs_dir: Path, name: str, values: dict[int, float]) -> None:
    writer = SummaryWriter(str(runs_dir / name))
    for step, value in values.items():
        writer.add_scalar("eval/novel_success_rate", value, step)
    writer.close()


def test_plot_groups_seeds_and_summarises_the_common_steps(tmp_path):
    runs = tmp_path / "runs"
    write_run(runs, "SpiralWorld__K8__G16__demo__1__100", {1000: 0.0, 2000: 0.5, 3000: 1.0})
    write_run(runs, "SpiralWorld__K8__G16__demo__2__200", {1000: 0.5, 2000: 0.5, 3000: 0.5, 4000: 0.0})
    write_run(runs, "SpiralWorld__K8__G0__demo__1__300", {1000: 0.25, 2000: 0.25, 3000: 0.25})
    write_run(runs, "SpiralWorld__K8__G0__other__1__400", {1000: 9.0})  # excluded by --match
    result = subprocess.run(
        [
            sys.executable,
            str(ROOT / "benchmark/analysis/plot.py"),
            "--runs-dir",
            str(runs),
            "--match",
            "__demo__",
            *PLOT_FLAGS,
            str(tmp_path / "out"),
        ],
        capture_output=True,
        text=True,
        timeout=HANG_TIMEOUT,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    table = (tmp_path / "out.md").read_text().splitlines()
    assert (tmp_path / "out.png").stat().st_size > 1000
    rows = {line.split(" | ")[0].strip("| "): line for line in table[2:]}
    assert set(rows) == {"SpiralWorld K8 G0 demo", "SpiralWorld K8 G16 demo"}
    # G16: steps 1000-3000 are common; final values 1.0 and 0.5 -> 0.75 +- 0.25; per-seed averages 0.5 and 0.5.
    assert "| 2 | 0.75 +- 0.25 (avg 0.5 +- 0)" in rows["SpiralWorld K8 G16 demo"]
    assert "| 1 | 0.25 +- 0 (avg 0.25 +- 0)" in rows["SpiralWorld K8 G0 demo"]


def test_plot_fails_clearly_when_nothing_matches(tmp_path):
    (tmp_path / "runs").mkdir()
    result = subprocess.run(
        [sys.executable, str(ROOT / "benchmark/analysis/plot.py"), "--runs-dir", str(tmp_path / "runs"), "--match", "nothing"],
        capture_output=True,
        text=True,
        timeout=HANG_TIMEOUT,
    )
    assert result.returncode != 0 and "no run in" in result.stderr


def test_plot_bins_runs_whose_evaluation_steps_differ(tmp_path):
    runs = tmp_path / "runs"
    write_run(runs, "KeyChest__G16__demo__1__100", {0: 0.0, 100: 1.0, 240: 2.0, 390: 3.0, 400: 4.0})
    write_run(runs, "KeyChest__G16__demo__2__200", {10: 1.0, 150: 1.0, 260: 3.0, 300: 5.0, 410: 9.0})
    flags = ["--runs-dir", str(runs), "--match", "__demo__", "--bins", "2", *PLOT_FLAGS, str(tmp_path / "out")]
    command = [sys.executable, str(ROOT / "benchmark/analysis/plot.py"), *flags]
    result = subprocess.run(command, capture_output=True, text=True, timeout=HANG_TIMEOUT)
    assert result.returncode == 0, result.stderr[-2000:]
    row = (tmp_path / "out.md").read_text().splitlines()[2]
    # Shared range [10, 400], bins [10, 205) and [205, 400]. Seed 1: (1.0) then (2, 3, 4) -> 1.0, 3.0;
    # seed 2: (1, 1) then (3, 5) -> 1.0, 4.0. Final bin 3.0 and 4.0 -> 3.5 +- 0.5; averages 2.0 and 2.5 -> 2.25 +- 0.25.
    assert "| 2 | 3.5 +- 0.5 (avg 2.25 +- 0.25)" in row
