"""Where the time of dgrl_amigo.py goes: environment steps/s, acting, one learner update, and whole training runs.

    python benchmark/speed/bench_amigo.py      # about 3 min on 2 CPU cores (plus compiling); run nothing else meanwhile
    python benchmark/speed/bench_amigo.py --parts update --fast eager compile  # the updates only, eager against compile

Prints one line per measurement:
- env: 16 fully observed envs stepped with random actions, as gymnasium's SyncVectorEnv of
  ImgObsWrapper(FullyObsWrapper(env)) and as the script's MiniGridVecEnv (no egocentric view);
- update: one student learner step (8 rollouts of 100 steps, V-trace, RMSProp) with --groups 0 and 16, and one teacher
  step (150 goal outcomes), on the agent the script's make_agent builds with its default flags, per --fast path (eager,
  compile: torch.compile'd whole, timed after compiling), side by side in one process, with the ratio;
- training: the script itself for 160,000 frames, one process on one CPU thread (--no-cuda), its final SPS (frames
  per second with acting, goal bookkeeping and all updates; the first collection's start-up included).
"""

import argparse
import copy
import re
import subprocess
import sys
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch
from minigrid.wrappers import FullyObsWrapper, ImgObsWrapper

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from timing import median_time  # benchmark/speed/timing.py

import dgrl_amigo as amigo

ROOT = Path(__file__).resolve().parents[2]

ENVS = ("MiniGrid-DoorKey-5x5-v0", "MiniGrid-KeyCorridorS3R1-v0", "MiniGrid-KeyCorridorS3R3-v0")


def sync_vector_speed(env_id: str, n: int = 16, steps: int = 500) -> float:
    envs = gym.vector.SyncVectorEnv(
        [lambda: ImgObsWrapper(FullyObsWrapper(gym.make(env_id))) for _ in range(n)],
        autoreset_mode=gym.vector.AutoresetMode.SAME_STEP,
    )
    envs.reset(seed=0)
    start = time.perf_counter()
    for _ in range(steps):
        envs.step(envs.action_space.sample())
    return n * steps / (time.perf_counter() - start)


def script_env_speed(env_id: str, n: int = 16, steps: int = 2000) -> float:
    envs = amigo.MiniGridVecEnv(env_id, n)
    envs.reset(seed=0)
    rng = np.random.default_rng(0)
    start = time.perf_counter()
    for _ in range(steps):
        envs.step(rng.integers(envs.n_actions, size=n))
    return n * steps / (time.perf_counter() - start)


def update_times(env_id: str, groups: int, paths: list[str], repeats: int = 5) -> dict[str, dict[str, float]]:
    """Seconds per student and per teacher update for each --fast path, from the same agent state and batches."""
    args = amigo.Args(env_id=env_id, groups=groups)
    envs = amigo.MiniGridVecEnv(env_id, args.batch_envs)
    w, h, t, b = envs.width, envs.height, args.num_steps, args.batch_envs
    cpu = torch.device("cpu")
    agent = amigo.make_agent(w, h, envs.n_actions, args, cpu)
    obs, _ = envs.reset(seed=0)
    grids, carry = obs["grid"], obs["carried"]
    rng = np.random.default_rng(0)
    rollout = {
        "grids": np.repeat(grids[None], t, 0),
        "carried": np.repeat(carry[None], t, 0),
        "goal_frames": np.repeat(grids[None], t, 0),
        "goals": rng.integers(w * h, size=(t, b)),
        "actions": rng.integers(envs.n_actions, size=(t, b)),
        "logps": np.full((t, b), -np.log(envs.n_actions), dtype=np.float32),
        "rewards": rng.random((t, b), dtype=np.float32),
        "dones": (rng.random((t, b)) < 0.01).astype(np.float32),
    }
    last = {"grids": grids, "carried": carry, "goal_frames": grids, "goals": rng.integers(w * h, size=b)}
    batch = amigo.student_batch(rollout, last, cpu)
    n = args.teacher_batch_size
    outcomes = {
        "frame": grids[rng.integers(b, size=n)],
        "goal": rng.integers(w * h, size=n),
        "logp": np.full(n, -np.log(w * h), dtype=np.float32),
    }
    teacher_batch = amigo.teacher_tensors(outcomes, rng.choice([-0.3, 0.7, 1.0], size=n), cpu)
    times = {}
    for path in paths:
        state = copy.deepcopy(agent)  # every path starts from the same weights; the learning rates stay put (floats)
        student = amigo.fast_update(amigo.student_update, path, [state.student_optimizer])
        teacher = amigo.fast_update(amigo.teacher_update, path, [state.teacher_optimizer])
        student(state, batch, args)  # compiles (compile time is not measured)
        teacher(state, teacher_batch, args)
        times[path] = {
            "student": median_time(lambda: student(state, batch, args), repeats),  # noqa: B023
            "teacher": median_time(lambda: teacher(state, teacher_batch, args), repeats * 4),  # noqa: B023
        }
    return times


def comparison(times: dict[str, dict[str, float]], update: str) -> str:
    """`eager X ms, compile Y ms (Z.ZZx)`: each path's time and its speed-up over the first path."""
    paths = list(times)
    base = times[paths[0]][update]
    parts = [
        f"{path} {times[path][update] * 1e3:.1f} ms" + (f" ({base / times[path][update]:.2f}x)" if i else "")
        for i, path in enumerate(paths)
    ]
    return ", ".join(parts)


def training_sps(env_id: str, groups: int, frames: int = 160_000) -> int:
    out = subprocess.run(
        [sys.executable, str(ROOT / "dgrl_amigo.py"), "--env-id", env_id, "--groups", str(groups), "--total-timesteps",
         str(frames), "--progress-frequency", str(frames), "--exp-name", "bench_amigo", "--no-cuda"],
        capture_output=True, text=True, check=True, cwd="/tmp", env={"OMP_NUM_THREADS": "1", "PATH": "/usr/bin:/bin"},
    )  # fmt: skip
    return int(re.findall(r"SPS (\d+)", out.stdout)[-1])


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--parts", nargs="+", choices=("env", "update", "training"), default=["env", "update", "training"])
    parser.add_argument("--fast", nargs="+", choices=("eager", "compile"), default=["eager", "compile"])
    parser.add_argument("--envs", nargs="+", default=list(ENVS), help="MiniGrid ids (default: %(default)s)")
    options = parser.parse_args()
    torch.set_num_threads(1)
    if "env" in options.parts:
        for env_id in options.envs:
            print(f"env {env_id}: SyncVectorEnv(FullyObs) {sync_vector_speed(env_id):,.0f} steps/s, "
                  f"MiniGridVecEnv {script_env_speed(env_id):,.0f} steps/s (16 envs, random actions)")  # fmt: skip
    if "update" in options.parts:
        for env_id in options.envs:
            for groups in (0, 16):
                times = update_times(env_id, groups, options.fast)
                print(f"update {env_id} G{groups}: {comparison(times, 'student')} per 800-frame learner batch", flush=True)
                print(f"teacher update {env_id} G{groups}: {comparison(times, 'teacher')} per 150-outcome batch", flush=True)
    if "training" in options.parts:
        for env_id in options.envs:
            for groups in (0, 8, 16):
                print(f"training {env_id} G{groups}: {training_sps(env_id, groups):,} frames/s")
