"""How well a dgrl_hrac.py controller reaches subgoals on its own, from checkpoints, against an untrained controller.

    python benchmark/analysis/hrac_controller.py sweeps/hrac-antmaze-cpu/*/runs/*/hrac-antmaze-cpu.cleanrl_model
    # the checkpoints of `python benchmark/launch.py --preset hrac-antmaze-cpu` (docs/dgrl_hrac.md)

For each checkpoint (and an untrained agent of the same flags, seed 0) the ant starts from a reset of AntMaze's open
start cell and is given, for 5 segments of k = 10 steps, the relative subgoal that points at one fixed point 4 m away
(re-targeted after every step, re-issued at every segment start, as the manager would), in 8 directions, with
deterministic actions. Prints the mean final distance to the point (4.0 = the ant did not get closer) and the mean
distance covered toward it.
"""

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
import dgrl_hrac as hrac


def agent_from(saved_args: dict) -> hrac.Agent:
    """An untrained agent (seed 0) with a checkpoint's flags, built by the script's make_agent (a 30-d state)."""
    torch.manual_seed(0)
    args = hrac.Args(**{name: value for name, value in saved_args.items() if name in hrac.Args.__dataclass_fields__})
    return hrac.make_agent(30, 8, args, torch.device("cpu"))


def probe(agent: hrac.Agent, radius: float = 4.0, segments: int = 5, k: int = 10) -> tuple[float, float]:
    env, rng, final = hrac.HiroAntEnv("AntMaze"), np.random.default_rng(0), []
    for direction in range(8):
        state, _ = env.reset(seed=100 + direction)
        angle = 2 * np.pi * direction / 8
        target = state[:2] + radius * np.array([np.cos(angle), np.sin(angle)])
        for t in range(segments * k):
            if t % k == 0:
                subgoal = target - state[:2]
            next_state, *_ = env.step(hrac.act(agent, state, subgoal, manager=False, noise=0.0, rng=rng))
            subgoal = hrac.subgoal_transition(state, subgoal, next_state)
            state = next_state
        final.append(np.linalg.norm(target - state[:2]))
    return float(np.mean(final)), radius - float(np.mean(final))


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("checkpoints", nargs="+", help="checkpoints of dgrl_hrac.py runs (--save-model)")
    torch.set_num_threads(1)
    torch.set_flush_denormal(True)
    for path in parser.parse_args().checkpoints:
        saved = torch.load(path, map_location="cpu", weights_only=True)
        if not isinstance(saved, dict) or saved.get("script") != "dgrl_hrac.py":
            print(f"{path}: skipped, not a checkpoint of dgrl_hrac.py", file=sys.stderr)
            continue
        if saved["args"]["env_id"] == "AntFall":
            print(
                f"{path}: skipped, an AntFall controller takes 3-d (xyz) subgoals; this probe gives 2-d ones", file=sys.stderr
            )
            continue
        untrained = probe(agent_from(saved["args"]))
        trained_agent = agent_from(saved["args"])
        trained_agent.load_state_dicts(saved)
        trained = probe(trained_agent)
        print(
            f"{path}: G{saved['args']['groups']}: final distance to a point 4 m away after 50 steps: untrained "
            f"{untrained[0]:.2f} (covered {untrained[1]:+.2f} m), trained {trained[0]:.2f} (covered {trained[1]:+.2f} m)"
        )
