"""DGRL on AMIGo in procedurally generated MiniGrid: a teacher proposes goals, a student learns to reach them.

Paper: Islam et al. 2022, "Discrete Factorial Representations as an Abstraction for Goal Conditioned RL", section
"Procedurally Generated MiniGrid Exploration Task" (table: KCmedium) and appendix "MiniGrid Environments". The agent is
AMIGo (Campero et al., ICLR 2021): a teacher (a conv net over the full grid) proposes a goal cell; the student, an
actor-critic over the full grid, earns an intrinsic reward for changing that cell (stepping on it, opening a door
there, picking up an object there); the teacher earns +0.7 when the student needs at least t* steps for a goal and
-0.3 otherwise, and t* rises as the student improves. DGRL (`--groups G`) embeds each goal with a goal encoder (the goal
frame and a one-hot goal cell), snaps the embedding to G codes of one shared EMA codebook and feeds the discrete
embedding to the student. `--groups 0` is AMIGo from the same file, with the same goal encoder left continuous.
The student is trained like the original's IMPALA learner: one pass of V-trace actor-critic per batch of rollouts.

    python dgrl_amigo.py --groups 16                           # paper setting (KCmedium = KeyCorridorS3R3, 3e7 frames)
    python dgrl_amigo.py --groups 0                            # AMIGo
    python dgrl_amigo.py --env-id MiniGrid-DoorKey-5x5-v0 --total-timesteps 1000000 --groups 16   # learns in ~3 min on a CPU

The study: benchmark/amigo.sh. Docs: docs/dgrl_amigo.md.
"""

import itertools
import os
import random
import re
import signal
import time
from dataclasses import dataclass

import gymnasium as gym
import minigrid  # noqa: F401  (registers the MiniGrid-* ids)
import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
import tyro
from minigrid.core.constants import COLOR_TO_IDX, OBJECT_TO_IDX
from torch.utils.tensorboard import SummaryWriter

from vq import VectorQuantizerEMA, active_codes, perplexity


@dataclass
class Args:
    exp_name: str = os.path.basename(__file__)[: -len(".py")]
    """the name of this experiment"""
    seed: int = 1
    """seed of the experiment"""
    torch_deterministic: bool = True
    """if toggled, `torch.backends.cudnn.deterministic=True`"""
    cuda: bool = False
    """if toggled, cuda will be enabled when available (off by default: these small networks run faster on the CPU)"""
    track: bool = False
    """if toggled, this experiment will be tracked with Weights and Biases"""
    wandb_project_name: str = "dgrl"
    """the wandb's project name"""
    wandb_entity: str | None = None
    """the entity (team) of wandb's project"""
    capture_video: bool = False
    """whether to record every --video-frequency-th episode of env 0, the current goal outlined (saved in `videos/`)"""
    save_model: bool = False
    """whether to save a checkpoint (student, teacher, goal encoder with its codebook, t*) at every progress line and at
    the end"""
    checkpoint: str | None = None
    """path of a saved checkpoint: run it for --eval-episodes episodes with its teacher's goals, then exit"""
    threads: int = 1
    """torch CPU threads (one is fastest for these small networks; two runs then fit side by side on 2 cores)"""

    # Environment
    env_id: str = "MiniGrid-KeyCorridorS3R3-v0"
    """any MiniGrid id (the paper's KCmedium is read as KeyCorridorS3R3: see the docs)"""
    total_timesteps: int = 30_000_000
    """total environment frames; both learning rates decay linearly to 0 over exactly this budget"""
    num_envs: int = 16
    """parallel environments (the original runs 40 actor processes)"""
    num_steps: int = 100
    """unroll length of each rollout"""
    batch_envs: int = 8
    """rollouts per learner batch (the original's batch size): each collection gives num_envs / batch_envs updates,
    every one after the first behind the acting policy by one or more updates, which V-trace corrects"""

    # Algorithm: student (IMPALA-style actor-critic with V-trace)
    learning_rate: float = 1e-3
    """student RMSProp learning rate"""
    rmsprop_alpha: float = 0.99
    """RMSProp smoothing constant (both optimizers)"""
    rmsprop_eps: float = 0.01
    """RMSProp epsilon (both optimizers)"""
    gamma: float = 0.99
    """student discount; reaching a goal does not cut bootstrapping"""
    entropy_coef: float = 0.0005
    """student entropy bonus"""
    baseline_coef: float = 0.5
    """student baseline (value) loss weight"""
    max_grad_norm: float = 40.0
    """gradient clipping (both optimizers)"""
    intrinsic_coef: float = 1.0
    """weight of the goal-reaching reward 1 - 0.9 * steps_since_goal / max_steps"""
    goal_channel: bool = True
    """the student's conv stack also sees the goal as a one-hot map channel (the original AMIGo student); with
    --no-goal-channel the goal reaches the student only through the goal encoder (and, under DGRL, its bottleneck)"""

    # Algorithm: teacher (goal generator)
    teacher_learning_rate: float = 2e-3
    """teacher RMSProp learning rate"""
    teacher_batch_size: int = 150
    """goal outcomes per teacher update (leftovers carry over to the next one)"""
    teacher_entropy_coef: float = 0.05
    """teacher entropy bonus"""
    teacher_baseline_coef: float = 0.5
    """teacher baseline loss weight"""
    teacher_reward_negative: float = -0.3
    """teacher reward for every goal outcome"""
    teacher_reward_positive: float = 1.0
    """added when the goal was reached in at least t* steps (so +0.7 / -0.3 with the defaults)"""
    t_star_start: int = 7
    """initial t*: the number of steps a goal must take to reward the teacher"""
    t_star_max: int = 100
    """t* never exceeds this"""
    t_star_threshold: float = -0.5
    """t* rises by one after --t-star-patience consecutive teacher updates with mean teacher reward >= this. The
    published -0.5 is always met (rewards are >= -0.3), which makes t* rise every 10 updates; -0.1 makes it adaptive"""
    t_star_patience: int = 10
    """consecutive teacher updates at or above --t-star-threshold that raise t* by one"""

    # Logging and evaluation
    progress_frequency: int = 100_000
    """frames between two progress lines (and checkpoints with --save-model)"""
    video_frequency: int = 100
    """with --capture-video, record every this-many-th episode of env 0"""
    eval_episodes: int = 100
    """episodes of a --checkpoint evaluation"""

    # DGRL
    groups: int = 16
    """G: factors of the goal embedding; 0 runs AMIGo (the goal encoder's output stays continuous)"""
    n_embed: int = 64
    """L: codes in the shared codebook"""
    vq_beta: float = 0.25
    """commitment-loss weight"""
    vq_decay: float = 0.99
    """EMA decay of the codebook"""
    vq_dead_code_steps: int = 50
    """restart a code unused for this many student updates at a random current segment (0 = off, as in the paper;
    without it the codebook collapses to one code here: see the docs)"""
    embed_dim: int = 128
    """size of the goal embedding (m) in both modes; must be divisible by groups"""


# --- Environment ------------------------------------------------------------------------------------------------------

N_OBJECTS, N_COLORS, N_STATES = 11, 6, 4  # MiniGrid's object, colour and state ids (the agent's state is its direction)
AGENT, EMPTY = OBJECT_TO_IDX["agent"], OBJECT_TO_IDX["empty"]


def minigrid_ids() -> list[str]:
    return sorted(name for name in gym.registry if name.startswith("MiniGrid-"))


def full_grid(env) -> np.ndarray:
    """The fully observed (W, H, 3) grid of [object, colour, state] ids, the agent as [agent, red, direction]: minigrid's
    FullyObsWrapper encoding, built from the grid's cell list (row-major, y * W + x) in one pass (2.3x faster)."""
    cells = [(EMPTY, 0, 0) if cell is None else cell.encode() for cell in env.grid.grid]
    grid = np.array(cells, dtype=np.uint8).reshape(env.height, env.width, 3).transpose(1, 0, 2)
    grid[env.agent_pos[0], env.agent_pos[1]] = (AGENT, COLOR_TO_IDX["red"], env.agent_dir)
    return grid


def _no_partial_view():
    """Replaces MiniGridEnv.gen_obs: the egocentric 7x7 view it renders at every step (80% of a step's time) is unused
    here, where teacher and student see the full grid."""
    return None


def carried(env) -> tuple[int, int]:
    """(object id, colour id) of what the agent carries; (empty, 0) when it carries nothing."""
    return (EMPTY, 0) if env.carrying is None else (OBJECT_TO_IDX[env.carrying.type], COLOR_TO_IDX[env.carrying.color])


class MiniGridVecEnv:
    """`num_envs` MiniGrid envs stepped in one loop, fully observed, with same-step autoreset.

    `step` returns the observations to act on next (reset frames for envs whose episode ended), the frames right after
    the step (before any reset: what the goal-reach test compares), the extrinsic rewards, terminated and truncated
    flags, and (return, length) of finished episodes. A new layout is generated at every reset (procedural generation).
    """

    def __init__(self, env_id: str, num_envs: int, render_env0: bool = False):
        self.envs = [
            gym.make(env_id, render_mode="rgb_array" if render_env0 and i == 0 else None).unwrapped for i in range(num_envs)
        ]
        for env in self.envs:
            env.gen_obs = _no_partial_view
        self.env_id, self.num_envs = env_id, num_envs
        self.width, self.height, self.max_steps = self.envs[0].width, self.envs[0].height, self.envs[0].max_steps
        self.n_actions = self.envs[0].action_space.n
        self.grids = np.zeros((num_envs, self.width, self.height, 3), dtype=np.uint8)  # observation to act on
        self.after = np.zeros_like(self.grids)  # frame right after the last step, before autoreset
        self.carried = np.zeros((num_envs, 2), dtype=np.int64)
        self.episode_return = np.zeros(num_envs)
        self.episode_length = np.zeros(num_envs, dtype=np.int64)
        self.record, self.frame0 = False, None  # when `record` is set, `frame0` is env 0's render after each step

    def _observe(self, i: int, target: np.ndarray) -> None:
        env = self.envs[i]
        grid = full_grid(env)
        if grid.shape != target.shape[1:]:
            raise RuntimeError(f"{self.env_id}: the grid changed size from {target.shape[1:3]} to {grid.shape[:2]}")
        target[i] = grid
        self.carried[i] = carried(env)

    def reset(self, seed: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        for i, env in enumerate(self.envs):
            env.reset(seed=None if seed is None else seed + i)
            self._observe(i, self.grids)
        self.episode_return[:], self.episode_length[:] = 0, 0
        return self.grids.copy(), self.carried.copy()

    def step(self, actions: np.ndarray):
        rewards = np.zeros(self.num_envs)
        terminated = np.zeros(self.num_envs, dtype=bool)
        truncated = np.zeros(self.num_envs, dtype=bool)
        for i, env in enumerate(self.envs):
            _, rewards[i], terminated[i], truncated[i], _ = env.step(int(actions[i]))
            self._observe(i, self.after)
        if self.record:
            self.frame0 = self.envs[0].render()
        self.grids[:] = self.after
        self.episode_return += rewards
        self.episode_length += 1
        done = terminated | truncated
        finished = (self.episode_return[done].copy(), self.episode_length[done].copy())
        for i in np.flatnonzero(done):
            self.envs[i].reset()
            self._observe(i, self.grids)
        self.episode_return[done], self.episode_length[done] = 0, 0
        return (self.grids.copy(), self.carried.copy()), self.after.copy(), rewards, terminated, truncated, finished

    def render(self) -> np.ndarray:
        return self.envs[0].render()

    def close(self) -> None:
        for env in self.envs:
            env.close()


class GoalBook:
    """Per-env goal bookkeeping in numpy: the goal cell (flat index x * H + y), the frame it was issued on, the
    teacher's log-probability of it and the steps taken since."""

    def __init__(self, num_envs: int, width: int, height: int):
        self.height = height
        self.goal = np.zeros(num_envs, dtype=np.int64)
        self.frame = np.zeros((num_envs, width, height, 3), dtype=np.uint8)
        self.logp = np.zeros(num_envs, dtype=np.float32)
        self.steps = np.zeros(num_envs, dtype=np.int64)

    def reached(self, frames: np.ndarray) -> np.ndarray:
        """The goal test of AMIGo's published runs: the goal cell's [object, colour, state] differs from the same cell
        in the goal frame (the agent stepped on it or turned there, a door there opened, an object there was moved)."""
        rows = np.arange(len(self.goal))
        x, y = np.divmod(self.goal, self.height)
        return (frames[rows, x, y] != self.frame[rows, x, y]).any(-1)

    def advance(self, after: np.ndarray) -> np.ndarray:
        """Count the step just taken and test every env's goal on the frame right after it (before any autoreset)."""
        self.steps += 1
        return self.reached(after)

    def issue(self, mask: np.ndarray, frames: np.ndarray, goals: np.ndarray, logps: np.ndarray) -> None:
        self.goal[mask], self.frame[mask], self.logp[mask], self.steps[mask] = goals, frames, logps, 0


def intrinsic_reward(reached: np.ndarray, steps: np.ndarray, max_steps: int, coef: float) -> np.ndarray:
    """AMIGo's goal reward: 1 - 0.9 * (steps since the goal was issued) / (episode step limit), on reaching it."""
    return coef * reached * (1.0 - 0.9 * steps / max_steps)


def student_reward(extrinsic: np.ndarray, intrinsic: np.ndarray) -> np.ndarray:
    """AMIGo's student reward: extrinsic + intrinsic clipped to [-1, 1], plus 1 more on extrinsic success."""
    return np.clip(extrinsic + intrinsic, -1.0, 1.0) + (extrinsic > 0)


def teacher_reward(reached, steps, extrinsic_success, t_star: int, negative: float = -0.3, positive: float = 1.0):
    """AMIGo's teacher reward per goal outcome: `negative`, plus `positive` if the goal was reached after at least t*
    steps, clipped to [-1, 1]; 1 whenever the episode's extrinsic reward came in the outcome's step."""
    rewards = np.clip(negative + positive * (reached & (steps >= t_star)), -1.0, 1.0)
    return np.where(extrinsic_success, 1.0, rewards)


class TStar:
    """AMIGo's difficulty schedule: after each teacher update, a mean teacher reward >= threshold extends a streak
    (anything lower ends it); a streak of `patience` raises t* by one (up to `maximum`) and starts a new streak."""

    def __init__(self, start: int, threshold: float, patience: int, maximum: int):
        self.value, self.threshold, self.patience, self.maximum = start, threshold, patience, maximum
        self.streak = 0

    def update(self, mean_teacher_reward: float) -> int:
        self.streak = self.streak + 1 if mean_teacher_reward >= self.threshold else 0
        if self.streak >= self.patience:
            self.value, self.streak = min(self.value + 1, self.maximum), 0
        return self.value


class OutcomeBuffer:
    """Goal outcomes waiting for a teacher update: one per reached goal and one per episode end (goal not reached)."""

    def __init__(self):
        self.parts: list[dict[str, np.ndarray]] = []
        self.size = 0

    def add(self, **columns: np.ndarray) -> None:
        n = len(next(iter(columns.values())))
        if n:
            self.parts.append(columns)
            self.size += n

    def pop(self, n: int) -> dict[str, np.ndarray]:
        """The oldest n outcomes; the rest stay for the next update."""
        merged = {key: np.concatenate([part[key] for part in self.parts]) for key in self.parts[0]}
        self.parts = [{key: value[n:] for key, value in merged.items()}] if self.size > n else []
        self.size = max(self.size - n, 0)
        return {key: value[:n] for key, value in merged.items()}


# --- Networks ---------------------------------------------------------------------------------------------------------


class GridEmbedding(nn.Module):
    """[object, colour, state] ids -> 5 + 3 + 2 = 10 learned channels, optionally with a one-hot goal channel."""

    def __init__(self):
        super().__init__()
        self.object, self.color, self.state = nn.Embedding(N_OBJECTS, 5), nn.Embedding(N_COLORS, 3), nn.Embedding(N_STATES, 2)

    def forward(self, grids: torch.Tensor, goals: torch.Tensor | None = None) -> torch.Tensor:
        grids = grids.long()
        x = torch.cat([self.object(grids[..., 0]), self.color(grids[..., 1]), self.state(grids[..., 2])], -1)
        x = x.permute(0, 3, 1, 2)  # (B, 10, W, H)
        if goals is not None:
            one_hot = F.one_hot(goals, x.shape[2] * x.shape[3]).view(-1, 1, x.shape[2], x.shape[3])
            x = torch.cat([x, one_hot.to(x.dtype)], 1)
        return x


def conv_stack(in_channels: int, width: int, height: int) -> tuple[nn.Sequential, int]:
    """AMIGo's student trunk: five [3x3 conv, stride 2, padding 1, 32 channels, ELU] blocks, orthogonal init."""
    layers, channels = [], in_channels
    for _ in range(5):
        conv = nn.Conv2d(channels, 32, 3, stride=2, padding=1)
        nn.init.orthogonal_(conv.weight, nn.init.calculate_gain("relu"))
        nn.init.zeros_(conv.bias)
        layers += [conv, nn.ELU()]
        channels = 32
    trunk = nn.Sequential(*layers, nn.Flatten())
    with torch.no_grad():
        out = trunk(torch.zeros(1, in_channels, width, height)).shape[1]
    return trunk, out


class Student(nn.Module):
    """AMIGo's student: the conv trunk over the embedded full grid (plus the goal channel), the carried object and
    colour embeddings and the goal embedding, then FC 256 - FC 256 (ReLU), a policy and a baseline head."""

    def __init__(self, width: int, height: int, n_actions: int, goal_channel: bool, embed_dim: int):
        super().__init__()
        self.goal_channel, self.embed_dim = goal_channel, embed_dim
        self.embedding = GridEmbedding()
        self.trunk, trunk_out = conv_stack(10 + goal_channel, width, height)
        self.carried_object, self.carried_color = nn.Embedding(N_OBJECTS, 5), nn.Embedding(N_COLORS, 3)
        self.fc = nn.Sequential(nn.Linear(trunk_out + 8 + embed_dim, 256), nn.ReLU(), nn.Linear(256, 256), nn.ReLU())
        self.policy, self.baseline = nn.Linear(256, n_actions), nn.Linear(256, 1)

    def forward(self, grids, carried, goals, goal_embedding) -> tuple[torch.Tensor, torch.Tensor]:
        x = self.trunk(self.embedding(grids, goals if self.goal_channel else None))
        x = torch.cat([x, self.carried_object(carried[:, 0]), self.carried_color(carried[:, 1]), goal_embedding], 1)
        x = self.fc(x)
        return self.policy(x), self.baseline(x).squeeze(-1)


class GoalEncoder(nn.Module):
    """Embeds a goal from what the student was shown when it was issued: the goal frame and the one-hot goal cell,
    through the same trunk design as the student's, to an `embed_dim` vector. Under DGRL the vector is split into G
    factors, each snapped to the nearest code of one shared EMA codebook; for AMIGo (G = 0) it stays continuous."""

    def __init__(self, width: int, height: int, embed_dim: int, args: "Args"):
        super().__init__()
        self.embedding = GridEmbedding()
        self.trunk, trunk_out = conv_stack(11, width, height)
        self.head = nn.Linear(trunk_out, embed_dim)
        self.vq = None
        if args.groups > 0:  # DGRL
            self.vq = VectorQuantizerEMA(
                embed_dim, args.n_embed, args.groups, args.vq_beta, args.vq_decay, dead_code_steps=args.vq_dead_code_steps
            )  # DGRL

    def forward(self, frames, goals, update: bool = False):
        """(goal embedding, commitment loss, code indices or None); `update=True` only in learner batches."""
        z = self.head(self.trunk(self.embedding(frames, goals)))
        if self.vq is None:
            return z, z.new_zeros(()), None
        return self.vq(z, update=update)  # DGRL: (z_q straight-through, commitment loss, (B, G) indices)


class Teacher(nn.Module):
    """AMIGo's goal generator: embedded full grid (10 channels), four 3x3 stride-1 convs 10-16-16-16-1 with ELU, one
    logit per grid cell (flat index x * H + y, walls included), and a baseline Linear(W * H -> 1) on the logits."""

    def __init__(self, width: int, height: int):
        super().__init__()
        self.embedding = GridEmbedding()
        channels = (10, 16, 16, 16, 1)
        layers = []
        for i, (cin, cout) in enumerate(itertools.pairwise(channels)):
            layers.append(nn.Conv2d(cin, cout, 3, stride=1, padding=1))
            if i < len(channels) - 2:
                layers.append(nn.ELU())
        self.net = nn.Sequential(*layers, nn.Flatten())
        self.baseline = nn.Linear(width * height, 1)

    def forward(self, grids: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        logits = self.net(self.embedding(grids))
        return logits, self.baseline(logits).squeeze(-1)


# --- Losses -----------------------------------------------------------------------------------------------------------


def vtrace(behaviour_logp, target_logp, rewards, values, bootstrap, discounts, rho_bar: float = 1.0, c_bar: float = 1.0):
    """V-trace targets and policy-gradient advantages (Espeholt et al. 2018), all (T, B) tensors but bootstrap (B,).

    v_s = V(x_s) + sum_t gamma^(t-s) (prod_{i<t} c_i) rho_t (r_t + gamma V(x_{t+1}) - V(x_t)), with truncated importance
    weights rho = min(rho_bar, pi/mu) and c = min(c_bar, pi/mu). On-policy (pi = mu) v_s is the n-step return.
    """
    with torch.no_grad():
        ratios = torch.exp(target_logp - behaviour_logp)
        rhos, cs = ratios.clamp(max=rho_bar), ratios.clamp(max=c_bar)
        next_values = torch.cat([values[1:], bootstrap[None]], 0)
        deltas = rhos * (rewards + discounts * next_values - values)
        corrections = torch.zeros_like(values)
        acc = torch.zeros_like(bootstrap)
        for t in reversed(range(len(values))):
            acc = deltas[t] + discounts[t] * cs[t] * acc
            corrections[t] = acc
        vs = values + corrections
        next_vs = torch.cat([vs[1:], bootstrap[None]], 0)
        advantages = rhos * (rewards + discounts * next_vs - values)
    return vs, advantages


def actor_critic_loss(logits, values, actions, vs, advantages, baseline_coef: float, entropy_coef: float):
    """IMPALA's loss, summed over the batch as in torchbeast: policy gradient + baseline_coef * 0.5 * (v_s - V)^2 -
    entropy_coef * entropy. Returns (total, policy, baseline, entropy)."""
    log_probs = F.log_softmax(logits, -1)
    policy_loss = -(log_probs.gather(-1, actions[..., None]).squeeze(-1) * advantages).sum()
    baseline_loss = 0.5 * ((vs - values) ** 2).sum()
    entropy = -(log_probs.exp() * log_probs).sum()
    return policy_loss + baseline_coef * baseline_loss - entropy_coef * entropy, policy_loss, baseline_loss, entropy


def teacher_loss(teacher: Teacher, batch: dict, rewards: np.ndarray, args: "Args", device) -> dict[str, torch.Tensor]:
    """The teacher's contextual-bandit update (discount 0): V-trace with one step reduces to an importance-weighted
    policy gradient, rho = min(1, pi/mu), with advantage rho * (r - b) and baseline target b + rho * (r - b)."""
    logits, baseline = teacher(torch.as_tensor(batch["frame"], device=device))
    goals = torch.as_tensor(batch["goal"], device=device)
    rewards_t = torch.as_tensor(rewards, dtype=torch.float32, device=device)
    behaviour = torch.as_tensor(batch["logp"], device=device)
    log_probs = F.log_softmax(logits, -1)
    logp = log_probs.gather(1, goals[:, None]).squeeze(1)
    no_discount = torch.zeros_like(rewards_t)
    vs, advantages = vtrace(
        behaviour[None], logp.detach()[None], rewards_t[None], baseline.detach()[None], no_discount, no_discount[None]
    )
    total, policy, base, entropy = actor_critic_loss(
        logits[None], baseline[None], goals[None], vs, advantages, args.teacher_baseline_coef, args.teacher_entropy_coef
    )
    return {"loss": total, "policy_loss": policy, "baseline_loss": base, "entropy": entropy / len(goals)}


def student_update(student, goal_encoder, optimizer, rollout: dict, last: dict, args: "Args", device) -> dict:
    """One learner step on a batch of rollouts: `rollout` holds (T, B, ...) arrays (grids, carried, goal_frames, goals,
    actions, logps of the acting policy, rewards, dones), `last` the (B, ...) observation after the rollout, whose value
    bootstraps. The goal encoder trains through the student's loss, plus the commitment loss under DGRL."""
    T, B = rollout["actions"].shape
    obs = {key: np.concatenate([rollout[key].reshape(T * B, *rollout[key].shape[2:]), last[key]]) for key in last}
    grids, carry, frames, goals = tensors(device, obs["grids"], obs["carried"], obs["goal_frames"], obs["goals"])
    embedding, vq_loss, codes = goal_encoder(frames, goals, update=True)  # DGRL: the codebook moves in learner batches only
    logits, values = student(grids, carry, goals, embedding)
    values = values.view(T + 1, B)  # row T: the bootstrap values
    logits = logits[: T * B].view(T, B, -1)
    actions, behaviour, rewards, dones = tensors(
        device, rollout["actions"], rollout["logps"], rollout["rewards"], rollout["dones"]
    )
    target_logp = F.log_softmax(logits, -1).gather(-1, actions[..., None]).squeeze(-1).detach()
    discounts = args.gamma * (1.0 - dones)
    vs, advantages = vtrace(behaviour, target_logp, rewards, values[:T].detach(), values[T].detach(), discounts)
    loss, policy_loss, baseline_loss, entropy = actor_critic_loss(
        logits, values[:T], actions, vs, advantages, args.baseline_coef, args.entropy_coef
    )
    optimizer.zero_grad(set_to_none=True)
    (loss + vq_loss * len(goals)).backward()  # DGRL: summed over the batch like the RL losses (zero for AMIGo)
    nn.utils.clip_grad_norm_([*student.parameters(), *goal_encoder.parameters()], args.max_grad_norm)
    optimizer.step()
    return {
        "policy_loss": policy_loss,
        "baseline_loss": baseline_loss,
        "entropy": entropy / (T * B),
        "vq_loss": vq_loss,
        "codes": codes,
    }


# --- Acting, evaluation, checkpoints ----------------------------------------------------------------------------------


def tensors(device, *arrays: np.ndarray) -> list[torch.Tensor]:
    return [torch.as_tensor(array, device=device) for array in arrays]


@torch.no_grad()
def propose_goals(teacher: Teacher, frames: np.ndarray, device) -> tuple[np.ndarray, np.ndarray]:
    """Sample one goal cell per frame from the teacher; (goals, their log-probabilities)."""
    logits, _ = teacher(torch.as_tensor(frames, device=device))
    dist = torch.distributions.Categorical(logits=logits)
    goals = dist.sample()
    return goals.cpu().numpy(), dist.log_prob(goals).cpu().numpy()


@torch.no_grad()
def embed_goals(goal_encoder: GoalEncoder, frames: np.ndarray, goals: np.ndarray, device) -> torch.Tensor:
    """Goal embeddings for acting: the codebook does not move (update=False). Acting computes them once per goal."""
    return goal_encoder(*tensors(device, frames, goals), update=False)[0]


@torch.no_grad()
def act(student: Student, grids, carry, book: GoalBook, goal_embedding: torch.Tensor, device):
    """The student's sampled actions and their log-probabilities."""
    grids_t, carry_t, goals_t = tensors(device, grids, carry, book.goal)
    logits, _ = student(grids_t, carry_t, goals_t, goal_embedding)
    actions = torch.distributions.Categorical(logits=logits).sample()
    return actions.cpu().numpy(), F.log_softmax(logits, -1).gather(1, actions[:, None]).squeeze(1).cpu().numpy()


def renew_goals(mask: np.ndarray, book: GoalBook, goal_embedding: torch.Tensor, grids, teacher, goal_encoder, device):
    """New teacher goals for the envs in `mask`, issued on their current frames, and their embeddings."""
    book.issue(mask, grids[mask], *propose_goals(teacher, grids[mask], device))
    goal_embedding[torch.as_tensor(mask, device=device)] = embed_goals(goal_encoder, book.frame[mask], book.goal[mask], device)


def goal_frame(frame: np.ndarray, goal: int, height: int, tile: int = 32) -> np.ndarray:
    """Outline the goal cell in yellow on an rgb_array render of the grid (minigrid draws cell (x, y) at rows y and
    columns x of `tile` pixels)."""
    frame = frame.copy()
    x, y = divmod(int(goal), height)
    cell = frame[y * tile : (y + 1) * tile, x * tile : (x + 1) * tile]
    cell[:3], cell[-3:], cell[:, :3], cell[:, -3:] = 255, 255, 255, 255
    cell[:3, :, 2], cell[-3:, :, 2], cell[:, :3, 2], cell[:, -3:, 2] = 0, 0, 0, 0
    return frame


def evaluate(envs: MiniGridVecEnv, student, goal_encoder, teacher, device, episodes: int, seed: int) -> dict[str, float]:
    """Run the student with its teacher's goals (as during training, actions sampled) until `episodes` episodes end;
    mean extrinsic return, success rate, goals reached per episode."""
    grids, carry = envs.reset(seed=seed)
    book = GoalBook(envs.num_envs, envs.width, envs.height)
    goal_embedding = torch.zeros(envs.num_envs, student.embed_dim, device=device)
    renew_goals(np.ones(envs.num_envs, dtype=bool), book, goal_embedding, grids, teacher, goal_encoder, device)
    returns, reached_total = [], 0
    while len(returns) < episodes:
        actions, _ = act(student, grids, carry, book, goal_embedding, device)
        (grids, carry), after, _, terminated, truncated, (finished, _) = envs.step(actions)
        reached = book.advance(after)
        reached_total += int(reached.sum())
        renew = reached | terminated | truncated
        if renew.any():
            renew_goals(renew, book, goal_embedding, grids, teacher, goal_encoder, device)
        returns.extend(finished.tolist())
    returns = np.array(returns[:episodes])
    return {"return": returns.mean(), "success": (returns > 0).mean(), "goals_per_episode": reached_total / len(returns)}


def save_checkpoint(path: str, modules: dict[str, nn.Module], extra: dict, args: Args) -> None:
    """Write atomically, so that a crash mid-write never destroys the previous checkpoint."""
    payload = {name: module.state_dict() for name, module in modules.items()} | extra | {"args": vars(args)}
    torch.save(payload, path + ".tmp")
    os.replace(path + ".tmp", path)


def write_video(path: str, frames: list[np.ndarray], fps: int = 8) -> None:
    from moviepy import ImageSequenceClip

    os.makedirs(os.path.dirname(path), exist_ok=True)
    ImageSequenceClip(frames, fps=fps).write_videofile(path, logger=None)


def validate(args: Args) -> None:
    """Reject bad flags before any work, naming the flag and the valid choices."""
    errors = []
    if args.env_id not in (ids := minigrid_ids()):
        key = re.sub(r"[^a-z0-9]", "", args.env_id.lower().removeprefix("minigrid"))[:8]
        close = [name for name in ids if key and key in re.sub(r"[^a-z0-9]", "", name.lower())]
        hint = f"did you mean {', '.join(close[:6])}? " if close else ""
        errors.append(f"--env-id {args.env_id!r} is not a MiniGrid id; {hint}choices: {', '.join(ids)}")
    if args.groups < 0 or (args.groups and args.embed_dim % args.groups):
        divisors = [g for g in range(1, args.embed_dim + 1) if args.embed_dim % g == 0]
        errors.append(
            f"--groups must be 0 (AMIGo) or divide --embed-dim {args.embed_dim}: one of {divisors}; got {args.groups}"
        )
    for flag in (
        "total_timesteps", "num_envs", "num_steps", "batch_envs", "teacher_batch_size", "t_star_patience",
        "progress_frequency", "video_frequency", "eval_episodes", "n_embed", "embed_dim", "threads",
    ):  # fmt: skip
        if getattr(args, flag) < 1:
            errors.append(f"--{flag.replace('_', '-')} must be >= 1; got {getattr(args, flag)}")
    for flag in ("learning_rate", "teacher_learning_rate", "rmsprop_eps", "max_grad_norm"):
        if getattr(args, flag) <= 0:
            errors.append(f"--{flag.replace('_', '-')} must be > 0; got {getattr(args, flag)}")
    for flag in (
        "entropy_coef",
        "baseline_coef",
        "teacher_entropy_coef",
        "teacher_baseline_coef",
        "intrinsic_coef",
        "vq_dead_code_steps",
    ):
        if getattr(args, flag) < 0:
            errors.append(f"--{flag.replace('_', '-')} must be >= 0; got {getattr(args, flag)}")
    if not 0 <= args.gamma <= 1:
        errors.append(f"--gamma must be in [0, 1]; got {args.gamma}")
    if args.checkpoint is None and args.batch_envs >= 1 and args.num_envs % args.batch_envs:
        errors.append(f"--batch-envs ({args.batch_envs}) must divide --num-envs ({args.num_envs})")
    if not 0 <= args.t_star_start <= args.t_star_max:
        errors.append(f"--t-star-start ({args.t_star_start}) must be in [0, --t-star-max ({args.t_star_max})]")
    if args.num_envs >= 1 and args.num_steps >= 1 and args.total_timesteps < args.num_envs * args.num_steps:
        frames = args.num_envs * args.num_steps
        errors.append(
            f"--total-timesteps ({args.total_timesteps}) must cover one collection: >= --num-envs x --num-steps ({frames})"
        )
    if args.checkpoint is not None and not os.path.isfile(args.checkpoint):
        errors.append(f"--checkpoint {args.checkpoint}: no such file")
    if errors:
        raise SystemExit("dgrl_amigo.py: invalid arguments:\n  " + "\n  ".join(errors))


if __name__ == "__main__":
    args = tyro.cli(Args)
    validate(args)
    dgrl = args.groups > 0
    run_name = f"{args.env_id}__G{args.groups}__{args.exp_name}__{args.seed}__{int(time.time())}"

    random.seed(args.seed)
    torch.manual_seed(args.seed)
    torch.backends.cudnn.deterministic = args.torch_deterministic
    torch.set_num_threads(args.threads)
    device = torch.device("cuda" if torch.cuda.is_available() and args.cuda else "cpu")

    envs = MiniGridVecEnv(args.env_id, args.num_envs, render_env0=args.capture_video)
    width, height, n_envs, T = envs.width, envs.height, args.num_envs, args.num_steps
    student = Student(width, height, envs.n_actions, args.goal_channel, args.embed_dim).to(device)
    goal_encoder = GoalEncoder(width, height, args.embed_dim, args).to(device)
    teacher = Teacher(width, height).to(device)
    modules = {"student": student, "goal_encoder": goal_encoder, "teacher": teacher}

    if args.checkpoint is not None:
        saved = torch.load(args.checkpoint, map_location=device)
        architecture = ("env_id", "groups", "embed_dim", "n_embed", "goal_channel")
        differ = [
            f"--{key.replace('_', '-')} {saved['args'][key]}"
            for key in architecture
            if saved["args"][key] != getattr(args, key)
        ]
        if differ:
            raise SystemExit(f"--checkpoint {args.checkpoint} was saved with other settings: pass {' '.join(differ)}")
        for name, module in modules.items():
            module.load_state_dict(saved[name])
        result = evaluate(envs, student, goal_encoder, teacher, device, args.eval_episodes, args.seed + 10_000)
        print(
            f"{args.eval_episodes} episodes (t* {saved['t_star']} at save): return {result['return']:.3f}, "
            f"success {result['success']:.0%}, goals reached per episode {result['goals_per_episode']:.1f}"
        )
        raise SystemExit(0)

    if args.track:
        import wandb

        wandb.init(
            project=args.wandb_project_name,
            entity=args.wandb_entity,
            sync_tensorboard=True,
            config=vars(args),
            name=run_name,
            save_code=True,
        )
    writer = SummaryWriter(f"runs/{run_name}")
    table = "\n".join(f"|{key}|{value}|" for key, value in vars(args).items())
    writer.add_text("hyperparameters", f"|param|value|\n|-|-|\n{table}")
    print(f"{run_name}: grid {width}x{height}, episodes of {envs.max_steps} steps, {args.total_timesteps} frames, {device}")

    rmsprop = {"alpha": args.rmsprop_alpha, "eps": args.rmsprop_eps}
    student_params = [*student.parameters(), *goal_encoder.parameters()]  # the goal encoder learns from the student's loss
    student_optimizer = torch.optim.RMSprop(student_params, lr=args.learning_rate, **rmsprop)
    teacher_optimizer = torch.optim.RMSprop(teacher.parameters(), lr=args.teacher_learning_rate, **rmsprop)
    t_star = TStar(args.t_star_start, args.t_star_threshold, args.t_star_patience, args.t_star_max)
    outcomes = OutcomeBuffer()

    # Rollout storage: raw observations and goals (never code indices), the behaviour policy's log-probabilities.
    rollout = {
        "grids": np.zeros((T, n_envs, width, height, 3), dtype=np.uint8),
        "carried": np.zeros((T, n_envs, 2), dtype=np.int64),
        "goal_frames": np.zeros((T, n_envs, width, height, 3), dtype=np.uint8),
        "goals": np.zeros((T, n_envs), dtype=np.int64),
        "actions": np.zeros((T, n_envs), dtype=np.int64),
        "logps": np.zeros((T, n_envs), dtype=np.float32),
        "rewards": np.zeros((T, n_envs), dtype=np.float32),
        "dones": np.zeros((T, n_envs), dtype=np.float32),
    }

    stop = []  # Ctrl-C or SIGTERM ends the run after the current collection, with the checkpoint saved and logs flushed

    def request_stop(number, frame):
        stop.append(number)
        signal.signal(number, signal.SIG_DFL)  # a second Ctrl-C or SIGTERM stops at once

    for signal_number in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signal_number, request_stop)

    grids, carry = envs.reset(seed=args.seed)
    book = GoalBook(n_envs, width, height)
    goal_embedding = torch.zeros(n_envs, args.embed_dim, device=device)
    renew_goals(np.ones(n_envs, dtype=bool), book, goal_embedding, grids, teacher, goal_encoder, device)
    start_time = last_print = time.time()
    step, student_updates, teacher_updates, next_progress = 0, 0, 0, args.progress_frequency
    window = {"return": [], "success": [], "reached": 0, "outcomes": 0, "goal_steps": [], "teacher_reward": []}
    envs.record, episodes_env0 = args.capture_video, 0  # record env 0's first episode, then every --video-frequency-th
    video = [goal_frame(envs.render(), book.goal[0], height)] if envs.record else []
    checkpoint_path = f"runs/{run_name}/{args.exp_name}.cleanrl_model"
    metrics = {}
    while step < args.total_timesteps and not stop:
        # Collect: T steps of every env; goals are renewed on reaching and at episode ends.
        goal_embedding = embed_goals(goal_encoder, book.frame, book.goal, device)  # once per goal (and per collection)
        for t in range(T):
            goal0 = book.goal[0]
            actions, logps = act(student, grids, carry, book, goal_embedding, device)
            rollout["grids"][t], rollout["carried"][t], rollout["goal_frames"][t] = grids, carry, book.frame
            rollout["goals"][t], rollout["actions"][t], rollout["logps"][t] = book.goal, actions, logps
            (grids, carry), after, extrinsic, terminated, truncated, (returns, lengths) = envs.step(actions)
            reached = book.advance(after)
            done = terminated | truncated
            intrinsic = intrinsic_reward(reached, book.steps, envs.max_steps, args.intrinsic_coef)
            rollout["rewards"][t], rollout["dones"][t] = student_reward(extrinsic, intrinsic), done
            # One teacher outcome per reached goal, and one per episode end for a goal still pending.
            renew = reached | done
            outcomes.add(
                frame=book.frame[renew], goal=book.goal[renew], logp=book.logp[renew], reached=reached[renew],
                steps=book.steps[renew], extrinsic_success=extrinsic[renew] > 0,
            )  # fmt: skip
            window["reached"] += int(reached.sum())
            window["outcomes"] += int(renew.sum())
            window["goal_steps"] += book.steps[reached].tolist()
            if renew.any():  # a new goal on the frame the student is in now (the reset frame after an episode end)
                renew_goals(renew, book, goal_embedding, grids, teacher, goal_encoder, device)
            for ret, length in zip(returns, lengths, strict=True):
                window["return"].append(ret)
                window["success"].append(float(ret > 0))
                writer.add_scalar("charts/episodic_return", ret, step)
                writer.add_scalar("charts/episodic_length", length, step)
                writer.add_scalar("charts/success_rate", float(ret > 0), step)
            step += n_envs
            if envs.record:  # env 0's frame before any reset, its goal as it was when acting
                video.append(goal_frame(envs.frame0, goal0, height))
            if done[0]:
                if envs.record:
                    write_video(f"videos/{run_name}/episode_{episodes_env0}.mp4", video)
                episodes_env0 += 1
                envs.record = args.capture_video and episodes_env0 % args.video_frequency == 0
                video = [goal_frame(envs.render(), book.goal[0], height)] if envs.record else []

        # Student: one V-trace actor-critic pass per batch of --batch-envs rollouts; the LR decays to 0 over the budget.
        lr_scale = max(1.0 - (step - n_envs * T) / args.total_timesteps, 0.0)
        student_optimizer.param_groups[0]["lr"] = args.learning_rate * lr_scale
        last = {"grids": grids, "carried": carry, "goal_frames": book.frame, "goals": book.goal}
        for first in range(0, n_envs, args.batch_envs):
            envs_slice = slice(first, first + args.batch_envs)
            metrics = student_update(
                student, goal_encoder, student_optimizer, {key: value[:, envs_slice] for key, value in rollout.items()},
                {key: value[envs_slice] for key, value in last.items()}, args, device,
            )  # fmt: skip
            student_updates += 1

        # Teacher: one update per --teacher-batch-size outcomes, rewards under the current t*; then the t* schedule.
        while outcomes.size >= args.teacher_batch_size:
            batch = outcomes.pop(args.teacher_batch_size)
            rewards = teacher_reward(
                batch["reached"], batch["steps"], batch["extrinsic_success"], t_star.value,
                args.teacher_reward_negative, args.teacher_reward_positive,
            )  # fmt: skip
            teacher_optimizer.param_groups[0]["lr"] = args.teacher_learning_rate * max(1.0 - step / args.total_timesteps, 0.0)
            losses = teacher_loss(teacher, batch, rewards, args, device)
            teacher_optimizer.zero_grad(set_to_none=True)
            losses["loss"].backward()
            nn.utils.clip_grad_norm_(teacher.parameters(), args.max_grad_norm)
            teacher_optimizer.step()
            teacher_updates += 1
            t_star.update(float(rewards.mean()))
            window["teacher_reward"].append(float(rewards.mean()))
            writer.add_scalar("teacher/reward", rewards.mean(), step)
            writer.add_scalar("teacher/t_star", t_star.value, step)
            writer.add_scalar("teacher/policy_loss", losses["policy_loss"].item(), step)
            writer.add_scalar("teacher/baseline_loss", losses["baseline_loss"].item(), step)
            writer.add_scalar("teacher/entropy", losses["entropy"].item(), step)
            writer.add_scalar("teacher/reached_rate", batch["reached"].mean(), step)

        # Log, print progress, checkpoint.
        if student_updates % 10 < n_envs // args.batch_envs:
            for name in ("policy_loss", "baseline_loss", "entropy"):
                writer.add_scalar(f"losses/{name}", metrics[name].item(), step)
            writer.add_scalar("charts/learning_rate", student_optimizer.param_groups[0]["lr"], step)
            if dgrl:  # DGRL
                writer.add_scalar("vq/commit_loss", metrics["vq_loss"].item(), step)  # DGRL
                writer.add_scalar("vq/perplexity", perplexity(metrics["codes"], args.n_embed).item(), step)  # DGRL
                writer.add_scalar("vq/active_codes", active_codes(metrics["codes"], args.n_embed).item(), step)  # DGRL
        if step >= next_progress or step >= args.total_timesteps or time.time() - last_print > 60:
            elapsed = time.time() - start_time
            sps = int(step / elapsed)
            writer.add_scalar("charts/SPS", sps, step)
            if window["outcomes"]:
                writer.add_scalar("charts/goal_reach_rate", window["reached"] / window["outcomes"], step)
            if window["goal_steps"]:
                writer.add_scalar("charts/steps_per_goal", np.mean(window["goal_steps"]), step)
            if step >= next_progress or step >= args.total_timesteps:
                next_progress += args.progress_frequency
                mean = lambda values: f"{np.mean(values):.2f}" if values else "-"  # noqa: E731
                print(
                    f"step {step:>9}/{args.total_timesteps}  return {mean(window['return'])}  "
                    f"success {mean(window['success'])}  t* {t_star.value}  teacher reward {mean(window['teacher_reward'])}  "
                    f"goals reached {window['reached'] / max(window['outcomes'], 1):.0%}  SPS {sps}  "
                    f"{elapsed:.0f}s elapsed, {(args.total_timesteps - step) / max(sps, 1):.0f}s left"
                )
                window = {key: [] if isinstance(value, list) else 0 for key, value in window.items()}
                if args.save_model:
                    save_checkpoint(checkpoint_path, modules, {"t_star": t_star.value, "step": step}, args)
            else:
                print(
                    f"step {step:>9}/{args.total_timesteps}  {student_updates} student updates  t* {t_star.value}  SPS {sps}"
                )
            last_print = time.time()

    if args.save_model:
        save_checkpoint(checkpoint_path, modules, {"t_star": t_star.value, "step": step}, args)
        print(f"checkpoint: {checkpoint_path}")
    print(
        f"{'stopped' if stop else 'done'}: {step} frames, {student_updates} student and {teacher_updates} teacher updates, "
        f"t* {t_star.value}, {time.time() - start_time:.0f} s"
    )
    envs.close()
    writer.close()
