"""The significance statements of docs/claims.md for the studies whose run folders were not kept.

    python benchmark/analysis/ledger_stats.py

The studies of docs/claims.md that ran before the current sweeps (AMIGo, RIS, Sawyer) published their per-seed figures
in the docs pages, taken from the runs' logs; their TensorBoard folders were not kept. This script holds those per-seed
figures, copied from the tables named with each, and prints for each comparison every seed's value, the means, and a
one-sided exact permutation p-value in DGRL's favour (benchmark/analysis/seed_stats.py's test). With 3 seeds against 3 the
smallest possible p is 1/20 = 0.05, with 2 against 2 it is 1/6: such studies can show a direction, not significance.
The studies with kept sweeps are compared by benchmark/analysis/seed_stats.py directly (its docstring).
"""

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from seed_stats import permutation_p  # benchmark/analysis/seed_stats.py

# docs/dgrl_amigo.md, "KeyCorridorS3R1, 3M frames": success per 200k frames, one row per seed (15 windows)
S3R1_3M = {
    "AMIGo": [
        [0.06, 0.02, 0.02, 0.19, 0.72, 0.98, 0.99, 1.00, 1.00, 1.00, 0.86, 0.00, 0.84, 1.00, 1.00],
        [0.08, 0.09, 0.06, 0.03, 0.09, 0.30, 0.57, 0.49, 0.95, 0.99, 1.00, 1.00, 1.00, 1.00, 1.00],
        [0.07, 0.04, 0.04, 0.06, 0.20, 0.45, 0.99, 1.00, 1.00, 0.97, 0.00, 0.00, 0.01, 0.03, 0.08],
    ],
    "G16": [
        [0.06, 0.00, 0.00, 0.06, 0.37, 0.92, 1.00, 1.00, 1.00, 1.00, 1.00, 1.00, 1.00, 1.00, 1.00],
        [0.08, 0.01, 0.00, 0.07, 0.34, 0.93, 1.00, 1.00, 1.00, 1.00, 1.00, 0.00, 0.00, 0.00, 0.00],
        [0.06, 0.01, 0.01, 0.06, 0.36, 0.71, 0.99, 1.00, 1.00, 1.00, 1.00, 1.00, 1.00, 1.00, 1.00],
    ],
}
# docs/dgrl_amigo.md, "DoorKey-5x5, 1M frames": success over the last 50k frames, per seed
DOORKEY_LAST = {"AMIGo": [0.96, 0.99, 0.77], "G8": [0.79, 0.93, 0.83], "G16": [0.76, 0.98, 0.20]}
# docs/dgrl_ris.md, "The CPU preset": the first evaluation at 90% test success or more, in thousands of steps
POINTMAZE_90 = {"RIS": [18, 18, 20], "G16": [22, 22, 20]}
# docs/dgrl_ris_sawyer.md, "The CPU preset": hand-only test success per evaluation (2k to 30k), per seed
SAWYER = {
    "RIS": [
        [0, 0, 0, 0, 0, 0, 0.1, 0.2, 0.2, 0, 0.3, 0.2, 0.4, 0, 0.4],
        [0] * 15,
    ],
    "G16": [
        [0] * 15,
        [0.1, 0, 0, 0, 0.2, 0, 0, 0, 0, 0, 0, 0, 0.1, 0.7, 0.9],
    ],
}


def compare(title: str, treated: list[float], control: list[float], higher_is_better: bool = True) -> str:
    t, c = np.array(treated, float), np.array(control, float)
    p = permutation_p(t, c, higher_is_better)
    return (
        f"{title}: DGRL {', '.join(f'{x:.3g}' for x in t)} (mean {t.mean():.3g}) against "
        f"{', '.join(f'{x:.3g}' for x in c)} (mean {c.mean():.3g}); one-sided exact p = {p:.3f}"
    )


def first_window_at(rows: list[list[float]], level: float, width: float) -> list[float]:
    """The start (in millions of frames) of the first window whose success is at least `level`."""
    return [width * next(i for i, value in enumerate(row) if value >= level) for row in rows]


def main() -> None:
    argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter).parse_args()
    mean_success = {name: [float(np.mean(row)) for row in rows] for name, rows in S3R1_3M.items()}
    reach = {name: first_window_at(rows, 0.9, 0.2) for name, rows in S3R1_3M.items()}
    lines = [
        compare("AMIGo KeyCorridorS3R1 3M, mean success of the 15 windows", mean_success["G16"], mean_success["AMIGo"]),
        compare("AMIGo KeyCorridorS3R1 3M, first 200k window at >= 0.9 (M frames)", reach["G16"], reach["AMIGo"], False),
        compare("AMIGo KeyCorridorS3R1 3M, last window", [r[-1] for r in S3R1_3M["G16"]], [r[-1] for r in S3R1_3M["AMIGo"]]),
        compare("AMIGo DoorKey-5x5 1M, G8, success over the last 50k frames", DOORKEY_LAST["G8"], DOORKEY_LAST["AMIGo"]),
        compare("AMIGo DoorKey-5x5 1M, G16, success over the last 50k frames", DOORKEY_LAST["G16"], DOORKEY_LAST["AMIGo"]),
        compare("RIS PointMaze U 30k, first evaluation at >= 90% (k steps)", POINTMAZE_90["G16"], POINTMAZE_90["RIS"], False),
        compare(
            "RIS Sawyer 30k, hand-only success, mean over evaluations",
            [float(np.mean(row)) for row in SAWYER["G16"]],
            [float(np.mean(row)) for row in SAWYER["RIS"]],
        ),
    ]
    print("\n".join(lines))


if __name__ == "__main__":
    main()
