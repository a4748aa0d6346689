"""Where the time of dgrl_ris.py goes: environment steps/s of every maze, and one RIS update with and without DGRL.

    python benchmark/speed/bench_ris.py                       # about 1 min on 2 CPU cores; run nothing else meanwhile
    python benchmark/speed/bench_ris.py --device cuda --fast eager compile cudagraphs   # on a GPU, every speed path

Prints one line per measurement (median of 5 blocks): each env id stepped alone with random actions (one env, the
script's default), acting (actor forward + sampling + env step), and one `ris_update` (HER batch sampled on the device,
critic, high level, actor with 10 imagined subgoals, targets) for the Ant state (31-d goal) and the PointMaze state
(2-d goal), --groups 0 and 16, at several batch sizes. RIS does one update per environment step, so training steps/s
is about 1 / (update time + acting time).
"""

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from timing import median_time  # benchmark/speed/timing.py

import dgrl_ris as ris


def env_speed(env_id: str, steps: int = 1000) -> float:
    threshold = ris.ANT_THRESHOLD if env_id in ris.ANT_MAZES else ris.ROBOTICS_THRESHOLD
    envs = ris.make_vector_env(env_id, 1, 0, False, 0, threshold)
    envs.reset(seed=0)
    start = time.perf_counter()
    for _ in range(steps):
        envs.step(envs.action_space.sample())
    envs.close()
    return steps / (time.perf_counter() - start)


def update_time(
    state_dim: int, goal_dim: int, action_dim: int, groups: int, batch: int, device: torch.device, fast: str = "eager"
) -> float:
    """Median seconds of one ris_update at the script's default hyper-parameters, on the agent the script builds, run
    through `--fast fast` (its compilation and capture done before the clock starts)."""
    args = ris.Args(groups=groups, batch_size=batch)
    torch._dynamo.reset()  # a new agent: compile afresh rather than against the previous agent's guards
    agent = ris.make_agent(state_dim, goal_dim, action_dim, args, device)
    replay = ris.EpisodeReplay(60_000, state_dim, action_dim, goal_dim, device)
    rng = np.random.default_rng(0)
    for _ in range(100):
        replay.add_episode(
            rng.normal(size=(600, state_dim)), rng.uniform(-1, 1, (600, action_dim)), rng.normal(size=(600, state_dim)),
            rng.normal(size=(600, goal_dim)),
        )  # fmt: skip

    update = ris.fast_update(ris.ris_update, fast, [agent.critic_optimizer, agent.high_optimizer, agent.actor_optimizer])

    def step():
        sample = replay.sample(batch, goal_dim, ris.ANT_THRESHOLD, args.her_goal_frac, args.her_random_frac)
        update(agent, sample, args)
        if device.type == "cuda":
            torch.cuda.synchronize()

    for _ in range(5):  # compilation, CUDA graph warm-up and capture
        step()
    return median_time(step, repeats=max(2, 2048 // batch * 2))


if __name__ == "__main__":
    parser = argparse.ArgumentParser()
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--batches", type=int, nargs="+", default=[128, 256, 2048])
    parser.add_argument("--fast", nargs="+", default=["eager", "compile"], choices=("eager", "compile", "cudagraphs"))
    parser.add_argument("--envs", action=argparse.BooleanOptionalAction, default=True, help="time the env steps too")
    parser.add_argument("--goals", nargs="+", default=["ant", "point"], choices=["ant", "point"], help="state sizes")
    options = parser.parse_args()
    torch.set_num_threads(options.threads)
    device = torch.device(options.device)
    if device.type == "cpu" and options.envs:
        for env_id in (*ris.ANT_MAZES, "PointMaze_UMaze-v3", "AntMaze_UMaze-v5"):
            print(f"env {env_id:<20} {env_speed(env_id):7.0f} steps/s (random actions, 1 env)")
    sizes = {"ant": ("Ant (31-d goal)", (31, 31, 8)), "point": ("PointMaze (2-d goal)", (6, 2, 2))}
    for name, dims in (sizes[goal] for goal in options.goals):
        for batch in options.batches:
            for groups in (0, 16):
                times = {fast: update_time(*dims, groups, batch, device, fast) for fast in options.fast}
                figures = ", ".join(f"{fast} {seconds * 1e3:7.2f} ms" for fast, seconds in times.items())
                ratios = ", ".join(f"{fast} {times[options.fast[0]] / times[fast]:.2f}x" for fast in options.fast[1:])
                label = "RIS" if groups == 0 else "RIS+DGRL G16"
                print(
                    f"update {name:<21} batch {batch:>5} {label:<12}: {figures} ({ratios} vs {options.fast[0]}), "
                    f"{options.threads} thread(s), {device}",
                    flush=True,
                )
