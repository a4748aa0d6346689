"""How well a dgrl_hrac.py controller reaches subgoals on its own, from checkpoints, against an untrained controller.

    python benchmark/hrac_controller.py runs/AntMaze__G*__cpu__1__*/cpu.cleanrl_model   # the study's checkpoints

For each checkpoint (and an untrained controller of the same architecture) the ant starts from a reset of AntMaze's open
start cell and is given, for 5 segments of k = 10 steps, the relative subgoal that points at one fixed point 4 m away
(re-targeted after every step, re-issued at every segment start, as the manager would), in 8 directions, with
deterministic actions. Prints the mean final distance to the point (4.0 = the ant did not get closer) and the mean
distance covered toward it.
"""

import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import dgrl_hrac as hrac


def controller_from(path: str | None, saved_args: dict) -> dict:
    args = hrac.Args(
        **{key: saved_args[key] for key in ("groups", "embed_dim", "n_embed", "encoder_hidden_dim", "hidden_dim")}
    )
    bounds = hrac.subgoal_bounds("AntMaze", saved_args["subgoal_scale"])
    goal_input = args.embed_dim if args.groups else len(bounds)
    torch.manual_seed(0)
    actor = hrac.Actor(30, goal_input, 8, 30.0, args.hidden_dim)
    encoder = hrac.SubgoalEncoder(len(bounds), bounds, args) if args.groups else None
    if path is not None:
        saved = torch.load(path, map_location="cpu", weights_only=False)
        actor.load_state_dict(saved["controller_actor"])
        if encoder is not None:
            encoder.load_state_dict(saved["subgoal_encoder"])
    return {"controller": {"actor": actor}, "encoder": encoder}


def probe(nets: dict, radius: float = 4.0, segments: int = 5, k: int = 10) -> tuple[float, float]:
    env, rng, final = hrac.HiroAntEnv("AntMaze"), np.random.default_rng(0), []
    for direction in range(8):
        state, _ = env.reset(seed=100 + direction)
        angle = 2 * np.pi * direction / 8
        target = state[:2] + radius * np.array([np.cos(angle), np.sin(angle)])
        for t in range(segments * k):
            if t % k == 0:
                subgoal = target - state[:2]
            next_state, *_ = env.step(hrac.controller_action(nets, state, subgoal, 0.0, rng))
            subgoal, state = hrac.subgoal_transition(state, subgoal, next_state), next_state
        final.append(np.linalg.norm(target - state[:2]))
    return float(np.mean(final)), radius - float(np.mean(final))


if __name__ == "__main__":
    torch.set_num_threads(1)
    torch.set_flush_denormal(True)
    for path in sys.argv[1:]:
        saved_args = torch.load(path, map_location="cpu", weights_only=False)["args"]
        untrained = probe(controller_from(None, saved_args))
        trained = probe(controller_from(path, saved_args))
        print(
            f"{path}: G{saved_args['groups']}: final distance to a point 4 m away after 50 steps: untrained "
            f"{untrained[0]:.2f} (covered {untrained[1]:+.2f} m), trained {trained[0]:.2f} (covered {trained[1]:+.2f} m)"
        )
