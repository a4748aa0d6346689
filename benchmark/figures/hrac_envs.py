"""The HIRO Ant suite of dgrl_hrac.py: a top-down render of every env and its random-action speed.

    python benchmark/figures/hrac_envs.py --out docs/img/hrac_envs.png   # headless Linux: dgrl_hrac sets MUJOCO_GL=egl

Prints env steps/s (one env, random actions, 2,000 steps after a reset) and writes one image with the five envs after a
reset and ten zero-action steps (AntMaze, AntMazeSparse, AntPush, AntFall, AntGather from left to right; y points up,
so the structures appear flipped top to bottom with respect to the row listing of `STRUCTURES` in dgrl_hrac.py).
"""

import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tyro

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
import dgrl_hrac as hrac


@dataclass
class Args:
    out: str = "results/hrac_envs.png"
    """output image"""
    steps: int = 2000
    """random-action steps per env for the speed measurement"""


if __name__ == "__main__":
    from PIL import Image

    args = tyro.cli(Args)
    frames = []
    for env_id in ("AntMaze", "AntMazeSparse", "AntPush", "AntFall", "AntGather"):
        env = hrac.HiroAntEnv(env_id, render_mode="rgb_array")
        env.reset(seed=0)
        for _ in range(10):
            env.step(np.zeros(8))
        frames.append(env.render())
        rng = np.random.default_rng(0)
        start = time.perf_counter()
        for _ in range(args.steps):
            *_, truncated, _ = env.step(rng.uniform(-30, 30, 8))
            if truncated:
                env.reset()
        print(f"{env_id}: {args.steps / (time.perf_counter() - start):,.0f} steps/s")
        env.close()
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.concatenate(frames, 1)).save(args.out)
    print(f"wrote {args.out}")
