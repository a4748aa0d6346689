"""Learning curves (mean +- std over seeds) and a results table from TensorBoard logs.

    python benchmark/analysis/plot.py --runs-dir runs --match "__study__" \
        --tags eval/novel_total_steps eval/train_success_rate --out docs/img/goal_dqn_study

A run directory is named `{setting}__{exp_name}__{seed}__{timestamp}` as the scripts name them; runs that differ only
in seed and timestamp form one setting. Each setting's curves are put on a common step grid (the steps its runs share)
and averaged. The table gives, per setting and tag, the final value and the average over all evaluations (an
area-under-the-curve summary that rewards learning early), each as mean +- std over seeds. Writes OUT.png and OUT.md.
"""

import re
from dataclasses import dataclass, field
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import tyro
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator


@dataclass
class Args:
    runs_dir: str = "runs"
    """folder searched (at any depth) for run folders of TensorBoard event files: runs/, or a sweep's folder"""
    match: str = ""
    """regular expression a run's folder name must contain to be included"""
    tags: list[str] = field(default_factory=lambda: ["eval/train_success_rate", "eval/novel_total_steps"])
    """scalar tags to plot and tabulate, one panel each"""
    panel_by: str = ""
    """regular expression with one group, e.g. '^([^_]+__K\\d+)': one figure row per distinct match (default: one row)"""
    out: str = "results/plot"
    """output path without extension: OUT.png and OUT.md are written"""
    title: str = ""
    """figure title"""
    bins: int = 0
    """if > 0, average each seed's values in this many equal bins of steps over the range every seed covers, for runs
    whose evaluation steps differ (episode-based schedules); "final" is then the last bin (0 = the exact common steps)"""


def setting_of(run_name: str) -> str:
    """The run name without its last two fields (seed and timestamp)."""
    return "__".join(run_name.split("__")[:-2])


def run_folders(runs_dir: Path) -> list[Path]:
    """Every folder under `runs_dir` (itself included, at any depth) holding TensorBoard event files: runs/{run_name} of
    the scripts, or the runs of a sweep of benchmark/launch.py (sweeps/{name}/{run_id}/runs/{run_name})."""
    return sorted({path.parent for path in runs_dir.rglob("events.out.tfevents.*")}, key=lambda path: (path.name, path))


def load_runs(run_dirs: list[Path], match: str, tags: list[str]) -> dict[str, list[dict[str, tuple[np.ndarray, np.ndarray]]]]:
    """{setting: [one {tag: (steps, values)} per seed]} for every run folder whose name matches."""
    settings: dict[str, list] = {}
    for run in sorted((path for path in run_dirs if re.search(match, path.name)), key=lambda path: (path.name, path)):
        accumulator = EventAccumulator(str(run), size_guidance={"scalars": 0})
        accumulator.Reload()
        available = set(accumulator.Tags()["scalars"])
        curves = {}
        for tag in tags:
            if tag in available:
                events = accumulator.Scalars(tag)
                curves[tag] = (np.array([e.step for e in events]), np.array([e.value for e in events]))
        if curves:
            settings.setdefault(setting_of(run.name), []).append(curves)
    return settings


def aggregate(seeds: list[dict], tag: str, bins: int = 0) -> tuple[np.ndarray, np.ndarray] | None:
    """(common steps, values of shape (seeds, steps)) of one tag: on the steps every seed logged, or with `bins`, the
    mean of each seed's values in each of `bins` equal bins over the steps all seeds cover (bin centres as steps; an
    empty bin is interpolated from its neighbours)."""
    curves = [seed[tag] for seed in seeds if tag in seed]
    if not curves:
        return None
    if bins > 0:
        start, end = max(steps[0] for steps, _ in curves), min(steps[-1] for steps, _ in curves)
        edges = np.linspace(start, end, bins + 1)
        centres = (edges[:-1] + edges[1:]) / 2
        rows = []
        for steps, values in curves:
            inside = (steps >= start) & (steps <= end)
            index = np.clip(np.searchsorted(edges, steps[inside], side="right") - 1, 0, bins - 1)
            counts = np.bincount(index, minlength=bins)
            means = np.bincount(index, weights=values[inside], minlength=bins) / np.maximum(counts, 1)
            filled = counts > 0
            rows.append(np.interp(centres, centres[filled], means[filled]))
        return centres, np.stack(rows)
    steps = curves[0][0]
    for other_steps, _ in curves[1:]:
        steps = np.intersect1d(steps, other_steps)
    return steps, np.stack([values[np.searchsorted(seed_steps, steps)] for seed_steps, values in curves])


def summary(values: np.ndarray) -> str:
    return f"{values.mean():.3g} +- {values.std():.2g}"


def plot_study(
    run_dirs: list[Path], tags: list[str], out: str, match: str = "", panel_by: str = "", title: str = "", bins: int = 0
) -> str:
    """Write OUT.png (curves, one panel per tag and row) and OUT.md (the table) for the runs whose folder name matches
    `match`; returns the table. Raises ValueError when no run matches and logs any of the tags."""
    settings = load_runs(run_dirs, match, tags)
    if not settings:
        raise ValueError(f"no run matches --match {match!r} and logs any of --tags {tags}")

    def panel_key(setting: str) -> str:
        found = re.search(panel_by, setting) if panel_by else None
        return found.group(1) if found and found.groups() else ""

    def short_labels(names: list[str]) -> dict[str, str]:
        """Each setting named by the fields that tell it apart from the others in its panel."""
        fields = [name.split("__") for name in names]
        varying = [i for i in range(max(map(len, fields))) if len({f[i] if i < len(f) else "" for f in fields}) > 1]
        return {name: " ".join(f[i] for i in varying if i < len(f)) or name for name, f in zip(names, fields, strict=True)}

    panels = sorted({panel_key(setting) for setting in settings})
    figure, axes = plt.subplots(len(panels), len(tags), figsize=(5 * len(tags), 3.6 * len(panels)), squeeze=False)
    rows = []
    for row, panel in enumerate(panels):
        panel_settings = sorted(s for s in settings if panel_key(s) == panel)
        labels = short_labels(panel_settings)
        for setting in panel_settings:
            cells = [setting.replace("__", " "), str(len(settings[setting]))]
            for column, tag in enumerate(tags):
                aggregated = aggregate(settings[setting], tag, bins)
                if aggregated is None:
                    cells.append("n/a")
                    continue
                steps, values = aggregated
                mean, std = values.mean(0), values.std(0)
                axis = axes[row, column]
                (line,) = axis.plot(steps, mean, label=f"{labels[setting]} (n={len(values)})")
                axis.fill_between(steps, mean - std, mean + std, color=line.get_color(), alpha=0.2)
                axis.set_title(f"{panel.replace('__', ' ')} {tag}".strip(), fontsize=9)
                axis.set_xlabel("environment steps")
                cells.append(f"{summary(values[:, -1])} (avg {summary(values.mean(1))})")
            rows.append(cells)
        for axis in axes[row]:
            axis.legend(fontsize=7)
            axis.grid(alpha=0.3)
    if title:
        figure.suptitle(title)
    figure.tight_layout()
    path = Path(out)
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path.with_suffix(".png"), dpi=110)
    plt.close(figure)
    header = "| setting | seeds | " + " | ".join(f"{tag}: final (avg over evals)" for tag in tags) + " |"
    table = "\n".join([header, "|" + "---|" * (len(tags) + 2)] + ["| " + " | ".join(cells) + " |" for cells in rows])
    path.with_suffix(".md").write_text(table + "\n")
    print(table)
    print(f"\nwrote {path.with_suffix('.png')} and {path.with_suffix('.md')}")
    return table


if __name__ == "__main__":
    args = tyro.cli(Args)
    runs_dir = Path(args.runs_dir)
    if not runs_dir.is_dir():
        raise SystemExit(f"error: --runs-dir {runs_dir} is not a folder")
    try:
        plot_study(run_folders(runs_dir), args.tags, args.out, args.match, args.panel_by, args.title, args.bins)
    except ValueError as error:
        raise SystemExit(f"error: no run in {runs_dir}: {error}") from None
