"""Top-down renders of the four Ant mazes of dgrl_ris.py on their test configuration (docs/img/ris_mazes.png).

    python benchmark/figures/ris_mazes.py        # headless too: dgrl_ris sets MUJOCO_GL=egl when there is no display

Each panel is the script's own MuJoCo scene (walls, ant at a test start, red goal marker at a test goal), rendered by
the env's `render()`; it lets a reader check the geometry against the maze table of docs/dgrl_ris.md at a glance.
"""

import argparse
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
import dgrl_ris as ris

if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parents[2] / "docs/img/ris_mazes.png")
    out = parser.parse_args().out
    figure, axes = plt.subplots(1, 4, figsize=(16, 4.4))
    for axis, (name, shape) in zip(axes, (("AntU", "U"), ("AntFb", "S"), ("AntMaze", "Pi"), ("AntFg", "omega")), strict=True):
        env = ris.AntMazeEnv(name, test=True, render_mode="rgb_array")
        observation, _ = env.reset(seed=0)
        axis.imshow(env.render())
        axis.set_title(f"{name} ({shape}): start {observation['state'][:2].round(1)}, goal {observation['goal'][:2].round(1)}")
        axis.axis("off")
        env.close()
    figure.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(out, dpi=80)
    print(f"wrote {out}")
