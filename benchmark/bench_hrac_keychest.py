"""Where the time of dgrl_hrac_keychest.py goes: environment frames/s, the cost of acting, and of each update.

    python benchmark/bench_hrac_keychest.py            # about 15 s on 2 CPU cores; run nothing else meanwhile

Whole-run speed, one run alone on the machine (the SPS of each progress line, and its deltas in the training phase):

    python dgrl_hrac_keychest.py --groups 0 --total-timesteps 400000 --threads 1 --exp-name speed
    python dgrl_hrac_keychest.py --groups 16 --total-timesteps 400000 --threads 1 --exp-name speed

Prints one line per measurement (median of 5 blocks): the environment alone (random actions, 8 envs in one batch),
a full acting step (low-level forward + sampling + env step, per frame), one HRAC high-level TD3 update (batch 64,
2x300 networks, adjacency loss), one low-level A2C update on a 500-step episode, and the DGRL autoencoder step, each
with 1 and 2 torch threads. HRAC does one TD3 update per k = 10 frames, so frames/s in training is bounded by
10 / (TD3 update time) whatever else is made fast.
"""

import sys
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from timing import median_time  # benchmark/timing.py

import dgrl_hrac_keychest as kc
from vq import make_target


def td3_seconds(rng: np.random.Generator) -> float:
    """One HRAC high-level update: twin critics, then the actor (critic term every other update) and Polyak targets."""
    torch.manual_seed(0)
    actor, critic, anet = kc.ManagerActor(300), kc.TwinCritic(300), kc.AdjacencyNet(128, 32).requires_grad_(False)
    actor_target, critic_target = make_target(actor), make_target(critic)
    actor_opt = torch.optim.Adam(actor.parameters(), lr=1e-4, fused=True)
    critic_opt = torch.optim.Adam(critic.parameters(), lr=1e-3, fused=True)
    replay = kc.ManagerReplay(20000, rng)
    replay.add(*(rng.random((20000, d)).astype(np.float32) * 10 for d in (3, 2)), np.zeros(20000, np.float32),
               rng.random((20000, 3)).astype(np.float32) * 10, np.zeros(20000, np.float32))  # fmt: skip
    counter = [0]
    args = kc.Args()

    def update():
        batch = replay.sample(64, torch.device("cpu"))
        kc.manager_update(actor, critic, actor_target, critic_target, actor_opt, critic_opt, anet, batch, args, 1.1,
                          policy_term=counter[0] % 2 == 0)  # fmt: skip
        counter[0] += 1

    return median_time(update, 100)


def controller_seconds(groups: int, envs: kc.KeyChestVecEnv, rng: np.random.Generator) -> tuple[float, float]:
    """(acting time per frame, one A2C update on a 500-step episode) for HRAC (groups 0) or DGRL."""
    torch.manual_seed(0)
    goal_ae = kc.GoalAutoencoder(64, 128, groups, 64, 0.25, 0.99, 0) if groups else None
    controller = kc.Controller(2, 300)  # DGRL's default: the low level gets the decoded discretized subgoal
    ctrl_opt = torch.optim.Adam(controller.parameters(), lr=1e-4, fused=True)
    states = torch.as_tensor(rng.random((500, 3)) * 10, dtype=torch.float32)
    goals = torch.as_tensor(rng.random((500, 2)) * 10, dtype=torch.float32)
    actions, returns = torch.as_tensor(rng.integers(4, size=500)), torch.rand(500)

    def a2c_update():
        goal_inputs = kc.controller_goals(goal_ae, goals, "decoded", update=True)[0]
        logits, values = controller(states, goal_inputs)
        loss = kc.a2c_loss(logits, values, actions, returns, 0.01)[0]
        ctrl_opt.zero_grad()
        loss.backward()
        ctrl_opt.step()

    acting_states = torch.as_tensor(envs._observe())
    acting_goals = kc.controller_goals(goal_ae, torch.rand(envs.num_envs, 2) * 10, "decoded")[0]

    def act():
        with torch.no_grad():
            logits, _ = controller(acting_states, acting_goals)
            chosen = torch.multinomial(F.softmax(logits, 1), 1).squeeze(1).numpy()
        envs.step(chosen)

    return median_time(act, 500) / envs.num_envs, median_time(a2c_update, 20)


def main() -> None:
    rng = np.random.default_rng(0)
    envs = kc.KeyChestVecEnv(8)
    envs.reset(seed=0)
    env_step = median_time(lambda: envs.step(rng.integers(4, size=8)), 2000)
    print(f"environment alone: {8 / env_step:,.0f} frames/s (8 envs, random actions)")
    for threads in (1, 2):
        torch.set_num_threads(threads)
        for groups in (0, 16):
            acting, a2c = controller_seconds(groups, envs, rng)
            print(f"threads {threads}, G{groups:<2}: acting {acting * 1e6:.0f} us/frame, A2C update (500 steps) "
                  f"{a2c * 1e3:.1f} ms = {a2c / 500 * 1e6:.0f} us/frame")  # fmt: skip
        td3 = td3_seconds(rng)
        print(f"threads {threads}: TD3 update {td3 * 1e3:.2f} ms = {td3 / 10 * 1e6:.0f} us/frame at one update per "
              f"10 frames: at most {10 / td3:,.0f} frames/s while both levels train")  # fmt: skip


if __name__ == "__main__":
    main()
