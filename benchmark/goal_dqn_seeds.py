"""Goal-DQN per seed: DGRL's G settings against the baseline, with a significance statement for each figure.

    python benchmark/launch.py --script dgrl_goal_dqn.py --env-ids SpiralWorld --groups 0 8 16 --seeds 1 2 3 4 5 \\
        --name gdqn-spiral16 -- --n-train-goals 16
    python benchmark/goal_dqn_seeds.py sweeps/gdqn-spiral16 --tags eval/novel_success_rate eval/novel_total_steps

Reads every run folder of the sweep (TensorBoard scalars; run names `{env}__K{k}__G{g}__...__{seed}__{time}`) and, for
each tag, prints per G the final value and the mean over all evaluations (which rewards learning early) of every seed,
their mean +- std, and for each G > 0 against G = 0: the difference of the means, a 95% bootstrap interval of it (10,000
resamples of the seeds within each group) and a one-sided exact permutation p-value in DGRL's favour (every split of
the pooled seeds; "favour" is higher for success rates and lower for total steps). With --markdown OUT the tables are
also written to OUT.
"""

import argparse
import itertools
import re
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from plot import load_runs, run_folders  # benchmark/plot.py


def permutation_p(treated: np.ndarray, control: np.ndarray, higher_is_better: bool) -> float:
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


def bootstrap_interval(treated: np.ndarray, control: np.ndarray, rng: np.random.Generator) -> tuple[float, float]:
    """95% percentile interval of mean(treated) - mean(control), resampling the seeds of each group."""
    draws = rng.choice(treated, (10_000, len(treated))).mean(1) - rng.choice(control, (10_000, len(control))).mean(1)
    return float(np.percentile(draws, 2.5)), float(np.percentile(draws, 97.5))


def main(sweep: Path, tags: list[str], markdown: Path | None) -> None:
    per_group: dict[int, dict[int, dict]] = {}
    for run in run_folders(sweep):
        group = int(re.search(r"__G(\d+)__", run.name).group(1))
        seed = int(run.name.split("__")[-2])
        for seeds in load_runs([run], "", tags).values():
            per_group.setdefault(group, {})[seed] = seeds[0]
    rng = np.random.default_rng(0)
    lines = [f"{sweep.name}: {', '.join(f'G{g} {len(s)} seeds' for g, s in sorted(per_group.items()))}"]
    for tag in tags:
        higher = "success" in tag
        for summary, pick in (("final", lambda values: values[-1]), ("mean over evaluations", np.mean)):
            values = {
                group: np.array([pick(curves[tag][1]) for _, curves in sorted(seeds.items()) if tag in curves])
                for group, seeds in sorted(per_group.items())
            }
            lines += ["", f"{tag}, {summary} ({'higher' if higher else 'lower'} is better)", ""]
            lines += [
                "| G | per seed | mean +- std | vs G0: difference [95% bootstrap] | one-sided p |",
                "|---|---|---|---|---|",
            ]
            for group, v in values.items():
                row = f"| {group} | {', '.join(f'{x:.3g}' for x in v)} | {v.mean():.3g} +- {v.std():.2g} |"
                if group == 0 or 0 not in values:
                    lines.append(row + " | |")
                    continue
                low, high = bootstrap_interval(v, values[0], rng)
                p = permutation_p(v, values[0], higher)
                lines.append(row + f" {v.mean() - values[0].mean():+.3g} [{low:+.3g}, {high:+.3g}] | {p:.3f} |")
    text = "\n".join(lines)
    print(text)
    if markdown is not None:
        markdown.write_text(text + "\n")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("sweep", type=Path, help="a sweep folder of benchmark/launch.py (or any folder of run folders)")
    parser.add_argument("--tags", nargs="+", default=["eval/novel_success_rate", "eval/novel_total_steps"])
    parser.add_argument("--markdown", type=Path, help="also write the tables to this file")
    options = parser.parse_args()
    main(options.sweep, options.tags, options.markdown)
