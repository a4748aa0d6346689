"""Where the time of dgrl_hrac.py goes: acting, one update at each level, and whole training runs, HRAC vs DGRL.

    python benchmark/speed/bench_hrac.py               # about 4 min on a CPU core; run nothing else meanwhile
    python benchmark/speed/bench_hrac.py --device cuda # the same updates on a GPU (acting and training runs on the CPU path)
    python benchmark/speed/bench_hrac.py --train-steps 0 --fast eager compile   # only the updates' speed paths side by side

Prints one line per measurement (env steps/s per env: benchmark/figures/hrac_envs.py):
- act: one controller action (state masked, subgoal through the encoder under DGRL), batch 1;
- controller update: one TD3 step at batch 128 (under DGRL also the encoder, the quantizer and its EMA step);
- manager update: one TD3 step at batch 128 with HIRO's off-policy correction (12 candidate subgoals rolled through 10
  stored steps: 15,360 controller forward passes) and the adjacency term;
- per 500-step episode: 500 acts + 500 controller updates + 50 manager updates, the steady-state training cost;
- training: the script itself on AntMaze for --train-steps steps, one process on one thread, its final SPS (env steps,
  acting, all updates, one evaluation of 5 episodes; the adjacency network not yet trained);
- update ... (--fast): each level's update through every speed path of --fast, side by side in one process, as
  milliseconds per update (the median of benchmark/speed/timing.py, compilation done before the clock starts), at batch 128.
"""

import re
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import tyro

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from timing import median_time  # benchmark/speed/timing.py

import dgrl_hrac as hrac

ROOT = Path(__file__).resolve().parents[2]


@dataclass
class Args:
    device: str = "cpu"
    """torch device of the update measurements"""
    threads: int = 1
    """torch CPU threads"""
    train_steps: int = 5000
    """steps of the whole-script measurement (0 skips it)"""
    fast: tuple[str, ...] = ("eager", "compile")
    """the speed paths of the side-by-side update measurement (none skips it; cudagraphs needs --device cuda)"""


def build(groups: int, device: str, **overrides) -> tuple[hrac.Args, np.ndarray, hrac.Agent]:
    """The script's agent on AntMaze (30-d state, 8 torques) with the script's default flags (but `overrides`), built by
    its make_agent."""
    args = hrac.Args(groups=groups, **overrides)
    bounds = hrac.subgoal_bounds(args.env_id, args.subgoal_scale)
    agent = hrac.make_agent(30, 8, args, torch.device(device))
    return args, bounds, agent


def timed(fn, repeats: int) -> float:
    for _ in range(3):
        fn()
    if torch.cuda.is_available():
        torch.cuda.synchronize()
    start = time.perf_counter()
    for _ in range(repeats):
        fn()
    if torch.cuda.is_available():
        torch.cuda.synchronize()
    return (time.perf_counter() - start) / repeats


def filled_replays(rng: np.random.Generator) -> tuple[hrac.Replay, hrac.Replay]:
    """A full controller replay and a full manager replay of AntMaze's shapes, of standard normal numbers."""
    ctrl_replay = hrac.Replay(20_000, states=(30,), goals=(2,), actions=(8,), rewards=(), next_states=(30,),
                              next_goals=(2,), dones=())  # fmt: skip
    man_replay = hrac.Replay(2_000, states=(30,), goals=(2,), actions=(2,), rewards=(), next_states=(30,), dones=(),
                             state_seq=(11, 30), action_seq=(10, 8))  # fmt: skip
    for replay in (ctrl_replay, man_replay):
        for array in replay.fields.values():
            array[:] = rng.normal(size=array.shape)
        replay.size = replay.capacity
    return ctrl_replay, man_replay


def measure_updates(groups: int, cli: Args, rng: np.random.Generator) -> None:
    args, bounds, agent = build(groups, cli.device)
    ctrl_replay, man_replay = filled_replays(rng)

    def controller_step():
        sample = hrac.as_tensors(ctrl_replay.sample(args.batch_size, rng), cli.device)
        hrac.controller_update(agent, sample, args)

    def manager_step():
        sample = man_replay.sample(args.batch_size, rng)
        hrac.manager_update(
            agent,
            hrac.manager_batch(sample, rng, bounds=bounds, correction_samples=args.correction_samples, device=cli.device),
            args,
            torch.as_tensor(bounds, device=cli.device),
        )

    act = timed(lambda: hrac.act(agent, rng.normal(size=30), rng.normal(size=2), manager=False, noise=1.0, rng=rng), 500)
    ctrl = timed(controller_step, 100)
    man = timed(manager_step, 20)
    episode = 500 * act + 500 * ctrl + 50 * man
    print(
        f"G{groups:<2} ({cli.device}, {cli.threads} thread): act {act * 1e6:.0f} us, "
        f"controller update {ctrl * 1e3:.1f} ms, manager update {man * 1e3:.1f} ms; per 500-step episode {episode:.2f} s "
        f"of agent time (at most {500 / episode:.0f} SPS before env time)"
    )


def update_time(level: str, groups: int, cli: Args, fast: str) -> float:
    """Seconds per update of `level` ("controller" or "manager") through `--fast fast`, on batches sampled beforehand
    (the update alone is timed); compiled and warmed up before the clock starts."""
    rng = np.random.default_rng(0)
    args, bounds, agent = build(groups, cli.device)
    ctrl_replay, man_replay = filled_replays(rng)
    if level == "controller":
        batches = [hrac.as_tensors(ctrl_replay.sample(args.batch_size, rng), cli.device) for _ in range(16)]
        flags = (args,)
        optimizers = [agent.controller.critic_optimizer, agent.controller.actor_optimizer]
        update = hrac.fast_update(hrac.controller_update, fast, optimizers)
    else:
        batches = [
            hrac.manager_batch(
                man_replay.sample(args.batch_size, rng), rng, bounds=bounds, correction_samples=args.correction_samples,
                device=cli.device,
            )
            for _ in range(16)
        ]  # fmt: skip
        flags = (args, torch.as_tensor(bounds, device=cli.device))
        optimizers = [agent.manager.critic_optimizer, agent.manager.actor_optimizer]
        update = hrac.fast_update(hrac.manager_update, fast, optimizers)
    calls = [0]

    def step():
        update(agent, batches[calls[0] % len(batches)], *flags)
        calls[0] += 1
        if cli.device.startswith("cuda"):
            torch.cuda.synchronize()

    for _ in range(5):  # compilation (and a CUDA graph's capture) before the clock starts
        step()
    return median_time(step, repeats=20 if level == "controller" else 5)


def measure_fast(cli: Args) -> None:
    for level in ("controller", "manager"):
        for groups in (0, 16):
            times = {fast: update_time(level, groups, cli, fast) for fast in cli.fast}
            figures = ", ".join(f"{fast} {seconds * 1e3:.2f} ms" for fast, seconds in times.items())
            ratios = ", ".join(f"{fast} {times[cli.fast[0]] / times[fast]:.2f}x" for fast in cli.fast[1:])
            print(
                f"update {level:<10} G{groups:<2} batch 128 ({cli.device}, {cli.threads} thread): {figures}"
                + (f" ({ratios} vs {cli.fast[0]})" if ratios else ""),
                flush=True,
            )


if __name__ == "__main__":
    cli = tyro.cli(Args)
    torch.set_num_threads(cli.threads)
    torch.set_flush_denormal(True)  # as the script does
    rng = np.random.default_rng(0)
    for groups in (0, 16):
        measure_updates(groups, cli, rng)
    if cli.fast:
        measure_fast(cli)
    for groups in (0, 16) if cli.train_steps else ():
        out = subprocess.run(
            [sys.executable, str(ROOT / "dgrl_hrac.py"), "--env-id", "AntMaze", "--groups", str(groups), "--total-timesteps",
             str(cli.train_steps), "--eval-frequency", str(cli.train_steps), "--exp-name", "bench", "--no-cuda"],
            capture_output=True, text=True, cwd="/tmp", env={"OMP_NUM_THREADS": "1", "PATH": "/usr/bin:/bin"}, check=True,
        ).stdout  # fmt: skip
        sps = re.findall(r"SPS (\d+)", out)[-1]
        print(f"training G{groups:<2}: AntMaze, {cli.train_steps} steps, one CPU thread: SPS {sps}")
