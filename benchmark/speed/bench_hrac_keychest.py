"""Where the time of dgrl_hrac_keychest.py goes: environment frames/s, the cost of acting, and of each update.

    python benchmark/speed/bench_hrac_keychest.py            # about 15 s on 2 CPU cores; run nothing else meanwhile
    python benchmark/speed/bench_hrac_keychest.py --fast eager compile   # the default: then each update eager vs compiled
    python benchmark/speed/bench_hrac_keychest.py --fast eager           # no --fast comparison (no compilation)

Whole-run speed, one run alone on the machine (the SPS of each progress line, and its deltas in the training phase):

    python dgrl_hrac_keychest.py --groups 0 --total-timesteps 400000 --threads 1 --exp-name speed
    python dgrl_hrac_keychest.py --groups 16 --total-timesteps 400000 --threads 1 --exp-name speed

Prints one line per measurement (median of 5 blocks): the environment alone (random actions, 8 envs in one batch),
a full acting step (low-level forward + sampling + env step, per frame), one HRAC high-level TD3 update (batch 64,
2x300 networks, adjacency loss), one low-level A2C update on a 500-step episode (with DGRL, the autoencoder step it
includes), each with 1 and 2 torch threads. Every network, optimizer and update is the script's own (`make_agent`,
`manager_update`, `controller_update`) at its default flags. HRAC does one TD3 update per k = 10 frames, so frames/s in
training is bounded by 10 / (TD3 update time) whatever else is made fast.

Then, with 1 torch thread and at the CPU preset's sizes (the defaults: batch 64, 300 hidden units, G = 16, the
autoencoder's pre-training batch 256), each update the script wraps in `fast_update` side by side in one process, as
`update ... eager X ms, compile Y ms (Z.ZZx)`: the TD3 update (critic term every other update), the A2C update on a
500-step episode (HRAC and DGRL) and the autoencoder's pre-training update. Compilation is excluded (warm-up calls
first).
"""

import argparse
import functools
import sys
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from timing import median_time  # benchmark/speed/timing.py

import dgrl_hrac_keychest as kc

CPU = torch.device("cpu")


def agent_from(args: kc.Args) -> kc.Agent:
    """The script's make_agent on the CPU."""
    return kc.make_agent(args, CPU)


def td3_seconds(rng: np.random.Generator) -> float:
    """One HRAC high-level update: twin critics, then the actor (critic term every other update) and Polyak targets."""
    torch.manual_seed(0)
    args = kc.Args(groups=0)
    agent = agent_from(args)
    replay = kc.ManagerReplay(args.man_buffer_size, rng)
    size = args.man_buffer_size
    replay.add(
        rng.random((size, 3)).astype(np.float32) * 10,
        rng.random((size, 2)).astype(np.float32) * 10,
        np.zeros(size, np.float32),
        rng.random((size, 3)).astype(np.float32) * 10,
        np.zeros(size, np.float32),
    )
    counter = [0]

    def update():
        kc.manager_update(
            agent,
            replay.sample(args.man_batch_size, CPU),
            args,
            threshold=(args.adj_margin_pos + args.adj_margin_neg) / 2,
            policy_term=counter[0] % args.man_policy_delay == 0,
        )
        counter[0] += 1

    return median_time(update, 100)


def controller_seconds(groups: int, envs: kc.KeyChestVecEnv, rng: np.random.Generator) -> tuple[float, float]:
    """(acting time per frame, one A2C update on a 500-step episode) for HRAC (groups 0) or DGRL (the default decoded
    subgoal for the low level)."""
    torch.manual_seed(0)
    args = kc.Args(groups=groups)
    agent = agent_from(args)
    states = torch.as_tensor(rng.random((500, 3)) * 10, dtype=torch.float32)
    goals = torch.as_tensor(rng.random((500, 2)) * 10, dtype=torch.float32)
    next_states = torch.as_tensor(rng.random((500, 3)) * 10, dtype=torch.float32)
    actions = torch.as_tensor(rng.integers(4, size=500))

    discounts = kc.segment_discounts(args.ctrl_gamma, args.k)

    def a2c_update():
        kc.controller_update(agent, states, goals, actions, next_states, discounts, args)

    acting_states = torch.as_tensor(envs._observe())
    acting_goals = kc.controller_goals(agent.goal_ae, torch.rand(envs.num_envs, 2) * 10, agent.dgrl_goal)[0]

    def act():
        with torch.no_grad():
            logits, _ = agent.controller(acting_states, acting_goals)
            chosen = torch.multinomial(F.softmax(logits, 1), 1).squeeze(1).numpy()
        envs.step(chosen)

    return median_time(act, 500) / envs.num_envs, median_time(a2c_update, 20)


def fast_updates(rng: np.random.Generator) -> dict[str, tuple]:
    """Per update the script compiles: (its function, a fresh agent at the preset's defaults, call(function, agent),
    optimizers(agent): those fast_update gets)."""
    updates = {}
    args = kc.Args()
    size = args.man_buffer_size
    replay = kc.ManagerReplay(size, rng)
    replay.add(rng.random((size, 3)) * 10, rng.random((size, 2)) * 10, rng.random(size), rng.random((size, 3)) * 10,
               np.zeros(size))  # fmt: skip
    batches = [replay.sample(args.man_batch_size, CPU) for _ in range(64)]
    threshold = (args.adj_margin_pos + args.adj_margin_neg) / 2
    manager_calls = [0]

    def manager(function, agent):
        i = manager_calls[0] = manager_calls[0] + 1
        function(agent, batches[i % 64], args, threshold=threshold, policy_term=i % args.man_policy_delay == 0)

    torch.manual_seed(0)
    agent = agent_from(kc.Args(groups=0))
    updates[f"TD3 (manager), batch {args.man_batch_size}"] = (
        kc.manager_update, agent, manager, lambda agent: [agent.critic_optimizer, agent.actor_optimizer]
    )  # fmt: skip
    episode = (
        torch.as_tensor(rng.random((500, 3)) * 10, dtype=torch.float32),
        torch.as_tensor(rng.random((500, 2)) * 10, dtype=torch.float32),
        torch.as_tensor(rng.integers(4, size=500)),
        torch.as_tensor(rng.random((500, 3)) * 10, dtype=torch.float32),
    )
    discounts = kc.segment_discounts(args.ctrl_gamma, args.k)
    for groups in (0, 16):
        torch.manual_seed(0)
        agent = agent_from(kc.Args(groups=groups))
        optimizers = lambda agent: [agent.controller_optimizer] + ([agent.ae_optimizer] if agent.goal_ae is not None else [])  # noqa: E731
        updates[f"A2C (controller), 500 steps, G{groups}"] = (
            kc.controller_update, agent, lambda function, agent: function(agent, *episode, discounts, args),
            optimizers,
        )  # fmt: skip
    torch.manual_seed(0)
    agent = agent_from(args)
    goals = kc.uniform_subgoals(args.ae_batch_size, CPU)
    updates[f"autoencoder pre-training, batch {args.ae_batch_size}, G{args.groups}"] = (
        kc.goal_autoencoder_update, agent, lambda function, agent: function(agent, goals), lambda agent: [agent.ae_optimizer]
    )  # fmt: skip
    return updates


def compare_fast_paths(paths: list[str], rng: np.random.Generator) -> None:
    """`update ... eager X ms, compile Y ms (Z.ZZx)` for each update the script compiles, 1 thread, compilation
    excluded (two warm-up calls: the TD3 update has a graph with and one without its delayed critic term)."""
    import copy

    torch.set_num_threads(1)
    for name, (function, agent, call, optimizers) in fast_updates(rng).items():
        times = {}
        for path in paths:
            state = copy.deepcopy(agent)
            fast = kc.fast_update(function, path, optimizers(state))
            call(fast, state)
            call(fast, state)
            times[path] = median_time(functools.partial(call, fast, state), 20)
        line = ", ".join(f"{path} {seconds * 1e3:.2f} ms" for path, seconds in times.items())
        if "eager" in times and len(times) > 1:
            line += "".join(f" ({times['eager'] / seconds:.2f}x)" for path, seconds in times.items() if path != "eager")
        print(f"update {name}: {line}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--fast", nargs="+", default=["eager", "compile"], choices=["eager", "compile"],
                        help="the --fast paths to time each compiled update with (eager alone: no comparison)")  # fmt: skip
    cli = parser.parse_args()
    rng = np.random.default_rng(0)
    envs = kc.KeyChestVecEnv(8)
    envs.reset(seed=0)
    env_step = median_time(lambda: envs.step(rng.integers(4, size=8)), 2000)
    print(f"environment alone: {8 / env_step:,.0f} frames/s (8 envs, random actions)")
    for threads in (1, 2):
        torch.set_num_threads(threads)
        for groups in (0, 16):
            acting, a2c = controller_seconds(groups, envs, rng)
            print(
                f"threads {threads}, G{groups:<2}: acting {acting * 1e6:.0f} us/frame, A2C update (500 steps) "
                f"{a2c * 1e3:.1f} ms = {a2c / 500 * 1e6:.0f} us/frame"
            )
        td3 = td3_seconds(rng)
        print(
            f"threads {threads}: TD3 update {td3 * 1e3:.2f} ms = {td3 / 10 * 1e6:.0f} us/frame at one update per "
            f"10 frames: at most {10 / td3:,.0f} frames/s while both levels train"
        )
    if cli.fast != ["eager"]:
        compare_fast_paths(cli.fast, rng)


if __name__ == "__main__":
    main()
