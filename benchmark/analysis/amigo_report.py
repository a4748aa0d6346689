"""The per-window numbers of docs/dgrl_amigo.md, read from the study's TensorBoard logs.

    python benchmark/analysis/amigo_report.py --runs-dir sweeps/amigo-doorkey --window 100000 --end 1000000
    python benchmark/analysis/amigo_report.py --runs-dir sweeps/amigo-s3r1-3m --window 200000 --end 3000000
    python benchmark/analysis/amigo_report.py --runs-dir sweeps/amigo-nochannel

(the sweeps of `python benchmark/launch.py --preset amigo-doorkey` and the others). Prints, for every run folder under
--runs-dir (at any depth) whose name matches: the training success rate averaged in consecutive
windows of --window frames (one row per seed, then the mean over seeds per setting), the start of the first window at
90% success or more, the mean success over the run (the mean of the windows), and, for DGRL runs, the median and
5th-95th percentiles of vq/active_codes and vq/perplexity after the first 100k frames.
"""

import itertools
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tyro
from plot import run_folders
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


if __name__ == "__main__":
    args = tyro.cli(Args)
    edges = np.arange(0, args.end + 1, args.window)
    settings: dict[str, list[np.ndarray]] = {}
    print(f"success per {args.window:,}-frame window, windows starting at {edges[0]:,} .. {edges[-2]:,}")
    for run in (path for path in run_folders(Path(args.runs_dir)) if re.search(args.match, path.name)):
        accumulator = EventAccumulator(str(run), size_guidance={"scalars": 0})
        accumulator.Reload()
        steps, success = scalars(accumulator, "charts/success_rate")
        row = np.array([success[(steps >= a) & (steps < b)].mean() for a, b in itertools.pairwise(edges)])
        setting, seed = "__".join(run.name.split("__")[:-2]), run.name.split("__")[-2]
        settings.setdefault(setting, []).append(row)
        solved = np.flatnonzero(row >= 0.9)
        first = f"{edges[solved[0]]:,}" if len(solved) else "never"
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
