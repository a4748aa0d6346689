"""The per-window numbers of docs/dgrl_amigo.md, read from the study's TensorBoard logs.

    python benchmark/analysis/amigo_report.py --runs-dir sweeps/amigo-doorkey --window 100000 --end 1000000
    python benchmark/analysis/amigo_report.py --runs-dir sweeps/amigo-s3r1-3m --window 200000 --end 3000000
    python benchmark/analysis/amigo_report.py --runs-dir sweeps/amigo-nochannel

(the sweeps of `python benchmark/launch.py --preset amigo-doorkey` and the others). Prints, for every run folder under
--runs-dir (at any depth) whose name matches: the training success rate averaged in consecutive
windows of --window frames (one row per seed, then the mean over seeds per setting), the start of the first window at
90% success or more, the mean success over the run (the mean of the windows), and, for DGRL runs, the median and
5th-95th percentiles of vq/active_codes and vq/perplexity after the first 100k frames. It ends with the paper's
table (its table 1: mean extrinsic return at the end of training), one row per G of each setting: per seed and as mean
+- std over seeds, the return and the success in the last window, the first window at 90% success (a run that never
gets there counts as --end, marked >) and the mean success over the run; for each G against G = 0 of the same setting,
one-sided exact permutation p-values in each direction (benchmark/analysis/seed_stats.py's test).
"""

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tyro
from plot import run_folders
from seed_stats import permutation_p
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator


@dataclass
class Args:
    runs_dir: str = "runs"
    """folder searched at any depth for run folders: runs/, or a sweep's folder"""
    match: str = ""
    """regular expression a run folder's name must contain"""
    window: int = 100_000
    """frames per window"""
    end: int = 1_000_000
    """last frame of the table"""


def scalars(accumulator: EventAccumulator, tag: str) -> tuple[np.ndarray, np.ndarray]:
    events = accumulator.Scalars(tag)
    return np.array([e.step for e in events]), np.array([e.value for e in events])


def window_means(steps: np.ndarray, values: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """The mean of the values logged in each window [edges[i], edges[i + 1]) (NaN where a window holds none)."""
    window = np.searchsorted(edges, steps, side="right") - 1  # the window each step falls in (-1, len: outside)
    return np.array([values[window == i].mean() if (window == i).any() else np.nan for i in range(len(edges) - 1)])


def paper_table(runs: dict[str, dict[int, dict[str, float]]], end: int) -> list[str]:
    """The summary table: `runs` maps a setting (its name with G) to {seed: {figure: value}}; one row per setting, and
    for each DGRL setting the p-values against the G0 setting whose name differs only in G."""
    figures = (("return", "return, last window", True), ("success", "success, last window", True),
               ("first", "first window >= 0.9 (frames)", False), ("mean", "mean success over the run", True))  # fmt: skip
    lines = ["| setting | seeds | " + " | ".join(title for _, title, _ in figures) + " |", "|---|---|" + "---|" * 4]
    tests = []
    for setting, seeds in sorted(runs.items()):
        cells = []
        for key, _, _ in figures:
            values = np.array([seeds[seed][key] for seed in sorted(seeds)])
            marks = [">" if key == "first" and v >= end else "" for v in values]
            shown = ", ".join(f"{mark}{v:.3g}" for mark, v in zip(marks, values, strict=True))
            cells.append(f"{values.mean():.3g} +- {values.std():.2g} ({shown})")
        lines.append(f"| {setting} | {len(seeds)} | " + " | ".join(cells) + " |")
        baseline = runs.get(re.sub(r"__G\d+__", "__G0__", setting))
        if baseline is not None and baseline is not seeds:
            for key, title, higher in figures:
                treated = np.array([seeds[seed][key] for seed in sorted(seeds)])
                control = np.array([baseline[seed][key] for seed in sorted(baseline)])
                p, p_worse = permutation_p(treated, control, higher), permutation_p(treated, control, not higher)
                tests.append(f"{setting} vs G0, {title}: p = {p:.3f} in DGRL's favour, {p_worse:.3f} in the baseline's")
    return [*lines, "", *tests]


if __name__ == "__main__":
    args = tyro.cli(Args)
    edges = np.arange(0, args.end + 1, args.window)
    settings: dict[str, list[np.ndarray]] = {}
    summaries: dict[str, dict[int, dict[str, float]]] = {}
    print(f"success per {args.window:,}-frame window, windows starting at {edges[0]:,} .. {edges[-2]:,}")
    for run in (path for path in run_folders(Path(args.runs_dir)) if re.search(args.match, path.name)):
        accumulator = EventAccumulator(str(run), size_guidance={"scalars": 0})
        accumulator.Reload()
        row = window_means(*scalars(accumulator, "charts/success_rate"), edges)
        returns = window_means(*scalars(accumulator, "charts/episodic_return"), edges)
        setting, seed = "__".join(run.name.split("__")[:-2]), run.name.split("__")[-2]
        settings.setdefault(setting, []).append(row)
        solved = np.flatnonzero(row >= 0.9)
        first = f"{edges[solved[0]]:,}" if len(solved) else "never"
        summary = {"return": returns[-1], "success": row[-1], "mean": row.mean()}
        summaries.setdefault(setting, {})[int(seed)] = summary | {"first": edges[solved[0]] if len(solved) else args.end}
        print(f"{setting} seed {seed}: {' '.join(f'{v:.2f}' for v in row)}  first >= 0.9 at {first}, mean {row.mean():.2f}")
        if "vq/active_codes" in accumulator.Tags()["scalars"]:
            for tag in ("vq/active_codes", "vq/perplexity"):
                tag_steps, values = scalars(accumulator, tag)
                p5, p50, p95 = np.percentile(values[tag_steps > 100_000], [5, 50, 95])
                print(f"    {tag} after 100k frames: median {p50:.1f}, 5th-95th percentile {p5:.1f}-{p95:.1f}")
    for setting, rows in settings.items():
        rows = np.array(rows)
        means = rows.mean(1)
        print(
            f"{setting} (mean of {len(rows)} seeds): {' '.join(f'{v:.2f}' for v in rows.mean(0))}  "
            f"mean over the run {means.mean():.2f} +- {means.std():.2f}"
        )
    print(f"\nthe paper's table: the last window is {edges[-2]:,}-{edges[-1]:,}\n")
    print("\n".join(paper_table(summaries, args.end)))
