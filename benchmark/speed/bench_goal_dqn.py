"""Per-update time of dgrl_goal_dqn.py's two updates and of dgrl_mnist.py's training step, on each --fast path.

    python benchmark/speed/bench_goal_dqn.py          # about 5 min on one CPU core (most of it compiling); run nothing else
    python benchmark/speed/bench_goal_dqn.py --device cuda --fast eager compile cudagraphs   # on a GPU, every speed path

Prints one line per update and setting (median of 5 blocks, compilation and CUDA graph capture done before the clock
starts), at the scripts' default sizes: goal-DQN's `pretrain_step` (Deep InfoMax on random-walk transitions, batch
128, the codebook's EMA for DGRL) and `td_update` (Double DQN on the frozen phi's cell table, batch 128, as the
default run; and with --finetune, which encodes the 36 cell images and trains phi and the codebook), --groups 0 and 16;
Color-MNIST's `train_step` (batch 128), --groups 0 and 2.
"""

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from timing import median_time  # benchmark/speed/timing.py

import dgrl_goal_dqn as gdqn


def timed(update, optimizers, fast: str, call, device: torch.device, repeats: int = 20) -> float:
    """Median seconds of `call(fast version of update)`, after 5 calls of compilation and capture."""
    function = gdqn.fast_update(update, fast, optimizers)

    def step():
        call(function)
        if device.type == "cuda":
            torch.cuda.synchronize()

    for _ in range(5):
        step()
    return median_time(step, repeats=repeats)


def goal_dqn_agent(groups: int, finetune: bool, device: torch.device) -> tuple[gdqn.Args, gdqn.Agent]:
    args = gdqn.Args(groups=groups, finetune=finetune)
    torch._dynamo.reset()  # a new agent: compile afresh rather than against the previous agent's guards
    agent = gdqn.make_agent(args, device)
    return args, agent


def pretrain_time(groups: int, device: torch.device, fast: str) -> float:
    """One pre-training step at the defaults (SpiralWorld, infomax, batch 128), rows drawn as the script draws them."""
    args, agent = goal_dqn_agent(groups, False, device)
    layout = gdqn.MazeLayout(args.env_id)
    rng = np.random.default_rng(0)
    embedder = gdqn.CellEmbedder(layout, args.noise, device, rng)
    walks = tuple(
        torch.as_tensor(c, device=device) for c in gdqn.random_walks(layout, args.rep_transitions, args.max_episode_steps, rng)
    )

    def call(function):
        rows = torch.as_tensor(rng.integers(args.rep_transitions, size=args.rep_batch_size), device=device)
        function(agent, *gdqn.pretrain_inputs(embedder, walks, rows, args.rep))

    return timed(gdqn.pretrain_step, [agent.rep_optimizer], fast, call, device)


def td_time(groups: int, finetune: bool, device: torch.device, fast: str) -> float:
    """One DQN step at the defaults (batch 128, Double DQN) from a full replay of random transitions: on the frozen
    phi's cell table (the default run), or encoding the cells and training phi (--finetune)."""
    args, agent = goal_dqn_agent(groups, finetune, device)
    layout = gdqn.MazeLayout(args.env_id)
    rng = np.random.default_rng(0)
    embedder = gdqn.CellEmbedder(layout, args.noise, device, rng)
    table = None
    if not finetune:
        agent.rep.eval()
        agent.rep.requires_grad_(False)
        table = gdqn.cell_table(agent.rep, embedder)
    replay = gdqn.ReplayBuffer(args.buffer_size, device)
    for _ in range(args.buffer_size):
        cell, goal, action = rng.integers(layout.n_cells), rng.integers(layout.n_cells), rng.integers(len(gdqn.MOVES))
        following = layout.next_cell[cell, action]
        replay.add(cell, following, goal, action, 5.0 if following == goal else -1.0, following == goal)

    def call(function):
        batch = replay.sample(args.batch_size, rng)
        function(agent, batch, table, gdqn.td_inputs(embedder, batch, table, finetune, args.double_dqn), args)

    return timed(gdqn.td_update, [agent.q_optimizer], fast, call, device)


def mnist_time(groups: int, device: torch.device, fast: str) -> float:
    """One Color-MNIST training step at the defaults (batch 128, hidden 400, latent 30, 256 codes) on random images."""
    import dgrl_mnist as mnist  # imported here: it needs matplotlib, which the goal-DQN cases (and gpu_check.sh) do not

    args = mnist.Args(groups=groups)
    torch._dynamo.reset()
    model = mnist.make_model(args, device)
    images = torch.rand(50, args.batch_size, 3, 28, 28, device=device)
    count = iter(range(10**9))

    def call(function):
        function(model, images[next(count) % len(images)])

    return timed(mnist.train_step, [model.optimizer], fast, call, device)


if __name__ == "__main__":
    parser = argparse.ArgumentParser()
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--fast", nargs="+", default=["eager", "compile"], choices=("eager", "compile", "cudagraphs"))
    parser.add_argument("--only", nargs="+", default=["pretrain", "td", "td-finetune", "mnist"])
    options = parser.parse_args()
    torch.set_num_threads(options.threads)
    device = torch.device(options.device)
    cases = {
        "pretrain": ("goal-DQN pretrain_step", (0, 16), lambda groups, fast: pretrain_time(groups, device, fast)),
        "td": ("goal-DQN td_update", (0, 16), lambda groups, fast: td_time(groups, False, device, fast)),
        "td-finetune": ("goal-DQN td_update finetune", (0, 16), lambda groups, fast: td_time(groups, True, device, fast)),
        "mnist": ("Color-MNIST train_step", (0, 2), lambda groups, fast: mnist_time(groups, device, fast)),
    }
    for key in options.only:
        name, groups_list, measure = cases[key]
        for groups in groups_list:
            times = {fast: measure(groups, fast) for fast in options.fast}
            figures = ", ".join(f"{fast} {seconds * 1e3:7.2f} ms" for fast, seconds in times.items())
            ratios = ", ".join(f"{fast} {times[options.fast[0]] / times[fast]:.2f}x" for fast in options.fast[1:])
            print(
                f"update {name:<27} batch 128 G{groups:<2}: {figures} ({ratios} vs {options.fast[0]}), "
                f"{options.threads} thread(s), {device}",
                flush=True,
            )
