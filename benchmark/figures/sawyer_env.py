"""The Sawyer push-and-reach env of dgrl_ris_sawyer.py: its speed with 84x84 image observations and what the images show.

    python benchmark/figures/sawyer_env.py --out results/sawyer_env.png

Prints env frames/s (one env, random actions, every step rendering its 84x84 observation image, resets included: each
reset also renders the goal image) for the training and the test configuration, and writes one image: a training reset's
state image and its goal image, then a test reset's state image and its goal image, upscaled `scale` times (nearest
neighbour). The hand is red, the puck blue; x grows to the right, y upwards.
"""

import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tyro

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
import dgrl_ris_sawyer as sawyer


@dataclass
class Args:
    out: str = "results/sawyer_env.png"
    """output image"""
    steps: int = 2000
    """random-action steps per configuration for the speed measurement"""
    seed: int = 0
    """seed of the pictured resets and of the random actions"""
    scale: int = 4
    """upscaling factor of the picture"""


if __name__ == "__main__":
    from PIL import Image

    args = tyro.cli(Args)
    panels = []
    for test in (False, True):
        env = sawyer.SawyerPushAndReachEnv(test=test)
        observation, _ = env.reset(seed=args.seed)
        panels += [observation["image"], observation["goal_image"]]
        env.action_space.seed(args.seed)
        start = time.perf_counter()
        for _ in range(args.steps):
            _, _, terminated, truncated, _ = env.step(env.action_space.sample())
            if terminated or truncated:
                env.reset()
        name = "test" if test else "training"
        print(f"{name} configuration: {args.steps / (time.perf_counter() - start):,.0f} frames/s (84x84 images)")
        env.close()
    gap = np.full((panels[0].shape[0], 2, 3), 255, np.uint8)
    picture = np.concatenate([part for panel in panels for part in (panel, gap)][:-1], 1)
    picture = picture.repeat(args.scale, 0).repeat(args.scale, 1)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(picture).save(args.out)
    print(f"wrote {args.out}: training state, training goal, test state, test goal")
