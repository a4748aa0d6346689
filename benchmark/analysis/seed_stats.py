"""Per seed, each DGRL setting of a sweep against its baseline (G = 0), with a significance statement for each figure.

    python benchmark/launch.py --script dgrl_goal_dqn.py --env-ids SpiralWorld --groups 0 8 16 --seeds 1 2 3 4 5 \\
        --name gdqn-spiral16 -- --n-train-goals 16
    python benchmark/analysis/seed_stats.py sweeps/gdqn-spiral16 --tags eval/novel_success_rate eval/novel_total_steps
    python benchmark/analysis/seed_stats.py sweeps/keychest --tags eval/return --summaries late mean --reach eval/return=5

Reads every run folder of the sweep (TensorBoard scalars; run names `{env}__...__G{g}__{exp_name}__{seed}__{time}`).
Runs whose names agree once `G{g}` is taken out form one comparison (e.g. one env and number of goals); within it, for
each tag and summary, it prints per G every seed's value, their mean +- std (population std, over seeds) and, for each
G > 0 against G = 0: the difference of the means, a 95% bootstrap interval of it (10,000 resamples of the seeds within
each group, generator seeded with 0) and one-sided exact permutation p-values, in DGRL's favour (the share of all
splits of the pooled seeds whose difference is at least as favourable as the observed one; ties count as extreme) and
in the baseline's (the same test the other way round: small when DGRL is worse).
"Favour" is lower for tags about steps, distances and losses, higher for every other tag.

The summaries of a curve: `final` (its last value), `mean` (over all its evaluations, which rewards learning early),
`late` (the mean over its last tenth of steps: a steadier "final" for noisy evaluations). `--reach TAG=X` adds the
first step at which TAG reached X or more (lower is better); a seed that never reached it counts as its last logged
step and is marked with `>`, so the test treats it as if it had reached X at the end, which favours neither side more
than the censoring itself. Runs whose curves end before the comparison's longest (still running, or stopped early) are
left out, and named. `--gain-between A B` compares the gain of each G over G = 0 between two comparisons of the sweep
(named as the headers name them, e.g. SpiralWorld__K8__goal-dqn-5seeds and SpiralWorld__K16__goal-dqn-5seeds): the
difference of the two gains with a 95% bootstrap interval (the seeds of all four groups resampled), the test of
whether a gain depends on the setting. `--against G` takes another arm as the reference instead of G = 0 (e.g.
`--against 16` tests whether any other G, the baseline included, differs from G = 16: the test of a ranking among the
DGRL arms). With --markdown OUT the tables are also written to OUT.

Many comparisons make a small p likely by chance alone, so the output ends with the family of every DGRL-vs-baseline
comparison it printed (each G, tag, summary and setting): how many favour DGRL and how many the baseline at p <= 0.05,
and each comparison's two-sided p (twice the smaller one-sided p, at most 1: the direction is chosen after seeing
the data) beside its Holm-adjusted value over the whole family (Holm's step-down: the k-th smallest of m times
m - k + 1, kept non-decreasing, at most 1), which controls the chance of any false finding at 0.05.
"""

import argparse
import itertools
import re
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from plot import load_runs, run_folders  # benchmark/analysis/plot.py

SUMMARIES = ("final", "mean", "late")
SUMMARY_NAMES = {"final": "final", "mean": "mean over evaluations", "late": "mean over the last tenth of steps"}


def late_mean(curve: tuple[np.ndarray, np.ndarray]) -> float:
    """The mean of a curve over its last tenth of steps."""
    steps, values = curve
    return float(values[steps >= steps.min() + 0.9 * (steps.max() - steps.min())].mean())


def summarise(curve: tuple[np.ndarray, np.ndarray], summary: str) -> float:
    if summary == "final":
        return float(curve[1][-1])
    if summary == "mean":
        return float(curve[1].mean())
    return late_mean(curve)


def first_reach(curve: tuple[np.ndarray, np.ndarray], threshold: float) -> tuple[float, bool]:
    """(the first step whose value is >= threshold, True), or (the last step, False) when no value reaches it."""
    steps, values = curve
    reached = np.flatnonzero(values >= threshold)
    return (float(steps[reached[0]]), True) if len(reached) else (float(steps[-1]), False)


def lower_is_better(tag: str) -> bool:
    return re.search(r"steps|distance|loss|mse", tag) is not None


def ranks(values: np.ndarray) -> np.ndarray:
    order = values.argsort(kind="stable")
    ranked = np.empty(len(values))
    ranked[order] = np.arange(len(values))
    for value in np.unique(values):  # ties share their mean rank
        ranked[values == value] = ranked[values == value].mean()
    return ranked


def spearman(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.corrcoef(ranks(a), ranks(b))[0, 1])


def permutation_p(treated: np.ndarray, control: np.ndarray, higher_is_better: bool = True) -> float:
    """One-sided exact p-value: the share of the splits of the pooled values whose difference of means is at least as
    favourable to `treated` as the observed one."""
    sign = 1.0 if higher_is_better else -1.0
    pooled, n = np.concatenate((treated, control)), len(treated)
    observed = sign * (treated.mean() - control.mean())
    differences = []
    for chosen in itertools.combinations(range(len(pooled)), n):
        mask = np.zeros(len(pooled), bool)
        mask[list(chosen)] = True
        differences.append(sign * (pooled[mask].mean() - pooled[~mask].mean()))
    return float(np.mean(np.array(differences) >= observed - 1e-12))


def signed_bootstrap_interval(
    signed_groups: tuple[tuple[int, np.ndarray], ...], rng: np.random.Generator
) -> tuple[float, float]:
    """95% percentile interval of sum(sign * mean(group)), resampling the seeds of each group (10,000 draws)."""
    draws = sum(sign * rng.choice(group, (10_000, len(group))).mean(1) for sign, group in signed_groups)
    return float(np.percentile(draws, 2.5)), float(np.percentile(draws, 97.5))


def bootstrap_interval(treated: np.ndarray, control: np.ndarray, rng: np.random.Generator) -> tuple[float, float]:
    """95% percentile interval of mean(treated) - mean(control), resampling the seeds of each group."""
    return signed_bootstrap_interval(((1, treated), (-1, control)), rng)


def holm(p_values: list[float]) -> list[float]:
    """Holm's step-down adjustment, in the given order: the k-th smallest of m p-values times m - k + 1 (k from 1),
    made non-decreasing in that order and capped at 1."""
    order = np.argsort(p_values, kind="stable")
    adjusted, running = np.empty(len(p_values)), 0.0
    for k, index in enumerate(order):
        running = max(running, min(1.0, (len(p_values) - k) * p_values[index]))
        adjusted[index] = running
    return [float(value) for value in adjusted]


def multiplicity_lines(family: list[tuple[str, float, float]], reference: int = 0) -> list[str]:
    """The family of comparisons (name, p in DGRL's favour, p in the reference's, G0 unless told): the counts at
    p <= 0.05 each way, and per comparison the two-sided p and its Holm-adjusted value."""
    if not family:
        return []
    two_sided = [min(1.0, 2 * min(p, p_worse)) for _, p, p_worse in family]
    adjusted = holm(two_sided)
    for_dgrl = sum(p <= 0.05 for _, p, _ in family)
    for_baseline = sum(p_worse <= 0.05 for _, _, p_worse in family)
    other, ref = ("DGRL", "G0") if reference == 0 else ("the other G", f"G{reference}")
    lines = [
        "",
        f"multiplicity: {len(family)} comparisons with {ref}; one-sided p <= 0.05 for {other} in {for_dgrl}, for "
        f"{ref} in {for_baseline}; Holm-adjusted two-sided p <= 0.05 in {sum(a <= 0.05 for a in adjusted)}",
        "",
    ]
    lines += ["| comparison | favours | two-sided p | Holm-adjusted |", "|---|---|---|---|"]
    for (name, p, p_worse), raw, holm_p in zip(family, two_sided, adjusted, strict=True):
        favours = ("DGRL" if reference == 0 else name.rsplit(", ", 1)[-1]) if p < p_worse else ref
        favours = favours if p != p_worse else "neither"
        lines.append(f"| {name} | {favours} | {raw:.3f} | {holm_p:.3f} |")
    return lines


def table(
    values: dict[int, np.ndarray],
    marks: dict[int, list[str]],
    higher: bool,
    rng: np.random.Generator,
    family: list | None = None,
    name: str = "",
    reference: int = 0,
) -> list[str]:
    """One row per G: its seeds, mean +- std and, for each G but the reference (G0 unless told), the comparison with
    the reference (appended to `family` as (name, p in this G's favour, p in the reference's) when given)."""
    this = "DGRL" if reference == 0 else "this G"
    lines = [
        f"| G | per seed | mean +- std | vs G{reference}: difference [95% bootstrap] | one-sided p, {this} better | "
        f"p, G{reference} better |",
        "|---|---|---|---|---|---|",
    ]
    for group, v in values.items():
        if not len(v):  # a tag this setting does not log (the codebook's, for G0)
            lines.append(f"| {group} | (not logged) | | | | |")
            continue
        seeds = ", ".join(f"{mark}{x:.3g}" for mark, x in zip(marks[group], v, strict=True))
        row = f"| {group} | {seeds} | {v.mean():.3g} +- {v.std():.2g} |"
        base = values.get(reference, np.array([]))
        if group == reference or not len(base):
            lines.append(row + " | | |")
            continue
        low, high = bootstrap_interval(v, base, rng)
        p, p_worse = permutation_p(v, base, higher), permutation_p(v, base, not higher)
        if family is not None:
            family.append((f"{name}G{group}", p, p_worse))
        lines.append(row + f" {v.mean() - base.mean():+.3g} [{low:+.3g}, {high:+.3g}] | {p:.3f} | {p_worse:.3f} |")
    return lines


def gain_difference_interval(
    treated_a: np.ndarray, control_a: np.ndarray, treated_b: np.ndarray, control_b: np.ndarray, rng: np.random.Generator
) -> tuple[float, float]:
    """95% percentile interval of (mean(treated_a) - mean(control_a)) - (mean(treated_b) - mean(control_b)),
    resampling the seeds of each of the four groups."""
    return signed_bootstrap_interval(((1, treated_a), (-1, control_a), (-1, treated_b), (1, control_b)), rng)


def gain_lines(
    results: dict[tuple[str, str, str], dict[int, np.ndarray]], contexts: list[str], a: str, b: str, rng
) -> list[str]:
    """Per tag, summary and G > 0 present in both comparisons a and b: each gain over G = 0 and their difference."""
    missing = [name for name in (a, b) if name not in contexts]
    if missing:
        named = ", ".join(contexts) or "none (no run logs the tags)"
        raise SystemExit(f"--gain-between: no comparison named {', '.join(missing)}; the sweep's: {named}")
    lines = ["", f"gain over G0 in {a} minus gain over G0 in {b}", ""]
    lines += ["| figure | G | gain in A | gain in B | A - B [95% bootstrap] |", "|---|---|---|---|---|"]
    for (context, tag, summary), values in results.items():
        other = results.get((b, tag, summary))
        if context != a or other is None or 0 not in values or 0 not in other:
            continue
        for group in sorted(set(values) & set(other) - {0}):
            gain_a, gain_b = values[group].mean() - values[0].mean(), other[group].mean() - other[0].mean()
            low, high = gain_difference_interval(values[group], values[0], other[group], other[0], rng)
            difference = gain_a - gain_b if abs(gain_a - gain_b) > 1e-12 else 0.0  # no -1e-16 from rounding
            lines.append(
                f"| {tag}, {SUMMARY_NAMES[summary]} | {group} | {gain_a:+.3g} | {gain_b:+.3g} | "
                f"{difference:+.3g} [{low:+.3g}, {high:+.3g}] |"
            )
    return lines


def drop_short_runs(per_group: dict[int, dict[int, dict]]) -> list[str]:
    """Remove (in place) the runs whose curves end before the longest of the comparison (runs still going, or
    stopped early), whose final and late values and first steps would not be comparable; returns their names."""
    end = max(curve[0][-1] for seeds in per_group.values() for curves in seeds.values() for curve in curves.values())
    short = []
    for group, seeds in sorted(per_group.items()):
        for seed, curves in sorted(seeds.items()):
            if max(curve[0][-1] for curve in curves.values()) < end:
                short.append(f"G{group} seed {seed}")
                del seeds[seed]
        if not seeds:
            del per_group[group]
    return short


def emit(lines: list[str], markdown: Path | None) -> None:
    """Print the lines, and write them to `markdown` when given."""
    text = "\n".join(lines)
    print(text)
    if markdown is not None:
        markdown.write_text(text + "\n")


def main(
    sweep: Path,
    tags: list[str],
    summaries: list[str],
    reach: list[str],
    markdown: Path | None,
    gain_between: list[str] | None = None,
    reference: int = 0,
) -> None:
    thresholds = [(item.split("=")[0], float(item.split("=")[1])) for item in reach]
    wanted = sorted(set(tags) | {tag for tag, _ in thresholds})
    comparisons: dict[str, dict[int, dict[int, dict]]] = {}
    for run in run_folders(sweep):
        match = re.search(r"__G(\d+)__", run.name)
        if match is None:
            continue
        context = re.sub(r"__G\d+__", "__", "__".join(run.name.split("__")[:-2]) + "__").strip("_")
        seed = int(run.name.split("__")[-2])
        for seeds in load_runs([run], "", wanted).values():
            comparisons.setdefault(context, {}).setdefault(int(match.group(1)), {})[seed] = seeds[0]
    groups = sorted({group for per_group in comparisons.values() for group in per_group})
    if groups and reference not in groups:
        raise SystemExit(f"--against {reference}: no run of the sweep has G = {reference}; its G: {groups}")
    rng = np.random.default_rng(0)
    lines: list[str] = []
    family: list[tuple[str, float, float]] = []  # every comparison with G0, for the multiplicity statement
    results: dict[tuple[str, str, str], dict[int, np.ndarray]] = {}
    for context, per_group in sorted(comparisons.items()):
        short = drop_short_runs(per_group)
        header = f"{sweep.name}: {', '.join(f'G{g} {len(s)} seeds' for g, s in sorted(per_group.items()))}"
        lines += ([""] if lines else []) + [header if len(comparisons) == 1 else f"{header} ({context})"]
        if short:
            lines.append(f"left out, their curves end before the others' (running or stopped): {', '.join(short)}")
        for tag in tags:
            higher = not lower_is_better(tag)
            for summary in summaries:
                values = {
                    group: np.array([summarise(c[tag], summary) for _, c in sorted(seeds.items()) if tag in c])
                    for group, seeds in sorted(per_group.items())
                }
                results[(context, tag, summary)] = values
                marks = {group: [""] * len(v) for group, v in values.items()}
                lines += ["", f"{tag}, {SUMMARY_NAMES[summary]} ({'higher' if higher else 'lower'} is better)", ""]
                where = f"{context}: " if len(comparisons) > 1 else ""
                lines += table(values, marks, higher, rng, family, f"{where}{tag}, {SUMMARY_NAMES[summary]}, ", reference)
        for tag, threshold in thresholds:
            reached = {
                group: [first_reach(c[tag], threshold) for _, c in sorted(seeds.items()) if tag in c]
                for group, seeds in sorted(per_group.items())
            }
            values = {group: np.array([step for step, _ in pairs]) for group, pairs in reached.items()}
            marks = {group: ["" if hit else ">" for _, hit in pairs] for group, pairs in reached.items()}
            lines += ["", f"first step with {tag} >= {threshold:g} (lower is better; > never reached)", ""]
            where = f"{context}: " if len(comparisons) > 1 else ""
            name = f"{where}first step with {tag} >= {threshold:g}, "
            lines += table(values, marks, False, rng, family, name, reference)
    lines += multiplicity_lines(family, reference)
    if gain_between:
        lines += gain_lines(results, sorted(comparisons), *gain_between, rng)
    emit(lines, markdown)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("sweep", type=Path, help="a sweep folder of benchmark/launch.py (or any folder of run folders)")
    parser.add_argument("--tags", nargs="+", default=["eval/novel_success_rate", "eval/novel_total_steps"])
    parser.add_argument("--summaries", nargs="+", choices=SUMMARIES, default=["final", "mean"])
    parser.add_argument("--reach", nargs="*", default=[], metavar="TAG=X", help="first step at which TAG >= X")
    parser.add_argument("--markdown", type=Path, help="also write the tables to this file")
    parser.add_argument("--against", type=int, default=0, metavar="G", help="the reference arm (default: G0)")
    parser.add_argument(
        "--gain-between", nargs=2, metavar=("A", "B"), help="compare each G's gain over G0 between comparisons A and B"
    )
    options = parser.parse_args()
    bad = [item for item in options.reach if not re.fullmatch(r"[^=]+=[-+0-9.eE]+", item)]
    if bad:
        parser.error(f"--reach takes TAG=NUMBER, got {' '.join(bad)}")
    main(
        options.sweep,
        options.tags,
        options.summaries,
        options.reach,
        options.markdown,
        options.gain_between,
        options.against,
    )
