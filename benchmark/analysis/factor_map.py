"""What each discrete factor encodes: its code for every goal, drawn over the environment's own space, one panel per
factor, with a summary of how factorial the codes are.

    python benchmark/analysis/factor_map.py CHECKPOINT [CHECKPOINT ...] --out docs/img/keychest_factors
    # CHECKPOINT: a --save-model checkpoint (runs/{run_name}/{exp_name}.cleanrl_model) of a script of SETTINGS below

For each checkpoint, the script's own networks (rebuilt from the flags the checkpoint holds) encode every goal of a
grid that covers the environment, and each factor's code index is drawn at the goal's place (walls black). The goals of
each setting (its function below says how they are made):
- goal-DQN's mazes and Key-Chest's 13 x 17 grid: every free cell as the goal (row, col);
- RIS's mazes: an xy grid over the free space (an Ant maze's other goal coordinates: the ant at rest, yaw 0);
- HRAC's Ant suite: an xy grid of subgoal offsets (HRAC's own adjacency embedding over the maze for the baseline);
- AMIGo: every cell of one layout that is not a wall (x, y and the object there);
- Sawyer: goal images with the hand moving over the arena (the puck at the test goal), then the puck moving.

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
bottleneck is clustered by k-means into as many clusters as a factor uses codes (the median over the run's factors; for a
baseline, over the factors of the figure's DGRL runs; the codebook's size when there are none), drawn as one panel the
same way and summarised like a factor: a clustering of the whole embedding is the comparison a factor's codes should beat
on the gap. Each panel renumbers its values in order, so that up to 20 codes get distinct colours.
Writes OUT.png and OUT.md (the summary table).
"""

import importlib
import math
import sys
import textwrap
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
    cut_to: str | None = None
    """also write each checkpoint cut down to what its map reads (its flags and networks), small enough to keep beside a
    figure (the map of a cut checkpoint is the map of the whole one): DIR/{script}_{env id}_G{groups}_s{seed}.pt"""


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
# Each returns one GoalGrid per map (Sawyer two: the hand's and the puck's). Continuous spaces are sampled on a regular xy
# grid, drawn as a map seen from above (x to the right, y up); the coordinates the shares use are the grid's indices.

CPU = torch.device("cpu")


def xy_grid(xs: np.ndarray, ys: np.ndarray, free: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(points (N, 2) xy, coords (N, 2) x and y indices, places (N, 2) (row, col), blocked) of the free points of a grid
    with x centres `xs`, y centres `ys` and `free` (len(ys), len(xs)); the top row of the drawing is the largest y."""
    iy, ix = np.nonzero(free)
    points = np.stack((xs[ix], ys[iy]), 1)
    return points, np.stack((ix, iy), 1), np.stack((len(ys) - 1 - iy, ix), 1), ~free[::-1]


def quantised(vq, embedding: torch.Tensor, groups: int) -> np.ndarray:
    """Each factor's code index for a batch of embeddings (the codebook untouched)."""
    return vq(embedding, update=False)[2].reshape(len(embedding), groups).numpy()


def keychest(saved: dict) -> list[GoalGrid]:
    """Key-Chest: every free cell (row, col) as the subgoal, through the subgoal autoencoder's encoder and codebook. For
    HRAC (G = 0), whose low level takes the raw cell, the embedding is its adjacency network's (HRAC's learned metric)."""
    kc = load_script("dgrl_hrac_keychest.py")
    args = kc.Args(**saved["args"])
    agent = kc.make_agent(args, CPU)
    goals = torch.as_tensor(kc.FREE_CELLS, dtype=torch.float32)
    with torch.no_grad():
        if args.groups:
            agent.goal_ae.load_state_dict(saved["goal_autoencoder"])
            embedding = agent.goal_ae.encoder(goals / agent.goal_ae.scale)
            codes = quantised(agent.goal_ae.vq, embedding, args.groups)
        else:
            agent.adjacency.load_state_dict(saved["adjacency"])
            embedding, codes = agent.adjacency(goals), None
    label = f"G = {args.groups}, seed {args.seed}"
    name = "encoder" if args.groups else "adjacency"
    cells = kc.FREE_CELLS
    return [GoalGrid(codes, embedding.numpy(), cells, ("row", "col"), cells, kc.WALLS, args.n_embed, label, name)]


def goal_dqn(saved: dict) -> list[GoalGrid]:
    """goal-DQN's pixel mazes: every cell's image (the agent drawn in it, no noise) as the goal, through phi and its
    bottleneck; drawn in the maze's 13 x 13 character layout (cells at odd places, walls black, openings white). For the
    baseline, phi's continuous embedding."""
    gd = load_script("dgrl_goal_dqn.py")
    args = gd.Args(**saved["args"])
    agent = gd.make_agent(args, CPU)
    agent.rep.load_state_dict(saved["representation"])
    layout = gd.MazeLayout(args.env_id)
    with torch.no_grad():
        embedding = agent.rep.embed(torch.as_tensor(layout.images))
        codes = quantised(agent.rep.vq, embedding, args.groups) if args.groups else None
    cells = np.stack(np.divmod(np.arange(layout.n_cells), layout.size), 1)  # (row, col)
    walls = np.array([[char == "#" for char in line] for line in gd.LAYOUTS[args.env_id]])
    label = f"{args.env_id} G = {args.groups}, seed {args.seed}"
    return [GoalGrid(codes, embedding.numpy(), cells, ("row", "col"), 2 * cells + 1, walls, args.n_embed, label, "phi")]


def ris(saved: dict, step: float = 0.25) -> list[GoalGrid]:
    """RIS's mazes: goals on an xy grid (`step` apart) over the maze's free space. PointMaze's goal is the xy itself; an
    Ant maze's goal is a whole 31-d state, the ant at rest at xy facing yaw 0 (the reference for the other coordinates).
    For RIS (G = 0), whose networks take the raw goal, the embedding clustered is that goal."""
    rs = load_script("dgrl_ris.py")
    args = rs.Args(**saved["args"])
    if args.env_id in rs.ANT_MAZES:
        (x0, x1), (y0, y1) = rs.ANT_MAZES[args.env_id]["interior"]
        xs, ys = np.arange(x0 + step, x1, 2 * step), np.arange(y0 + step, y1, 2 * step)  # 0.5 m apart in an Ant maze
        points = np.stack(np.meshgrid(xs, ys), -1).reshape(-1, 2)
        free = (rs.wall_distance(points, rs.maze_boxes(args.env_id)) > 0).reshape(len(ys), len(xs))
        points, coords, places, blocked = xy_grid(xs, ys, free)
        goals = np.stack([rs.goal_state(point, 0.0) for point in points])
    else:  # a gymnasium-robotics maze: its map's free cells, each sampled on a (1 / step) x (1 / step) grid
        env = rs.make_env(args.env_id, 0, False, args.max_episode_steps, rs.ROBOTICS_THRESHOLD)()
        maze = env.unwrapped.maze
        walls, scale = np.array(maze.maze_map) == 1, maze.maze_size_scaling
        per_cell = round(1 / step)
        xs = (np.arange(walls.shape[1] * per_cell) + 0.5) * scale / per_cell - maze.x_map_center
        ys = maze.y_map_center - (np.arange(walls.shape[0] * per_cell) + 0.5) * scale / per_cell
        free = ~walls.repeat(per_cell, 0).repeat(per_cell, 1)
        order = np.argsort(ys)  # xy_grid wants ys increasing
        points, coords, places, blocked = xy_grid(xs, ys[order], free[order])
        goals = points
        env.close()
    goals = torch.as_tensor(goals, dtype=torch.float32)
    codes = None
    with torch.no_grad():
        if args.groups:
            encoder = rs.GoalEncoder(goals.shape[1], args)
            encoder.load_state_dict(saved["goal_encoder"])
            embedding = encoder.encoder(goals)
            codes = quantised(encoder.vq, embedding, args.groups)
        else:
            embedding = goals
    label = f"{args.env_id} G = {args.groups}, seed {args.seed}"
    name = "encoder" if args.groups else "goal itself"
    return [GoalGrid(codes, embedding.numpy(), coords, ("x", "y"), places, blocked, args.n_embed, label, name)]


def hrac(saved: dict, step: float = 1.0) -> list[GoalGrid]:
    """HRAC's Ant suite: DGRL quantises the manager's subgoal, an xy offset from the ant within +-subgoal_scale (AntFall's
    z offset at 0, the reference), so its map is over that square of offsets, `step` apart, with nothing blocked. HRAC
    (G = 0) gives its controller the raw offset; its learned embedding is the adjacency network's, of absolute 1 m cells
    of the maze (its blocks black), which is drawn instead."""
    hr = load_script("dgrl_hrac.py")
    args = hr.Args(**saved["args"])
    with torch.no_grad():
        if args.groups:
            bounds = hr.subgoal_bounds(args.env_id, args.subgoal_scale)
            xs = ys = np.arange(-args.subgoal_scale, args.subgoal_scale + step / 2, step)
            points, coords, places, blocked = xy_grid(xs, ys, np.ones((len(ys), len(xs)), bool))
            goals = np.concatenate((points, np.zeros((len(points), len(bounds) - 2))), 1)
            encoder = hr.SubgoalEncoder(bounds, args)
            encoder.load_state_dict(saved["subgoal_encoder"])
            embedding = encoder.encoder(torch.as_tensor(goals, dtype=torch.float32) / encoder.scale)
            codes, name = quantised(encoder.vq, embedding, args.groups), "encoder (subgoal offsets)"
        else:
            scaling, structure = hr.STRUCTURES[args.env_id]
            origin = hr.structure_origin(structure)
            rows, cols = len(structure), len(structure[0])
            x0, y0 = hr.cell_centre(0, 0, scaling, origin)
            xs = np.arange(np.ceil(x0 - scaling / 2), x0 - scaling / 2 + cols * scaling, step)
            ys = np.arange(np.ceil(y0 - scaling / 2), y0 - scaling / 2 + rows * scaling, step)
            cell_col = np.floor((xs - x0 + scaling / 2) / scaling).astype(int)
            cell_row = np.floor((ys - y0 + scaling / 2) / scaling).astype(int)
            free = np.array([[structure[i][j] not in (1, -1) for j in cell_col] for i in cell_row])
            points, coords, places, blocked = xy_grid(xs, ys, free)
            adjacency = hr.AdjacencyNet(2)
            adjacency.load_state_dict(saved["adjacency"])
            embedding, codes, name = adjacency(torch.as_tensor(points, dtype=torch.float32)), None, "adjacency (maze cells)"
    label = f"{args.env_id} G = {args.groups}, seed {args.seed}"
    return [GoalGrid(codes, embedding.numpy(), coords, ("x", "y"), places, blocked, args.n_embed, label, name)]


def amigo(saved: dict, layout_seed: int = 0) -> list[GoalGrid]:
    """AMIGo's MiniGrid: one layout (the env's reset with `layout_seed`), every cell that is not a wall as the goal,
    issued on the layout's first frame, through the goal encoder (and its codebook). Besides x and y, the shares measure
    the object at the goal's cell (empty, door, key, the agent ...). AMIGo's encoder is continuous: k-means of it."""
    am = load_script("dgrl_amigo.py")
    args = am.Args(**saved["args"])
    envs = am.MiniGridVecEnv(args.env_id, 1)
    frame = envs.reset(seed=layout_seed)[0]["grid"][0]  # (W, H, 3)
    width, height = frame.shape[:2]
    x, y = np.divmod(np.arange(width * height), height)  # the teacher's flat goal index is x * H + y
    objects = frame[x, y, 0]
    keep = objects != am.OBJECT_TO_IDX["wall"]
    encoder = am.GoalEncoder(width, height, args)
    encoder.load_state_dict(saved["goal_encoder"])
    with torch.no_grad():
        frames, goals = torch.as_tensor(np.repeat(frame[None], keep.sum(), 0)), torch.as_tensor(np.flatnonzero(keep))
        embedding = encoder.head(encoder.trunk(encoder.embedding(frames, goals)))  # before the bottleneck
        codes = quantised(encoder.vq, embedding, args.groups) if args.groups else None
    envs.close()
    coords = np.stack((x[keep], y[keep], objects[keep]), 1)
    places = np.stack((y[keep], x[keep]), 1)
    label = f"{args.env_id.removeprefix('MiniGrid-')} G = {args.groups}, seed {args.seed}"
    blocked = (frame[..., 0] == am.OBJECT_TO_IDX["wall"]).T
    return [GoalGrid(codes, embedding.numpy(), coords, ("x", "y", "object"), places, blocked, args.n_embed, label, "encoder")]


def sawyer(saved: dict, step: float = 0.02) -> list[GoalGrid]:
    """Sawyer push-and-reach: goal images rendered by the env, two maps: the hand over the arena with the puck at the test
    goal's centre (the reference), and the puck over the arena with the hand at the test goal's centre; places where the
    two would overlap (closer than a training goal allows) are blocked. Codes from the image encoder and the bottleneck;
    for RIS (G = 0), the encoder's continuous features."""
    sw = load_script("dgrl_ris_sawyer.py")
    args = sw.Args(**saved["args"])
    agent = sw.make_agent(sw.IMAGE_SIZE, 2, args, CPU)
    agent.encoder.load_state_dict(saved["encoder"])
    if args.groups:
        agent.vq.load_state_dict(saved["vq"])
    env = sw.SawyerPushAndReachEnv()
    env.reset(seed=0)
    reference = {name: np.mean(sw.TEST_BOXES[f"{name}_goal"], 0) for name in ("hand", "puck")}
    xs = np.arange(sw.ARENA_LOW[0], sw.ARENA_HIGH[0] + step / 2, step)
    ys = np.arange(sw.ARENA_LOW[1], sw.ARENA_HIGH[1] + step / 2, step)
    grid = np.stack(np.meshgrid(xs, ys), -1)
    grids = []
    for moving, fixed in (("hand", "puck"), ("puck", "hand")):
        free = np.linalg.norm(grid - reference[fixed], axis=-1) >= sw.GOAL_CLEARANCE
        points, coords, places, blocked = xy_grid(xs, ys, free)
        pairs = (points, np.broadcast_to(reference[fixed], points.shape))
        states = np.concatenate(pairs if moving == "hand" else pairs[::-1], 1)
        images = np.stack([env.render_state(state) for state in states])
        with torch.no_grad():
            embedding = agent.encoder(sw.image_batch(images, CPU))
            codes = quantised(agent.vq, embedding, args.groups) if args.groups else None
        label = f"G = {args.groups}, seed {args.seed}: the {moving} moves"
        grids.append(GoalGrid(codes, embedding.numpy(), coords, ("x", "y"), places, blocked, args.n_embed, label, "encoder"))
    env.close()
    return grids


SETTINGS = {  # script: (the function that makes its goals and encodes them, the networks its map reads besides the flags)
    "dgrl_goal_dqn.py": (goal_dqn, ("representation",)),
    "dgrl_ris.py": (ris, ("goal_encoder",)),
    "dgrl_hrac.py": (hrac, ("subgoal_encoder", "adjacency")),
    "dgrl_hrac_keychest.py": (keychest, ("goal_autoencoder", "adjacency")),
    "dgrl_ris_sawyer.py": (sawyer, ("encoder", "vq")),
    "dgrl_amigo.py": (amigo, ("goal_encoder",)),
}  # --cut-to keeps the networks a map reads


# --- The figure and the table ------------------------------------------------------------------------------------------


def panel(axis, grid: GoalGrid, values: np.ndarray, title: str) -> None:
    """The goals' values (code indices, cluster labels) at their places, one colour per value (20 colours, reused beyond
    20 values: the values are renumbered in order, so that the codes of one factor get distinct colours first)."""
    image = np.full(grid.blocked.shape, np.nan)
    image[grid.places[:, 0], grid.places[:, 1]] = np.unique(values, return_inverse=True)[1] % 20
    axis.imshow(np.where(grid.blocked, 1.0, np.nan), cmap="Greys", vmin=0, vmax=1)  # walls black
    axis.imshow(image, cmap="tab20", vmin=0, vmax=19, interpolation="nearest")
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
    figure, axes = plt.subplots(sum(lines_of), per_line, figsize=(1.7 * per_line, 1.8 * sum(lines_of)), squeeze=False)
    # k-means gets as many clusters as a factor uses codes: the median over the run's factors, or for a baseline over the
    # figure's DGRL runs' factors (the codebook's size when there are none)
    used = {id(grid): [len(np.unique(column)) for column in grid.codes.T] for grid in grids if grid.codes is not None}
    every = [count for counts in used.values() for count in counts]
    for axis in axes.flat:
        axis.axis("off")
    table = ["| run | factor | codes | " + " | ".join(f"share {n}" for n in grids[0].coord_names) + " | gap |"]
    table.append("|---" * (4 + len(grids[0].coord_names)) + "|")
    first = 0
    for grid, rows, count in zip(grids, summaries, lines_of, strict=True):
        cells = axes[first : first + count].flat
        first += count
        counts = used.get(id(grid), every)
        clusters = kmeans(grid.embedding, int(np.median(counts)) if counts else grid.n_embed)
        (clustered,) = summarise(clusters[:, None], grid.coords, grid.coord_names)
        shares = " ".join(f"{name} {value:.2f}" for name, value in clustered["share"].items())
        title = "\n".join(textwrap.wrap(f"{grid.label}: k-means of its {grid.embedding_name},", 26))
        title += f"\n{clustered['codes']} clusters:\n{shares}"
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
        encode, needs = SETTINGS[script]
        grids += encode(saved)
        if args.cut_to is not None:
            kept = {key: saved[key] for key in ("script", "format", "args", *needs) if saved.get(key) is not None}
            env = saved["args"].get("env_id")  # the scripts with several envs name theirs
            stem = script.removeprefix("dgrl_").removesuffix(".py") + (f"_{env.removeprefix('MiniGrid-')}" if env else "")
            Path(args.cut_to).mkdir(parents=True, exist_ok=True)
            torch.save(kept, Path(args.cut_to) / f"{stem}_G{saved['args']['groups']}_s{saved['args']['seed']}.pt")
    if len({grid.coord_names for grid in grids}) > 1:
        raise SystemExit("factor_map.py: give checkpoints of one setting (their goals have other coordinates)")
    print("\n".join(draw(grids, args.factors, args.out)))
    print(f"wrote {args.out}.png and {args.out}.md")


if __name__ == "__main__":
    main(tyro.cli(Args, description=__doc__))
