"""DGRL on RIS in the vision-based Sawyer push-and-reach task: discretized goal and subgoal embeddings from pixels.

Paper: Islam et al. 2022, "Discrete Factorial Representations as an Abstraction for Goal Conditioned RL", section
"Vision Based Robotic Manipulation", appendix "Robotic Manipulation Task", Algorithm 1 and its snippet's image branch.
The agent is RIS (Chane-Sane et al. 2021) from pixels: a conv encoder (random-translate augmentation) maps 84x84 state
and goal images to 16-d features for an actor and twin critics; a high-level policy proposes subgoal features halfway to
the goal; the actor's loss replaces SAC's entropy term by a KL divergence to the target actor averaged over imagined
subgoals. The critic's loss and DRIML's local-global InfoNCE loss on (s_t, a_t, s_t+1) (Mazoure et al. 2020) train the
encoder. DGRL (`--groups G`; 0: RIS) discretizes the embeddings the actor, the critics and the prior see with vq.py's
shared codebook; the mean of the commitment losses of s, s', g and s_g (the paper's text; `--vq-loss-reduction sum`: the
snippet's sum) trains the encoder through all four, as in the snippet (`--vq-commitment-grad state`: s only).

The task: multiworld's `SawyerPushAndReachXYEnv` ("TrainEnvBig" / "TestEnvBig") on `mujoco`, its MJCF scene made in code
(a table, four low walls, a puck, a mocap-driven end effector; no arm: its meshes ship in no installable package).
Training resets anywhere in the arena; evaluation uses the test configuration, where hand and puck cross the arena.

    python dgrl_ris_sawyer.py --groups 16  # paper setting (G=16, batch 256): a GPU job; --groups 0: RIS
    python dgrl_ris_sawyer.py --total-timesteps 30000 --batch-size 32 --start-timesteps 2000 \
        --eval-frequency 2000 --eval-episodes 10  # CPU preset: 30-35 min (--vq-commitment-grad state; ~2x by default)
    python dgrl_ris_sawyer.py --total-timesteps 600 --start-timesteps 300 --batch-size 16 \
        --eval-frequency 600 --eval-episodes 2    # 1-minute smoke run
    python dgrl_ris_sawyer.py --groups 16 --resume runs/<run_name>   # continue a stopped run (with its flags)

Env frames/s and images: benchmark/figures/sawyer_env.py; update times: benchmark/speed/bench_ris_sawyer.py; the CPU
study: python benchmark/launch.py --preset sawyer-cpu; docs, deviations and results: docs/dgrl_ris_sawyer.md.
"""

import copy
import fcntl
import importlib.util
import math
import os
import random
import shutil
import signal
import sys
import time
from dataclasses import dataclass, field
from functools import partial
from typing import ClassVar, Literal

if sys.platform.startswith("linux") and not os.environ.get("DISPLAY"):
    os.environ.setdefault("MUJOCO_GL", "egl")  # headless rendering without a display; set MUJOCO_GL to override

import gymnasium as gym
import mujoco
import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
import tyro
from torch.utils.tensorboard import SummaryWriter

from vq import VectorQuantizerEMA, active_codes, make_target, perplexity, update_target


@dataclass
class Args:
    # Algorithm: RIS from pixels
    num_envs: int = 1
    """environments stepped together; each env step is followed by one update, as in RIS"""
    total_timesteps: int = 1_000_000
    """total environment steps (RIS gives no Sawyer budget; 1M is this script's choice)"""
    buffer_size: int = 100_000
    """replay capacity in rows: the transitions plus, per episode, its last observation and its goal image"""
    batch_size: int = 256
    """transitions per update"""
    start_timesteps: int = 10_000
    """steps of uniform random actions before the first update"""
    gamma: float = 0.99
    """discount"""
    tau: float = 0.005
    """Polyak rate of the critic and actor targets"""
    q_lr: float = 1e-3
    """Adam learning rate of the twin critics"""
    actor_lr: float = 1e-4
    """Adam learning rate of the actor"""
    h_lr: float = 1e-4
    """Adam learning rate of the high-level policy"""
    hidden_dim: int = 256
    """hidden units of every 2-layer MLP"""
    alpha: float = 0.1
    """weight of the KL divergence to the imagined-subgoal prior in the actor loss"""
    h_lambda: float = 0.1
    """temperature of the high level's advantage weights"""
    n_subgoals: int = 10
    """imagined subgoals per state for the prior policy"""
    prior_epsilon: float = 1e-4
    """added to the prior density inside the log (RIS's Sawyer value)"""
    her_goal_frac: float = 0.2
    """fraction of each batch keeping the rollout goal"""
    her_random_frac: float = 0.4
    """fraction relabelled with a random replay state (the rest: a future state of the same episode)"""
    image_pad: int = 8
    """random-translate augmentation: pad by this many pixels (zeros, as RIS), crop back at a random offset"""

    # Representation: RIS's image encoder, also trained by DRIML
    feature_dim: int = 16
    """size of the encoder's features (RIS: 16); states, goals and subgoals live in this space"""
    encoder_lr: float = 1e-4
    """Adam learning rate of the encoder (a parameter group of the critic optimizer; the DRIML heads train at --q-lr)"""
    driml_coef: float = 1.0
    """weight of the DRIML loss in the critic's loss (0 = RIS's encoder, trained by the critic alone)"""
    driml_dim: int = 64
    """output size of the DRIML loss's local and global projection heads"""

    # Evaluation
    eval_frequency: int = 5000
    """environment steps between evaluations"""
    eval_episodes: int = 20
    """episodes per evaluation, on the test configuration"""
    eval_deterministic: bool = False
    """act with the mean action during evaluation (RIS samples actions, as in training)"""

    # DGRL
    groups: int = 16  # DGRL
    """G: factors of the 16-d embedding; 0 runs RIS"""
    n_embed: int = 64
    """L: codes in the shared codebook"""
    vq_beta: float = 0.25
    """commitment-loss weight"""
    vq_decay: float = 0.99
    """EMA decay of the codebook"""
    vq_dead_code_steps: int = 0
    """restart a code unused for this many updates at a random current segment (0 = off, as in the paper)"""
    vq_loss_reduction: str = "mean"
    """how the commitment losses of s, s', g and s_g combine: mean (the paper's text) or sum (its code snippet)"""
    vq_commitment_grad: str = "all"
    """whose commitment losses train the encoder: all (s, s', g, s_g: the paper's snippet) or state (s only, as RIS)"""

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

LOG_STD_MIN, LOG_STD_MAX = -20.0, 2.0
IMAGE_SIZE = 84  # the environment's square RGB images


def mlp(in_dim: int, hidden_dim: int, out_dim: int) -> nn.Sequential:
    hidden_layers = nn.Linear(in_dim, hidden_dim), nn.ReLU(), nn.Linear(hidden_dim, hidden_dim), nn.ReLU()
    return nn.Sequential(*hidden_layers, nn.Linear(hidden_dim, out_dim))


class Policy(nn.Module):
    """Location and scale of a distribution given (z_s, z_g): the actor's Gaussian over pre-tanh actions u (the action
    is tanh(u)), or the high level's Laplace over subgoal features (given continuous state and goal features)."""

    def __init__(self, feature_dim: int, out_dim: int, hidden_dim: int):
        super().__init__()
        self.net = mlp(2 * feature_dim, hidden_dim, 2 * out_dim)

    def forward(self, states: torch.Tensor, goal_inputs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        mean, log_std = self.net(torch.cat((states, goal_inputs), -1)).chunk(2, -1)
        return mean, log_std.clamp(LOG_STD_MIN, LOG_STD_MAX).exp()

    def sample(self, states: torch.Tensor, goal_inputs: torch.Tensor) -> torch.Tensor:
        mean, std = self(states, goal_inputs)
        return torch.tanh(mean + std * torch.randn_like(mean))

    def laplace(self, states: torch.Tensor, goals: torch.Tensor) -> torch.distributions.Laplace:
        return torch.distributions.Laplace(*self(states, goals), validate_args=False)


class TwinCritic(nn.Module):
    """Two Q-networks on (z_s, a, z_g); returns Q values of shape (2, batch)."""

    def __init__(self, feature_dim: int, action_dim: int, hidden_dim: int):
        super().__init__()
        self.q1 = mlp(2 * feature_dim + action_dim, hidden_dim, 1)
        self.q2 = mlp(2 * feature_dim + action_dim, hidden_dim, 1)

    def forward(self, states: torch.Tensor, actions: torch.Tensor, goal_inputs: torch.Tensor) -> torch.Tensor:
        inputs = torch.cat((states, actions, goal_inputs), -1)
        return torch.stack((self.q1(inputs).squeeze(-1), self.q2(inputs).squeeze(-1)))


class ImageEncoder(nn.Module):
    """RIS's encoder: 3x3 convs (32 channels; strides 2, 2, 2, 1; ReLUs) -> the 32 x 7 x 7 map (DRIML's) -> Linear."""

    channels = 32

    def __init__(self, feature_dim: int, image_size: int = IMAGE_SIZE):
        super().__init__()
        layers, in_channels, side = [], 3, image_size
        for stride in (2, 2, 2, 1):
            layers += [nn.Conv2d(in_channels, self.channels, 3, stride), nn.ReLU(inplace=True)]
            in_channels, side = self.channels, (side - 3) // stride + 1
        self.convs = nn.Sequential(*layers)
        self.linear = nn.Linear(self.channels * side * side, feature_dim)
        for conv in self.convs[::2]:  # delta-orthogonal convolutions (ReLU gain), orthogonal linear layer, zero biases
            nn.init.zeros_(conv.weight)
            nn.init.orthogonal_(conv.weight.data[:, :, 1, 1], nn.init.calculate_gain("relu"))  # kernel centre
            nn.init.zeros_(conv.bias)
        nn.init.orthogonal_(self.linear.weight)
        nn.init.zeros_(self.linear.bias)

    def conv_map(self, images: torch.Tensor) -> torch.Tensor:
        return self.convs(images)

    def head(self, conv_map: torch.Tensor) -> torch.Tensor:
        return self.linear(conv_map.flatten(1))

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.head(self.convs(images))


class DrimlHeads(nn.Module):
    """DRIML's projections: local (one position of s_t's conv map, with a_t) and global (the features of s_t+1)."""

    def __init__(self, channels: int, action_dim: int, feature_dim: int, dim: int):
        super().__init__()
        self.local = nn.Sequential(nn.Linear(channels + action_dim, dim), nn.ReLU(), nn.Linear(dim, dim))
        self.globl = nn.Sequential(nn.Linear(feature_dim, dim), nn.ReLU(), nn.Linear(dim, dim))


def combined_commitment_loss(pooled: torch.Tensor, n_embeddings: int, reduction: str) -> torch.Tensor:
    """One call's loss over n embeddings is their mean (the paper's text); `sum`: n times it (the snippet's sum)."""
    return pooled if reduction == "mean" else n_embeddings * pooled


def goal_input(vq: VectorQuantizerEMA | None, features: torch.Tensor) -> torch.Tensor:
    """What the actor and critics see of a goal or subgoal: its features (RIS) or their discrete embedding (DGRL)."""
    return features if vq is None else vq(features, update=False)[0]  # DGRL


@dataclass
class Agent:
    """RIS from pixels: the networks, the actor and critic targets, the optimizers and, under DGRL, the codebook (moved
    by EMA, in no optimizer). The critic's optimizer also trains the encoder (at --encoder-lr) and the DRIML heads (at
    --q-lr: at --encoder-lr the DRIML loss stayed at log(batch) for the first thousand updates)."""

    encoder: ImageEncoder
    driml_heads: DrimlHeads
    actor: Policy
    critic: TwinCritic
    high: Policy
    actor_target: Policy
    critic_target: TwinCritic
    critic_optimizer: torch.optim.Adam
    actor_optimizer: torch.optim.Adam
    high_optimizer: torch.optim.Adam
    vq: VectorQuantizerEMA | None  # the DGRL bottleneck; None under --groups 0

    # What a checkpoint holds (its key: the attribute), and what resume.pt adds for training.
    NETWORKS: ClassVar = dict(actor="actor", critic="critic", high="high", encoder="encoder", driml="driml_heads")
    TRAINING_ONLY: ClassVar = ("actor_target", "critic_target", "critic_optimizer", "actor_optimizer", "high_optimizer")

    def state_dicts(self) -> dict[str, dict | None]:
        """What evaluation needs: the online networks, the codebook with its EMA statistics (None under --groups 0)."""
        networks = {key: getattr(self, name).state_dict() for key, name in self.NETWORKS.items()}
        return networks | {"vq": None if self.vq is None else self.vq.state_dict()}

    def load_state_dicts(self, saved: dict) -> None:
        for key, name in self.NETWORKS.items():
            getattr(self, name).load_state_dict(saved[key])
        if self.vq is not None:
            self.vq.load_state_dict(saved["vq"])


def make_agent(image_size: int, action_dim: int, args: Args, device: torch.device) -> Agent:
    """The agent of a run (the networks are created in this order, so a seed gives the same weights)."""
    actor = Policy(args.feature_dim, action_dim, args.hidden_dim).to(device)
    critic = TwinCritic(args.feature_dim, action_dim, args.hidden_dim).to(device)
    encoder = ImageEncoder(args.feature_dim, image_size).to(device)
    driml_heads = DrimlHeads(ImageEncoder.channels, action_dim, args.feature_dim, args.driml_dim).to(device)
    high = Policy(args.feature_dim, args.feature_dim, args.hidden_dim).to(device)  # the high level
    codebook = args.feature_dim, args.n_embed, args.groups, args.vq_beta, args.vq_decay  # DGRL's bottleneck; RIS: none
    vq = VectorQuantizerEMA(*codebook, dead_code_steps=args.vq_dead_code_steps).to(device) if args.groups > 0 else None
    adam = partial(torch.optim.Adam, fused=device.type in ("cpu", "cuda"))
    encoder_group = {"params": encoder.parameters(), "lr": args.encoder_lr}
    critic_groups = [{"params": [*critic.parameters(), *driml_heads.parameters()], "lr": args.q_lr}, encoder_group]
    targets = make_target(actor), make_target(critic)
    optimizers = adam(critic_groups), adam(actor.parameters(), lr=args.actor_lr), adam(high.parameters(), lr=args.h_lr)
    return Agent(encoder, driml_heads, actor, critic, high, *targets, *optimizers, vq)


# --- Augmentation and replay ------------------------------------------------------------------------------------------


def image_batch(images: np.ndarray | torch.Tensor, device) -> torch.Tensor:
    """(N, H, W, 3) uint8 -> (N, 3, H, W) floats in [0, 1], a channels-last view (faster for CPU convolutions)."""
    return torch.as_tensor(images, device=device).permute(0, 3, 1, 2).float().div_(255.0)


def translate(images: torch.Tensor, shifts: torch.Tensor) -> torch.Tensor:
    """Shift each (N, H, W, 3) uint8 image by its (rows, columns) in `shifts` (N, 2), the border it uncovers black (pad
    with zeros and crop back, as RIS's augmentation, in one gather); returns image_batch's floats."""
    n, height, width, _ = images.shape
    rows = torch.arange(height, device=images.device) - shifts[:, :1]  # output row i reads row i - dy
    columns = torch.arange(width, device=images.device) - shifts[:, 1:]
    inside = ((rows >= 0) & (rows < height))[:, :, None] & ((columns >= 0) & (columns < width))[:, None, :]
    samples = torch.arange(n, device=images.device)[:, None, None]
    shifted = images[samples, rows.clamp(0, height - 1)[:, :, None], columns.clamp(0, width - 1)[:, None, :]]
    return image_batch(shifted * inside[..., None], images.device)


def random_translate(images: torch.Tensor, pad: int) -> torch.Tensor:
    """RIS's augmentation: each image shifted by its own offset, uniform in [-pad, pad]^2 (pad, then a random crop)."""
    return translate(images, torch.randint(-pad, pad + 1, (len(images), 2), device=images.device))


class ImageEpisodeReplay:
    """Whole episodes of uint8 images and 4-d states in a ring of rows: o_0..o_L, then the goal (L + 2 rows). Transition
    t lives in o_t's row with a_t and its episode's last-transition and goal rows; s_t+1 is the next row, so each image
    is stored once (21 KB a row). An episode that would cross the end starts at row 0; an overwritten one leaves a
    suffix with its goal. Images, states and actions stay on `device`; numpy picks the rows."""

    ARRAYS = ("images", "states", "actions", "episode_end", "goal_row", "is_transition")  # what --resume saves
    ON_DEVICE = ("images", "states", "actions")

    def __init__(self, capacity: int, image_shape: tuple, action_dim: int, device: torch.device | str = "cpu"):
        self.capacity, self.device = capacity, torch.device(device)
        self.images = torch.zeros((capacity, *image_shape), dtype=torch.uint8, device=self.device)
        self.states = torch.zeros((capacity, 4), dtype=torch.float32, device=self.device)
        self.actions = torch.zeros((capacity, action_dim), dtype=torch.float32, device=self.device)
        self.episode_end, self.goal_row = np.zeros(capacity, np.int64), np.zeros(capacity, np.int64)  # row numbers
        self.is_transition, self.position, self.size = np.zeros(capacity, bool), 0, 0  # False at the o_L and goal rows

    def add_episode(self, images: np.ndarray, states: np.ndarray, actions: np.ndarray, goal_image, goal_state) -> None:
        """images, states: o_0..o_L (L + 1 rows); actions: a_0..a_L-1."""
        length = len(actions)
        start = self.position if self.position + length + 2 <= self.capacity else 0  # no episode crosses the end
        goal = start + length + 1
        rows = slice(start, goal + 1)  # o_0..o_L and the goal: one copy to the device for each tensor
        self.images[rows] = torch.as_tensor(np.concatenate((images, goal_image[None]))).to(self.device)
        self.states[rows] = torch.as_tensor(np.concatenate((states, goal_state[None]))).to(self.device)
        self.actions[start : start + length] = torch.as_tensor(actions).to(self.device)
        self.is_transition[rows] = np.arange(length + 2) < length
        self.episode_end[rows] = start + length - 1
        self.goal_row[rows] = goal
        self.position = goal + 1
        self.size = max(self.size, self.position)

    def state(self) -> dict:
        """For --resume: the filled rows, host tensors of their own (torch.save writes just those), and the position."""
        rows = {name: getattr(self, name)[: self.size] for name in self.ARRAYS}
        host = {name: row.cpu().numpy() if name in self.ON_DEVICE else row for name, row in rows.items()}
        return {key: torch.from_numpy(row) for key, row in host.items()} | dict(position=self.position, size=self.size)

    def load_state(self, state: dict) -> None:
        self.position, self.size = state["position"], state["size"]
        for name in self.ARRAYS:
            rows = state[name].to(self.device) if name in self.ON_DEVICE else state[name].numpy()
            getattr(self, name)[: self.size] = rows

    def transitions(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """Rows of n transitions, uniform over the stored ones."""
        rows = rng.integers(self.size, size=n)
        while not (valid := self.is_transition[rows]).all():
            rows[~valid] = rng.integers(self.size, size=int((~valid).sum()))
        return rows

    def sample(self, batch_size: int, goal_frac: float, random_frac: float, rng: np.random.Generator) -> dict:
        """A HER batch on the replay's device: images of (s, s', g, s_g) as one (4B, H, W, 3) uint8 tensor, actions,
        states of s, s' and g, rewards (-1), done (s' reaches g). g: the rollout goal (first `goal_frac`), a random
        state (next `random_frac`) or a uniform future s' of the episode; s_g: random states. `rng` draws the rows."""
        index = self.transitions(batch_size, rng)
        n_keep, n_random = round(goal_frac * batch_size), round(random_frac * batch_size)
        future = index[n_keep + n_random :]
        future_rows = future + 1 + (rng.random(len(future)) * (self.episode_end[future] - future + 1)).astype(np.int64)
        goal_rows = np.concatenate((self.goal_row[index[:n_keep]], self.transitions(n_random, rng), future_rows))
        subgoal_rows = self.transitions(batch_size, rng)
        rows = torch.from_numpy(np.concatenate((index, index + 1, goal_rows, subgoal_rows))).to(self.device)
        states, next_states, goal_states, _ = self.states[rows].chunk(4)
        rewards, done = torch.full((batch_size,), -1.0, device=self.device), reached(next_states, goal_states).float()
        batch = dict(images=self.images[rows], actions=self.actions[rows[:batch_size]], rewards=rewards, done=done)
        return batch | dict(states=states, next_states=next_states, goal_states=goal_states)


def reached(states, goals):
    """The success test, max(hand distance, puck distance) < 0.05, on (..., 4) arrays or tensors of (hand xy, puck
    xy): norms computed as numpy's norm does (sum of squares, then square root), so both agree bit for bit."""
    difference = states - goals
    hand = (difference[..., :2] * difference[..., :2]).sum(-1) ** 0.5
    puck = (difference[..., 2:] * difference[..., 2:]).sum(-1) ** 0.5
    return (hand < SUCCESS_DISTANCE) & (puck < SUCCESS_DISTANCE)


# --- Losses, the update, and acting -----------------------------------------------------------------------------------


def local_global_infonce(local: torch.Tensor, global_: torch.Tensor) -> torch.Tensor:
    """InfoNCE of each local vector of sample b (local: (B, P, D)) against the batch's global vectors (global_: (B, D)):
    dot-product scores, (b, b) the positive pair; the mean cross-entropy (log B when the features say nothing)."""
    batch, positions, _ = local.shape
    scores = torch.einsum("bpd,kd->bpk", local, global_).reshape(batch * positions, batch)
    return F.cross_entropy(scores, torch.arange(batch, device=local.device).repeat_interleave(positions))


def driml_loss(heads: DrimlHeads, conv_map, actions, next_features) -> torch.Tensor:
    """DRIML's local-global loss: each position of s_t's conv map (B, C, H, W), with a_t, picks out s_t+1's features."""
    local = conv_map.flatten(2).transpose(1, 2)  # (B, H * W, C)
    local = torch.cat((local, actions.unsqueeze(1).expand(-1, local.shape[1], -1)), -1)
    return local_global_infonce(heads.local(local), heads.globl(next_features))


def advantage_weights(distance_proposed, distance_candidates, temperature: float) -> torch.Tensor:
    """softmax over the batch of (D(proposed subgoal) - D(candidate)) / lambda: the better candidates weigh more."""
    return F.softmax((distance_proposed - distance_candidates) / temperature, dim=0)


def subgoal_cost(values_to_subgoal: torch.Tensor, values_from_subgoal: torch.Tensor) -> torch.Tensor:
    """D(s_g) = max(|clip(V(s, s_g), -100, 0)|, |clip(V(s_g, g), -100, 0)|): the longer of the two halves."""
    return torch.maximum(values_to_subgoal.clamp(-100.0, 0.0).abs(), values_from_subgoal.clamp(-100.0, 0.0).abs())


def prior_kl(actions_pre_tanh, mean, std, prior_mean, prior_std, epsilon: float) -> torch.Tensor:
    """Single-sample KL(pi || prior) at u (B, A): log N(u; mu, sigma) - log(mean_k N(u; mu_k, sigma_k) + epsilon), the
    prior (K, B, A) from the target actor at K imagined subgoals; logsumexp, so tiny densities do not underflow."""
    normal = partial(torch.distributions.Normal, validate_args=False)
    log_policy = normal(mean, std).log_prob(actions_pre_tanh).sum(-1)
    log_prior = normal(prior_mean, prior_std).log_prob(actions_pre_tanh[None]).sum(-1)
    log_terms = torch.cat((log_prior - math.log(len(log_prior)), torch.full_like(log_prior[:1], math.log(epsilon))))
    return log_policy - torch.logsumexp(log_terms, dim=0)


def learn(optimizer: torch.optim.Optimizer, loss: torch.Tensor, max_grad_norm: float | None = None) -> None:
    """One step on `loss`: clear the gradients, backpropagate, clip their norm to `max_grad_norm` if given, step."""
    optimizer.zero_grad()
    loss.backward()
    if max_grad_norm is not None:
        params = [param for group in optimizer.param_groups for param in group["params"]]
        torch.nn.utils.clip_grad_norm_(params, max_grad_norm, foreach=True)
    optimizer.step()


def ris_update(agent: Agent, batch: dict, args: Args) -> dict[str, torch.Tensor]:
    """One RIS update from pixels with DGRL's bottleneck, on ImageEpisodeReplay.sample's batch; free of host syncs."""
    actions, rewards, done = batch["actions"], batch["rewards"], batch["done"]
    batch_size = len(actions)

    # Augmented s, s', g, s_g: RIS encodes s alone with gradient; DGRL's snippet also s', g, s_g for their commitment
    # losses (RIS's losses see them detached). No target encoder (RIS): the target critic and DRIML see s' online.
    images = random_translate(batch["images"], args.image_pad)
    if agent.vq is not None and args.vq_commitment_grad == "all":  # DGRL: one pass over the four, all with gradient
        conv_maps = agent.encoder.conv_map(images)
        conv_map, features = conv_maps[:batch_size], agent.encoder.head(conv_maps)
        state_z = features[:batch_size]
        next_z, goal_z, subgoal_z = features[batch_size:].detach().chunk(3)  # DGRL: RIS's losses see them detached
    else:
        conv_map = agent.encoder.conv_map(images[:batch_size])
        state_z = agent.encoder.head(conv_map)
        with torch.no_grad():
            next_z, goal_z, subgoal_z = agent.encoder(images[batch_size:]).chunk(3)
        features = torch.cat((state_z, next_z, goal_z, subgoal_z)) if agent.vq is not None else None  # DGRL
    driml = driml_loss(agent.driml_heads, conv_map, actions, next_z)
    representation_loss = args.driml_coef * driml
    goal_in, metrics = goal_z, {}  # goal_in: what the actor and the critics see of the goal
    if agent.vq is not None:
        z_q, vq_loss, codes = agent.vq(features, update=True)  # DGRL: the four in one call, one EMA step
        goal_in = z_q[2 * batch_size : 3 * batch_size].detach()  # DGRL: the nets see the discrete goal embedding
        representation_loss = representation_loss + combined_commitment_loss(vq_loss, 4, args.vq_loss_reduction)  # DGRL
        metrics = dict(vq_loss=vq_loss, codes=codes)

    # Critic (policy evaluation); its loss also trains the encoder, the DRIML heads (and, under DGRL, commits to codes).
    with torch.no_grad():
        next_actions = agent.actor.sample(next_z, goal_in)  # DGRL: z_q(g), detached
        next_q = agent.critic_target(next_z, next_actions, goal_in).min(0).values  # DGRL: z_q(g), detached
        target_q = rewards + (1.0 - done) * args.gamma * next_q
    q_values = agent.critic(state_z, actions, goal_in)  # DGRL: z_q(g), detached
    critic_loss = 0.5 * (q_values - target_q).pow(2).sum(0).mean()
    learn(agent.critic_optimizer, critic_loss + representation_loss)
    state_z = state_z.detach()

    # High level: advantage-weighted regression onto the features of random replay states.
    subgoal_distribution = agent.high.laplace(state_z, goal_z)
    proposed = subgoal_distribution.loc.detach()
    with torch.no_grad():
        value_states = torch.cat((state_z, subgoal_z, state_z, proposed))  # V(s, s_g), V(s_g, g), V(s, p), V(p, g)
        value_goals = goal_input(agent.vq, torch.cat((subgoal_z, goal_z, proposed, goal_z)))  # DGRL: z_q(y) of V(x, y)
        value_actions = torch.tanh(agent.actor(value_states, value_goals)[0])  # DGRL: z_q(y)
        values = agent.critic(value_states, value_actions, value_goals).min(0).values.view(4, -1)  # DGRL: z_q(y)
        weights = advantage_weights(subgoal_cost(*values[2:]), subgoal_cost(*values[:2]), args.h_lambda)
    high_loss = -(weights * subgoal_distribution.log_prob(subgoal_z).sum(-1)).mean()
    learn(agent.high_optimizer, high_loss)

    # Actor: maximise Q with a KL penalty towards the target actor averaged over imagined subgoals.
    with torch.no_grad():
        imagined = goal_input(agent.vq, agent.high.laplace(state_z, goal_z).sample((args.n_subgoals,)))  # DGRL: z_q
        prior_mean, prior_std = agent.actor_target(state_z.expand(args.n_subgoals, -1, -1), imagined)  # DGRL: z_q(s_g)
    mean, std = agent.actor(state_z, goal_in)  # DGRL: z_q(g), detached
    actions_pre_tanh = mean + std * torch.randn_like(mean)
    kl = prior_kl(actions_pre_tanh, mean, std, prior_mean, prior_std, args.prior_epsilon)
    actor_q = agent.critic(state_z, torch.tanh(actions_pre_tanh), goal_in).min(0).values  # DGRL: z_q(g), detached
    actor_loss = (args.alpha * kl - actor_q).mean()
    learn(agent.actor_optimizer, actor_loss)

    update_target(agent.critic_target, agent.critic, args.tau)
    update_target(agent.actor_target, agent.actor, args.tau)
    metrics.update(critic_loss=critic_loss, driml_loss=driml, high_loss=high_loss, actor_loss=actor_loss, kl=kl.mean())
    metrics.update(q_values=q_values.mean(), high_weight_max=weights.max())
    return {name: value.detach() for name, value in metrics.items()}


@torch.no_grad()
def act(agent: Agent, observations: dict, device, deterministic: bool) -> np.ndarray:
    """Actions for a batch of observations: the un-augmented state and goal images through the encoder."""
    features = agent.encoder(image_batch(np.concatenate((observations["image"], observations["goal_image"])), device))
    state_z, goal_z = features.chunk(2)
    goal_in = goal_input(agent.vq, goal_z)  # DGRL: the goal quantized, no codebook update
    if deterministic:
        return torch.tanh(agent.actor(state_z, goal_in)[0]).cpu().numpy()  # DGRL: z_q(g)
    return agent.actor.sample(state_z, goal_in).cpu().numpy()  # DGRL: z_q(g)


# --- The run: setup, the training loop, the end; evaluation -----------------------------------------------------------


def main(args: Args) -> None:
    """Train RIS (--groups 0) or DGRL on Sawyer push-and-reach from pixels, or evaluate a --checkpoint and exit."""
    validate(args)
    run_name = f"SawyerPushAndReach__G{args.groups}__{args.exp_name}__{args.seed}__{int(time.time())}"
    if args.resume is not None:
        run_name = os.path.basename(os.path.normpath(args.resume))
        hold_run_folder(run_name, check_only=True)  # a run still running elsewhere: exit 2 at once, touching nothing
    resumed = None if args.resume is None else load_resume(args)
    device = seed_and_device(args)
    must_match = MUST_MATCH + (DGRL_MUST_MATCH if args.groups > 0 else ())
    saved = None if args.checkpoint is None else load_checkpoint(args.checkpoint, args, must_match, device)
    rng = np.random.default_rng(args.seed)  # replay sampling
    stop = stop_on_signals()  # from here on Ctrl-C or SIGTERM ends the run cleanly (rc 0), at the next check of `stop`

    envs = make_vector_env(args.num_envs, args.seed, test=False)
    eval_envs = make_vector_env(args.eval_episodes, args.seed + 10_000, test=True)
    try:  # the first render: a renderer that cannot start is refused here, before any work
        eval_envs.reset(seed=args.seed + 10_000)  # one evaluation stream per run, continued across evaluations
    except RenderingError as error:
        exit_on_errors([str(error)])
    image_shape, action_dim = envs.single_observation_space["image"].shape, envs.single_action_space.shape[0]
    agent = make_agent(image_shape[0], action_dim, args, device)

    if saved is not None:  # --checkpoint: evaluate the saved networks and exit
        return evaluate_checkpoint(saved, agent, eval_envs, device, stop, args, run_name)

    replay = ImageEpisodeReplay(args.buffer_size, image_shape, action_dim, device)
    episode = {key: [[] for _ in range(args.num_envs)] for key in ("images", "states", "actions")}
    loop = LoopState(envs.reset(seed=args.seed)[0], episode, next_eval=args.eval_frequency)
    if resumed is not None:  # continue where the stopped run's resume.pt left off: every piece of state, then the RNGs
        loop = restore_training_state(resumed, agent, replay, envs, eval_envs, rng)

    _lock = hold_run_folder(run_name)  # one process writes a run folder, from its first write to its end
    writer = make_writer(args, run_name, purge_step=None if resumed is None else loop.step + 1)
    about = f"{image_shape} images, {args.feature_dim}-d features, {args.total_timesteps} steps, device {device}"
    print(f"{run_name}: {about}" + ("" if resumed is None else f", resumed at step {loop.step}"))
    if device.type == "cpu" and args.batch_size >= 128:
        print(f"note: --batch-size {args.batch_size} takes 0.5-1 s an update on a CPU; see the docstring's CPU preset")
    update = fast_update(ris_update, args.fast, [agent.critic_optimizer, agent.high_optimizer, agent.actor_optimizer])
    progress = Progress(args.total_timesteps, start_step=loop.step)
    checkpoint_path = f"runs/{run_name}/{args.exp_name}.cleanrl_model"
    if resumed is not None:
        rng_states(restore=resumed["rng"])  # last: building the run above drew from them
    while not loop.finished and not stop:
        # Evaluate when due and at the end, first in the loop: a run stopped mid-evaluation resumes with it.
        if loop.step >= loop.next_eval or loop.step >= args.total_timesteps:
            video = [] if args.capture_video and loop.evaluations % 10 == 0 else None
            eval_envs_before, rngs_before = vector_env_state(eval_envs), rng_states()
            result = evaluate(eval_envs, agent, device, args.eval_deterministic, video, stop)
            if result is None:  # stopped mid-evaluation: nothing logged, and its draws undone for the resumed run
                set_vector_env_state(eval_envs, eval_envs_before)
                rng_states(restore=rngs_before)
                break
            loop.next_eval += args.eval_frequency
            loop.result = result
            loop.evaluations += 1
            for name, value in result.items():
                writer.add_scalar(f"eval/{name}", value, loop.step)
            writer.add_scalar("charts/SPS", progress.sps(loop.step), loop.step)
            train_success = f"{np.mean(loop.recent_success):4.0%}" if loop.recent_success else "   -"  # none finished
            loop.recent_success = []
            success = f"eval success {result['success_rate']:4.0%} hand {result['hand_success_rate']:4.0%}"
            distance = f"distance hand {result['final_hand_distance']:.3f} puck {result['final_puck_distance']:.3f}"
            progress.line(loop.step, f"{success}  {distance}  train success {train_success}")
            if video:
                write_video(f"videos/{run_name}/eval_{loop.step}.mp4", video, fps=RENDER_FPS)
            if args.save_model:
                save_checkpoint(checkpoint_path, agent.state_dicts(), args)
        if loop.step >= args.total_timesteps:
            loop.finished = True
            break
        if progress.resume_due(loop.step, args.checkpoint_every, args.checkpoint_every_steps):  # every figure is logged
            save_resume(run_name, training_state(agent, replay, envs, eval_envs, rng, loop), args)

        observations, episode = loop.observations, loop.episode
        if loop.step < args.start_timesteps:
            actions = envs.action_space.sample()
        else:
            actions = act(agent, observations, device, deterministic=False)
        loop.observations, _, terminations, truncations, infos = envs.step(actions)
        loop.step += args.num_envs

        # Stage each env's step; a finished episode goes to the replay whole, with its true last observation and goal.
        for env in range(args.num_envs):
            episode["images"][env].append(observations["image"][env])
            episode["states"][env].append(observations["state"][env])
            episode["actions"][env].append(actions[env])
            if terminations[env] or truncations[env]:
                last, final_info = infos["final_obs"][env], infos["final_info"]
                episode["images"][env].append(last["image"])
                episode["states"][env].append(last["state"])
                arrays = [np.stack(episode[key][env]) for key in ("images", "states", "actions")]
                replay.add_episode(*arrays, observations["goal_image"][env], observations["goal"][env])
                for key in episode:
                    episode[key][env] = []
                loop.recent_success.append(float(terminations[env]))
                writer.add_scalar("charts/episodic_return", final_info["episode"]["r"][env], loop.step)
                writer.add_scalar("charts/episodic_length", final_info["episode"]["l"][env], loop.step)
                writer.add_scalar("charts/success_rate", float(terminations[env]), loop.step)
                writer.add_scalar("charts/hand_distance", final_info["hand_distance"][env], loop.step)
                writer.add_scalar("charts/puck_distance", final_info["puck_distance"][env], loop.step)

        # Train: one update per environment step once the random phase is over.
        if loop.step >= max(args.start_timesteps, args.batch_size) and replay.size >= args.batch_size:
            for _ in range(args.num_envs):
                batch = replay.sample(args.batch_size, args.her_goal_frac, args.her_random_frac, rng)
                metrics = update(agent, batch, args)
                loop.updates += 1
            if loop.updates >= loop.next_log:
                loop.next_log += 100
                losses = ("critic_loss", "actor_loss", "high_loss", "driml_loss", "kl", "q_values", "high_weight_max")
                for name in losses:
                    writer.add_scalar(f"losses/{name}", metrics[name].item(), loop.step)
                if agent.vq is not None:  # the codebook's statistics
                    writer.add_scalar("vq/commit_loss", metrics["vq_loss"].item(), loop.step)
                    writer.add_scalar("vq/perplexity", perplexity(metrics["codes"], args.n_embed).item(), loop.step)
                    writer.add_scalar("vq/active_codes", active_codes(metrics["codes"], args.n_embed).item(), loop.step)
        progress.line(loop.step, f"{loop.updates} updates", heartbeat=True)

    save_resume(run_name, training_state(agent, replay, envs, eval_envs, rng, loop), args)
    if args.save_model:
        save_checkpoint(checkpoint_path, agent.state_dicts(), args)
        print(f"checkpoint: {checkpoint_path}")
    summary = f"last eval success {loop.result['success_rate']:.0%} (hand {loop.result['hand_success_rate']:.0%})"
    progress.finish(bool(stop), run_name, f"{loop.step} steps, {loop.updates} updates, {summary}")
    envs.close()
    eval_envs.close()
    writer.close()


def evaluate(envs, agent: Agent, device, deterministic: bool, frames: list | None = None, stop=()) -> dict | None:
    """One test episode per env: EVAL_METRICS (hand success: the hand alone at its goal); None if `stop` fills first."""
    observations, _ = envs.reset()
    finished, (success, hand, puck) = np.zeros(envs.num_envs, dtype=bool), np.zeros((3, envs.num_envs))
    while not finished.all():
        if stop:
            return None
        if frames is not None and not finished[0]:  # the state image beside the goal image, upscaled 3x
            frame = np.concatenate((observations["image"][0], observations["goal_image"][0]), 1)
            frames.append(frame.repeat(3, 0).repeat(3, 1))
        actions = act(agent, observations, device, deterministic)
        observations, _, terminations, truncations, infos = envs.step(actions)
        ended = (terminations | truncations) & ~finished
        for env in np.flatnonzero(ended):
            hand[env] = infos["final_info"]["hand_distance"][env]
            puck[env] = infos["final_info"]["puck_distance"][env]
            success[env] = terminations[env]
        finished |= ended
    figures = success.mean(), (hand < SUCCESS_DISTANCE).mean(), hand.mean(), puck.mean()
    return dict(zip(EVAL_METRICS, figures, strict=True))


def evaluate_checkpoint(saved: dict, agent: Agent, eval_envs, device, stop, args: Args, run_name: str) -> None:
    """--checkpoint: evaluate the saved networks on --eval-episodes test episodes (a video with --capture-video)."""
    agent.load_state_dicts(saved)
    video = [] if args.capture_video else None
    result = evaluate(eval_envs, agent, device, args.eval_deterministic, video, stop)
    if result is None:
        print("stopped before every test episode ended")
        return
    hand, puck = result["final_hand_distance"], result["final_puck_distance"]
    success = f"success {result['success_rate']:.0%}, hand success {result['hand_success_rate']:.0%}"
    distances = f"final hand distance {hand:.3f}, final puck distance {puck:.3f}"
    print(f"{args.eval_episodes} test episodes: {success}, {distances}")
    if video:
        write_video(f"videos/{run_name}/checkpoint_eval.mp4", video, fps=RENDER_FPS)


def write_video(path: str, frames: list[np.ndarray], fps: int) -> None:
    """Frames (H, W, 3) uint8 to an mp4 (moviepy loaded only here), one encoder thread: with more, the bytes vary."""
    os.makedirs(os.path.dirname(path), exist_ok=True)
    importlib.import_module("moviepy").ImageSequenceClip(frames, fps=fps).write_videofile(path, logger=None, threads=1)


# --- Environments -----------------------------------------------------------------------------------------------------

ARENA_LOW, ARENA_HIGH = np.array((-0.2, 0.5)), np.array((0.2, 0.7))  # bounds of the hand's and the puck's centres (xy)
HAND_Z, HAND_RADIUS = 0.06, 0.015  # the end effector moves at this fixed height
PUCK_RADIUS, PUCK_HALF_HEIGHT = 0.04, 0.015
WALL_HALF_THICKNESS, WALL_HALF_HEIGHT = 0.01, 0.02
PUCK_RING = (0.055, 0.075)  # training resets put the puck at this distance from the hand
GOAL_CLEARANCE = PUCK_RADIUS + HAND_RADIUS  # training goals keep the hand and the puck this far apart (0.055)
TEST_BOXES = {  # (low xy, high xy) of the test configuration's uniform draws
    "hand_start": ((0.15, 0.65), (0.20, 0.70)), "puck_start": ((-0.15, 0.55), (-0.10, 0.60)),
    "hand_goal": ((-0.20, 0.50), (-0.15, 0.55)), "puck_goal": ((0.15, 0.65), (0.20, 0.70)),
}  # fmt: skip
SUCCESS_DISTANCE, EPISODE_STEPS = 0.05, 100  # success: hand and puck this close to their goals; truncation
TIMESTEP, FRAME_SKIP, RENDER_FPS = 0.002, 50, 10  # 0.1 s per env step: videos at 10 frames/s
CAMERA_HEIGHT = 0.65  # the top camera's height: its 45-degree field of view spans 0.54 m, the arena and its walls
INTEGRATION = mujoco.mjtState.mjSTATE_INTEGRATION  # what mj_getState saves for an exact restore
EPISODE_STATISTICS = ("episode_returns", "episode_lengths", "episode_count")  # RecordEpisodeStatistics' running figures


def sawyer_xml() -> str:
    """The scene: a table at z = 0, four walls whose inner faces stop the puck's centre at the arena's bounds, a puck
    and an end effector (a vertical capsule) on two slide joints each, the hand welded to a mocap body, a camera above;
    qpos = (hand xy, puck xy) in world coordinates. The puck cannot tip, fly or touch the table: dry friction on its
    joints stands in for the table's, so it stops when no longer pushed. Contacts and the hand's joint limits are much
    stiffer than the weld: the puck yields to the hand, and walls hold a puck pressed on them (by default: 1 cm past).
    No shadows: 3x faster software rendering. The weld's relpose is given (identity), not inferred from the bodies."""
    cx, cy = (ARENA_LOW + ARENA_HIGH) / 2
    half_x, half_y = (ARENA_HIGH - ARENA_LOW) / 2 + PUCK_RADIUS  # the half-extents inside the walls
    t, h, grey = WALL_HALF_THICKNESS, WALL_HALF_HEIGHT, "0.45 0.45 0.5 1"
    return f"""<mujoco model="sawyer_push_and_reach">
  <option timestep="{TIMESTEP}"/>
  <visual>
    <quality shadowsize="0"/>
    <headlight ambient="0.5 0.5 0.5" diffuse="0.5 0.5 0.5" specular="0 0 0"/>
  </visual>
  <default>
    <geom solref="0.004 1" solimp="0.99 0.999 0.001"/>
    <joint solreflimit="0.004 1" solimplimit="0.99 0.999 0.001"/>
  </default>
  <worldbody>
    <geom name="table" type="plane" pos="{cx} {cy} 0" size="{half_x + 0.2} {half_y + 0.2} 0.01" rgba="0.9 0.88 0.82 1"
          contype="0" conaffinity="0"/>
    <geom name="wall_left" type="box" pos="{cx - half_x - t} {cy} {h}" size="{t} {half_y + 2 * t} {h}" rgba="{grey}"/>
    <geom name="wall_right" type="box" pos="{cx + half_x + t} {cy} {h}" size="{t} {half_y + 2 * t} {h}" rgba="{grey}"/>
    <geom name="wall_near" type="box" pos="{cx} {cy - half_y - t} {h}" size="{half_x} {t} {h}" rgba="{grey}"/>
    <geom name="wall_far" type="box" pos="{cx} {cy + half_y + t} {h}" size="{half_x} {t} {h}" rgba="{grey}"/>
    <camera name="top" pos="{cx} {cy} {CAMERA_HEIGHT}" xyaxes="1 0 0 0 1 0"/>
    <body name="hand_target" mocap="true" pos="{cx} {cy} {HAND_Z}"/>
    <body name="hand" pos="0 0 {HAND_Z}">
      <joint name="hand_x" type="slide" axis="1 0 0" limited="true" range="{ARENA_LOW[0]} {ARENA_HIGH[0]}"/>
      <joint name="hand_y" type="slide" axis="0 1 0" limited="true" range="{ARENA_LOW[1]} {ARENA_HIGH[1]}"/>
      <geom name="hand" type="capsule" fromto="0 0 {PUCK_HALF_HEIGHT - HAND_Z} 0 0 0" size="{HAND_RADIUS}" mass="0.1"
            rgba="0.85 0.1 0.1 1"/>
    </body>
    <body name="puck" pos="0 0 {PUCK_HALF_HEIGHT}">
      <joint name="puck_x" type="slide" axis="1 0 0" frictionloss="0.3" damping="0.5"/>
      <joint name="puck_y" type="slide" axis="0 1 0" frictionloss="0.3" damping="0.5"/>
      <geom name="puck" type="cylinder" size="{PUCK_RADIUS} {PUCK_HALF_HEIGHT}" mass="0.1" rgba="0.1 0.35 0.9 1"/>
    </body>
  </worldbody>
  <equality>
    <weld name="hand_to_target" body1="hand_target" body2="hand" relpose="0 0 0 1 0 0 0" solref="0.02 1"/>
  </equality>
</mujoco>"""


class RenderingError(RuntimeError):
    """MuJoCo's off-screen renderer could not start (the MUJOCO_GL backend is missing or has no display)."""


class SawyerPushAndReachEnv(gym.Env):
    """multiworld's Sawyer push-and-reach (xy) task on `mujoco`, the arm replaced by its end effector. As in the
    original, an action in [-1, 1]^2 moves the hand's mocap target by action * action_scale (clipped to the arena), then
    FRAME_SKIP physics steps: the hand tracks the target and pushes the puck. The original's slanted camera cuts off the
    arena's sides at 84 x 84 (the docs' deviations): a camera straight above takes the images. Observation: Dict(image,
    state = (hand xy, puck xy), goal_image, goal). Reward -1 a step (RIS); terminated on success (`reached`), truncated
    after EPISODE_STEPS. Resets: uniform draws (training: PUCK_RING, GOAL_CLEARANCE; test: TEST_BOXES)."""

    metadata: ClassVar[dict] = {"render_modes": ["rgb_array"], "render_fps": RENDER_FPS}

    def __init__(self, test: bool = False, image_size: int = IMAGE_SIZE, action_scale: float = 0.02, render_mode=None):
        self.test, self.image_size, self.action_scale, self.render_mode = test, image_size, action_scale, render_mode
        self.model = mujoco.MjModel.from_xml_string(sawyer_xml())
        self.data = mujoco.MjData(self.model)
        image = gym.spaces.Box(0, 255, (image_size, image_size, 3), np.uint8)
        walls = np.tile(ARENA_LOW - PUCK_RADIUS, 2), np.tile(ARENA_HIGH + PUCK_RADIUS, 2)  # no centre gets past them
        state = gym.spaces.Box(walls[0].astype(np.float32), walls[1].astype(np.float32), (4,), np.float32)
        self.observation_space = gym.spaces.Dict(image=image, state=state, goal_image=image, goal=state)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.goal, self.goal_image = np.zeros(4, np.float32), np.zeros((image_size, image_size, 3), np.uint8)
        self.steps, self._renderer = 0, None

    def set_state4(self, state4: np.ndarray) -> None:
        """Put the hand and the puck at rest at (hand xy, puck xy), with the mocap target on the hand."""
        self.data.qpos[:4] = state4
        self.data.qvel[:] = 0.0
        self.data.mocap_pos[0] = (state4[0], state4[1], HAND_Z)
        mujoco.mj_forward(self.model, self.data)

    def render_state(self, state4: np.ndarray) -> np.ndarray:
        """An image of the configuration state4; the simulation's state is restored exactly afterwards."""
        snapshot = self.snapshot()
        self.set_state4(state4)
        image = self.render()
        self.restore(snapshot)
        return image

    def _training_start(self) -> np.ndarray:
        hand = self.np_random.uniform(ARENA_LOW, ARENA_HIGH)
        while True:
            angle, radius = self.np_random.uniform(0.0, 2 * np.pi), self.np_random.uniform(*PUCK_RING)
            puck = hand + radius * np.array((np.cos(angle), np.sin(angle)))
            if np.all(puck >= ARENA_LOW) and np.all(puck <= ARENA_HIGH):
                return np.concatenate((hand, puck))

    def _training_goal(self) -> np.ndarray:
        while True:
            hand, puck = self.np_random.uniform(ARENA_LOW, ARENA_HIGH), self.np_random.uniform(ARENA_LOW, ARENA_HIGH)
            if np.linalg.norm(hand - puck) > GOAL_CLEARANCE:
                return np.concatenate((hand, puck))

    def _info(self, state: np.ndarray) -> dict:
        hand_distance = float(np.linalg.norm(state[:2] - self.goal[:2]))
        puck_distance = float(np.linalg.norm(state[2:] - self.goal[2:]))
        success = max(hand_distance, puck_distance) < SUCCESS_DISTANCE
        return {"success": success, "hand_distance": hand_distance, "puck_distance": puck_distance}

    def _observe(self) -> tuple[dict, dict]:
        state = self.data.qpos[:4].astype(np.float32)
        observation = dict(image=self.render(), state=state, goal_image=self.goal_image.copy(), goal=self.goal.copy())
        return observation, self._info(state)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        mujoco.mj_resetData(self.model, self.data)
        if self.test:
            box, uniform = TEST_BOXES, self.np_random.uniform
            start = np.concatenate((uniform(*box["hand_start"]), uniform(*box["puck_start"])))
            goal = np.concatenate((uniform(*box["hand_goal"]), uniform(*box["puck_goal"])))
        else:
            start, goal = self._training_start(), self._training_goal()
        self.goal = goal.astype(np.float32)
        self.set_state4(start)
        self.goal_image = self.render_state(self.goal)
        self.steps = 0
        return self._observe()

    def step(self, action):
        delta = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0) * self.action_scale
        self.data.mocap_pos[0, :2] = np.clip(self.data.mocap_pos[0, :2] + delta, ARENA_LOW, ARENA_HIGH)
        mujoco.mj_step(self.model, self.data, nstep=FRAME_SKIP)
        self.steps += 1
        observation, info = self._observe()
        return observation, -1.0, info["success"], self.steps >= EPISODE_STEPS, info

    def snapshot(self) -> dict:
        """For --resume: MuJoCo's integration state, the goal and its image, the step count, the reset generator."""
        physics = np.empty(mujoco.mj_stateSize(self.model, INTEGRATION))
        mujoco.mj_getState(self.model, self.data, physics, INTEGRATION)
        goal = {"goal": self.goal.copy(), "goal_image": self.goal_image.copy(), "steps": self.steps}
        return goal | {"physics": physics, "np_random": self.np_random.bit_generator.state}

    def restore(self, saved: dict) -> None:
        mujoco.mj_setState(self.model, self.data, saved["physics"], INTEGRATION)
        mujoco.mj_forward(self.model, self.data)
        self.goal, self.goal_image, self.steps = saved["goal"].copy(), saved["goal_image"].copy(), saved["steps"]
        self.np_random.bit_generator.state = saved["np_random"]

    def render(self) -> np.ndarray:
        """The current state as an image_size x image_size RGB array."""
        if self._renderer is None:
            try:
                self._renderer = mujoco.Renderer(self.model, self.image_size, self.image_size)
            except mujoco.FatalError as error:
                backend = os.environ.get("MUJOCO_GL", "the default")
                advice = "try MUJOCO_GL=egl or osmesa"
                raise RenderingError(f"off-screen rendering failed (MUJOCO_GL={backend}): {advice}") from error
            self._renderer.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0
        self._renderer.update_scene(self.data, camera="top")
        return self._renderer.render()

    def close(self):
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


def make_env(seed: int, test: bool) -> gym.Env:
    env = gym.wrappers.RecordEpisodeStatistics(SawyerPushAndReachEnv(test=test))
    env.action_space.seed(seed)
    return env


def make_vector_env(n: int, seed: int, test: bool) -> gym.vector.SyncVectorEnv:
    thunks = [partial(make_env, seed + i, test) for i in range(n)]
    return gym.vector.SyncVectorEnv(thunks, autoreset_mode=gym.vector.AutoresetMode.SAME_STEP)


def vector_env_state(envs: gym.vector.SyncVectorEnv) -> dict:
    """For --resume: each env's snapshot, action-space generator and episode statistics, and the batched action space's
    generator (pickling an env would rebuild it from its constructor). SAME_STEP autoreset keeps nothing else."""
    per_env = [
        {"env": env.unwrapped.snapshot(), "action_space": env.action_space.np_random.bit_generator.state}
        | {name: getattr(env, name) for name in EPISODE_STATISTICS}
        for env in envs.envs
    ]
    return {"envs": per_env, "action_space": envs.action_space.np_random.bit_generator.state}


def set_vector_env_state(envs: gym.vector.SyncVectorEnv, state: dict) -> None:
    for env, saved in zip(envs.envs, state["envs"], strict=True):
        env.unwrapped.restore(saved["env"])
        env.action_space.np_random.bit_generator.state = saved["action_space"]
        for name in EPISODE_STATISTICS:
            setattr(env, name, saved[name])
    envs.action_space.np_random.bit_generator.state = state["action_space"]


# --- Resume: the loop's state and everything else a run needs to continue exactly -------------------------------------

EVAL_METRICS = ("success_rate", "hand_success_rate", "final_hand_distance", "final_puck_distance")  # evaluate's result


@dataclass
class LoopState:
    """The variables the training loop carries from one step to the next."""

    observations: dict  # the envs' last observations
    episode: dict  # the episodes in progress: images, states and actions, one list per env
    step: int = 0
    updates: int = 0
    evaluations: int = 0
    next_eval: int = 0
    next_log: int = 1  # losses every 100 updates, from the first
    recent_success: list = field(default_factory=list)  # training episodes' successes since the last evaluation
    result: dict = field(default_factory=lambda: dict.fromkeys(EVAL_METRICS, float("nan")))  # the last evaluation
    finished: bool = False  # the last evaluation is done


def training_state(agent: Agent, replay: ImageEpisodeReplay, envs, eval_envs, rng, loop: LoopState) -> dict:
    """Everything a run needs to continue exactly but the flags and global random states (save_resume adds them); the
    loop's variables as a plain dict, so that a run started as __main__ resumes imported."""
    agent_state = agent.state_dicts() | {name: getattr(agent, name).state_dict() for name in agent.TRAINING_ONLY}
    environments = {"envs": vector_env_state(envs), "eval_envs": vector_env_state(eval_envs)}
    loop_state = {"replay_rng": rng.bit_generator.state, "loop": copy.deepcopy(vars(loop))}
    return {"agent": agent_state, "replay": replay.state()} | environments | loop_state


def restore_training_state(saved: dict, agent: Agent, replay: ImageEpisodeReplay, envs, eval_envs, rng) -> LoopState:
    """Put training_state's pieces back into a freshly built run; returns the loop's state."""
    agent.load_state_dicts(saved["agent"])
    for name in agent.TRAINING_ONLY:
        getattr(agent, name).load_state_dict(saved["agent"][name])
    replay.load_state(saved["replay"])
    set_vector_env_state(envs, saved["envs"])
    set_vector_env_state(eval_envs, saved["eval_envs"])
    rng.bit_generator.state = saved["replay_rng"]
    return LoopState(**saved["loop"])


MUST_MATCH = ("feature_dim", "hidden_dim", "driml_dim", "groups")  # what shapes a checkpoint's networks (env: fixed)
DGRL_MUST_MATCH = ("n_embed",)  # the codebook's size, which matters only under --groups > 0


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
    """Refuse bad flags before any work: each message names the flag and the valid values; exit status 2."""
    errors = common_errors(args)
    errors += range_errors(args, "start_timesteps driml_coef", 0)
    errors += range_errors(args, "image_pad", 0, IMAGE_SIZE - 1)  # a larger shift leaves none of the image's content
    errors += range_errors(args, "total_timesteps num_envs buffer_size batch_size hidden_dim n_subgoals", 1)
    errors += range_errors(args, "feature_dim driml_dim eval_frequency eval_episodes", 1)
    errors += range_errors(args, "q_lr actor_lr h_lr encoder_lr alpha h_lambda prior_epsilon", 0, low_open=True)
    errors += range_errors(args, "gamma tau", 0, 1, low_open=True)
    if args.vq_loss_reduction not in ("mean", "sum"):
        choices = "mean (the paper's text) or sum (the paper's snippet)"
        errors.append(f"--vq-loss-reduction must be {choices}; got {args.vq_loss_reduction!r}")
    if args.vq_commitment_grad not in ("all", "state"):
        choices = "all (s, s', g and s_g, the paper's snippet) or state (s only, RIS's stop-gradient)"
        errors.append(f"--vq-commitment-grad must be {choices}; got {args.vq_commitment_grad!r}")
    if args.feature_dim >= 1 and (args.groups < 0 or (args.groups and args.feature_dim % args.groups)):
        divisors = [g for g in range(1, args.feature_dim + 1) if args.feature_dim % g == 0]
        choices = f"0 (RIS) or divide --feature-dim {args.feature_dim}: one of {divisors}"
        errors.append(f"--groups must be {choices}; got {args.groups}")
    if not (0 <= args.her_goal_frac and 0 <= args.her_random_frac and args.her_goal_frac + args.her_random_frac <= 1):
        fractions = f"--her-goal-frac ({args.her_goal_frac}) and --her-random-frac ({args.her_random_frac})"
        errors.append(f"{fractions} must be >= 0 with a sum <= 1 (the rest are future goals)")
    # An episode that does not fit restarts at row 0: the replay surely fills to a batch only with room for one more.
    need_rows = args.batch_size + EPISODE_STEPS + 1
    if args.buffer_size >= 1 and args.buffer_size < need_rows:
        rows = f"(whole episodes of up to {EPISODE_STEPS + 2} rows, and a batch besides); got {args.buffer_size}"
        errors.append(f"--buffer-size must be >= --batch-size + {EPISODE_STEPS + 1} = {need_rows} {rows}")
    row_bytes = IMAGE_SIZE * IMAGE_SIZE * 3 + 4 * 4 + 4 * 2 + 8 + 8 + 1  # image, state, action, two row indices, flag
    memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") if hasattr(os, "sysconf") else math.inf
    if args.buffer_size * row_bytes > memory:
        need = f"{args.buffer_size * row_bytes / 1e9:.0f} GB of host memory ({row_bytes / 1e3:.0f} KB a row)"
        errors.append(f"--buffer-size {args.buffer_size} needs {need}; this machine has {memory / 1e9:.0f} GB")
    first_update = max(args.start_timesteps + 1, args.batch_size + (EPISODE_STEPS - 1) * args.num_envs)
    if args.total_timesteps >= 1 and args.total_timesteps < first_update:
        why = f"for any update to run: updates start after --start-timesteps ({args.start_timesteps}) random steps,"
        why += f" once finished episodes of up to {EPISODE_STEPS} steps per env hold --batch-size ({args.batch_size})"
        errors.append(f"--total-timesteps must be >= {first_update} {why} transitions; got {args.total_timesteps}")
    exit_on_errors(errors)


if __name__ == "__main__":
    main(tyro.cli(Args))
