"""What the teacher proposes: its goal distribution over the cells of a few fresh layouts, from saved checkpoints.

    python benchmark/analysis/amigo_teacher.py --checkpoints runs/<run A>/dgrl_amigo.cleanrl_model runs/<run B>/... \
        --out docs/img/amigo_teacher.png

One row per checkpoint, one column per layout (env seeds 0, 1, 2, ...): the rendered grid with each cell tinted by the
teacher's probability of proposing it (red = the most likely cell of that layout) and the probability of the most
likely cell written in the title. The env id comes from the checkpoint. Prints, per checkpoint over
--summary-layouts layouts, the teacher's mean probability mass on wall cells (against the walls' share of the cells),
its mean largest cell probability and how often that cell is a wall.
"""

import sys
from dataclasses import dataclass, field
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import torch
import tyro

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
import dgrl_amigo as amigo


@dataclass
class Args:
    checkpoints: list[str] = field(default_factory=list)
    """checkpoints saved by dgrl_amigo.py --save-model"""
    layouts: int = 3
    """fresh layouts (env seeds 0 .. layouts - 1) per checkpoint"""
    out: str = "results/amigo_teacher.png"
    """output image"""
    summary_layouts: int = 20
    """layouts (env seeds 0 .. summary_layouts - 1) of the printed summary"""


def teacher_maps(checkpoint: str, seeds: int) -> tuple[list[tuple[np.ndarray, np.ndarray, np.ndarray]], str]:
    """One checkpoint's teacher on the layouts of env seeds 0 .. seeds - 1: a list of (rendered frame, goal
    probabilities as (W, H), wall mask as (W, H)), and a label for the checkpoint."""
    saved = torch.load(checkpoint, map_location="cpu", weights_only=True)
    flags = dict(saved["args"])
    if isinstance(flags.get("goal_channel"), bool):  # saved when --goal-channel was a boolean (True: today's on)
        flags["goal_channel"] = "on" if flags["goal_channel"] else "off"
    envs = amigo.MiniGridVecEnv(flags["env_id"], 1, render_env0=True)
    args = amigo.Args(**{name: value for name, value in flags.items() if name in amigo.Args.__dataclass_fields__})
    agent = amigo.make_agent(envs.width, envs.height, envs.n_actions, args, "cpu")
    agent.load_state_dicts(saved)
    maps = []
    for seed in range(seeds):
        grids = envs.reset(seed=seed)[0]["grid"]
        with torch.no_grad():
            logits, _ = agent.teacher(torch.as_tensor(grids))
        probs = torch.softmax(logits, -1).view(envs.width, envs.height).numpy()
        maps.append((envs.render()[0], probs, grids[0, ..., 0] == amigo.OBJECT_TO_IDX["wall"]))
    return maps, f"G{saved['args']['groups']} seed {saved['args']['seed']}, t* {saved['t_star']}"


def tint(frame: np.ndarray, probs: np.ndarray, tile: int = 32) -> np.ndarray:
    """Blend each cell's pixels towards red in proportion to its probability (relative to the layout's largest)."""
    weight = (probs / probs.max()).T.repeat(tile, 0).repeat(tile, 1)[..., None]  # (H * tile, W * tile, 1)
    red = np.array([255, 0, 0], dtype=np.float32)
    return (frame * (1 - 0.7 * weight) + red * 0.7 * weight).astype(np.uint8)


if __name__ == "__main__":
    args = tyro.cli(Args)
    if not args.checkpoints:
        raise SystemExit("--checkpoints: give at least one checkpoint saved by dgrl_amigo.py --save-model")
    fig, axes = plt.subplots(len(args.checkpoints), args.layouts, figsize=(2.6 * args.layouts, 2.9 * len(args.checkpoints)))
    axes = np.atleast_2d(axes)
    for row, checkpoint in enumerate(args.checkpoints):
        maps, label = teacher_maps(checkpoint, max(args.layouts, args.summary_layouts))
        for col, (frame, probs, _) in enumerate(maps[: args.layouts]):
            axes[row, col].imshow(tint(frame, probs))
            axes[row, col].set_title(f"{label}\nmax p {probs.max():.2f}", fontsize=8)
            axes[row, col].axis("off")
        maps = maps[: args.summary_layouts]
        on_walls = np.mean([probs[walls].sum() for _, probs, walls in maps])
        wall_share = np.mean([walls.mean() for *_, walls in maps])
        top = np.mean([probs.max() for _, probs, _ in maps])
        top_wall = np.mean([walls.flat[probs.argmax()] for _, probs, walls in maps])
        print(
            f"{checkpoint}: mass on walls {on_walls:.2f} (walls are {wall_share:.2f} of the cells), largest cell "
            f"probability {top:.2f}, largest cell is a wall in {top_wall:.0%} of {args.summary_layouts} layouts"
        )
    fig.tight_layout()
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=110)
    print(f"wrote {args.out}")
