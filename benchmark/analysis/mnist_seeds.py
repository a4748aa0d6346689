"""Color-MNIST across seeds: how often the two factors separate shape from colour, and what the separating seeds share.

    python benchmark/launch.py --preset mnist --seeds 1 2 3 4 5 6 7 8 9 10 --name mnist-10seeds   # 20 runs, ~25 min
    python benchmark/analysis/mnist_seeds.py sweeps/mnist-10seeds
    python benchmark/analysis/mnist_seeds.py sweeps/mnist-10seeds sweeps/mnist-restart50 \
        --against ColorMNIST__G2__mnist-10seeds

Reads every run folder of the sweep (TensorBoard scalars) and prints, per run: the swap test's better assignment (the
fraction of factor-swapped decodings whose digit comes from one image and colour from the other; chance about 0.0125),
the referees' digit and colour accuracy on each factor-only reconstruction, the test reconstruction error, and for DGRL
the codebook's usage in the last logged tenth of training (perplexity and active codes of the 256, mean over the
batches logged there) and the final reconstruction and commitment losses. Then, per mode, the distribution of the
better swap rate (mean, std, median, range, how many seeds exceed 0.25 = 20x chance), a one-sided exact permutation
test of DGRL's better swap rate against the baseline's (the share of the label permutations whose mean difference is at
least the observed one), and among DGRL's seeds the Spearman correlation of the better swap rate with each usage figure.
Several sweeps can be read together (each mode is named by its sweep's exp name); with --against MODE, every other
DGRL mode is also compared with that one (a variant against the default), with the exact permutation p in both
directions. With --markdown OUT the per-run table and the summary are also written to OUT; with --plot OUT.png, the
better swap rate of every seed per mode, the same seed joined across modes.
"""

import argparse
import re
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from plot import load_runs, run_folders  # benchmark/analysis/plot.py
from seed_stats import emit, late_mean, permutation_p, spearman  # benchmark/analysis/seed_stats.py

SWAPS = ("factor/swap/shape1_colour2", "factor/swap/colour1_shape2")
FACTORS = [f"factor/factor{i}/{what}_acc" for i in (1, 2) for what in ("digit", "colour")]
USAGE = ("vq/perplexity", "vq/active_codes", "losses/reconstruction", "vq/commit_loss")
TAGS = [*SWAPS, *FACTORS, "factor/test/reconstruction_mse", *USAGE]


def plot_seeds(swaps: dict[str, dict[int, float]], out: Path) -> None:
    """One column per mode, one dot per seed, each seed's dots joined: a paired view of the modes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = sorted(swaps)
    figure, axis = plt.subplots(figsize=(2.2 * len(names) + 2, 4.5))
    for seed in sorted({seed for values in swaps.values() for seed in values}):
        xs = [i for i, name in enumerate(names) if seed in swaps[name]]
        ys = [swaps[names[i]][seed] for i in xs]
        axis.plot(xs, ys, "-o", color="0.6", markersize=4, linewidth=0.8)
        axis.annotate(str(seed), (xs[-1], ys[-1]), xytext=(5, 0), textcoords="offset points", fontsize=7, va="center")
    axis.axhline(0.0125, color="tab:red", linestyle="--", linewidth=0.8, label="chance (about 0.0125)")
    axis.set_xticks(range(len(names)), [name.replace("ColorMNIST__", "").replace("__", "\n") for name in names])
    axis.set_ylabel("better swap rate (one image's digit, the other's colour)")
    axis.set_title("Color-MNIST: factor swap per seed")
    axis.legend(fontsize=8)
    figure.tight_layout()
    figure.savefig(out, dpi=110)
    print(f"wrote {out}")


def main(sweeps: list[Path], markdown: Path | None, against: str | None = None, plot: Path | None = None) -> None:
    settings: dict[str, list[tuple[int, dict]]] = {}
    for run in (
        run for sweep in sweeps for run in run_folders(sweep)
    ):  # run names: ColorMNIST__G{g}__{exp_name}__{seed}__{time}
        for setting, seeds in load_runs([run], r"ColorMNIST__G\d+", TAGS).items():
            settings.setdefault(setting, []).extend((int(run.name.split("__")[-2]), curves) for curves in seeds)
    lines = [
        "| run | better swap | f1 digit | f1 colour | f2 digit | f2 colour | test MSE | perplexity (last 10%) | "
        "active codes | reconstruction loss | commit loss |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    better: dict[str, list[float]] = {}
    by_seed: dict[str, dict[int, float]] = {}
    usage: dict[str, list[list[float]]] = {}
    for setting, seeds in sorted(settings.items()):
        for seed, curves in sorted(seeds, key=lambda pair: pair[0]):
            if not all(tag in curves for tag in SWAPS):  # still running: the factor tests come at the end
                continue
            swap = max(float(curves[tag][1][-1]) for tag in SWAPS)
            better.setdefault(setting, []).append(swap)
            by_seed.setdefault(setting, {})[seed] = swap
            factors = [f"{float(curves[tag][1][-1]):.2f}" for tag in FACTORS]
            late = [late_mean(curves[tag]) if tag in curves else float("nan") for tag in USAGE]
            usage.setdefault(setting, []).append(late)
            mse = float(curves["factor/test/reconstruction_mse"][1][-1])
            figures = " | ".join(f"{value:.3g}" for value in late)
            lines.append(f"| {setting} seed {seed} | {swap:.3f} | {' | '.join(factors)} | {mse:.4f} | {figures} |")
    lines += ["", "| mode | seeds | better swap: mean +- std | median | range | seeds > 0.25 |", "|---|---|---|---|---|---|"]
    for setting, values in sorted(better.items()):
        v = np.array(values)
        lines.append(
            f"| {setting} | {len(v)} | {v.mean():.3f} +- {v.std():.3f} | {np.median(v):.3f} | {v.min():.3f}-{v.max():.3f} | "
            f"{int((v > 0.25).sum())} |"
        )
    names = sorted(better)
    baseline = next((name for name in names if re.search(r"__G0(__|$)", name)), None)
    for name in names:
        if name == baseline or baseline is None:
            continue
        p = permutation_p(np.array(better[name]), np.array(better[baseline]))
        lines.append(f"\n{name} vs {baseline}: one-sided exact permutation p = {p:.4f} (better swap rate, mean difference)")
        table = np.array(usage[name])
        swaps = np.array(better[name])
        correlations = ", ".join(
            f"{tag} {spearman(swaps, table[:, column]):+.2f}"
            for column, tag in enumerate(USAGE)
            if np.isfinite(table[:, column]).all()
        )
        lines.append(f"{name}: Spearman correlation of the better swap rate with {correlations}")
    if against is not None:
        if against not in better:
            raise SystemExit(f"--against {against}: no such mode; the modes read: {', '.join(names)}")
        reference = np.array(better[against])
        for name in names:
            if name in (against, baseline):
                continue
            variant = np.array(better[name])
            higher, lower = permutation_p(variant, reference), permutation_p(variant, reference, higher_is_better=False)
            lines.append(
                f"\n{name} vs {against}: better swap rate {variant.mean() - reference.mean():+.3f}; one-sided exact "
                f"permutation p = {higher:.4f} (higher), {lower:.4f} (lower)"
            )
    emit(lines, markdown)
    if plot is not None:
        plot_seeds(by_seed, plot)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "sweeps", type=Path, nargs="+", help="sweep folders of benchmark/launch.py (or any folders of run folders)"
    )
    parser.add_argument("--markdown", type=Path, help="also write the tables to this file")
    parser.add_argument("--against", help="also compare every other DGRL mode with this mode (e.g. a variant's default)")
    parser.add_argument("--plot", type=Path, help="also draw every seed's better swap rate per mode to this .png")
    options = parser.parse_args()
    main(options.sweeps, options.markdown, options.against, options.plot)
