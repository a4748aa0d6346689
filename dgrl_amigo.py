"""DGRL on AMIGo in procedurally generated MiniGrid: a teacher proposes goals, a student learns to reach them.

Paper: Islam et al. 2022, "Discrete Factorial Representations as an Abstraction for Goal Conditioned RL", section
"Procedurally Generated MiniGrid Exploration Task" (table: KCmedium) and appendix "MiniGrid Environments". The agent is
AMIGo (Campero et al., ICLR 2021): a teacher proposes a goal cell; the student, an actor-critic trained like the
original's IMPALA learner, earns an intrinsic reward for changing that cell; the teacher earns +0.7 when the student
needs at least t* steps for a goal and -0.3 otherwise, and t* rises as the student improves. DGRL (`--groups G`) snaps
each goal's embedding to G codes of one shared EMA codebook and feeds them to the student; `--groups 0` is AMIGo, the
same encoder left continuous. AMIGo's student also sees its goal as a one-hot channel of its grid; under DGRL the goal
reaches it only through the codes, the paper's "goal discretization" (`--goal-channel auto`; `on` or `off` in both).

    python dgrl_amigo.py --groups 16                    # paper setting (KCmedium = KeyCorridorS3R3, 3e7 frames)
    python dgrl_amigo.py --groups 0                     # AMIGo
    python dgrl_amigo.py --groups 16 --goal-channel on  # with the goal channel too (the CPU studies' DGRL variant)
    python dgrl_amigo.py --groups 16 --env-id MiniGrid-DoorKey-5x5-v0 --total-timesteps 1000000  # learns in 3 min (CPU)
    python dgrl_amigo.py --groups 16 --resume runs/<run_name>  # continue a stopped run exactly (its flags, same folder)

The studies: `python benchmark/launch.py --preset amigo-paper` (and the CPU presets amigo-*). Docs: docs/dgrl_amigo.md.
"""

import copy
import fcntl
import importlib.util
import math
import os
import random
import re
import shutil
import signal
import sys
import time
from dataclasses import dataclass, field
from typing import ClassVar, Literal

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
    # Environment
    env_id: str = "MiniGrid-KeyCorridorS3R3-v0"
    """any MiniGrid id (the paper's KCmedium is read as KeyCorridorS3R3: see the docs)"""
    total_timesteps: int = 30_000_000
    """total frames (env steps x --num-envs); both learning rates decay linearly to 0 over exactly this budget"""
    num_envs: int = 16
    """parallel environments (the original runs 40 actor processes)"""
    num_steps: int = 100
    """unroll length of each rollout (steps of every env per collection)"""
    batch_envs: int = 8
    """rollouts per learner batch: num_envs / batch_envs updates per collection, the later ones corrected by V-trace"""

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
    goal_channel: Literal["auto", "on", "off"] = "auto"
    """the student's one-hot goal-cell channel: auto = on for AMIGo, off under DGRL (the goal only through the codes)"""

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
    """t* rises after --t-star-patience updates of mean reward >= this (published -0.5: always met; -0.1 adapts)"""
    t_star_patience: int = 10
    """consecutive teacher updates at or above --t-star-threshold that raise t* by one"""

    # Logging and evaluation
    progress_frequency: int = 100_000
    """frames between two progress lines (and checkpoints with --save-model)"""
    video_frequency: int = 100
    """with --capture-video, record env 0's first episode, then every this-many-th one (counted in episodes)"""
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
    """restart a code unused for this many student updates at a random current segment (0 = off, as in the paper)"""
    embed_dim: int = 128
    """size of the goal embedding (m) in both modes; must be divisible by --groups"""

    # Every script's flags (the same block in all seven)
    exp_name: str = os.path.basename(__file__)[: -len(".py")]
    """the name of this experiment"""
    seed: int = 1
    """seed of the experiment"""
    torch_deterministic: bool = True
    """if toggled, `torch.backends.cudnn.deterministic=True`"""
    cuda: bool = True
    """if toggled, cuda will be enabled when available"""
    track: bool = False
    """if toggled, this experiment will be tracked with Weights and Biases (needs `pip install wandb`)"""
    wandb_project_name: str = "dgrl"
    """the wandb's project name"""
    wandb_entity: str | None = None
    """the entity (team) of wandb's project"""
    capture_video: bool = False
    """whether to record videos of evaluation episodes to `videos/{run_name}` (unused where there is no environment)"""
    save_model: bool = False
    """whether to save a checkpoint (networks with their codebook) to `runs/{run_name}/{exp_name}.cleanrl_model`"""
    checkpoint: str | None = None
    """a checkpoint saved by this script with --save-model: evaluate it and exit, without training"""
    threads: int = 1
    """torch CPU threads (one is fastest for these small networks, and lets runs share a machine's cores)"""
    fast: Literal["eager", "compile", "cudagraphs"] = "eager"
    """the update's speed path: eager (plain PyTorch), compile (torch.compile), cudagraphs (CUDA graphs; GPU only)"""
    resume: str | None = None
    """a run folder, runs/{run_name}, to continue exactly where its resume.pt left off (run from the folder of runs/)"""
    checkpoint_every_steps: int = 0
    """also write runs/{run_name}/resume.pt whenever the run's count (steps, frames, images) passes a multiple of it"""
    checkpoint_every: int = 1800
    """wall-clock seconds between writes of runs/{run_name}/resume.pt (0: only on a stop signal and at the end)"""


# --- Networks ---------------------------------------------------------------------------------------------------------


class GridEmbedding(nn.Module):
    """[object, colour, state] ids -> 5 + 3 + 2 = 10 learned channels, optionally with a one-hot goal channel."""

    def __init__(self):
        super().__init__()
        self.object = nn.Embedding(N_OBJECTS, 5)
        self.color = nn.Embedding(N_COLORS, 3)
        self.state = nn.Embedding(N_STATES, 2)

    def forward(self, grids: torch.Tensor, goals: torch.Tensor | None = None) -> torch.Tensor:
        grids = grids.long()
        x = torch.cat([self.object(grids[..., 0]), self.color(grids[..., 1]), self.state(grids[..., 2])], -1)
        x = x.permute(0, 3, 1, 2)  # (B, 10, W, H)
        if goals is not None:
            cells = torch.arange(x.shape[2] * x.shape[3], device=goals.device)  # F.one_hot would sync on its range
            one_hot = (goals[:, None] == cells).view(-1, 1, x.shape[2], x.shape[3])
            x = torch.cat([x, one_hot.to(x.dtype)], 1)
        return x


def conv_stack(in_channels: int, width: int, height: int) -> tuple[nn.Sequential, int]:
    """AMIGo's student trunk: five [3x3 conv, stride 2, padding 1, 32 channels, ELU] blocks, orthogonal init."""
    layers = []
    for i in range(5):
        conv = nn.Conv2d(32 if i else in_channels, 32, 3, stride=2, padding=1)
        nn.init.orthogonal_(conv.weight, nn.init.calculate_gain("relu"))
        nn.init.zeros_(conv.bias)
        layers += [conv, nn.ELU()]
    trunk = nn.Sequential(*layers, nn.Flatten())
    with torch.no_grad():  # the flattened output's size
        return trunk, trunk(torch.zeros(1, in_channels, width, height)).shape[1]


class Student(nn.Module):
    """AMIGo's student: the conv trunk over the embedded grid (plus the one-hot goal channel when `goal_channel`), the
    carried object's embeddings and the goal embedding, then FC 256 - FC 256 (ReLU), a policy and a baseline head."""

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
        carried_embedding = [self.carried_object(carried[:, 0]), self.carried_color(carried[:, 1])]
        x = self.fc(torch.cat([x, *carried_embedding, goal_embedding], 1))
        return self.policy(x), self.baseline(x).squeeze(-1)


class GoalEncoder(nn.Module):
    """A goal's frame and one-hot cell, through a student-like trunk, to --embed-dim (DGRL: snapped to G codes)."""

    def __init__(self, width: int, height: int, args: Args):
        super().__init__()
        self.embedding = GridEmbedding()
        self.trunk, trunk_out = conv_stack(11, width, height)
        self.head = nn.Linear(trunk_out, args.embed_dim)
        flags = (args.embed_dim, args.n_embed, args.groups, args.vq_beta, args.vq_decay)  # m, L, G, beta, decay
        self.vq = VectorQuantizerEMA(*flags, dead_code_steps=args.vq_dead_code_steps) if args.groups else None  # DGRL

    def forward(self, frames, goals, update: bool = False):
        """(goal embedding, commitment loss, code indices or None); `update=True` only in learner batches."""
        z = self.head(self.trunk(self.embedding(frames, goals)))
        if self.vq is None:
            return z, z.new_zeros(()), None  # AMIGo's embedding stays continuous, with no commitment loss
        return self.vq(z, update=update)  # DGRL: (z_q straight-through, commitment loss, (B, G) indices)


class Teacher(nn.Module):
    """AMIGo's goal generator: four 3x3 stride-1 convs 10-16-16-16-1 over the embedded grid, each with an ELU (the
    last too, as in the original: no cell's probability reaches 0), give one logit per cell (x * H + y, walls too)."""

    def __init__(self, width: int, height: int):
        super().__init__()
        self.embedding = GridEmbedding()
        convs = [nn.Conv2d(cin, cout, 3, stride=1, padding=1) for cin, cout in ((10, 16), (16, 16), (16, 16), (16, 1))]
        self.net = nn.Sequential(*(layer for conv in convs for layer in (conv, nn.ELU())), nn.Flatten())
        self.baseline = nn.Linear(width * height, 1)  # reads the logits

    def forward(self, grids: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        logits = self.net(self.embedding(grids))
        return logits, self.baseline(logits).squeeze(-1)


@dataclass
class Agent:
    """AMIGo's two learners and their optimizers; under DGRL `goal_encoder.vq` holds the codebook (moved by EMA)."""

    student: Student
    goal_encoder: GoalEncoder
    teacher: Teacher
    student_optimizer: torch.optim.Optimizer  # the student's and the goal encoder's parameters
    teacher_optimizer: torch.optim.Optimizer

    def state_dicts(self) -> dict[str, dict]:  # the goal encoder's with its codebook buffers
        return {name: getattr(self, name).state_dict() for name in ("student", "goal_encoder", "teacher")}

    def load_state_dicts(self, saved: dict) -> None:
        for name in ("student", "goal_encoder", "teacher"):
            getattr(self, name).load_state_dict(saved[name])


def resolve_goal_channel(goal_channel: str, groups: int) -> str:
    """--goal-channel as a run uses and saves it: "auto" keeps AMIGo's one-hot goal channel and drops it under DGRL."""
    if goal_channel not in ("auto", "on", "off"):
        raise ValueError(f"goal_channel must be one of auto, on, off; got {goal_channel!r}")
    return ("off" if groups > 0 else "on") if goal_channel == "auto" else goal_channel  # DGRL: the goal only as codes


def make_agent(width: int, height: int, n_actions: int, args: Args, device) -> Agent:
    """The student, the goal encoder and the teacher (in this order: seeded weights depend on it), their RMSProps."""
    channel = resolve_goal_channel(args.goal_channel, args.groups) == "on"
    student = Student(width, height, n_actions, channel, args.embed_dim).to(device)
    goal_encoder = GoalEncoder(width, height, args).to(device)
    teacher = Teacher(width, height).to(device)
    rmsprop = {"alpha": args.rmsprop_alpha, "eps": args.rmsprop_eps}
    student_params = [*student.parameters(), *goal_encoder.parameters()]  # the encoder learns from the student's loss
    student_optimizer = torch.optim.RMSprop(student_params, lr=args.learning_rate, **rmsprop)
    teacher_optimizer = torch.optim.RMSprop(teacher.parameters(), lr=args.teacher_learning_rate, **rmsprop)
    return Agent(student, goal_encoder, teacher, student_optimizer, teacher_optimizer)


# --- Losses and updates -----------------------------------------------------------------------------------------------


def vtrace(behaviour_logp, target_logp, rewards, values, bootstrap, discounts):
    """V-trace targets and policy-gradient advantages (Espeholt et al. 2018) on (T, B) tensors, bootstrap (B,):
    v_s = V(x_s) + sum_t gamma^(t-s) (prod_{i<t} c_i) rho_t (r_t + gamma V(x_{t+1}) - V(x_t)), rho = c = min(1, pi/mu)
    (IMPALA's rho_bar = c_bar = 1). On-policy (pi = mu) v_s is the n-step return."""
    with torch.no_grad():
        rhos = torch.exp(target_logp - behaviour_logp).clamp(max=1.0)
        next_values = torch.cat([values[1:], bootstrap[None]], 0)
        deltas = rhos * (rewards + discounts * next_values - values)
        # acc_s = deltas_s + discounts_s c_s acc_{s+1} as one (T, T, B) product: a loop of T small steps was slower
        upper = torch.ones(len(values), len(values), dtype=torch.bool, device=values.device).triu()[..., None]  # i >= s
        inclusive = torch.where(upper, (discounts * rhos)[None], 1.0).cumprod(1)  # [s, i]: prod_{s <= j <= i}
        traces = torch.cat([torch.ones_like(inclusive[:, :1]), inclusive[:, :-1]], 1) * upper  # prod_{s <= j < t}
        vs = values + (traces * deltas[None]).sum(1)
        next_vs = torch.cat([vs[1:], bootstrap[None]], 0)
        advantages = rhos * (rewards + discounts * next_vs - values)
    return vs, advantages


def actor_critic_loss(logits, values, actions, vs, advantages, baseline_coef: float, entropy_coef: float):
    """IMPALA's loss on (T, B) tensors, each term averaged over the batch and summed over time as in AMIGo's code (the
    scale its RMSprop eps and gradient clip are set for): (total, policy, baseline 0.5 (v_s - V)^2, entropy)."""
    log_probs = F.log_softmax(logits, -1)
    policy_loss = -(log_probs.gather(-1, actions[..., None]).squeeze(-1) * advantages).mean(1).sum()
    baseline_loss = 0.5 * ((vs - values) ** 2).mean(1).sum()
    entropy = -(log_probs.exp() * log_probs).sum(-1).mean(1).sum()
    return policy_loss + baseline_coef * baseline_loss - entropy_coef * entropy, policy_loss, baseline_loss, entropy


def teacher_tensors(batch: dict, rewards: np.ndarray, device) -> dict[str, torch.Tensor]:
    """OutcomeBuffer.pop's outcomes and their rewards as teacher_update's tensors (logp: the proposing teacher's)."""
    outcomes = {key: torch.as_tensor(batch[key], device=device) for key in ("frame", "goal", "logp")}
    return outcomes | {"reward": torch.as_tensor(rewards, dtype=torch.float32, device=device)}


def teacher_loss(teacher: Teacher, batch: dict[str, torch.Tensor], *, baseline_coef: float, entropy_coef: float):
    """The teacher's contextual-bandit update (discount 0): V-trace with one step reduces to an importance-weighted
    policy gradient, rho = min(1, pi/mu), with advantage rho * (r - b) and baseline target b + rho * (r - b)."""
    logits, baseline = teacher(batch["frame"])
    goals = batch["goal"]
    with torch.no_grad():
        logp = F.log_softmax(logits, -1).gather(1, goals[:, None]).squeeze(1)
        advantages = torch.exp(logp - batch["logp"]).clamp(max=1.0) * (batch["reward"] - baseline)
    vs = baseline.detach() + advantages
    one_step = [tensor[None] for tensor in (logits, baseline, goals, vs, advantages)]  # T = 1
    total, policy, base, entropy = actor_critic_loss(*one_step, baseline_coef, entropy_coef)
    return {"loss": total, "policy_loss": policy, "baseline_loss": base, "entropy": entropy}  # (one step: the mean)


def learn(optimizer: torch.optim.Optimizer, loss: torch.Tensor, max_grad_norm: float | None = None) -> None:
    """One step on `loss`: clear the gradients, backpropagate, clip their norm to `max_grad_norm` if given, step."""
    optimizer.zero_grad()
    loss.backward()
    if max_grad_norm is not None:
        params = [param for group in optimizer.param_groups for param in group["params"]]
        torch.nn.utils.clip_grad_norm_(params, max_grad_norm, foreach=True)
    optimizer.step()


def teacher_update(agent: Agent, batch: dict[str, torch.Tensor], args: Args) -> dict:
    """One teacher step on teacher_tensors' batch: tensors in, detached loss tensors out, free of host syncs."""
    coefs = {"baseline_coef": args.teacher_baseline_coef, "entropy_coef": args.teacher_entropy_coef}
    losses = teacher_loss(agent.teacher, batch, **coefs)
    learn(agent.teacher_optimizer, losses["loss"], args.max_grad_norm)
    return {name: value.detach() for name, value in losses.items()}


def student_batch(rollout: dict, last: dict, device) -> dict[str, torch.Tensor]:
    """student_update's tensors from `rollout`'s (T, B, ...) arrays and `last`, the (B, ...) observation after it: the
    observations flattened to (T * B + B, ...) with the bootstrap rows last, the rest (T, B)."""
    T, B = rollout["actions"].shape
    obs = {key: np.concatenate([rollout[key].reshape(T * B, *rollout[key].shape[2:]), last[key]]) for key in last}
    keys = ("actions", "logps", "rewards", "dones")
    return dict(zip([*obs, *keys], tensors(device, *obs.values(), *(rollout[key] for key in keys)), strict=True))


def student_update(agent: Agent, batch: dict[str, torch.Tensor], args: Args) -> dict:
    """One learner step on student_batch's tensors (the goal encoder's too): detached metrics out, no host syncs."""
    T, B = batch["actions"].shape
    goals, actions = batch["goals"], batch["actions"]
    embedding, vq_loss, codes = agent.goal_encoder(batch["goal_frames"], goals, update=True)  # DGRL: the codebook moves
    logits, values = agent.student(batch["grids"], batch["carried"], goals, embedding)  # DGRL: z_q, straight-through
    logits, values = logits[: T * B].view(T, B, -1), values.view(T + 1, B)  # values' row T: the bootstrap values
    target_logp = F.log_softmax(logits, -1).gather(-1, actions[..., None]).squeeze(-1).detach()
    discounts, detached = args.gamma * (1.0 - batch["dones"]), values.detach()
    vs, advantages = vtrace(batch["logps"], target_logp, batch["rewards"], detached[:T], detached[T], discounts)
    coefs = (args.baseline_coef, args.entropy_coef)
    loss, policy_loss, baseline_loss, entropy = actor_critic_loss(logits, values[:T], actions, vs, advantages, *coefs)
    # DGRL: the commitment loss (a mean over (T + 1) * B goals) summed over time like the RL losses; zero for AMIGo
    learn(agent.student_optimizer, loss + vq_loss * (len(goals) / B), args.max_grad_norm)
    metrics = {"policy_loss": policy_loss, "baseline_loss": baseline_loss, "entropy": entropy / T}
    return {name: value.detach() for name, value in metrics.items()} | {"vq_loss": vq_loss.detach(), "codes": codes}


def linear_decay(frames: int, total: int) -> float:
    """The learning-rate factor after `frames` of a `total`-frame run: 1 at the start, 0 at the end."""
    return max(1.0 - frames / total, 0.0)


def update_lr_factor(updates: int, args: Args) -> float:
    """AMIGo's schedule for both optimizers: an optimizer's `updates`-th step (counting it) runs at its flag's rate
    times linear_decay of `updates` student batches' frames, so the teacher, updating far less often, stays near 1."""
    return linear_decay(updates * args.num_steps * args.batch_envs, args.total_timesteps)


def set_learning_rate(optimizer: torch.optim.Optimizer, lr: float) -> None:
    """Set every group's learning rate, in place where it is a tensor (see learning_rates_as_tensors)."""
    for group in optimizer.param_groups:
        group["lr"] = group["lr"].fill_(lr) if isinstance(group["lr"], torch.Tensor) else lr


def learning_rates_as_tensors(optimizers: list[torch.optim.Optimizer], as_tensors: bool) -> None:
    """Each group's learning rate as a 0-d tensor on its parameters' device (--fast: a float one would be baked into the
    compiled update, recompiled at every decay step) or a float (eager: a tensor one is read back to the host)."""
    for optimizer in optimizers:
        for group in optimizer.param_groups:
            lr = float(group["lr"])
            group["lr"] = torch.tensor(lr, dtype=torch.float32, device=group["params"][0].device) if as_tensors else lr


# --- Acting and the teacher's curriculum: goals, rewards, difficulty, outcomes ----------------------------------------


def tensors(device, *arrays: np.ndarray) -> list[torch.Tensor]:
    return [torch.as_tensor(array, device=device) for array in arrays]


@torch.no_grad()
def embed_goals(goal_encoder: GoalEncoder, frames: np.ndarray, goals: np.ndarray, device) -> torch.Tensor:
    """Goal embeddings for acting, computed once per goal."""
    return goal_encoder(*tensors(device, frames, goals), update=False)[0]  # DGRL: acting never moves the codebook


@torch.no_grad()
def act(student: Student, obs: dict, goals: np.ndarray, goal_embedding: torch.Tensor, device):
    """The student's sampled actions and their log-probabilities."""
    logits, _ = student(*tensors(device, obs["grid"], obs["carried"], goals), goal_embedding)  # DGRL: z_q of the goal
    actions = torch.distributions.Categorical(logits=logits, validate_args=False).sample()
    return actions.cpu().numpy(), F.log_softmax(logits, -1).gather(1, actions[:, None]).squeeze(1).cpu().numpy()


@torch.no_grad()
def renew_goals(agent: Agent, book: "GoalBook", mask: np.ndarray, grids: np.ndarray, goal_embedding, device):
    """New teacher goals for the envs in `mask`, sampled and issued on their current frames, and their embeddings."""
    logits, _ = agent.teacher(torch.as_tensor(grids[mask], device=device))
    dist = torch.distributions.Categorical(logits=logits, validate_args=False)  # validation reads values back: a sync
    goals = dist.sample()
    book.issue(mask, grids[mask], goals.cpu().numpy(), dist.log_prob(goals).cpu().numpy())
    embeddings = embed_goals(agent.goal_encoder, book.frame[mask], book.goal[mask], device)
    goal_embedding[torch.as_tensor(np.flatnonzero(mask), device=device)] = embeddings  # a boolean index would sync


class GoalBook:
    """Each env's goal in numpy: its cell (flat index x * H + y), the frame it was issued on, log-prob, steps since."""

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

    def advance(self, after: np.ndarray) -> np.ndarray:  # the frame right after the step, before any autoreset
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
    """AMIGo's teacher reward per goal outcome; 1 whenever the episode's extrinsic reward came in the outcome's step."""
    rewards = np.clip(negative + positive * (reached & (steps >= t_star)), -1.0, 1.0)
    return np.where(extrinsic_success, 1.0, rewards)


class TStar:
    """AMIGo's difficulty schedule: `patience` teacher updates in a row of mean reward >= threshold raise t* by one."""

    def __init__(self, start: int, threshold: float, patience: int, maximum: int):
        self.value, self.threshold, self.patience, self.maximum, self.streak = start, threshold, patience, maximum, 0

    def update(self, mean_teacher_reward: float) -> int:
        self.streak = self.streak + 1 if mean_teacher_reward >= self.threshold else 0
        if self.streak >= self.patience:
            self.value, self.streak = min(self.value + 1, self.maximum), 0
        return self.value


class OutcomeBuffer:
    """Goal outcomes waiting for a teacher update: one per reached goal and one per episode end (goal not reached)."""

    def __init__(self):
        self.parts, self.size = [], 0

    def add(self, **columns: np.ndarray) -> None:
        if n := len(next(iter(columns.values()))):
            self.parts.append(columns)
            self.size += n

    def pop(self, n: int) -> dict[str, np.ndarray]:
        """The oldest n outcomes; the rest stay for the next update."""
        merged = {key: np.concatenate([part[key] for part in self.parts]) for key in self.parts[0]}
        self.parts = [{key: value[n:] for key, value in merged.items()}] if self.size > n else []
        self.size = max(self.size - n, 0)
        return {key: value[:n] for key, value in merged.items()}


# --- The run: constants, setup, the training loop, the end ------------------------------------------------------------

MUST_MATCH = ("env_id", "groups", "embed_dim", "n_embed", "goal_channel")  # what a checkpoint's networks are built for
LOSS_LOG_UPDATES = 10  # student updates between two writes of the student's losses
VIDEO_FPS = 8


def main(args: Args) -> None:
    """Train AMIGo (--groups 0) or DGRL on AMIGo (--groups G) with `args`, or evaluate --checkpoint."""
    validate(args)
    args.goal_channel = resolve_goal_channel(args.goal_channel, args.groups)  # saved, matched and resumed as on or off
    run_name = f"{args.env_id}__G{args.groups}__{args.exp_name}__{args.seed}__{int(time.time())}"
    if args.resume is not None:
        run_name = os.path.basename(os.path.normpath(args.resume))
        hold_run_folder(run_name, check_only=True)  # a run still running elsewhere: exit 2 at once, touching nothing
    saved = load_resume(args) if args.resume is not None else None
    device = seed_and_device(args)
    envs = MiniGridVecEnv(args.env_id, args.num_envs, render_env0=args.capture_video)
    width, height, n_envs, T = envs.width, envs.height, args.num_envs, args.num_steps
    agent = make_agent(width, height, envs.n_actions, args, device)
    stop = stop_on_signals()
    if args.checkpoint is not None:
        return evaluate_checkpoint(args, agent, envs, device, stop)

    _lock = hold_run_folder(run_name)  # one process writes a run folder, from its first write to its end
    writer = make_writer(args, run_name, purge_step=None if saved is None else saved["loop"]["step"] + 1)
    print(f"{run_name}: grid {width}x{height}, {envs.max_steps}-step episodes, {args.total_timesteps} frames, {device}")
    t_star = TStar(args.t_star_start, args.t_star_threshold, args.t_star_patience, args.t_star_max)
    outcomes = OutcomeBuffer()
    obs, _ = envs.reset(seed=args.seed)
    book = GoalBook(n_envs, width, height)
    goal_embedding = torch.zeros(n_envs, args.embed_dim, device=device)
    renew_goals(agent, book, np.ones(n_envs, dtype=bool), obs["grid"], goal_embedding, device)
    envs.record = args.capture_video  # record env 0's first episode, then every --video-frequency-th
    video = [goal_frame(envs.render()[0], book.goal[0], height)] if envs.record else []
    loop = LoopState(obs, envs.record, video, next_progress=args.progress_frequency, next_loss_log=LOSS_LOG_UPDATES)
    if saved is not None:  # continue where the stopped run left off: its envs mid-episode, its goals, its counters
        loop = restore_training_state(saved, agent, envs, book, t_star, outcomes)
        envs.record = loop.record = args.capture_video and loop.record  # --capture-video may change on resume
        loop.video = loop.video if loop.record else []
        print(f"resumed from runs/{run_name}/{RESUME_FILE} at frame {loop.step}")
        rng_states(restore=saved["rng"])  # last: building the run above drew from them
    model_path = f"runs/{run_name}/{args.exp_name}.cleanrl_model"
    learning_rates_as_tensors([agent.student_optimizer, agent.teacher_optimizer], as_tensors=args.fast != "eager")
    update_student = fast_update(student_update, args.fast, [agent.student_optimizer])
    update_teacher = fast_update(teacher_update, args.fast, [agent.teacher_optimizer])
    progress = Progress(args.total_timesteps, unit="frame", start_step=loop.step)
    while loop.step < args.total_timesteps and not stop:
        # Collect: T steps of every env, storing raw observations and goals (never code indices) and acting log-probs.
        goal_embedding = embed_goals(agent.goal_encoder, book.frame, book.goal, device)  # the encoder changed since
        steps = []
        for _ in range(T):
            goal0 = book.goal[0]
            actions, logps = act(agent.student, loop.obs, book.goal, goal_embedding, device)
            step = {"grids": loop.obs["grid"], "carried": loop.obs["carried"], "actions": actions, "logps": logps}
            step |= {"goal_frames": book.frame.copy(), "goals": book.goal.copy()}
            loop.obs, extrinsic, terminated, truncated, info = envs.step(actions)
            reached = book.advance(info["final_grid"])
            done = terminated | truncated
            intrinsic = intrinsic_reward(reached, book.steps, envs.max_steps, args.intrinsic_coef)
            rewards = student_reward(extrinsic, intrinsic)
            steps.append(step | {"rewards": rewards.astype(np.float32), "dones": done.astype(np.float32)})
            renew = reached | done  # a teacher outcome for each (OutcomeBuffer), and a new goal
            issued = {"frame": book.frame, "goal": book.goal, "logp": book.logp}
            outcome = issued | {"reached": reached, "steps": book.steps, "extrinsic_success": extrinsic > 0}
            outcomes.add(**{key: value[renew] for key, value in outcome.items()})
            loop.window["reached"] += int(reached.sum())
            loop.window["outcomes"] += int(renew.sum())
            loop.window["goal_steps"] += book.steps[reached].tolist()
            if renew.any():  # a new goal on the frame the student is in now (the reset frame after an episode end)
                renew_goals(agent, book, renew, loop.obs["grid"], goal_embedding, device)
            ended = info["_episode"]
            for ret, length in zip(info["episode"]["r"][ended], info["episode"]["l"][ended], strict=True):
                loop.window["return"].append(ret)
                loop.window["success"].append(float(ret > 0))
                writer.add_scalar("charts/episodic_return", ret, loop.step)
                writer.add_scalar("charts/episodic_length", length, loop.step)
                writer.add_scalar("charts/success_rate", float(ret > 0), loop.step)
            loop.step += n_envs
            if loop.record:  # env 0's frame before any reset, with its goal as it was when acting
                loop.video.append(goal_frame(envs.frame0, goal0, height))
            if done[0]:
                if loop.record:
                    write_video(f"videos/{run_name}/episode_{loop.episodes_env0}.mp4", loop.video, VIDEO_FPS)
                loop.episodes_env0 += 1
                envs.record = loop.record = args.capture_video and loop.episodes_env0 % args.video_frequency == 0
                loop.video = [goal_frame(envs.render()[0], book.goal[0], height)] if loop.record else []

        # Student: one V-trace actor-critic pass per batch of --batch-envs rollouts; the LR decays to 0 over the budget.
        rollout = {key: np.stack([step[key] for step in steps]) for key in steps[0]}
        last = {"grids": loop.obs["grid"], "carried": loop.obs["carried"]}
        last |= {"goal_frames": book.frame, "goals": book.goal}
        for first in range(0, n_envs, args.batch_envs):
            part = slice(first, first + args.batch_envs)
            rollout_part = {key: value[:, part] for key, value in rollout.items()}
            last_part = {key: value[part] for key, value in last.items()}
            student_lr = args.learning_rate * update_lr_factor(loop.student_updates + 1, args)
            set_learning_rate(agent.student_optimizer, student_lr)
            metrics = update_student(agent, student_batch(rollout_part, last_part, device), args)
            loop.student_updates += 1

        # Teacher: one update per --teacher-batch-size outcomes, rewards under the current t*; then the t* schedule.
        while outcomes.size >= args.teacher_batch_size:
            batch = outcomes.pop(args.teacher_batch_size)
            reward_flags = (t_star.value, args.teacher_reward_negative, args.teacher_reward_positive)
            rewards = teacher_reward(batch["reached"], batch["steps"], batch["extrinsic_success"], *reward_flags)
            teacher_lr = args.teacher_learning_rate * update_lr_factor(loop.teacher_updates + 1, args)
            set_learning_rate(agent.teacher_optimizer, teacher_lr)
            losses = update_teacher(agent, teacher_tensors(batch, rewards, device), args)
            loop.teacher_updates += 1
            t_star.update(float(rewards.mean()))
            loop.window["teacher_reward"].append(float(rewards.mean()))
            writer.add_scalar("teacher/reward", rewards.mean(), loop.step)
            writer.add_scalar("teacher/t_star", t_star.value, loop.step)
            for name in ("policy_loss", "baseline_loss", "entropy"):
                writer.add_scalar(f"teacher/{name}", losses[name].item(), loop.step)
            writer.add_scalar("teacher/reached_rate", batch["reached"].mean(), loop.step)

        # The student's losses (of the collection's last update), every LOSS_LOG_UPDATES student updates.
        if loop.student_updates >= loop.next_loss_log:
            loop.next_loss_log += LOSS_LOG_UPDATES
            for name in ("policy_loss", "baseline_loss", "entropy"):
                writer.add_scalar(f"losses/{name}", metrics[name].item(), loop.step)
            writer.add_scalar("charts/learning_rate", student_lr, loop.step)
            if args.groups > 0:
                writer.add_scalar("vq/commit_loss", metrics["vq_loss"].item(), loop.step)
                writer.add_scalar("vq/perplexity", perplexity(metrics["codes"], args.n_embed).item(), loop.step)
                writer.add_scalar("vq/active_codes", active_codes(metrics["codes"], args.n_embed).item(), loop.step)

        # Progress line (and checkpoint), every --progress-frequency frames and at the end.
        if loop.step >= loop.next_progress or loop.step >= args.total_timesteps:
            loop.next_progress += args.progress_frequency
            window = loop.window
            writer.add_scalar("charts/SPS", progress.sps(loop.step), loop.step)
            if window["outcomes"]:
                writer.add_scalar("charts/goal_reach_rate", window["reached"] / window["outcomes"], loop.step)
            if window["goal_steps"]:
                writer.add_scalar("charts/steps_per_goal", np.mean(window["goal_steps"]), loop.step)
            figures = f"return {mean_text(window['return'])}  success {mean_text(window['success'])}  t* {t_star.value}"
            figures += f"  teacher reward {mean_text(window['teacher_reward'])}"
            progress.line(loop.step, f"{figures}  goals reached {window['reached'] / max(window['outcomes'], 1):.0%}")
            loop.window = new_window()
            if args.save_model:
                save_checkpoint(model_path, {**agent.state_dicts(), "t_star": t_star.value, "step": loop.step}, args)
        progress.line(loop.step, f"{loop.student_updates} student updates  t* {t_star.value}", heartbeat=True)
        if progress.resume_due(loop.step, args.checkpoint_every, args.checkpoint_every_steps):
            writer.flush()  # a run killed outright after this save still has every scalar up to it on disk
            save_resume(run_name, training_state(agent, envs, book, t_star, outcomes, loop), args)

    save_resume(run_name, training_state(agent, envs, book, t_star, outcomes, loop), args)  # stopped or done
    if args.save_model:
        save_checkpoint(model_path, {**agent.state_dicts(), "t_star": t_star.value, "step": loop.step}, args)
        print(f"checkpoint: {model_path}")
    updates = f"{loop.student_updates} student and {loop.teacher_updates} teacher updates"
    progress.finish(bool(stop), run_name, f"{loop.step} frames, {updates}, t* {t_star.value}")
    envs.close()
    writer.close()


# --- Evaluation -------------------------------------------------------------------------------------------------------


def goal_frame(frame: np.ndarray, goal: int, height: int, tile: int = 32) -> np.ndarray:
    """Outline the goal cell in yellow on a render of the grid (minigrid draws cell (x, y) at rows y, columns x)."""
    frame = frame.copy()
    x, y = divmod(int(goal), height)
    cell = frame[y * tile : (y + 1) * tile, x * tile : (x + 1) * tile]
    for edge in (cell[:3], cell[-3:], cell[:, :3], cell[:, -3:]):
        edge[:] = (255, 255, 0)
    return frame


def evaluate(agent: Agent, envs: "MiniGridVecEnv", episodes: int, seed: int, device, stop=()) -> dict[str, float]:
    """The student on its teacher's goals, sampling as in training, for `episodes` episodes or until a `stop` signal."""
    obs, _ = envs.reset(seed=seed)
    book = GoalBook(envs.num_envs, envs.width, envs.height)
    goal_embedding = torch.zeros(envs.num_envs, agent.student.embed_dim, device=device)
    renew_goals(agent, book, np.ones(envs.num_envs, dtype=bool), obs["grid"], goal_embedding, device)
    returns, reached_total = [], 0
    while len(returns) < episodes and not stop:
        actions, _ = act(agent.student, obs, book.goal, goal_embedding, device)
        obs, _, terminated, truncated, info = envs.step(actions)
        reached = book.advance(info["final_grid"])
        reached_total += int(reached.sum())
        renew = reached | terminated | truncated
        if renew.any():
            renew_goals(agent, book, renew, obs["grid"], goal_embedding, device)
        returns.extend(info["episode"]["r"][info["_episode"]].tolist())
    returns = np.array(returns[:episodes])
    if not len(returns):
        return {"episodes": 0, "return": math.nan, "success": math.nan, "goals_per_episode": math.nan}
    success, per_episode = (returns > 0).mean(), reached_total / len(returns)
    return {"episodes": len(returns), "return": returns.mean(), "success": success, "goals_per_episode": per_episode}


def mean_text(values: list[float]) -> str:
    return f"{np.mean(values):.2f}" if values else "-"


def new_window() -> dict:
    """What a progress line reports: episodes ended, goal outcomes and teacher rewards since the previous line."""
    return {"return": [], "success": [], "reached": 0, "outcomes": 0, "goal_steps": [], "teacher_reward": []}


def evaluate_checkpoint(args: Args, agent: Agent, envs: "MiniGridVecEnv", device, stop: list[int]) -> None:
    """--checkpoint: load its networks into `agent`, evaluate them for --eval-episodes episodes, print the result."""
    evaluated = load_checkpoint(args.checkpoint, args, MUST_MATCH, device)
    agent.load_state_dicts(evaluated)
    result = evaluate(agent, envs, args.eval_episodes, args.seed + 10_000, device, stop)
    text = f"{result['episodes']} episodes (t* {evaluated['t_star']} at save): return {result['return']:.3f}, "
    print(text + f"success {result['success']:.0%}, goals reached per episode {result['goals_per_episode']:.1f}")
    envs.close()


def write_video(path: str, frames: list[np.ndarray], fps: int) -> None:
    """Frames (H, W, 3) uint8 to an mp4 (moviepy loaded only here), one encoder thread: with more, the bytes vary."""
    os.makedirs(os.path.dirname(path), exist_ok=True)
    importlib.import_module("moviepy").ImageSequenceClip(frames, fps=fps).write_videofile(path, logger=None, threads=1)


# --- Environment ------------------------------------------------------------------------------------------------------

N_OBJECTS, N_COLORS, N_STATES = 11, 6, 4  # MiniGrid's object, colour and state ids (the agent's state is its direction)
AGENT, EMPTY = OBJECT_TO_IDX["agent"], OBJECT_TO_IDX["empty"]


def minigrid_ids() -> list[str]:
    return sorted(name for name in gym.registry if name.startswith("MiniGrid-"))


def full_grid(env) -> np.ndarray:
    """The full (W, H, 3) grid of [object, colour, state] ids, as FullyObsWrapper's, built in one pass (2.3x faster)."""
    cells = [(EMPTY, 0, 0) if cell is None else cell.encode() for cell in env.grid.grid]
    grid = np.array(cells, dtype=np.uint8).reshape(env.height, env.width, 3).transpose(1, 0, 2)
    grid[env.agent_pos[0], env.agent_pos[1]] = (AGENT, COLOR_TO_IDX["red"], env.agent_dir)
    return grid


def carried(env) -> tuple[int, int]:
    """(object id, colour id) of what the agent carries; (empty, 0) when it carries nothing."""
    return (EMPTY, 0) if env.carrying is None else (OBJECT_TO_IDX[env.carrying.type], COLOR_TO_IDX[env.carrying.color])


class MiniGridVecEnv(gym.vector.VectorEnv):
    """`num_envs` fully observed MiniGrid envs stepped in one loop with same-step autoreset. Observations: "grid"
    (`full_grid`'s ids) and "carried"; `reset(seed=s)` seeds env i with s + i; every reset draws a new layout. info:
    "final_grid" (each grid right after the step, before any reset), "episode" and "_episode"; only env 0 renders."""

    metadata: ClassVar[dict] = {"autoreset_mode": gym.vector.AutoresetMode.SAME_STEP, "render_modes": ["rgb_array"]}
    NOT_ENV_STATE = ("window", "clock", "render_mode", "spec", "gen_obs")  # renderer, free --capture-video, spec, patch

    def __init__(self, env_id: str, num_envs: int, render_env0: bool = False):
        render_modes = ["rgb_array" if render_env0 and i == 0 else None for i in range(num_envs)]
        self.envs = [gym.make(env_id, render_mode=mode).unwrapped for mode in render_modes]
        for env in self.envs:
            env.gen_obs = lambda: None  # the egocentric 7x7 view, 80% of a step's time, unused: both see the full grid
        self.env_id, self.num_envs, self.render_mode = env_id, num_envs, "rgb_array" if render_env0 else None
        self.width, self.height, self.max_steps = self.envs[0].width, self.envs[0].height, self.envs[0].max_steps
        self.n_actions = int(self.envs[0].action_space.n)
        highest_id = np.broadcast_to(np.array([N_OBJECTS, N_COLORS, N_STATES]) - 1, (self.width, self.height, 3))
        grid_space = gym.spaces.Box(0, highest_id.astype(np.uint8), dtype=np.uint8)
        carried_space = gym.spaces.Box(0, np.array([N_OBJECTS - 1, N_COLORS - 1]), dtype=np.int64)
        self.single_observation_space = gym.spaces.Dict({"grid": grid_space, "carried": carried_space})
        self.observation_space = gym.vector.utils.batch_space(self.single_observation_space, num_envs)
        self.single_action_space = gym.spaces.Discrete(self.n_actions)
        self.action_space = gym.spaces.MultiDiscrete(np.full(num_envs, self.n_actions))
        self.grids = np.zeros((num_envs, self.width, self.height, 3), dtype=np.uint8)  # observation to act on
        self.after = np.zeros_like(self.grids)  # frame right after the last step, before autoreset
        self.carried = np.zeros((num_envs, 2), dtype=np.int64)
        self.episode_return, self.episode_length = np.zeros(num_envs), np.zeros(num_envs, dtype=np.int64)
        self.record, self.frame0 = False, None  # while `record` is set, `frame0` is env 0's render after each step

    def _observe(self, i: int, target: np.ndarray) -> None:
        grid = full_grid(self.envs[i])
        if grid.shape != target.shape[1:]:
            raise RuntimeError(f"{self.env_id}: the grid changed size from {target.shape[1:3]} to {grid.shape[:2]}")
        target[i], self.carried[i] = grid, carried(self.envs[i])

    def _observation(self) -> dict[str, np.ndarray]:
        return {"grid": self.grids.copy(), "carried": self.carried.copy()}

    def reset(self, *, seed: int | list[int | None] | None = None, options: dict | None = None):
        seeds = seed if isinstance(seed, list) else [None if seed is None else seed + i for i in range(self.num_envs)]
        for i, env in enumerate(self.envs):
            env.reset(seed=seeds[i], options=options)
            self._observe(i, self.grids)
        self.episode_return[:], self.episode_length[:] = 0, 0
        return self._observation(), {}

    def step(self, actions: np.ndarray):
        rewards = np.zeros(self.num_envs)
        terminated, truncated = np.zeros((2, self.num_envs), dtype=bool)
        for i, env in enumerate(self.envs):
            _, rewards[i], terminated[i], truncated[i], _ = env.step(int(actions[i]))
            self._observe(i, self.after)
        if self.record:
            self.frame0 = self.envs[0].render()
        self.grids[:] = self.after
        self.episode_return += rewards
        self.episode_length += 1
        done = terminated | truncated
        episode = {"r": np.where(done, self.episode_return, 0.0), "l": np.where(done, self.episode_length, 0)}
        info = {"final_grid": self.after.copy(), "episode": episode, "_episode": done}
        for i in np.flatnonzero(done):
            self.envs[i].reset()
            self._observe(i, self.grids)
        self.episode_return[done], self.episode_length[done] = 0, 0
        return self._observation(), rewards, terminated, truncated, info

    def render(self) -> tuple[np.ndarray]:
        return (self.envs[0].render(),)

    def close_extras(self, **kwargs) -> None:
        for env in self.envs:
            env.close()

    def get_state(self) -> dict:
        """For --resume: each env's attributes but NOT_ENV_STATE (grid, agent, step count, np_random, ...), the
        observation and the episode statistics, deep-copied as a whole so that shared objects stay shared."""
        envs = [{key: value for key, value in vars(env).items() if key not in self.NOT_ENV_STATE} for env in self.envs]
        arrays = {key: getattr(self, key) for key in ("grids", "carried", "episode_return", "episode_length")}
        return copy.deepcopy({"envs": envs, **arrays})

    def set_state(self, state: dict) -> None:
        """Continue from `get_state()`'s copy (which stays the caller's): the episodes in progress go on."""
        state = copy.deepcopy(state)
        for env, attributes in zip(self.envs, state.pop("envs"), strict=True):
            env.__dict__.update(attributes)
        for key, value in state.items():
            getattr(self, key)[:] = value


# --- Resuming ---------------------------------------------------------------------------------------------------------


@dataclass
class LoopState:
    """The variables the training loop carries from one step to the next; resume.pt holds them as a plain dict."""

    obs: dict  # the observation to act on
    record: bool  # whether env 0's episode in progress is recorded (envs.record)
    video: list  # its frames so far
    next_progress: int  # the frame of the next progress line
    next_loss_log: int  # the student update of the next write of its losses
    step: int = 0  # frames: env steps x --num-envs
    student_updates: int = 0
    teacher_updates: int = 0
    episodes_env0: int = 0
    window: dict = field(default_factory=new_window)  # what the next progress line reports


def training_state(agent: Agent, envs, book: GoalBook, t_star: TStar, outcomes, loop: LoopState) -> dict:
    """What a stopped run needs to continue exactly (save_resume adds the RNG states); it stops between collections."""
    return {
        "networks": agent.state_dicts(),
        "student_optimizer": agent.student_optimizer.state_dict(),
        "teacher_optimizer": agent.teacher_optimizer.state_dict(),
        "envs": envs.get_state(),
        "goal_book": {"goal": book.goal, "frame": book.frame, "logp": book.logp, "steps": book.steps},
        "t_star": {"value": t_star.value, "streak": t_star.streak},
        "outcomes": {"parts": outcomes.parts, "size": outcomes.size},
        "loop": copy.deepcopy(vars(loop)),
    }


def restore_training_state(saved: dict, agent: Agent, envs, book: GoalBook, t_star, outcomes) -> LoopState:
    """Put `training_state`'s entries back into a freshly built run; returns the LoopState."""
    agent.load_state_dicts(saved["networks"])
    agent.student_optimizer.load_state_dict(saved["student_optimizer"])
    agent.teacher_optimizer.load_state_dict(saved["teacher_optimizer"])
    envs.set_state(saved["envs"])
    for key, value in saved["goal_book"].items():
        getattr(book, key)[:] = value
    t_star.value, t_star.streak = saved["t_star"]["value"], saved["t_star"]["streak"]
    outcomes.parts, outcomes.size = saved["outcomes"]["parts"], saved["outcomes"]["size"]
    return LoopState(**saved["loop"])


# --- Run management and checks: identical in every script (tests/test_skeleton.py) ------------------------------------

CHECKPOINT_FORMAT, RESUME_FORMAT = 2, 3  # the layouts of a checkpoint and of resume.pt, one number in every script
RESUME_FILE, LOCK_FILE = "resume.pt", "run.lock"  # in runs/{run_name}: the training state (--resume); the writer's lock
FREE_FLAGS = ("resume", "checkpoint_every", "checkpoint_every_steps", "threads", "fast", "capture_video", "save_model",
              "track", "wandb_project_name", "wandb_entity")  # fmt: skip


def seed_and_device(args) -> torch.device:
    """Seed Python and torch (numpy draws come from seeded Generators), set threads and determinism, pick the device."""
    random.seed(args.seed)
    torch.manual_seed(args.seed)
    torch.backends.cudnn.deterministic = args.torch_deterministic
    torch.set_num_threads(args.threads)
    return torch.device("cuda" if torch.cuda.is_available() and args.cuda else "cpu")


def make_writer(args, run_name: str, purge_step: int | None = None) -> SummaryWriter:
    """TensorBoard in runs/{run_name} (W&B too with --track); a resumed run's `purge_step` drops what came after it."""
    if args.track:
        options = {"project": args.wandb_project_name, "entity": args.wandb_entity, "config": vars(args)}
        importlib.import_module("wandb").init(name=run_name, **options, sync_tensorboard=True, save_code=True)
    writer = SummaryWriter(f"runs/{run_name}", purge_step=purge_step)
    if purge_step is None:
        table = "\n".join(f"|{key}|{value}|" for key, value in vars(args).items())
        writer.add_text("hyperparameters", f"|param|value|\n|-|-|\n{table}")
    return writer


def stop_on_signals() -> list[int]:
    """Ctrl-C, SIGTERM, SIGUSR1/2 (Slurm's) stop the run after its step (a second: at once); the loop polls the list."""
    received = []
    for number in (signal.SIGINT, signal.SIGTERM, signal.SIGUSR1, signal.SIGUSR2):  # note it; a second: the default
        signal.signal(number, lambda number, frame: (received.append(number), signal.signal(number, signal.SIG_DFL)))
    return received


class Progress:
    """Progress lines (step, figures, SPS, time elapsed and left), a heartbeat after a quiet minute, resume cadence."""

    def __init__(self, total: int, unit: str = "step", start_step: int = 0):
        self.total, self.unit, self.start_step = total, unit, start_step
        self.start_time = self.print_time = self.save_time = time.time()
        self.print_step = self.save_step = start_step

    def sps(self, step: int) -> int:
        return int((step - self.start_step) / max(time.time() - self.start_time, 1e-6))

    def resume_due(self, step: int, seconds: int, steps: int) -> bool:
        """True once every `seconds` of wall clock, and whenever `step` passes a multiple of `steps` (0: either off)."""
        now = time.time()
        if (seconds and now - self.save_time >= seconds) or (steps and step // steps > self.save_step // steps):
            self.save_time, self.save_step = now, step
            return True
        return False

    def line(self, step: int, figures: str = "", heartbeat: bool = False) -> None:
        now = time.time()
        if heartbeat and now - self.print_time <= 60:  # a heartbeat: only after a quiet minute, marked (running)
            return
        rate = (step - self.print_step) / max(now - self.print_time, 1e-6)  # since the last line: this phase's rate
        left = f"{(self.total - step) / rate:.0f}s left" if rate > 0 else "time left unknown"
        times = f"{now - self.start_time:.0f}s elapsed, {left}" + " (running)" * heartbeat
        print(f"{self.unit} {step:>9}/{self.total}  {figures}  SPS {self.sps(step)}  {times}", flush=True)
        self.print_time, self.print_step = now, step

    def finish(self, stopped: bool, run_name: str, summary: str) -> None:
        outcome = "stopped" if stopped else "done"
        print(f"{outcome}: {summary}; {time.time() - self.start_time:.0f}s; logs in runs/{run_name}", flush=True)


def save_checkpoint(path: str, entries: dict, args) -> None:
    """Save `entries` with the script's name, format and flags, to a temporary file, flushed, then renamed: atomic."""
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    with open(path + ".tmp", "wb") as file:
        torch.save(dict(script=os.path.basename(__file__), format=CHECKPOINT_FORMAT, args=vars(args)) | entries, file)
        file.flush()
        os.fsync(file.fileno())
    os.replace(path + ".tmp", path)


def load_checkpoint(path: str, args, must_match: tuple[str, ...], device, resume: bool = False) -> dict:
    """`path` if this script wrote it with these `must_match` flags (else exit 2); resume.pt unpickles: yours only."""
    script, shown = os.path.basename(__file__), f"--resume {args.resume}" if resume else f"--checkpoint {path}"
    layout = RESUME_FORMAT if resume else CHECKPOINT_FORMAT
    its_version = "continue it with the version that started it" if resume else "use its version"
    try:
        saved = torch.load(path, map_location=device, weights_only=not resume)
    except Exception as error:  # truncated, empty or not a torch file: the file is left as it is
        cause = f"{type(error).__name__}: {str(error)[:120]}"
        damaged = f"{path} cannot be read ({cause}); it is damaged or incomplete: start the run afresh without --resume"
        foreign = f"{shown} is not a checkpoint ({cause}); pass a file that `{script} --save-model` wrote"
        exit_on_errors([f"{shown}: {damaged}, or put back an older copy of the file" if resume else foreign])
    if not isinstance(saved, dict) or (saved.get("script"), saved.get("format")) != (script, layout):
        got = f"{saved.get('script')} format {saved.get('format')}" if isinstance(saved, dict) else type(saved).__name__
        wanted = f"; it needs one that {script} (format {CHECKPOINT_FORMAT}) wrote with --save-model"
        exit_on_errors([f"{shown} holds {got}" + (f": {its_version}" if resume else wanted)])
    if older := " ".join(f"--{key.replace('_', '-')}" for key in must_match if key not in saved["args"]):  # added since
        exit_on_errors([f"{shown} was {'started' if resume else 'written'} before {older} existed; {its_version}"])
    if differ := [flag_text(key, saved["args"][key]) for key in must_match if saved["args"][key] != getattr(args, key)]:
        exit_on_errors([f"{shown} was {'started' if resume else 'saved'} with other settings: pass {' '.join(differ)}"])
    return saved


def rng_states(restore: dict | None = None) -> dict:
    """The global random states a run draws from (Python's, torch's CPU and GPUs'), first set to `restore` if given."""
    if restore is not None:
        random.setstate(restore["python"])
        torch.set_rng_state(restore["torch"])
        torch.cuda.set_rng_state_all(restore.get("cuda", []))
    return {"python": random.getstate(), "torch": torch.get_rng_state(), "cuda": torch.cuda.get_rng_state_all()}


def save_resume(run_name: str, state: dict, args) -> None:
    """The whole training state, with the global random states, to runs/{run_name}/resume.pt (for --resume)."""
    entries = {"format": RESUME_FORMAT, "rng": rng_states()} | state
    save_checkpoint(os.path.join("runs", run_name, RESUME_FILE), entries, args)


def load_resume(args) -> dict:
    """--resume's state (on the CPU), saved by this script with the same flags but FREE_FLAGS (otherwise exit 2)."""
    must_match = tuple(key for key in vars(args) if key not in FREE_FLAGS)
    return load_checkpoint(os.path.join(args.resume, RESUME_FILE), args, must_match, "cpu", resume=True)


def fast_update(update, fast: str, optimizers: list[torch.optim.Optimizer]):
    """--fast: `update` as it is, compiled, or as CUDA graphs that later calls replay (torch's "reduce-overhead")."""
    if fast == "eager":  # (the inductor import costs seconds: an eager run never loads it)
        return update
    torch._inductor.config.fallback_random = True  # compiled random draws as in eager: a seed gives the same numbers
    if fast == "compile":
        return torch.compile(update)
    for optimizer in optimizers:  # torch makes fresh optimizers capturable; a resumed one's step counts move to the GPU
        for group in optimizer.param_groups:
            group["capturable"] = True
        optimizer.load_state_dict(optimizer.state_dict())
    compiled = torch.compile(update, mode="reduce-overhead")

    def replayed(*args, **kwargs):
        torch.compiler.cudagraph_mark_step_begin()  # a new step: the graphs reuse their outputs' memory: return copies
        return torch.utils._pytree.tree_map_only(torch.Tensor, torch.clone, compiled(*args, **kwargs))

    return replayed


def flag_text(key: str, value) -> str:
    """How a user writes `key = value` on the command line (tyro's --name / --no-name for booleans)."""
    name = key.replace("_", "-")
    return (f"--{name}" if value else f"--no-{name}") if isinstance(value, bool) else f"--{name} {value}"


def range_errors(args, flags: str, low=-math.inf, high=math.inf, low_open=False, high_open=False) -> list[str]:
    """A message for each of `flags` (field names) outside [low, high]; low_open and high_open exclude that bound."""
    errors = []
    for key in flags.split():
        value = getattr(args, key)
        if isinstance(value, float) and not math.isfinite(value):
            continue  # common_errors' message
        if value < low or value > high or (low_open and value == low) or (high_open and value == high):
            bounds = f"in {'(' if low_open else '['}{low:g}, {high:g}{')' if high_open else ']'}"
            wanted = f"{'>' if low_open else '>='} {low:g}" if high == math.inf else bounds
            errors.append(f"--{key.replace('_', '-')} must be {wanted}; got {value}")
    return errors


def common_errors(args) -> list[str]:
    """The checks every script makes: the common flags' values, and the folders a run reads from and writes to."""
    infinite = [key for key, value in vars(args).items() if isinstance(value, float) and not math.isfinite(value)]
    errors = [f"--{key.replace('_', '-')} must be a finite number; got {getattr(args, key)}" for key in infinite]
    if not 0 <= args.seed < 2**64:
        errors.append(f"--seed must be in [0, 2**64) (what numpy, gymnasium and torch accept); got {args.seed}")
    errors += range_errors(args, "threads n_embed", 1)
    if args.threads > (cores := os.cpu_count() or 1):  # torch would start them all, and the machine would crawl
        errors.append(f"--threads {args.threads} is more than this machine's {cores} cores: use at most {cores}")
    errors += range_errors(args, "vq_beta vq_dead_code_steps checkpoint_every checkpoint_every_steps", 0)
    errors += range_errors(args, "vq_decay", 0, 1, high_open=True)  # at 1 the codebook would never move
    if args.track and importlib.util.find_spec("wandb") is None:
        errors.append("--track needs Weights and Biases: `pip install wandb`, or run without --track")
    if args.checkpoint is not None and not os.path.isfile(args.checkpoint):
        errors.append(f"--checkpoint {args.checkpoint}: no such file")
    if not args.exp_name or any(separator in args.exp_name for separator in {"/", os.sep, os.altsep or "/"}):
        errors.append(f"--exp-name {args.exp_name!r} must be a plain name, without '/': it names a folder in runs/")
    if args.fast == "cudagraphs" and not (args.cuda and torch.cuda.is_available()):
        errors.append("--fast cudagraphs needs a CUDA device (none visible, or --no-cuda): use --fast compile or eager")
    elif args.fast != "eager" and not (args.cuda and torch.cuda.is_available()) and shutil.which("g++") is None:
        errors.append(f"--fast {args.fast} on a CPU needs g++ (torch.compile's compiler): install it, or use eager")
    if args.resume is not None:
        name = os.path.basename(os.path.normpath(args.resume))
        if not os.path.isfile(os.path.join(args.resume, RESUME_FILE)):
            errors.append(f"--resume {args.resume}: no {RESUME_FILE} there (a run of this version's scripts writes it)")
        elif os.path.realpath(args.resume) != os.path.realpath(os.path.join("runs", name)):
            errors.append(f"--resume {args.resume}: run from the folder that holds it as runs/{name} (it writes there)")
        if args.checkpoint is not None:
            errors.append("--resume continues a training run and --checkpoint only evaluates one: pass one of them")
    folder = args.resume or "runs"  # where a training run writes: found unwritable now, not by a PermissionError later
    existing = folder if os.path.lexists(folder) else os.path.dirname(os.path.abspath(folder))
    if args.checkpoint is None and not os.path.isdir(existing):
        errors.append(f"{folder} is in the way: the run writes its logs in a folder of that name; move it")
    elif args.checkpoint is None and not os.access(existing, os.W_OK | os.X_OK):
        wanted = f"create {folder}/ in" if existing != folder else "write to"
        errors.append(f"cannot {wanted} {os.path.abspath(existing)} (permission denied): use a folder you can write to")
    return errors


def exit_on_errors(errors: list[str]) -> None:
    """Print every error with the script's name and exit with status 2 (as for an unknown flag), before any work."""
    if errors:
        print(f"{os.path.basename(__file__)}: invalid arguments:\n  " + "\n  ".join(errors), file=sys.stderr)
        raise SystemExit(2)


def hold_run_folder(run_name: str, check_only: bool = False):
    """Lock runs/{run_name} for this process's life (the kernel drops it however the process ends); keep the returned
    file. A second process on the folder exits 2 naming the holder; `check_only`: that refusal alone, no write."""
    path = os.path.join("runs", run_name, LOCK_FILE)
    if check_only and not os.path.isfile(path):
        return None
    os.makedirs(os.path.dirname(path), exist_ok=True)
    lock = open(path, "r" if check_only else "a+")  # open while the run lives: closing it would unlock
    try:
        fcntl.flock(lock, (fcntl.LOCK_SH if check_only else fcntl.LOCK_EX) | fcntl.LOCK_NB)
    except BlockingIOError:
        lock.seek(0)
        holder = lock.read().strip() or "a run that is starting"
        exit_on_errors([f"runs/{run_name} is in use by {holder}: one process at a time writes a run; wait for its end"])
    if check_only:
        return lock.close()
    lock.truncate(0)
    print(f"pid {os.getpid()} on {os.uname().nodename}", file=lock, flush=True)
    return lock


# --- end of the shared block ------------------------------------------------------------------------------------------


def validate(args: Args) -> None:
    """Refuse bad flags before any work, naming the flag and the valid choices; exit with status 2."""
    errors = common_errors(args)
    if args.env_id not in (ids := minigrid_ids()):
        key = re.sub(r"[^a-z0-9]", "", args.env_id.lower().removeprefix("minigrid"))[:8]
        close = [name for name in ids if key and key in re.sub(r"[^a-z0-9]", "", name.lower())]
        hint = f"did you mean {', '.join(close[:6])}? " if close else ""
        errors.append(f"--env-id {args.env_id!r} is not a MiniGrid id; {hint}choices: {', '.join(ids)}")
    else:
        try:  # a MiniGrid id whose env fails to build or reset here
            with gym.make(args.env_id) as env:
                env.unwrapped.reset(seed=0)
        except Exception as error:
            cause = f"{type(error).__name__}: {error}"
            errors.append(f"--env-id {args.env_id} fails to build or reset here ({cause}); pick another MiniGrid id")
    counts = "total_timesteps num_envs num_steps batch_envs teacher_batch_size t_star_patience progress_frequency"
    errors += range_errors(args, f"{counts} video_frequency eval_episodes embed_dim", 1)
    errors += range_errors(args, "learning_rate teacher_learning_rate rmsprop_eps max_grad_norm", 0, low_open=True)
    weights = "entropy_coef baseline_coef teacher_entropy_coef teacher_baseline_coef intrinsic_coef"
    errors += range_errors(args, weights, 0)
    errors += range_errors(args, "gamma", 0, 1, low_open=True)
    errors += range_errors(args, "rmsprop_alpha", 0, 1, high_open=True)
    if args.t_star_threshold > 1:
        errors.append(f"--t-star-threshold must be <= 1 (teacher rewards are at most 1); got {args.t_star_threshold}")
    if not 0 <= args.t_star_start <= args.t_star_max:
        errors.append(f"--t-star-start ({args.t_star_start}) must be in [0, --t-star-max ({args.t_star_max})]")
    if args.num_envs >= 1 and args.num_steps >= 1 and args.total_timesteps < (frames := args.num_envs * args.num_steps):
        collection = f"one collection: >= --num-envs x --num-steps ({frames})"
        errors.append(f"--total-timesteps ({args.total_timesteps}) must cover {collection}")
    if args.checkpoint is None and args.batch_envs >= 1 and args.num_envs % args.batch_envs:
        errors.append(f"--batch-envs ({args.batch_envs}) must divide --num-envs ({args.num_envs})")
    if args.checkpoint is not None and (args.save_model or args.capture_video):
        errors.append("--save-model and --capture-video apply to training, not to a --checkpoint evaluation")
    if args.groups < 0 or (args.groups and args.embed_dim >= 1 and args.embed_dim % args.groups):
        divisors = [g for g in range(1, args.embed_dim + 1) if args.embed_dim % g == 0]
        wanted = f"0 (AMIGo) or divide --embed-dim {args.embed_dim}: one of {divisors}"
        errors.append(f"--groups must be {wanted}; got {args.groups}")
    exit_on_errors(errors)


if __name__ == "__main__":
    main(tyro.cli(Args))
