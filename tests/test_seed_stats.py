"""benchmark/analysis/seed_stats.py: the statistics against values worked out by hand, and a sweep compared per seed."""

import os
import subprocess
import sys
from math import comb
from pathlib import Path

import numpy as np
import pytest
from torch.utils.tensorboard import SummaryWriter

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmark" / "analysis"))

import float_paths
import seed_stats
from conftest import HANG_TIMEOUT

ROOT = Path(__file__).resolve().parents[1]


def test_permutation_p_of_fully_separated_groups_is_one_split_in_all():
    treated, control = np.array([3.0, 4.0, 5.0]), np.array([0.0, 1.0, 2.0])
    assert seed_stats.permutation_p(treated, control) == pytest.approx(1 / comb(6, 3))
    assert seed_stats.permutation_p(treated, control, higher_is_better=True) == pytest.approx(1 / 20)
    # lower is better: the same data is the least favourable split of all
    assert seed_stats.permutation_p(treated, control, higher_is_better=False) == pytest.approx(1.0)
    assert seed_stats.permutation_p(control, treated, higher_is_better=False) == pytest.approx(1 / 20)


def test_permutation_p_counts_ties_as_extreme():
    same = np.array([1.0, 1.0])
    assert seed_stats.permutation_p(same, same) == 1.0  # every split gives the observed difference, 0


def test_spearman_uses_ranks_with_shared_ranks_for_ties():
    a = np.array([1.0, 2.0, 3.0, 4.0])
    assert seed_stats.spearman(a, a**3) == pytest.approx(1.0)  # monotone, not linear
    assert seed_stats.spearman(a, -a) == pytest.approx(-1.0)
    np.testing.assert_allclose(seed_stats.ranks(np.array([5.0, 1.0, 5.0, 2.0])), [2.5, 0.0, 2.5, 1.0])


def test_bootstrap_interval_brackets_the_difference_and_is_a_point_for_constant_groups():
    rng = np.random.default_rng(0)
    assert seed_stats.bootstrap_interval(np.full(5, 2.0), np.full(5, 0.5), rng) == (1.5, 1.5)
    low, high = seed_stats.bootstrap_interval(np.array([1.0, 2, 3, 4, 5]), np.array([0.0, 1, 2, 3, 4]), rng)
    assert low < 1.0 < high and high - low < 4.0


def test_gain_difference_interval_of_constant_groups_is_the_difference_of_the_gains():
    rng = np.random.default_rng(0)
    ones = np.ones(3)
    assert seed_stats.gain_difference_interval(3 * ones, ones, 1.5 * ones, ones, rng) == pytest.approx((1.5, 1.5))
    low, high = seed_stats.gain_difference_interval(np.array([2.0, 4.0]), ones, 1.5 * ones, ones, rng)
    assert low == pytest.approx(0.5) and high == pytest.approx(2.5)  # treated_a resampled: means 2, 3 or 4


def test_late_mean_averages_the_last_tenth_of_steps():
    steps = np.arange(0, 101, dtype=float)
    values = np.where(steps >= 90, 7.0, 0.0)
    assert seed_stats.late_mean((steps, values)) == 7.0


def test_summaries_and_first_reach_of_a_curve():
    curve = (np.array([10.0, 20.0, 30.0, 40.0]), np.array([0.0, 6.0, 2.0, 4.0]))
    assert seed_stats.summarise(curve, "final") == 4.0
    assert seed_stats.summarise(curve, "mean") == 3.0
    assert seed_stats.summarise(curve, "late") == 4.0  # steps >= 37: the last one only
    assert seed_stats.first_reach(curve, 5.0) == (20.0, True)
    assert seed_stats.first_reach(curve, 7.0) == (40.0, False)  # never: censored at the last step
    assert seed_stats.lower_is_better("eval/novel_total_steps") and seed_stats.lower_is_better("eval/subgoal_distance")
    assert not seed_stats.lower_is_better("eval/return") and not seed_stats.lower_is_better("eval/train_success_rate")


def write_run(runs_dir: Path, name: str, values: list[float]) -> None:
    writer = SummaryWriter(str(runs_dir / name))
    for step, value in enumerate(values, start=1):
        writer.add_scalar("eval/return", value, step * 1000)
    writer.close()


def test_a_sweep_is_compared_per_env_against_its_own_baseline(tmp_path):
    for seed in (1, 2, 3):
        write_run(tmp_path, f"KeyChest__G0__study__{seed}__1", [0.0, 1.0, 2.0, 2.0])
        write_run(tmp_path, f"KeyChest__G16__study__{seed}__1", [0.0, 5.0, 6.0, 6.0 - seed])
        write_run(tmp_path, f"KeyChest__G4__study__{seed}__1", [0.0, 0.0, 1.0, 1.0])
        write_run(tmp_path, f"Other__G0__study__{seed}__1", [9.0, 9.0, 9.0, 9.0])  # another comparison
    write_run(tmp_path, "KeyChest__G16__study__4__1", [0.0, 6.0])  # still running: left out
    write_run(tmp_path, "Other__G16__study__1__1", [0.0])  # its group's only run, still running
    result = subprocess.run(
        [sys.executable, str(ROOT / "benchmark/analysis/seed_stats.py"), str(tmp_path), "--tags", "eval/return",
         "--summaries", "final", "--reach", "eval/return=5", "--markdown", str(tmp_path / "out.md")],
        capture_output=True, text=True, timeout=HANG_TIMEOUT,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    text = (tmp_path / "out.md").read_text()
    keychest, other = text.split("\n\n" + tmp_path.name + ": ")
    assert "G0 3 seeds, G4 3 seeds, G16 3 seeds (KeyChest__study)" in keychest and "G0 3 seeds (Other__study)" in other
    assert "(running or stopped): G16 seed 4" in keychest and "(running or stopped): G16 seed 1" in other
    assert "| 0 | 2, 2, 2 | 2 +- 0 | |" in keychest
    # G16 ends on 5, 4, 3: 2 above the baseline, every split as favourable is the observed one: p = 1 / C(6, 3)
    assert f"| 16 | 5, 4, 3 | 4 +- 0.82 | +2 [+1, +3] | {1 / comb(6, 3):.3f} | 1.000 |" in keychest
    # first evaluation with a return of 5: G16 at step 2000, the baseline never (censored at its last step, 4000)
    assert "| 0 | >4e+03, >4e+03, >4e+03 | 4e+03 +- 0 | |" in keychest
    assert f"| 16 | 2e+03, 2e+03, 2e+03 | 2e+03 +- 0 | -2e+03 [-2e+03, -2e+03] | {1 / comb(6, 3):.3f} | 1.000 |" in keychest
    # G4 ends on 1, 1, 1, below every baseline seed: p = 1 in its favour, 1 / C(6, 3) in the baseline's
    assert f"| 4 | 1, 1, 1 | 1 +- 0 | -1 [-1, -1] | 1.000 | {1 / comb(6, 3):.3f} |" in keychest
    assert "vs G0" in other and "| 0 | 9, 9, 9 | 9 +- 0 | |" in other and "| 16 |" not in other
    # the family: G4 and G16 of KeyChest, final and first reach (Other has no DGRL run left); each direction counted
    assert "multiplicity: 4 comparisons with G0; one-sided p <= 0.05 for DGRL in 2, for G0 in 1;" in other
    assert "| KeyChest__study: eval/return, final, G16 | DGRL | 0.100 | 0.400 |" in other  # 3 at 0.1: 0.1 x 4
    gains = subprocess.run(
        [sys.executable, str(ROOT / "benchmark/analysis/seed_stats.py"), str(tmp_path), "--tags", "eval/return",
         "--summaries", "final", "--gain-between", "KeyChest__study", "Other__study"],
        capture_output=True, text=True, timeout=HANG_TIMEOUT,
    )  # fmt: skip
    assert gains.returncode == 0 and "gain over G0 in KeyChest__study minus gain over G0 in Other__study" in gains.stdout
    assert "| eval/return, final | 4 |" not in gains.stdout  # Other has no G4 (and its G16 run was left out)
    missing = subprocess.run(
        [sys.executable, str(ROOT / "benchmark/analysis/seed_stats.py"), str(tmp_path), "--tags", "eval/return",
         "--gain-between", "KeyChest__study", "Nope"],
        capture_output=True, text=True, timeout=HANG_TIMEOUT,
    )  # fmt: skip
    assert missing.returncode != 0 and "named Nope; the sweep's: KeyChest__study, Other__study" in missing.stderr


def test_against_takes_another_arm_as_the_reference(tmp_path):
    """--against 16: every other G, the baseline included, is compared with G16 (a ranking among the DGRL arms)."""
    for seed in (1, 2, 3):
        write_run(tmp_path, f"Maze__G0__study__{seed}__1", [0.0, 2.0])
        write_run(tmp_path, f"Maze__G16__study__{seed}__1", [0.0, 6.0 - seed])
        write_run(tmp_path, f"Maze__G4__study__{seed}__1", [0.0, 1.0])
    command = [sys.executable, str(ROOT / "benchmark/analysis/seed_stats.py"), str(tmp_path), "--tags", "eval/return",
               "--summaries", "final"]  # fmt: skip
    result = subprocess.run([*command, "--against", "16"], capture_output=True, text=True, timeout=HANG_TIMEOUT)
    assert result.returncode == 0, result.stderr
    assert "| G | per seed | mean +- std | vs G16: difference [95% bootstrap] | one-sided p, this G better |" in result.stdout
    # G16 ends on 5, 4, 3, above every seed of G0 (2) and of G4 (1): each split as extreme is the observed one
    assert f"| 0 | 2, 2, 2 | 2 +- 0 | -2 [-3, -1] | 1.000 | {1 / comb(6, 3):.3f} |" in result.stdout
    assert f"| 4 | 1, 1, 1 | 1 +- 0 | -3 [-4, -2] | 1.000 | {1 / comb(6, 3):.3f} |" in result.stdout
    assert "| 16 | 5, 4, 3 | 4 +- 0.82 | | |" in result.stdout
    assert "2 comparisons with G16; one-sided p <= 0.05 for the other G in 0, for G16 in 2;" in result.stdout
    assert "| eval/return, final, G4 | G16 | 0.100 | 0.200 |" in result.stdout
    missing = subprocess.run([*command, "--against", "8"], capture_output=True, text=True, timeout=HANG_TIMEOUT)
    assert missing.returncode != 0 and "--against 8: no run of the sweep has G = 8; its G: [0, 4, 16]" in missing.stderr


def test_holm_multiplies_the_kth_smallest_by_m_minus_k_plus_1_and_keeps_the_order():
    # sorted: 0.01 x 4 = 0.04, 0.03 x 3 = 0.09, 0.04 x 2 = 0.08 -> 0.09 (never below the one before), 0.2 x 1 = 0.2
    assert seed_stats.holm([0.01, 0.04, 0.03, 0.2]) == pytest.approx([0.04, 0.09, 0.09, 0.2])
    assert seed_stats.holm([0.5, 0.6]) == [1.0, 1.0]  # capped at 1
    assert seed_stats.holm([]) == []


def test_the_multiplicity_statement_counts_each_direction_and_adjusts_two_sided_p():
    family = [("a, G4", 0.004, 1.0), ("a, G16", 0.9, 0.1), ("b, G4", 1.0, 0.02)]
    lines = seed_stats.multiplicity_lines(family)
    assert "3 comparisons with G0; one-sided p <= 0.05 for DGRL in 1, for G0 in 1; Holm-adjusted" in lines[1]
    # two-sided 0.008, 0.2, 0.04: Holm 0.008 x 3 = 0.024, 0.04 x 2 = 0.08, 0.2 x 1 -> 0.2
    assert "| a, G4 | DGRL | 0.008 | 0.024 |" in lines and "| b, G4 | G0 | 0.040 | 0.080 |" in lines
    assert "| a, G16 | G0 | 0.200 | 0.200 |" in lines and lines[1].endswith("p <= 0.05 in 1")
    assert seed_stats.multiplicity_lines([]) == []


def test_a_tag_the_baseline_does_not_log_is_tabulated_without_a_comparison(recwarn):
    """The codebook's tags: G0 has no codebook, so its row says so and no DGRL row is compared with it (no NaN)."""
    values = {0: np.array([]), 4: np.array([8.0, 9.0]), 16: np.array([58.0, 60.0])}
    marks = {group: [""] * len(v) for group, v in values.items()}
    lines = seed_stats.table(values, marks, True, np.random.default_rng(0))
    assert lines[2:] == ["| 0 | (not logged) | | | | |", "| 4 | 8, 9 | 8.5 +- 0.5 | | | |", "| 16 | 58, 60 | 59 +- 1 | | | |"]
    assert not [warning for warning in recwarn if issubclass(warning.category, RuntimeWarning)]


def test_ledger_stats_windows_and_its_transcribed_tables():
    import ledger_stats

    assert ledger_stats.first_window_at([[0.1, 0.95, 0.2], [0.0, 0.5, 0.9]], 0.9, 0.2) == [0.2, 0.4]
    # the published tables: 15 windows of 200k frames (3M), 15 evaluations every 2k steps (30k), 3 or 2 seeds
    assert all(len(row) == 15 for rows in ledger_stats.S3R1_3M.values() for row in rows)
    assert all(len(row) == 15 for rows in ledger_stats.SAWYER.values() for row in rows)
    assert ledger_stats.compare("x", [3.0, 4.0, 5.0], [0.0, 1.0, 2.0]).endswith(f"p = {1 / comb(6, 3):.3f}")


def write_mnist_run(runs_dir: Path, name: str, swaps: tuple[float, float]) -> None:
    writer = SummaryWriter(str(runs_dir / name))
    for tag in ("vq/perplexity", "vq/active_codes", "losses/reconstruction", "vq/commit_loss"):
        writer.add_scalar(tag, 10.0 + swaps[0], 1)
    for tag in ("factor/factor1/digit_acc", "factor/factor1/colour_acc", "factor/factor2/digit_acc"):
        writer.add_scalar(tag, 0.5, 1)
    writer.add_scalar("factor/factor2/colour_acc", 0.5, 1)
    writer.add_scalar("factor/test/reconstruction_mse", 0.02, 1)
    writer.add_scalar("factor/swap/shape1_colour2", swaps[0], 1)
    writer.add_scalar("factor/swap/colour1_shape2", swaps[1], 1)
    writer.close()


def test_mnist_seeds_reads_several_sweeps_and_compares_a_variant_with_the_default(tmp_path):
    default, variant = tmp_path / "default", tmp_path / "variant"
    for seed in (1, 2, 3):
        write_mnist_run(default, f"ColorMNIST__G0__ten__{seed}__1", (0.05, 0.06))
        write_mnist_run(default, f"ColorMNIST__G2__ten__{seed}__1", (0.1 * seed, 0.6))  # the better swap: 0.6 each
        write_mnist_run(variant, f"ColorMNIST__G2__restart__{seed}__1", (0.1 * seed, 0.0))  # 0.1, 0.2, 0.3
    result = subprocess.run(
        [sys.executable, str(ROOT / "benchmark/analysis/mnist_seeds.py"), str(default), str(variant),
         "--against", "ColorMNIST__G2__ten", "--markdown", str(tmp_path / "out.md"), "--plot", str(tmp_path / "seeds.png")],
        capture_output=True, text=True, timeout=HANG_TIMEOUT,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    text = (tmp_path / "out.md").read_text()
    assert "| ColorMNIST__G2__ten | 3 | 0.600 +- 0.000 | 0.600 | 0.600-0.600 | 3 |" in text
    assert "| ColorMNIST__G2__restart | 3 | 0.200 +- 0.082 | 0.200 | 0.100-0.300 | 1 |" in text
    # every restart seed below every default seed: p = 1 / C(6, 3) for "lower", 1 for "higher"
    expected = f"-0.400; one-sided exact permutation p = 1.0000 (higher), {1 / comb(6, 3):.4f} (lower)"
    assert f"ColorMNIST__G2__restart vs ColorMNIST__G2__ten: better swap rate {expected}" in text
    assert "ColorMNIST__G2__restart vs ColorMNIST__G0__ten: one-sided exact permutation p = 0.0500" in text
    assert (tmp_path / "seeds.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    bad = subprocess.run(
        [sys.executable, str(ROOT / "benchmark/analysis/mnist_seeds.py"), str(default), "--against", "ColorMNIST__G2__nope"],
        capture_output=True, text=True, timeout=HANG_TIMEOUT,
    )  # fmt: skip
    assert bad.returncode != 0 and "--against ColorMNIST__G2__nope: no such mode" in bad.stderr


def test_float_paths_runs_one_seeded_command_on_three_floating_point_paths():
    """benchmark/analysis/float_paths.py: the three paths each run the command to its end and print its curve; on an
    AVX-512 machine the env variables reach torch (held to AVX2, the capability it reports there changes)."""
    smoke = ("dgrl_goal_dqn.py --env-id LoopWorld --groups 0 --seed 1 --n-train-goals 4 --total-timesteps 1500 "
             "--rep-steps 50 --rep-batch-size 16 --rep-transitions 300 --learning-starts 20 --eval-frequency 500 "
             "--batch-size 16 --buffer-size 1000 --max-episode-steps 50").split()  # fmt: skip
    tool = ROOT / "benchmark/analysis/float_paths.py"
    result = subprocess.run([sys.executable, str(tool), "--", *smoke], capture_output=True, text=True, timeout=HANG_TIMEOUT)
    assert result.returncode == 0, result.stderr
    lines = result.stdout.strip().splitlines()
    assert lines[0].startswith("dgrl_goal_dqn.py --env-id LoopWorld") and "CPU capability" in lines[0]
    assert [line.split(":")[0].strip() for line in lines[1:]] == list(float_paths.PATHS)
    for line in lines[1:]:
        mean, values = float(line.split("mean ")[1].split()[0]), line.split("; ")[1].split(", ")
        assert len(values) == 3 and mean == pytest.approx(sum(map(float, values)) / 3, abs=1e-3)
    capability = subprocess.run(
        [sys.executable, "-c", "import torch; print(torch.backends.cpu.get_cpu_capability())"],
        env=dict(os.environ, ATEN_CPU_CAPABILITY="avx2"), capture_output=True, text=True, timeout=HANG_TIMEOUT,
    ).stdout.strip()  # fmt: skip
    assert capability in ("AVX2", "DEFAULT")  # the variable the tool sets is the one torch reads


def test_amigo_report_windows_and_the_papers_table(tmp_path):
    """benchmark/analysis/amigo_report.py: windowed success and return per run, the first window at 90% (censored at
    --end, marked >), and the table's exact permutation p of each G against G0 of the same setting."""
    import amigo_report

    steps, values = np.array([0, 50, 100, 150, 250]), np.array([0.0, 1.0, 0.5, 0.5, 1.0])
    means = amigo_report.window_means(steps, values, np.array([0, 100, 200, 300, 400]))
    assert means[:3] == pytest.approx([0.5, 0.5, 1.0]) and np.isnan(means[3])  # the last window logged nothing
    for seed in (1, 2, 3):
        for group, success in ((0, [0.0, 0.1, 0.2]), (16, [0.0, 0.5, 0.9 + seed / 100])):
            writer = SummaryWriter(str(tmp_path / f"KeyCorridor__G{group}__study__{seed}__1"))
            for step, value in zip((0, 1000, 2000), success, strict=True):
                writer.add_scalar("charts/success_rate", value, step)
                writer.add_scalar("charts/episodic_return", value / 2, step)
            writer.close()
    result = subprocess.run(
        [sys.executable, str(ROOT / "benchmark/analysis/amigo_report.py"), "--runs-dir", str(tmp_path), "--window", "1000",
         "--end", "3000"],
        capture_output=True, text=True, timeout=HANG_TIMEOUT,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    table = result.stdout.split("the paper's table: the last window is 2,000-3,000")[1]
    # G16 reaches 0.91-0.93 in the last window (first >= 0.9 at 2000); G0 never (censored at --end, 3000)
    assert "| KeyCorridor__G0__study | 3 | 0.1 +- 0 (0.1, 0.1, 0.1) | 0.2 +- 0 (0.2, 0.2, 0.2) | 3e+03 +- 0 (>3e+03," in table
    assert "| KeyCorridor__G16__study | 3 | 0.46 +- 0.0041 (0.455, 0.46, 0.465) | 0.92 +- 0.0082 (0.91, 0.92, 0.93) |" in table
    assert "2e+03 +- 0 (2e+03, 2e+03, 2e+03)" in table
    # every G16 seed above every G0 seed: one split in C(6, 3) = 20 as extreme
    assert f"G16__study vs G0, return, last window: p = {1 / comb(6, 3):.3f} in DGRL's favour, 1.000" in table
    assert f"first window >= 0.9 (frames): p = {1 / comb(6, 3):.3f} in DGRL's favour" in table
