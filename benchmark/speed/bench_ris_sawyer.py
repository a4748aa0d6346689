"""Where the time of dgrl_ris_sawyer.py goes: acting (env step with rendering + encoder + actor) and one RIS update from
pixels, with and without DGRL.

    python benchmark/speed/bench_ris_sawyer.py                 # about 2 min on a CPU core; run nothing else meanwhile
    python benchmark/speed/bench_ris_sawyer.py --device cuda   # the same on a GPU (the paper's batch 256)
    python benchmark/speed/bench_ris_sawyer.py --fast eager compile   # also the update alone, eager beside --fast compile

Prints one line per measurement (median of 5 blocks): one training step's acting (an 84x84 render of the new state, the
encoder on state and goal images, the actor's sample), and one `ris_update` (HER batch of 4 x batch uint8 images sampled
from the replay on the device, random translate, encoder, DRIML loss, critic, high level, actor
with 10 imagined subgoals, targets) for --groups 0 and 16 at each batch size, G16 both with its default
--vq-commitment-grad all (s, s', g and s_g through the encoder with gradient) and with --vq-commitment-grad state (s
alone, RIS's stop-gradient), the three timed in turn, block by block. RIS does one update per environment step, so
training steps/s is about 1 / (update time + acting time). The agents come from the script's make_agent.
Then, for each --fast path (default: eager and compile), the update alone (batches sampled beforehand) of the same agent,
in one process, after warm-up calls (compile time excluded): `update ... eager X ms, compile Y ms (eager / compile)`.
"""

import argparse
import copy
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from timing import median_time  # benchmark/speed/timing.py

import dgrl_ris_sawyer as sawyer


def filled_replay(episodes: int, rng: np.random.Generator, device: torch.device) -> sawyer.ImageEpisodeReplay:
    """A replay of random-action episodes of the training env (real images, so the DRIML loss sees real inputs)."""
    env = sawyer.SawyerPushAndReachEnv()
    replay = sawyer.ImageEpisodeReplay(episodes * (sawyer.EPISODE_STEPS + 2), (84, 84, 3), 2, device)
    for episode in range(episodes):
        observation, _ = env.reset(seed=episode)
        images, states, actions = [observation["image"]], [observation["state"]], []
        for _ in range(sawyer.EPISODE_STEPS):
            actions.append(rng.uniform(-1, 1, 2).astype(np.float32))
            step = env.step(actions[-1])
            images.append(step[0]["image"])
            states.append(step[0]["state"])
            if step[2]:
                break
        replay.add_episode(
            np.stack(images), np.stack(states), np.stack(actions), observation["goal_image"], observation["goal"]
        )
    env.close()
    return replay


def agent_of(args: sawyer.Args, device: torch.device) -> sawyer.Agent:
    """The script's make_agent with the flags of `args`, for 84x84 images and 2-d actions."""
    return sawyer.make_agent(84, 2, args, device)


def act_time(groups: int, device: torch.device) -> float:
    agent = agent_of(sawyer.Args(groups=groups), device)
    envs = sawyer.make_vector_env(1, 0, test=False)
    observations, _ = envs.reset(seed=0)

    def step():
        nonlocal observations
        actions = sawyer.act(agent, observations, device, deterministic=False)
        observations = envs.step(actions)[0]

    seconds = median_time(step, repeats=200)
    envs.close()
    return seconds


UPDATE_SETTINGS = {"RIS": {"groups": 0}, "G16": {"groups": 16}, "G16 state": {"groups": 16, "vq_commitment_grad": "state"}}


def update_times(replay, batch: int, device: torch.device, rng: np.random.Generator, blocks: int = 5) -> dict[str, float]:
    """Median seconds of one ris_update for each of UPDATE_SETTINGS, their blocks interleaved (one block of each in turn),
    so that a machine whose load changes slows them alike."""
    repeats = max(2, 256 // batch * 2)
    steps = {}
    for name, flags in UPDATE_SETTINGS.items():
        args = sawyer.Args(batch_size=batch, **flags)
        agent = agent_of(args, device)

        def step(agent=agent, args=args):
            sample = replay.sample(batch, args.her_goal_frac, args.her_random_frac, rng)
            sawyer.ris_update(agent, sample, args)
            if device.type == "cuda":
                torch.cuda.synchronize()

        step()  # warm-up
        steps[name] = step
    times = {name: [] for name in steps}
    for _ in range(blocks):
        for name, step in steps.items():
            start = time.perf_counter()
            for _ in range(repeats):
                step()
            times[name].append((time.perf_counter() - start) / repeats)
    return {name: statistics.median(values) for name, values in times.items()}


def fast_update_times(replay, groups: int, batch: int, device: torch.device, rng, paths: list[str]) -> dict[str, float]:
    """Seconds per ris_update call on each --fast path, on 8 batches sampled beforehand, from the same starting agent."""
    args = sawyer.Args(groups=groups, batch_size=batch)
    agent = agent_of(args, device)
    batches = [replay.sample(batch, args.her_goal_frac, args.her_random_frac, rng) for _ in range(8)]
    times = {}
    for path in paths:
        state = copy.deepcopy(agent)
        optimizers = [state.critic_optimizer, state.high_optimizer, state.actor_optimizer]
        update = sawyer.fast_update(sawyer.ris_update, path, optimizers)
        calls = 0

        def step(update=update, state=state):
            nonlocal calls
            update(state, batches[calls % len(batches)], args)
            calls += 1
            if device.type == "cuda":
                torch.cuda.synchronize()

        for _ in range(3):  # compilation (or CUDA graph capture) and first calls
            step()
        times[path] = median_time(step, repeats=max(2, 256 // batch * 2))
    return times


if __name__ == "__main__":
    parser = argparse.ArgumentParser()
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--batches", type=int, nargs="+", default=[32, 256])
    parser.add_argument("--fast", nargs="*", default=["eager", "compile"], choices=("eager", "compile", "cudagraphs"))
    options = parser.parse_args()
    torch.set_num_threads(options.threads)
    device = torch.device(options.device)
    rng = np.random.default_rng(0)
    replay = filled_replay(20, rng, device)
    for groups in (0, 16):
        print(
            f"act + env step, G{groups:<2}: {act_time(groups, device) * 1e3:6.1f} ms ({options.threads} thread(s), {device})"
        )
    for batch in options.batches:
        times = update_times(replay, batch, device, rng)
        print(
            f"update batch {batch:>4}: RIS {times['RIS'] * 1e3:7.1f} ms, RIS+DGRL G16 {times['G16'] * 1e3:7.1f} ms "
            f"({times['G16'] / times['RIS']:.2f}x), G16 --vq-commitment-grad state {times['G16 state'] * 1e3:7.1f} ms "
            f"({times['G16 state'] / times['RIS']:.2f}x), {options.threads} thread(s), {device}"
        )
    for batch in options.batches if options.fast else ():
        for groups in (0, 16):
            times = fast_update_times(replay, groups, batch, device, rng, options.fast)
            figures = ", ".join(f"{path} {seconds * 1e3:.1f} ms" for path, seconds in times.items())
            ratio = f" ({times['eager'] / times[options.fast[-1]]:.2f}x)" if "eager" in times and len(times) > 1 else ""
            print(f"update batch {batch:>4} G{groups:<2}: {figures}{ratio}, {options.threads} thread(s), {device}")
