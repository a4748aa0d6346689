"""What each discrete factor encodes: its code for every goal, drawn over the environment's own space, one panel per
factor, with a summary of how factorial the codes are.

    python benchmark/analysis/factor_map.py CHECKPOINT [CHECKPOINT ...] --out docs/img/keychest_factors
    # CHECKPOINT: a --save-model checkpoint (runs/{run_name}/{exp_name}.cleanrl_model) of a script of SETTINGS below

For each checkpoint, the script's own networks (rebuilt from the flags the checkpoint holds) encode every goal of a
grid that covers the environment, and each factor's code index is drawn at the goal's place (walls black). Settings so
far: Key-Chest (dgrl_hrac_keychest.py), every free cell of its 13 x 17 grid as the subgoal (row, col).

The summary, the same in every setting (`summarise`), for each factor over the goals of the grid:
- `codes`: how many codes of the shared codebook it uses;
- `share[c]` = I(code; c) / H(code) for each goal coordinate c: the fraction of the factor's information that c alone
  carries (mutual information of the discrete code with the coordinate's values, in bits; 0 for a factor with one code).
  A factor that follows one coordinate has share 1 for it and 0 for the others; one that marks regions (rooms, a
  quadrant) has shares between 0 and 1 for several; the codes are a function of the goal, so all the coordinates
  together always carry all of it;
- `gap`: the largest share less the second largest; the figure's `mean gap` averages it over the factors that use
  more than one code: 1 when every factor follows exactly one coordinate, 0 when none prefers one coordinate.
The baseline (--groups 0) has no codes: for it, and next to each DGRL panel set, the continuous embedding before the
bottleneck is clustered by k-means into as many clusters as the codebook has codes, drawn as one panel the same way.
Writes OUT.png and OUT.md (the summary table).
"""

import importlib
import math
import sys
from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import torch
import tyro

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))  # the scripts import vq.py


@dataclass
class Args:
    checkpoints: tyro.conf.Positional[tuple[str, ...]]
    """--save-model checkpoints of one setting's runs (e.g. G = 16 and a smaller G), one row of panels each"""
    out: str = "factor_map"
    """output path without extension: OUT.png and OUT.md"""
    factors: int = 16
    """panels per checkpoint: the first this many factors"""


@dataclass
class GoalGrid:
    """Every goal of one setting's grid, as a checkpoint's networks see it."""

    codes: np.ndarray | None  # (goals, G) code index of each factor; None for the baseline
    embedding: np.ndarray  # (goals, D) the continuous embedding before the bottleneck (or the goal itself)
    coords: np.ndarray  # (goals, C) the goal coordinates the shares are measured against, discrete values
    coord_names: tuple[str, ...]
    places: np.ndarray  # (goals, 2) the (row, col) where each goal is drawn
    blocked: np.ndarray  # (rows, cols) True where no goal is (walls), drawn black
    n_embed: int  # codes in the codebook (k-means clusters for the embedding)
    label: str  # e.g. "G = 16, seed 4"
    embedding_name: str  # what `embedding` is, for the k-means panel's title


def entropy(labels: np.ndarray) -> float:
    """Entropy in bits of the empirical distribution of `labels` (rows of an array count as one label)."""
    _, counts = np.unique(labels, axis=0, return_counts=True)
    p = counts / counts.sum()
    return float(-(p * np.log2(p)).sum())


def summarise(codes: np.ndarray, coords: np.ndarray, names: tuple[str, ...]) -> list[dict]:
    """Per factor: codes used, share[c] = I(code; c) / H(code) per coordinate, and the gap between the two largest."""
    rows = []
    for factor in range(codes.shape[1]):
        code = codes[:, factor]
        h_code = entropy(code)
        share = {}
        for c, name in enumerate(names):
            mutual = h_code + entropy(coords[:, c]) - entropy(np.stack((code, coords[:, c]), 1))
            share[name] = mutual / h_code if h_code > 1e-12 else 0.0
        top = [*sorted(share.values(), reverse=True), 0.0]
        rows.append({"factor": factor, "codes": len(np.unique(code)), "share": share, "gap": top[0] - top[1]})
    return rows


def mean_gap(rows: list[dict]) -> float:
    gaps = [row["gap"] for row in rows if row["codes"] > 1]
    return float(np.mean(gaps)) if gaps else math.nan


def kmeans(points: np.ndarray, k: int, seed: int = 0, iterations: int = 50) -> np.ndarray:
    """Cluster labels of `points` (Lloyd's algorithm from k distinct random points; k is capped at their number)."""
    rng = np.random.default_rng(seed)
    distinct = np.unique(points, axis=0)
    centres = distinct[rng.choice(len(distinct), min(k, len(distinct)), replace=False)]
    for _ in range(iterations):
        labels = ((points[:, None] - centres[None]) ** 2).sum(-1).argmin(1)
        moved = np.stack([points[labels == i].mean(0) if (labels == i).any() else centres[i] for i in range(len(centres))])
        if np.allclose(moved, centres):
            break
        centres = moved
    return ((points[:, None] - centres[None]) ** 2).sum(-1).argmin(1)


def load_script(name: str):
    return importlib.import_module(name.removesuffix(".py"))  # from the repository's root, as the tests import them


# --- The settings: a checkpoint's networks over every goal of the environment -------------------------------------------


def keychest(saved: dict) -> GoalGrid:
    """Key-Chest: every free cell (row, col) as the subgoal, through the subgoal autoencoder's encoder and codebook. For
    HRAC (G = 0), whose low level takes the raw cell, the embedding is its adjacency network's (HRAC's learned metric)."""
    kc = load_script("dgrl_hrac_keychest.py")
    args = kc.Args(**saved["args"])
    agent = kc.make_agent(args, torch.device("cpu"))
    goals = torch.as_tensor(kc.FREE_CELLS, dtype=torch.float32)
    with torch.no_grad():
        if args.groups:
            agent.goal_ae.load_state_dict(saved["goal_autoencoder"])
            embedding = agent.goal_ae.encoder(goals / agent.goal_ae.scale)
            codes = agent.goal_ae.vq(embedding, update=False)[2].reshape(len(goals), args.groups).numpy()
        else:
            agent.adjacency.load_state_dict(saved["adjacency"])
            embedding, codes = agent.adjacency(goals), None
    return GoalGrid(
        codes=codes,
        embedding=embedding.numpy(),
        coords=kc.FREE_CELLS,
        coord_names=("row", "col"),
        places=kc.FREE_CELLS,
        blocked=kc.WALLS,
        n_embed=args.n_embed,
        label=f"G = {args.groups}, seed {args.seed}",
        embedding_name="encoder" if args.groups else "adjacency",
    )


SETTINGS = {"dgrl_hrac_keychest.py": keychest}


# --- The figure and the table ------------------------------------------------------------------------------------------


def panel(axis, grid: GoalGrid, values: np.ndarray, title: str) -> None:
    image = np.full(grid.blocked.shape, np.nan)
    image[grid.places[:, 0], grid.places[:, 1]] = values
    axis.imshow(np.where(grid.blocked, 1.0, np.nan), cmap="Greys", vmin=0, vmax=1)  # walls black
    axis.imshow(image, cmap="tab20", vmin=0, vmax=max(19, int(np.nanmax(image))), interpolation="nearest")
    axis.set_title(title, fontsize=7)
    axis.axis("on")
    axis.set_xticks([])
    axis.set_yticks([])


def draw(grids: list[GoalGrid], factors: int, out: str, per_line: int = 9) -> list[str]:
    """OUT.png (for each checkpoint: its k-means panel, then one panel per factor, `per_line` panels a line) and the
    summary table's lines (OUT.md)."""
    summaries = [[] if grid.codes is None else summarise(grid.codes, grid.coords, grid.coord_names) for grid in grids]
    summaries = [rows[:factors] for rows in summaries]
    lines_of = [math.ceil((1 + len(rows)) / per_line) for rows in summaries]
    figure, axes = plt.subplots(sum(lines_of), per_line, figsize=(1.7 * per_line, 1.6 * sum(lines_of)), squeeze=False)
    for axis in axes.flat:
        axis.axis("off")
    table = ["| run | factor | codes | " + " | ".join(f"share {n}" for n in grids[0].coord_names) + " | gap |"]
    table.append("|---" * (4 + len(grids[0].coord_names)) + "|")
    first = 0
    for grid, rows, count in zip(grids, summaries, lines_of, strict=True):
        cells = axes[first : first + count].flat
        first += count
        clusters = kmeans(grid.embedding, grid.n_embed)
        (clustered,) = summarise(clusters[:, None], grid.coords, grid.coord_names)
        shares = " ".join(f"{name} {value:.2f}" for name, value in clustered["share"].items())
        title = f"{grid.label}: k-means of its\n{grid.embedding_name}, {clustered['codes']}: {shares}"
        panel(next(cells), grid, clusters, title)
        for row in rows:
            shares = " ".join(f"{name} {value:.2f}" for name, value in row["share"].items())
            panel(next(cells), grid, grid.codes[:, row["factor"]], f"factor {row['factor']}: {row['codes']} codes\n{shares}")
        for row in [dict(clustered, factor="k-means"), *rows]:
            shares = " | ".join(f"{value:.2f}" for value in row["share"].values())
            table.append(f"| {grid.label} | {row['factor']} | {row['codes']} | {shares} | {row['gap']:.2f} |")
        if rows:
            blanks = "| " * len(grid.coord_names)
            table.append(f"| {grid.label} | mean gap (factors with > 1 code) | | {blanks}{mean_gap(rows):.2f} |")
    figure.tight_layout()
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(f"{out}.png", dpi=110)
    Path(f"{out}.md").write_text("\n".join(table) + "\n")
    return table


def main(args: Args) -> None:
    if not args.checkpoints:
        raise SystemExit("factor_map.py: give one or more checkpoints (--help)")
    missing = [path for path in args.checkpoints if not Path(path).is_file()]
    if missing:
        raise SystemExit(f"factor_map.py: no such checkpoint: {', '.join(missing)}")
    grids = []
    for path in args.checkpoints:
        saved = torch.load(path, map_location="cpu", weights_only=True)
        script = saved.get("script") if isinstance(saved, dict) else None
        if script not in SETTINGS:
            raise SystemExit(f"{path}: a checkpoint of {script}; factor maps exist for {', '.join(SETTINGS)}")
        grids.append(SETTINGS[script](saved))
    print("\n".join(draw(grids, args.factors, args.out)))
    print(f"wrote {args.out}.png and {args.out}.md")


if __name__ == "__main__":
    main(tyro.cli(Args, description=__doc__))
