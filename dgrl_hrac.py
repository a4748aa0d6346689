"""DGRL on HRAC in the HIRO Ant suite (AntMaze, AntMazeSparse, AntPush, AntFall, AntGather): discretized subgoals.

Paper: Islam et al. 2022, "Discrete Factorial Representations as an Abstraction for Goal Conditioned RL", section "Ant
Manipulation Control Domains" and appendix "Ant Manipulation tasks". The agent is HRAC (Zhang et al., NeurIPS 2020): a
TD3 manager proposes a relative xy subgoal every k = 10 steps to a TD3 controller rewarded for reaching it; HIRO's
off-policy correction relabels the manager's stored subgoals; an adjacency network over 1 m grid cells (a contrastive
loss) keeps the subgoals k-step reachable by an extra actor loss. DGRL (`--groups G`; 0: plain HRAC) passes the subgoal
through an encoder and vq.py's shared-codebook bottleneck: the controller's actor and critic see its z_q instead.

The HIRO Ant suite as HRAC's authors use it: gymnasium's Ant edited in code (ctrl +-30, gear 1, timestep 0.02 with RK4,
frame_skip 5) in structures of fixed, sliding and elevated blocks generated into MJCF at run time (rllab's and HIRO's
maze generator, rewritten here); AntGather adds apples, bombs and range sensors. Studies: benchmark/launch.py --preset
hrac-antmaze-cpu (CPU) or hrac-paper; env speed and renders: benchmark/figures/hrac_envs.py. Docs: docs/dgrl_hrac.md.

    python dgrl_hrac.py --env-id AntPush --groups 16      # DGRL G=16 on AntPush, the paper's 5M steps (a GPU job)
    python dgrl_hrac.py --env-id AntMaze --groups 0 --total-timesteps 300000   # HRAC: the short CPU run of the docs
    python dgrl_hrac.py --env-id AntFall --total-timesteps 2000 --ctrl-updates 50 --man-updates 5  # 15-second smoke run
    python dgrl_hrac.py --env-id AntPush --groups 16 --resume runs/<run_name>   # continue a stopped run, same flags
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
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from typing import ClassVar, Literal

if sys.platform.startswith("linux") and not os.environ.get("DISPLAY"):
    os.environ.setdefault("MUJOCO_GL", "egl")  # headless rendering (videos) without a display; set it to override

import gymnasium as gym
import mujoco
import numpy as np
import torch
import torch.nn as nn
import tyro
from torch.utils.tensorboard import SummaryWriter

from vq import VectorQuantizerEMA, active_codes, make_target, perplexity, update_target


@dataclass
class Args:
    # Environment
    env_id: str = "AntMaze"
    """AntMaze, AntMazeSparse, AntPush, AntFall or AntGather"""

    # Algorithm: HRAC with the hyper-parameters of its authors' Ant configuration
    total_timesteps: int = 5_000_000
    """total environment steps"""
    k: int = 10
    """controller steps per subgoal (the manager acts every k steps); must divide the 500-step episode"""
    buffer_size: int = 200_000
    """capacity of each level's replay (controller steps; manager k-step segments)"""
    batch_size: int = 128
    """transitions per update at both levels"""
    ctrl_updates: int = 0
    """controller updates at each episode end (0 = the episode's length, 500)"""
    man_updates: int = 0
    """manager updates at each episode end (0 = the episode's length / k, 50)"""
    ctrl_gamma: float = 0.95
    """controller discount per env step"""
    man_gamma: float = 0.99
    """manager discount per k-step segment"""
    tau: float = 0.005
    """Polyak rate of the target networks at both levels"""
    actor_lr: float = 1e-4
    """Adam learning rate of both actors"""
    critic_lr: float = 1e-3
    """Adam learning rate of both twin critics"""
    critic_weight_decay: float = 1e-4
    """weight decay of both critic optimizers"""
    policy_noise: float = 0.2
    """std of the target-action noise (absolute units at both levels: torques, metres)"""
    noise_clip: float = 0.5
    """clip of the target-action noise (absolute units)"""
    ctrl_noise: float = 1.0
    """std of the Gaussian exploration noise on the controller's torques (which range over +-30)"""
    man_noise: float = 1.0
    """std of the Gaussian exploration noise on the manager's subgoals, in metres (the subgoal's own units)"""
    man_reward_scale: float = 0.0
    """scale of the summed env reward the manager learns from (0 = 0.1, or 1.0 for AntMazeSparse and AntGather)"""
    subgoal_scale: float = 10.0
    """the manager proposes xy offsets in [-scale, scale] metres (AntFall's third, z, dimension: +-0.5)"""
    correction_samples: int = 10
    """Gaussian candidates of the off-policy correction (plus the stored subgoal and the achieved offset)"""
    hidden_dim: int = 300
    """hidden units of every actor and critic layer"""

    # Adjacency network
    adj_frequency: int = 50_000
    """env steps between adjacency-network trainings, each at an episode end (the labels persist over the run)"""
    adj_epochs: int = 25
    """epochs over all pairs of visited cells at each training"""
    adj_batch_size: int = 64
    """cell pairs per adjacency step"""
    adj_lr: float = 2e-4
    """Adam learning rate of the adjacency network"""
    adj_weight: float = 20.0
    """weight of the adjacency loss in the manager's actor loss"""
    adj_margin_pos: float = 1.0
    """contrastive margin of adjacent cell pairs (the manager's adjacency threshold is the mean of the two margins)"""
    adj_margin_neg: float = 1.2
    """contrastive margin of non-adjacent cell pairs"""

    # Evaluation
    eval_frequency: int = 5000
    """env steps between evaluations (each at the end of an episode)"""
    eval_episodes: int = 5
    """deterministic evaluation episodes (AntMaze: on the fixed evaluation goal)"""

    groups: int = 16  # DGRL
    """G: factors of the subgoal embedding; 0 runs HRAC"""
    n_embed: int = 64
    """L: codes in the shared codebook"""
    vq_beta: float = 0.25
    """commitment-loss weight"""
    vq_decay: float = 0.99
    """EMA decay of the codebook"""
    vq_dead_code_steps: int = 0
    """restart a code unused for this many updates at a random current segment (0 = off, as in the paper)"""
    embed_dim: int = 64
    """size of the subgoal embedding (m); must be divisible by groups"""
    encoder_hidden_dim: int = 128
    """hidden units of the subgoal encoder and decoder"""
    encoder_lr: float = 1e-4
    """Adam learning rate of the subgoal encoder and decoder (a parameter group of the controller's critic Adam)"""

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


def mlp(in_dim: int, hidden_dim: int, out_dim: int, n_hidden: int = 2) -> nn.Sequential:
    layers, width = [], in_dim
    for _ in range(n_hidden):
        layers += [nn.Linear(width, hidden_dim), nn.ReLU()]
        width = hidden_dim
    return nn.Sequential(*layers, nn.Linear(width, out_dim))


class Actor(nn.Module):
    """HRAC's TD3 actor at either level: (state, goal) -> 300 -> 300 -> tanh x max_action."""

    def __init__(self, state_dim: int, goal_dim: int, action_dim: int, max_action, hidden_dim: int = 300):
        super().__init__()
        self.net = mlp(state_dim + goal_dim, hidden_dim, action_dim)
        self.register_buffer("max_action", torch.as_tensor(max_action, dtype=torch.float32))  # a float or one per dim
        self.max_action_numpy = np.asarray(max_action, dtype=np.float64)  # for clipping noisy actions on the host

    def forward(self, states: torch.Tensor, goals: torch.Tensor) -> torch.Tensor:
        return self.max_action * torch.tanh(self.net(torch.cat([states, goals], -1)))


class TwinCritic(nn.Module):
    """Two Q networks (state, goal, action) -> 300 -> 300 -> 1."""

    def __init__(self, state_dim: int, goal_dim: int, action_dim: int, hidden_dim: int = 300):
        super().__init__()
        self.q1 = mlp(state_dim + goal_dim + action_dim, hidden_dim, 1)
        self.q2 = mlp(state_dim + goal_dim + action_dim, hidden_dim, 1)

    def forward(self, states, goals, actions) -> tuple[torch.Tensor, torch.Tensor]:
        x = torch.cat([states, goals, actions], -1)
        return self.q1(x).squeeze(-1), self.q2(x).squeeze(-1)


class AdjacencyNet(nn.Module):
    """HRAC's adjacency network: goal-space point -> 128 -> 128 -> 128 -> 32 (ReLU)."""

    def __init__(self, goal_dim: int, hidden_dim: int = 128, embed_dim: int = 32):
        super().__init__()
        self.net = mlp(goal_dim, hidden_dim, embed_dim, n_hidden=3)

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        return self.net(points)


class SubgoalEncoder(nn.Module):  # DGRL
    """DGRL: subgoal / bounds -> MLP -> vq.py's quantizer -> z_q, the controller's input; a decoder reconstructs it."""

    def __init__(self, scale: np.ndarray, args: Args):
        super().__init__()
        self.encoder = mlp(len(scale), args.encoder_hidden_dim, args.embed_dim)  # DGRL
        self.decoder = mlp(args.embed_dim, args.encoder_hidden_dim, len(scale))  # DGRL
        vq_flags = (args.embed_dim, args.n_embed, args.groups, args.vq_beta, args.vq_decay)
        self.vq = VectorQuantizerEMA(*vq_flags, dead_code_steps=args.vq_dead_code_steps)  # DGRL
        self.register_buffer("scale", torch.as_tensor(scale, dtype=torch.float32))

    def forward(self, subgoals: torch.Tensor, update: bool = False) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(z_q, commitment loss, code indices); the codebook moves only with update=True."""
        return self.vq(self.encoder(subgoals / self.scale), update=update)  # DGRL


@dataclass
class Level:
    """One of HRAC's two TD3 levels: the actor, the twin critics, their target copies and their optimizers."""

    actor: Actor
    critic: TwinCritic
    actor_target: Actor
    critic_target: TwinCritic
    actor_optimizer: torch.optim.Optimizer
    critic_optimizer: torch.optim.Optimizer


@dataclass
class Agent:
    """HRAC's two levels, the adjacency network with its optimizer and (DGRL; None for HRAC) the subgoal encoder."""

    manager: Level
    controller: Level
    adjacency: AdjacencyNet
    adjacency_optimizer: torch.optim.Optimizer
    encoder: SubgoalEncoder | None

    def parts(self, training: bool = False) -> dict:
        """A checkpoint's networks (DGRL: with the encoder and codebook); `training` adds the targets and optimizers."""
        names = ["actor", "critic"]
        names += ["actor_target", "critic_target", "actor_optimizer", "critic_optimizer"] if training else []
        levels = {"manager": self.manager, "controller": self.controller}
        parts = {f"{level_name}_{name}": getattr(level, name) for level_name, level in levels.items() for name in names}
        parts |= {"adjacency": self.adjacency} | ({} if self.encoder is None else {"subgoal_encoder": self.encoder})
        return parts | ({"adjacency_optimizer": self.adjacency_optimizer} if training else {})

    def state_dicts(self, training: bool = False) -> dict[str, dict]:
        return {name: part.state_dict() for name, part in self.parts(training).items()}

    def load_state_dicts(self, entries: dict[str, dict], training: bool = False) -> None:
        for name, part in self.parts(training).items():
            part.load_state_dict(entries[name])


def make_level(actor: Actor, critic: TwinCritic, args: Args, extra_critic_groups=()) -> Level:
    """A level: the networks, their target copies, fused Adams (the critics' with weight decay and extra groups)."""
    fused = next(actor.parameters()).device.type in ("cpu", "cuda")
    critic_groups = [{"params": critic.parameters(), "weight_decay": args.critic_weight_decay}, *extra_critic_groups]
    actor_optimizer = torch.optim.Adam(actor.parameters(), lr=args.actor_lr, fused=fused)
    critic_optimizer = torch.optim.Adam(critic_groups, lr=args.critic_lr, fused=fused)
    return Level(actor, critic, make_target(actor), make_target(critic), actor_optimizer, critic_optimizer)


def make_agent(state_dim: int, action_dim: int, args: Args, device: torch.device) -> Agent:
    """The agent for --env-id's task, built in a fixed order (a seed gives the same agent). The encoder trains with the
    controller's critic optimizer (lr --encoder-lr, no weight decay); its codebook moves by EMA, in no optimizer."""
    bounds = subgoal_bounds(args.env_id, args.subgoal_scale)
    goal_dim, man_goal_dim, hidden = len(bounds), MANAGER_GOAL_DIMS[args.env_id], args.hidden_dim
    ctrl_goal_dim = args.embed_dim if args.groups else goal_dim  # DGRL: the controller takes z_q(g) instead of g
    manager_actor = Actor(state_dim, man_goal_dim, goal_dim, bounds, hidden).to(device)
    manager_critic = TwinCritic(state_dim, man_goal_dim, goal_dim, hidden).to(device)
    controller_actor = Actor(state_dim, ctrl_goal_dim, action_dim, 30.0, hidden).to(device)
    controller_critic = TwinCritic(state_dim, ctrl_goal_dim, action_dim, hidden).to(device)
    adjacency = AdjacencyNet(2).to(device)  # over xy cells at every env (AntFall's z is not part of the grid)
    encoder = SubgoalEncoder(bounds, args).to(device) if args.groups else None  # DGRL
    encoder_groups = [dict(params=encoder.parameters(), lr=args.encoder_lr, weight_decay=0.0)] if args.groups else []
    manager = make_level(manager_actor, manager_critic, args)
    controller = make_level(controller_actor, controller_critic, args, encoder_groups)
    adjacency_optimizer = torch.optim.Adam(adjacency.parameters(), lr=args.adj_lr, fused=device.type in ("cpu", "cuda"))
    return Agent(manager, controller, adjacency, adjacency_optimizer, encoder)


# --- HRAC's computations ----------------------------------------------------------------------------------------------


def controller_input(states: np.ndarray | torch.Tensor):
    """The controller's view of a state: xy zeroed (HRAC's controller sees only where its relative subgoal points)."""
    masked = states.clone() if isinstance(states, torch.Tensor) else states.copy()
    masked[..., :2] = 0
    return masked


def subgoal_transition(states, subgoals, next_states):
    """The relative subgoal re-targeted after a step, to keep pointing at the same place: g' = s[:d] + g - s'[:d]."""
    d = subgoals.shape[-1]
    return states[..., :d] + subgoals - next_states[..., :d]


def controller_reward(states, subgoals, next_states):
    """HRAC's low-level reward: -||s[:d] + g - s'[:d]||, the distance of the step's end from the subgoal's target."""
    offset = subgoal_transition(states, subgoals, next_states)
    return -np.linalg.norm(offset, axis=-1) if isinstance(offset, np.ndarray) else -offset.norm(dim=-1)


@torch.no_grad()
def off_policy_correction(controller: Actor, states, actions, subgoals, scale, noise, goal_encoder=None):
    """HIRO's relabelling of manager transitions (states (B, k + 1, S), actions (B, k, A), subgoals (B, d)): of the
    stored subgoal, the achieved offset s_k - s_0 and it plus `noise` (clipped to +-scale), each re-targeted along the
    k steps, the one that makes the stored actions likeliest under the current controller (DGRL: via `goal_encoder`)."""
    (batch, k), d = actions.shape[:2], subgoals.shape[-1]
    achieved = states[:, -1, :d] - states[:, 0, :d]
    clipped = torch.clamp(achieved[:, None] + noise, -scale, scale)
    candidates = torch.cat([subgoals[:, None].to(clipped.dtype), achieved[:, None].to(clipped.dtype), clipped], 1)
    goals = [candidates]  # (B, 2 + n_samples, d) at each of the k steps
    for t in range(1, k):
        goals.append(subgoal_transition(states[:, None, t - 1], goals[-1], states[:, None, t]))
    observed_in = controller_input(states[:, None, :k]).float().expand(batch, candidates.shape[1], k, states.shape[-1])
    goals_in = controller_goal_input(goal_encoder, torch.stack(goals, 2).float())  # (B, n, k, d); DGRL: their z_q
    predicted = controller(observed_in, goals_in)  # DGRL: the candidates' z_q
    log_likelihood = -0.5 * ((predicted - actions[:, None]) ** 2).sum(-1).sum(-1)  # (B, n)
    return candidates[torch.arange(batch, device=candidates.device), log_likelihood.argmax(1)]


def correction_noise(rng: np.random.Generator, batch: int, n_samples: int, scale: np.ndarray) -> np.ndarray:
    """The off-policy correction's draws N(0, (0.5 scale)^2), shape (batch, n_samples, d), from the run's generator."""
    return rng.normal(0.0, 0.5 * scale, (batch, n_samples, len(scale)))


def contrastive_loss(emb_a, emb_b, labels: torch.Tensor, margin_pos: float = 1.0, margin_neg: float = 1.2):
    """HRAC's adjacency loss: mean(l * max(0, d - m+)) + mean((1 - l) * max(0, m- - d)), d = ||phi_a - phi_b||."""
    distances = torch.sqrt((emb_a - emb_b).pow(2).sum(-1) + 1e-12)
    positive = (labels * (distances - margin_pos).clamp(min=0)).mean()
    return positive + ((1 - labels) * (margin_neg - distances).clamp(min=0)).mean()


def adjacency_loss(anet: AdjacencyNet, positions: torch.Tensor, subgoals: torch.Tensor, threshold: float = 1.1):
    """The manager actor's adjacency term (before its weight 20): mean(max(0, ||phi(s_xy) - phi(s_xy + g)|| - 1.1)),
    the distance as HRAC takes it (`pairwise_distance`, which adds 1e-6 to each coordinate of the difference)."""
    d = subgoals.shape[-1]
    distance = torch.nn.functional.pairwise_distance(anet(positions[..., :d]), anet(positions[..., :d] + subgoals))
    return (distance - threshold).clamp(min=0).mean()


class AdjacencyMemory:
    """HRAC's adjacency labels, kept over the run: 1 m cells t and t + j (0 < j < k) of a trajectory are adjacent."""

    def __init__(self, k: int = 10):
        self.k, self.index, self.edges = k, {}, set()  # index: cell -> id, in the order of the ids

    def add_trajectory(self, positions: np.ndarray) -> None:
        cells = map(tuple, np.round(positions[:, :2]).astype(np.int64))
        ids = np.array([self.index.setdefault(cell, len(self.index)) for cell in cells], dtype=np.int64)
        for offset in range(1, min(self.k, len(ids))):
            pairs = zip(ids[:-offset], ids[offset:], strict=True)
            self.edges.update((min(a, b), max(a, b)) for a, b in pairs if a != b)

    def labelled_pairs(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(cells_a (P, 2), cells_b (P, 2), labels (P,)) over every pair of distinct visited cells."""
        cells = np.array(list(self.index), dtype=np.float32).reshape(-1, 2)
        first, second = np.triu_indices(len(cells), 1)
        labels = np.array([(a, b) in self.edges for a, b in zip(first, second, strict=True)], dtype=np.float32)
        return cells[first], cells[second], labels

    def state_dict(self) -> dict[str, np.ndarray]:
        """The visited cells in the order of their ids (C, 2) and the adjacent pairs of ids (E, 2), for --resume."""
        cells = np.array(list(self.index), dtype=np.int64).reshape(-1, 2)
        return {"cells": cells, "edges": np.array(sorted(self.edges), dtype=np.int64).reshape(-1, 2)}

    def load_state_dict(self, state: dict[str, np.ndarray]) -> None:
        self.index = {cell: i for i, cell in enumerate(map(tuple, state["cells"]))}
        self.edges = set(map(tuple, state["edges"]))


class Replay:
    """A ring of numpy arrays, one per field; `sample` draws uniformly, or all entries while at most a batch (HRAC)."""

    def __init__(self, capacity: int, **shapes: tuple[int, ...]):
        self.capacity, self.size, self.position = capacity, 0, 0
        self.fields = {name: np.zeros((capacity, *shape), dtype=np.float32) for name, shape in shapes.items()}

    def add(self, **values) -> None:
        for name, array in self.fields.items():
            array[self.position] = values[name]
        self.position = (self.position + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)

    def sample(self, batch_size: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
        index = np.arange(self.size) if self.size <= batch_size else rng.integers(self.size, size=batch_size)
        return {name: array[index] for name, array in self.fields.items()}

    def state_dict(self) -> dict:
        """For --resume: size, position and the filled part of every field (as tensors sharing the arrays' memory)."""
        filled = {name: torch.from_numpy(array[: self.size]) for name, array in self.fields.items()}
        return {"size": self.size, "position": self.position, "fields": filled}

    def load_state_dict(self, state: dict) -> None:
        self.size, self.position = state["size"], state["position"]
        for name, array in self.fields.items():
            array[: self.size] = state["fields"][name].numpy()


def learn(optimizer: torch.optim.Optimizer, loss: torch.Tensor, max_grad_norm: float | None = None) -> None:
    """One step on `loss`: clear the gradients, backpropagate, clip their norm to `max_grad_norm` if given, step."""
    optimizer.zero_grad()
    loss.backward()
    if max_grad_norm is not None:
        params = [param for group in optimizer.param_groups for param in group["params"]]
        torch.nn.utils.clip_grad_norm_(params, max_grad_norm, foreach=True)
    optimizer.step()


def td3_update(level: Level, batch: dict, gamma: float, args: Args, actor_extra=None, critic_extra=0.0) -> dict:
    """One TD3 step as HRAC runs it at both levels: clipped target-action noise, the min of the target critics, a Huber
    critic loss plus `critic_extra` (DGRL: the encoder's losses, `goals` carrying its graph), the actor updated at every
    step (no policy delay) to maximise Q1 plus `actor_extra(actions)` (the manager's adjacency term), Polyak targets."""
    with torch.no_grad():
        noise = (torch.randn_like(batch["actions"]) * args.policy_noise).clamp(-args.noise_clip, args.noise_clip)
        next_actions = level.actor_target(batch["next_states"], batch["next_goals"])  # DGRL
        next_actions = (next_actions + noise).clamp(-level.actor.max_action, level.actor.max_action)
        target_q = torch.min(*level.critic_target(batch["next_states"], batch["next_goals"], next_actions))  # DGRL
        target = batch["rewards"] + gamma * (1.0 - batch["dones"]) * target_q
    q1, q2 = level.critic(batch["states"], batch["goals"], batch["actions"])  # DGRL: z_q(g), straight-through
    critic_loss = nn.functional.smooth_l1_loss(q1, target) + nn.functional.smooth_l1_loss(q2, target)
    learn(level.critic_optimizer, critic_loss + critic_extra)
    goals = batch["goals"].detach()  # DGRL: the controller's actor sees z_q(g) without gradient
    actions = level.actor(batch["states"], goals)  # DGRL: the controller's z_q(g), detached
    actor_loss = -level.critic(batch["states"], goals, actions)[0].mean()  # DGRL: the controller's z_q(g), detached
    if actor_extra is not None:
        actor_loss = actor_loss + actor_extra(actions)
    learn(level.actor_optimizer, actor_loss)
    update_target(level.actor_target, level.actor, args.tau)
    update_target(level.critic_target, level.critic, args.tau)
    metrics = {"critic_loss": critic_loss.detach(), "actor_loss": actor_loss.detach(), "q": q1.detach().mean()}
    return metrics | {"target_q": target_q.mean()}


# --- The agent: updates, adjacency training, acting ------------------------------------------------------------------

ENV_IDS = ("AntMaze", "AntMazeSparse", "AntPush", "AntFall", "AntGather")
MANAGER_GOAL_DIMS = {"AntMaze": 2, "AntPush": 2, "AntFall": 3, "AntMazeSparse": 0, "AntGather": 0}


def subgoal_bounds(env_id: str, scale: float) -> np.ndarray:
    """The manager's output range per subgoal dimension: xy +-scale; AntFall's subgoals add z within +-0.5."""
    return np.array([scale, scale, 0.5]) if env_id == "AntFall" else np.array([scale, scale])


def manager_goal(env: "HiroAntEnv") -> np.ndarray:
    """What the manager sees of the task: the goal's xy (AntFall xyz); AntMazeSparse and AntGather give it nothing."""
    return np.zeros(0) if MANAGER_GOAL_DIMS[env.env_id] == 0 else env.goal.astype(np.float32)


def controller_goal_input(goal_encoder: SubgoalEncoder | None, subgoals: torch.Tensor) -> torch.Tensor:
    """What the controller sees of its subgoal: the subgoal (HRAC) or its z_q (DGRL), codebook untouched."""
    return subgoals if goal_encoder is None else goal_encoder(subgoals)[0]  # DGRL


def as_tensors(sample: dict[str, np.ndarray], device: torch.device | str) -> dict[str, torch.Tensor]:
    return {name: torch.as_tensor(value, device=device) for name, value in sample.items()}


def controller_update(agent: Agent, batch: dict[str, torch.Tensor], args: Args) -> dict[str, torch.Tensor]:
    """One controller TD3 step, no host sync. DGRL: subgoals and next subgoals quantized in one call (one EMA step)."""
    extra, metrics = 0.0, {}  # under DGRL the encoder's losses, added to the critic loss
    if (encoder := agent.encoder) is not None:  # DGRL
        n = len(batch["goals"])
        z_q, vq_loss, codes = encoder(torch.cat([batch["goals"], batch["next_goals"]]), update=True)  # DGRL
        reconstruction = nn.functional.mse_loss(encoder.decoder(z_q[:n]), batch["goals"] / encoder.scale)  # DGRL
        batch = batch | {"goals": z_q[:n], "next_goals": z_q[n:].detach()}  # DGRL
        extra = reconstruction + vq_loss  # DGRL
        metrics = {"reconstruction_loss": reconstruction.detach(), "vq_loss": vq_loss.detach(), "codes": codes}
    return metrics | td3_update(agent.controller, batch, gamma=args.ctrl_gamma, args=args, critic_extra=extra)


def manager_batch(sample: dict, rng: np.random.Generator, *, bounds: np.ndarray, correction_samples: int, device):
    """A manager replay sample as tensors on `device`, with `noise`: the off-policy correction's Gaussian draws."""
    noise = correction_noise(rng, len(sample["actions"]), correction_samples, bounds)
    return as_tensors(sample | {"noise": noise}, device)


def manager_update(agent: Agent, batch: dict, args: Args, bounds: torch.Tensor) -> dict[str, torch.Tensor]:
    """One manager TD3 step on a manager_batch, its subgoals relabelled by the off-policy correction (`bounds`: float64
    on its device), its actor loss plus --adj-weight x the adjacency loss of the subgoals' xy. No host sync."""
    stored = (batch["state_seq"], batch["action_seq"], batch["actions"])
    actions = off_policy_correction(agent.controller.actor, *stored, bounds, batch["noise"], goal_encoder=agent.encoder)
    names = ("states", "goals", "rewards", "next_states", "dones")
    batch = {name: batch[name] for name in names} | {"actions": actions.float(), "next_goals": batch["goals"]}
    threshold = (args.adj_margin_pos + args.adj_margin_neg) / 2  # the embedding distance deemed "reachable in k steps"
    positions = batch["states"][:, :2]

    def adjacency_term(subgoals: torch.Tensor) -> torch.Tensor:
        return args.adj_weight * adjacency_loss(agent.adjacency, positions, subgoals[:, :2], threshold)

    metrics = td3_update(agent.manager, batch, gamma=args.man_gamma, args=args, actor_extra=adjacency_term)
    with torch.no_grad():
        metrics["adjacency_loss"] = adjacency_loss(agent.adjacency, positions, batch["actions"][:, :2], threshold)
    return metrics


def train_adjacency(anet, optimizer, memory, rng, args: Args, *, epochs: int, device, stop=()):
    """`epochs` epochs on all visited-cell pairs: (epochs run, last epoch's loss, accuracy), NaNs if none or stopped."""
    cells_a, cells_b, labels = (torch.as_tensor(x, device=device) for x in memory.labelled_pairs())
    if len(labels) == 0:
        return epochs, float("nan"), float("nan")
    margins = (args.adj_margin_pos, args.adj_margin_neg)
    for epoch in range(epochs):
        if stop:
            return epoch, float("nan"), float("nan")
        order = torch.as_tensor(rng.permutation(len(labels)), device=device)
        losses = []
        for start in range(0, len(labels), args.adj_batch_size):
            index = order[start : start + args.adj_batch_size]
            loss = contrastive_loss(anet(cells_a[index]), anet(cells_b[index]), labels[index], *margins)
            learn(optimizer, loss)
            losses.append(loss.detach())
    with torch.no_grad():
        predicted = (anet(cells_a) - anet(cells_b)).norm(dim=-1) < sum(margins) / 2
        accuracy = (predicted.float() == labels).float().mean().item()
    return epochs, torch.stack(losses).mean().item(), accuracy


@torch.no_grad()
def act(agent: Agent, state: np.ndarray, goal: np.ndarray, *, manager: bool, noise: float, rng: np.random.Generator):
    """The manager's subgoal for (state, task goal) or the controller's torques for (xy-masked state, subgoal; DGRL: its
    z_q, codebook untouched), plus Gaussian noise of std `noise` clipped to the actor's range (subgoal bounds or 30)."""
    actor = agent.manager.actor if manager else agent.controller.actor
    device = actor.max_action.device
    state = torch.as_tensor(state if manager else controller_input(state), dtype=torch.float32, device=device)[None]
    goal = torch.as_tensor(goal, dtype=torch.float32, device=device)[None]
    goal = goal if manager else controller_goal_input(agent.encoder, goal)  # DGRL: z_q of the subgoal
    action = actor(state, goal)[0].cpu().numpy().astype(np.float64)  # DGRL: the controller sees z_q
    if noise > 0:
        limit = actor.max_action_numpy  # on the host: reading the device buffer back every step would be a sync
        action = np.clip(action + rng.normal(0.0, noise, action.shape), -limit, limit)
    return action


# --- The run: setup, the training loop, the end, evaluation -----------------------------------------------------------


def main(args: Args) -> None:
    """Train HRAC (--groups 0) or DGRL on a HIRO Ant task, or evaluate a --checkpoint and exit."""
    validate(args)
    run_name = f"{args.env_id}__G{args.groups}__{args.exp_name}__{args.seed}__{int(time.time())}"
    run_name = run_name if args.resume is None else os.path.basename(os.path.normpath(args.resume))
    if args.resume is not None:  # a run still running elsewhere: exit 2 at once, touching nothing
        hold_run_folder(run_name, check_only=True)
    saved = load_resume(args) if args.resume is not None else None
    man_reward_scale = args.man_reward_scale or (1.0 if args.env_id in ("AntMazeSparse", "AntGather") else 0.1)
    device = seed_and_device(args)
    rng = np.random.default_rng(args.seed)
    # The critics' weight decay drives the weights of dead ReLU units into subnormal floats, which slow a CPU's matrix
    # multiplies 20x (measured: 27 ms instead of 1.2 ms per batch after 5k steps); flush them to zero.
    torch.set_flush_denormal(True)

    env = HiroAntEnv(args.env_id, segment=args.k)
    eval_env = HiroAntEnv(args.env_id, evaluate=True, render_mode="rgb_array" if args.capture_video else None)
    eval_env.reset(seed=args.seed + 10_000)  # one evaluation stream per run, continued across evaluations
    if args.capture_video:  # a renderer that cannot start fails here, before any work, not at the first evaluation
        try:
            eval_env.render()
        except Exception as error:
            problem = f"--capture-video cannot render with MUJOCO_GL={os.environ.get('MUJOCO_GL')} ({error})"
            exit_on_errors([f"{problem}; set MUJOCO_GL=egl or osmesa, or run without --capture-video"])
    state_dim, action_dim = env.observation_space.shape[0], env.action_space.shape[0]
    bounds = subgoal_bounds(args.env_id, args.subgoal_scale)
    goal_dim, man_goal_dim = len(bounds), MANAGER_GOAL_DIMS[args.env_id]
    agent = make_agent(state_dim, action_dim, args, device)
    stop = stop_on_signals()

    if args.checkpoint is not None:
        evaluate_checkpoint(args, agent, eval_env, rng, stop, device, run_name)
        return

    # A resumed run logs from the step after its resume file's (TensorBoard drops what the stopped run logged later).
    _lock = hold_run_folder(run_name)  # one process writes a run folder, from its first write to its end
    writer = make_writer(args, run_name, purge_step=None if saved is None else saved["loop"]["step"] + 1)
    dims = f"state {state_dim}-d, subgoal {goal_dim}-d (bounds {bounds.tolist()}), manager goal {man_goal_dim}-d"
    print(f"{run_name}: {dims}, {args.total_timesteps} steps, device {device}")
    if args.adj_frequency > args.total_timesteps:
        print(f"note: the adjacency network never trains (--adj-frequency {args.adj_frequency} > --total-timesteps)")
    shapes = {"states": (state_dim,), "rewards": (), "next_states": (state_dim,), "dones": ()}  # both replays' fields
    ctrl_replay = Replay(args.buffer_size, **shapes, goals=(goal_dim,), actions=(action_dim,), next_goals=(goal_dim,))
    segment_shapes = {"state_seq": (args.k + 1, state_dim), "action_seq": (args.k, action_dim)}
    man_replay = Replay(args.buffer_size, **shapes, goals=(man_goal_dim,), actions=(goal_dim,), **segment_shapes)
    memory = AdjacencyMemory(args.k)
    checkpoint_path = f"runs/{run_name}/{args.exp_name}.cleanrl_model"
    state, _ = env.reset(seed=args.seed)
    empty_segment = {"seg_states": np.zeros((args.k + 1, state_dim)), "seg_actions": np.zeros((args.k, action_dim))}
    loop = LoopState(next_eval=args.eval_frequency, next_adjacency=args.adj_frequency, state=state, **empty_segment)
    stores = {"ctrl_replay": ctrl_replay, "man_replay": man_replay, "memory": memory, "env": env, "eval_env": eval_env}
    if saved is not None:  # continue where the stopped run left off, mid-episode and mid-segment included
        loop = restore_training_state(saved, agent, stores, rng)
        print(f"resuming at step {loop.step}: {loop.episode_steps} steps into episode {loop.episodes + 1}")
    # --fast wraps each level's update once a resumed run's optimizer states are loaded; adjacency training stays eager.
    ctrl, man = agent.controller, agent.manager
    update_controller = fast_update(controller_update, args.fast, [ctrl.critic_optimizer, ctrl.actor_optimizer])
    update_manager = fast_update(manager_update, args.fast, [man.critic_optimizer, man.actor_optimizer])
    bounds_tensor = torch.as_tensor(bounds, device=device)  # float64, the precision of the correction's candidates
    correction = {"bounds": bounds, "correction_samples": args.correction_samples, "device": device}
    progress = Progress(args.total_timesteps, start_step=loop.step)
    # A stop request (Ctrl-C, SIGTERM, SIGUSR1/2) ends the loop at its top, so that the resume file holds whole steps
    # (an episode end's updates finish first), or between two epochs of an adjacency training.
    while not stop:
        # Adjacency network: retrained every adj_frequency steps (after an episode end) on the labels gathered so far.
        if loop.adjacency_due:
            began = time.time()
            epochs = args.adj_epochs - loop.adjacency_epochs  # fewer when a stopped training resumes
            epochs_run, adj_loss, adj_accuracy = train_adjacency(
                agent.adjacency, agent.adjacency_optimizer, memory, rng, args, epochs=epochs, device=device, stop=stop
            )
            loop.adjacency_epochs += epochs_run
            if loop.adjacency_epochs < args.adj_epochs:
                continue  # stopped between two epochs: the loop ends, the training still due (--resume runs the rest)
            loop.adjacency_due, loop.adjacency_epochs = False, 0
            cells, edges = len(memory.index), len(memory.edges)
            for name, value in {"loss": adj_loss, "accuracy": adj_accuracy, "cells": cells, "edges": edges}.items():
                writer.add_scalar(f"adjacency/{name}", value, loop.step)
            trained = f"{cells} cells, {edges} adjacent pairs"
            quality = f"loss {adj_loss:.3f}, accuracy {adj_accuracy:.1%} ({time.time() - began:.0f} s)"
            print(f"step {loop.step:>9}: adjacency network trained on {trained}: {quality}", flush=True)

        # Evaluate (deterministic; AntMaze on its fixed evaluation goal), print progress, save the checkpoint.
        if loop.eval_due:
            loop.eval_due = False
            video = [] if args.capture_video and loop.evaluations % 10 == 0 else None
            loop.result = evaluate(eval_env, agent, k=args.k, rng=rng, episodes=args.eval_episodes, frames=video)
            loop.evaluations += 1
            for name, tag in (("success", "success_rate"), ("distance", "final_distance"), ("return", "return")):
                writer.add_scalar(f"eval/{tag}", loop.result[name], loop.step)
            writer.add_scalar("charts/SPS", progress.sps(loop.step), loop.step)
            summary = {name: float(np.mean(values)) if values else float("nan") for name, values in loop.recent.items()}
            loop.recent = {name: [] for name in loop.recent}
            task = f"success {loop.result['success']:4.0%} distance {loop.result['distance']:5.2f}"
            task = f"return {loop.result['return']:6.2f}" if args.env_id == "AntGather" else task
            train = f"train return {summary['return']:8.1f} final distance {summary['final_distance']:5.2f}"
            progress.line(loop.step, f"eval {task}  {train}  subgoal distance {summary['subgoal_distance']:5.2f}")
            if video:
                write_video(f"videos/{run_name}/eval_{loop.step}.mp4", video, HiroAntEnv.metadata["render_fps"])
            if args.save_model:
                save_checkpoint(checkpoint_path, agent.state_dicts(), args)

        if loop.step >= args.total_timesteps:
            break

        # Act: the manager proposes a relative subgoal every k steps; the controller chases it, re-targeted every step.
        if loop.episode_steps == 0:
            loop.goal = manager_goal(env)
            loop.positions = [loop.state[:2]]
            loop.remaining = []  # per segment: the distance left to the subgoal's target after k steps
            loop.proposals = []  # per segment: the length of the proposed subgoal
            loop.episode_return = loop.ctrl_rewards = 0.0
        t = loop.episode_steps % args.k
        if t == 0:
            loop.subgoal = act(agent, loop.state, loop.goal, manager=True, noise=args.man_noise, rng=rng)
            loop.proposed = loop.subgoal
            loop.seg_states[0] = loop.state
            loop.seg_reward = 0.0
        state, subgoal = loop.state, loop.subgoal
        action = act(agent, state, subgoal, manager=False, noise=args.ctrl_noise, rng=rng)
        next_state, reward, terminated, truncated, info = env.step(action)
        loop.step += 1
        loop.episode_steps += 1
        loop.episode_return += reward
        loop.seg_reward += man_reward_scale * reward

        # Store the controller's step and, once a segment is whole, the manager's. An episode's end is terminal at both
        # levels, as in HRAC: the 500-step cut (the observation holds the step count) or AntMazeSparse's early end.
        done = float(terminated or truncated)
        next_subgoal = subgoal_transition(state, subgoal, next_state)
        ctrl_reward = controller_reward(state, subgoal, next_state)
        loop.ctrl_rewards += ctrl_reward
        transition = {"states": controller_input(state), "goals": subgoal, "actions": action, "rewards": ctrl_reward}
        ctrl_replay.add(**transition, next_states=controller_input(next_state), next_goals=next_subgoal, dones=done)
        loop.seg_states[t + 1] = next_state
        loop.seg_actions[t] = action
        loop.positions.append(next_state[:2])
        loop.state, loop.subgoal = next_state, next_subgoal
        if t == args.k - 1:
            start = {"states": loop.seg_states[0], "goals": loop.goal, "actions": loop.proposed}
            end = {"rewards": loop.seg_reward, "next_states": next_state, "dones": done}
            man_replay.add(**start, **end, state_seq=loop.seg_states, action_seq=loop.seg_actions)
            loop.remaining.append(np.linalg.norm(next_subgoal[:2]))
            loop.proposals.append(np.linalg.norm(loop.proposed[:2]))
        progress.line(loop.step, f"{loop.episodes} episodes", heartbeat=True)

        # Episode end: log it, then train both levels (HRAC: an update per step and per segment of it, no warm-up).
        if terminated or truncated or loop.step >= args.total_timesteps:
            loop.episodes += 1
            memory.add_trajectory(np.array(loop.positions))
            loop.recent["return"].append(loop.episode_return)
            loop.recent["subgoal_distance"].extend(loop.remaining)
            writer.add_scalar("charts/episodic_return", loop.episode_return, loop.step)
            writer.add_scalar("charts/episodic_length", loop.episode_steps, loop.step)
            writer.add_scalar("charts/controller_reward", loop.ctrl_rewards / loop.episode_steps, loop.step)
            if loop.remaining:
                writer.add_scalar("charts/subgoal_distance", float(np.mean(loop.remaining)), loop.step)
                writer.add_scalar("charts/subgoal_norm", float(np.mean(loop.proposals)), loop.step)
            if "distance" in info:
                loop.recent["final_distance"].append(info["distance"])
                writer.add_scalar("charts/final_distance", info["distance"], loop.step)
                writer.add_scalar("charts/success_rate", float(info["success"]), loop.step)
            # A replay no larger than a batch is sampled whole (in the first episodes): that other shape takes the eager
            # update, so that a compiled one (a CUDA graph) keeps the one shape of --batch-size.
            ctrl_metrics, man_metrics = {}, {}
            ctrl_step = update_controller if ctrl_replay.size > args.batch_size else controller_update
            for _ in range(args.ctrl_updates or loop.episode_steps):
                ctrl_metrics = ctrl_step(agent, as_tensors(ctrl_replay.sample(args.batch_size, rng), device), args)
            man_step = update_manager if man_replay.size > args.batch_size else manager_update
            for _ in range((args.man_updates or -(-loop.episode_steps // args.k)) if man_replay.size else 0):
                sample = man_replay.sample(args.batch_size, rng)  # then the correction's noise, from the same generator
                man_metrics = man_step(agent, manager_batch(sample, rng, **correction), args, bounds_tensor)
            for level, metrics in (("controller", ctrl_metrics), ("manager", man_metrics)):
                for name in ("critic_loss", "actor_loss", "q", "adjacency_loss"):  # the manager's adjacency term too
                    if name in metrics:
                        writer.add_scalar(f"losses/{level}_{name}", metrics[name].item(), loop.step)
            if args.groups and ctrl_metrics:
                writer.add_scalar("losses/reconstruction", ctrl_metrics["reconstruction_loss"].item(), loop.step)
                writer.add_scalar("vq/commit_loss", ctrl_metrics["vq_loss"].item(), loop.step)
                for tag, measure in (("vq/perplexity", perplexity), ("vq/active_codes", active_codes)):
                    writer.add_scalar(tag, measure(ctrl_metrics["codes"], args.n_embed).item(), loop.step)

            # What the episode end calls for; both come first in the next iteration, where a stop can end the training.
            loop.adjacency_due = loop.step >= loop.next_adjacency
            loop.eval_due = loop.step >= loop.next_eval or loop.step >= args.total_timesteps
            loop.next_adjacency += args.adj_frequency if loop.adjacency_due else 0
            loop.next_eval += args.eval_frequency if loop.eval_due else 0
            loop.state, _ = env.reset()
            loop.episode_steps = 0
        # The periodic resume write, never with work pending: its logs at this step would follow the file, and a run
        # killed after them would log them twice (TensorBoard's purge on --resume drops the later steps only).
        work_pending = loop.adjacency_due or loop.eval_due
        if not work_pending and progress.resume_due(loop.step, args.checkpoint_every, args.checkpoint_every_steps):
            writer.flush()  # the logs up to this step on disk before the state that continues after them (a kill -9)
            save_resume(run_name, training_state(loop, agent, stores, rng), args)

    writer.flush()
    save_resume(run_name, training_state(loop, agent, stores, rng), args)  # stopped or done: --resume continues it
    if args.save_model:
        save_checkpoint(checkpoint_path, agent.state_dicts(), args)
        print(f"checkpoint: {checkpoint_path}")
    result = loop.result
    last = f"last eval success {result['success']:.0%} distance {result['distance']:.2f} return {result['return']:.2f}"
    stopped = loop.step < args.total_timesteps or loop.adjacency_due or loop.eval_due
    progress.finish(stopped, run_name, f"{loop.step} steps, {loop.episodes} episodes, {last}")
    env.close()
    eval_env.close()
    writer.close()


MUST_MATCH = ("env_id", "groups", "hidden_dim", "subgoal_scale", "k")  # what a checkpoint must match to be evaluated
DGRL_MUST_MATCH = ("n_embed", "embed_dim", "encoder_hidden_dim")  # and under DGRL (HRAC has no encoder or codebook)


@torch.no_grad()
def evaluate(env: "HiroAntEnv", agent: Agent, *, k: int, rng, episodes: int, frames: list | None = None, stop=()):
    """HRAC's deterministic evaluation, episodes ending at the first success (AntMazeSparse: reward > 0) or step 500:
    success rate, mean final distance and return, episodes run (fewer on a stop); `frames`: the first one's renders."""
    columns = {"success": [], "distance": [], "return": []}
    for episode in range(episodes):
        if stop and columns["success"]:
            break
        state, _ = env.reset()
        goal, total = manager_goal(env), 0.0
        for t in range(EPISODE_STEPS):
            if t % k == 0:
                subgoal = act(agent, state, goal, manager=True, noise=0.0, rng=rng)
            action = act(agent, state, subgoal, manager=False, noise=0.0, rng=rng)
            next_state, reward, terminated, truncated, info = env.step(action)
            subgoal, state = subgoal_transition(state, subgoal, next_state), next_state
            total += reward
            if frames is not None and episode == 0:
                frames.append(env.render())
            reached = reward > 0 if env.env_id == "AntMazeSparse" else info["success"]
            if reached or terminated or truncated:
                break
        columns["success"].append(float(reached))
        columns["distance"].append(info.get("distance", float("nan")))
        columns["return"].append(total)
    return {name: float(np.mean(values)) for name, values in columns.items()} | {"episodes": len(columns["success"])}


def evaluate_checkpoint(args: Args, agent: Agent, eval_env: "HiroAntEnv", rng, stop: list[int], device, run_name: str):
    """--checkpoint: evaluate the saved agent over --eval-episodes episodes, print the result (and write a video)."""
    must_match = MUST_MATCH + (DGRL_MUST_MATCH if args.groups else ())  # HRAC has no codebook to match
    agent.load_state_dicts(load_checkpoint(args.checkpoint, args, must_match, device))
    episodes = f"{args.eval_episodes} episodes"
    print(f"evaluating {args.checkpoint} over {episodes} (Ctrl-C ends it after the current one)", flush=True)
    video = [] if args.capture_video else None
    result = evaluate(eval_env, agent, k=args.k, rng=rng, episodes=args.eval_episodes, frames=video, stop=stop)
    figures = f"success {result['success']:.0%}, distance {result['distance']:.2f}, return {result['return']:.2f}"
    print(f"{result['episodes']} evaluation episodes: {figures}")
    if video:
        write_video(f"videos/{run_name}/checkpoint.mp4", video, HiroAntEnv.metadata["render_fps"])
        print(f"video: videos/{run_name}/checkpoint.mp4")


def write_video(path: str, frames: list[np.ndarray], fps: int) -> None:
    """Frames (H, W, 3) uint8 to an mp4 (moviepy loaded only here), one encoder thread: with more, the bytes vary."""
    os.makedirs(os.path.dirname(path), exist_ok=True)
    importlib.import_module("moviepy").ImageSequenceClip(frames, fps=fps).write_videofile(path, logger=None, threads=1)


# --- Environments -----------------------------------------------------------------------------------------------------

# HIRO's structures, rows top to bottom: 1 fixed block, 0 free, r robot start (the first is the origin; AntMazeSparse
# starts on any of them), XY a block sliding in x and y, YZ one sliding in y and z, -1 a chasm; SPARSE: AntMazeSparse's.
SPARSE = "1111111111 1rrrrrrrr1 1rrrrrrrr1 1111111rr1 10rrrrrrr1 10rrrrrrr1 1111111rr1 1rrrrrrrr1 1rrrrrrrr1 1111111111"
STRUCTURES = {
    "AntMaze": (8.0, ((1, 1, 1, 1, 1), (1, "r", 0, 0, 1), (1, 1, 1, 0, 1), (1, 0, 0, 0, 1), (1, 1, 1, 1, 1))),
    "AntPush": (8.0, ((1, 1, 1, 1, 1), (1, 0, "r", 1, 1), (1, 0, "XY", 0, 1), (1, 1, 0, 1, 1), (1, 1, 1, 1, 1))),
    "AntFall": (8.0, ((1, 1, 1, 1), (1, "r", 0, 1), (1, 0, "YZ", 1), (1, -1, -1, 1), (1, 0, 0, 1), (1, 1, 1, 1))),
    "AntMazeSparse": (2.0, tuple(tuple(int(c) if c in "01" else c for c in row) for row in SPARSE.split())),
}
MAZE_HEIGHT = 0.5  # walls are MAZE_HEIGHT * scaling tall
SOLID = {"conaffinity": "1", "contype": "1"}  # a block's collision flags
EVAL_GOALS = {"AntMaze": (0.0, 16.0), "AntMazeSparse": (2.0, 9.0), "AntPush": (0.0, 19.0), "AntFall": (0.0, 27.0, 4.5)}
SUCCESS_DISTANCE = {"AntMaze": 5.0, "AntMazeSparse": 1.0, "AntPush": 5.0, "AntFall": 5.0}
EPISODE_STEPS = 500
GATHER = {"apples": 8, "bombs": 8, "wall": 11.0, "catch": 1.0, "bins": 10, "range": 6.0, "span": 2 * np.pi}


def structure_origin(structure) -> tuple[int, int]:
    """(row, column) of the first robot cell: the world origin, where the ant starts."""
    return next((i, j) for i, row in enumerate(structure) for j, cell in enumerate(row) if cell == "r")


def cell_centre(i: int, j: int, scaling: float, origin: tuple[int, int]) -> tuple[float, float]:
    """World xy of cell (row i, column j): x grows with the column, y with the row (HIRO's convention)."""
    return j * scaling - origin[1] * scaling, i * scaling - origin[0] * scaling


def structure_blocks(env_id: str) -> list[dict]:
    """An env's blocks as MuJoCo boxes: name, centre, half-sizes, the axes it slides along ("" if fixed), a movable
    one's mass. A structure with a chasm is elevated: a platform under every other cell carries the rest."""
    scaling, structure = STRUCTURES[env_id]
    origin = structure_origin(structure)
    elevated = any(cell == -1 for row in structure for cell in row)
    floor = MAZE_HEIGHT * scaling if elevated else 0.0  # the height the walls stand on
    half, wall_half_height = 0.5 * scaling, 0.5 * MAZE_HEIGHT * scaling
    blocks = []
    for i, row in enumerate(structure):
        for j, cell in enumerate(row):
            x, y = cell_centre(i, j, scaling, origin)
            if elevated and cell != -1:
                size = (half, half, floor / 2)
                blocks.append(dict(name=f"platform_{i}_{j}", pos=(x, y, floor / 2), size=size, axes=""))
            pos = (x, y, floor + wall_half_height)
            if cell == 1:
                blocks.append(dict(name=f"block_{i}_{j}", pos=pos, size=(half, half, wall_half_height), axes=""))
            elif cell in ("XY", "YZ"):
                shrink, mass = (0.99, 0.001) if "Z" in cell else (1.0, 0.0002)  # the falling one fits the chasm
                size = (half * shrink, half * shrink, wall_half_height)
                blocks.append(dict(name=f"movable_{i}_{j}", pos=pos, size=size, axes=cell.lower(), mass=mass))
    return blocks


def hiro_ant_xml(env_id: str) -> str:
    """Gymnasium's Ant model edited as HIRO's (ctrl +-30 with gear 1, timestep 0.02, RK4) with the env's blocks; the
    ant keeps the first 15 qpos and 14 qvel entries (the blocks' slide joints come after it)."""
    root = ET.parse(os.path.join(os.path.dirname(gym.__file__), "envs/mujoco/assets/ant.xml")).getroot()
    root.find("option").set("timestep", "0.02")
    for motor in root.iter("motor"):
        motor.attrib |= {"gear": "1", "ctrlrange": "-30 30"}
    world = root.find("worldbody")
    world.find("geom[@name='floor']").set("size", "60 60 40")
    blocks = [] if env_id == "AntGather" else structure_blocks(env_id)
    scaling = STRUCTURES[env_id][0] if blocks else 0.0
    if any(block["name"].startswith("platform") for block in blocks):  # the ant starts on the platform
        world.find("body[@name='torso']").set("pos", f"0 0 {0.75 + MAZE_HEIGHT * scaling}")
    for block in blocks:
        name, pos, size = block["name"], " ".join(map(str, block["pos"])), " ".join(map(str, block["size"]))
        if not block["axes"]:
            ET.SubElement(world, "geom", name=name, type="box", pos=pos, size=size, **SOLID, rgba="0.4 0.4 0.4 1")
            continue
        body = ET.SubElement(world, "body", name=name, pos=pos)
        geom = dict(name=name + "_geom", type="box", size=size, mass=str(block["mass"]), **SOLID)
        ET.SubElement(body, "geom", **geom, rgba="0.9 0.1 0.1 1", solimp="0.995 0.995 0.01")
        for axis in block["axes"]:
            direction = {"x": "1 0 0", "y": "0 1 0", "z": "0 0 1"}[axis]
            joint = ET.SubElement(body, "joint", name=f"{name}_{axis}", type="slide", axis=direction, pos="0 0 0")
            joint.attrib |= {"armature": "0", "damping": "0.0", "limited": "false"}
            if "z" in block["axes"]:  # the falling block drops at most the platform's height
                span = f"{-MAZE_HEIGHT * scaling} 0" if axis == "z" else f"{-scaling} {scaling}"
                joint.attrib |= {"limited": "true", "range": span}
    # A camera over the middle of the structure that sees all of it (45-degree field of view).
    xs, ys = [b["pos"][0] for b in blocks] or [0.0], [b["pos"][1] for b in blocks] or [0.0]
    extent = max(max(xs) - min(xs), max(ys) - min(ys)) + scaling if blocks else 2 * GATHER["wall"] + 1
    camera = f"{(min(xs) + max(xs)) / 2} {(min(ys) + max(ys)) / 2} {1.25 * extent}"
    ET.SubElement(world, "camera", name="top", pos=camera, xyaxes="1 0 0 0 1 0")
    if env_id == "AntGather":
        w = GATHER["wall"]
        walls = {"north": (0, w, w, 0.5), "south": (0, -w, w, 0.5), "east": (w, 0, 0.5, w), "west": (-w, 0, 0.5, w)}
        for name, (x, y, hx, hy) in walls.items():
            geom = dict(name=f"wall_{name}", type="box", pos=f"{x} {y} 0.5", size=f"{hx} {hy} 0.5", **SOLID)
            ET.SubElement(world, "geom", **geom, rgba="0.4 0.4 0.4 1")
    return ET.tostring(root, encoding="unicode")


def gather_readings(xy: np.ndarray, yaw: float, objects: np.ndarray) -> np.ndarray:
    """rllab's range sensor: `bins` bearing bins centred on the heading, each the largest 1 - distance / range in it."""
    readings = np.zeros(GATHER["bins"])
    offsets = objects - xy
    distance = np.linalg.norm(offsets, axis=1)
    bearing = (np.arctan2(offsets[:, 1], offsets[:, 0]) - yaw + GATHER["span"] / 2) % (2 * np.pi)
    bins = np.minimum((bearing / (GATHER["span"] / GATHER["bins"])).astype(int), GATHER["bins"] - 1)
    seen = distance < GATHER["range"]
    np.maximum.at(readings, bins[seen], 1.0 - distance[seen] / GATHER["range"])
    return readings


class HiroAntEnv(gym.Env):
    """A HIRO Ant env on the `mujoco` bindings. Observation: the ant's qpos[:15], qvel[:14], t * 0.001 (30-d; AntGather:
    the first 29, 10 apple and 10 bomb range readings, t * 0.01). Action: 8 torques in [-30, 30]. Reset: qpos +
    U(-0.1, 0.1), qvel + 0.1 N(0, 1), AntMazeSparse on any robot cell. Goal: AntMaze trains on U([-4, -4], [20, 20])
    and evaluates on (0, 16); the others' is fixed (AntGather: none). Reward: -||xy - g|| (AntFall: xyz), AntMazeSparse
    1 within 1 of the goal, AntGather apples - bombs caught. Truncated at 500 steps; AntMazeSparse's training episodes
    end at the first multiple of `segment` steps after a success (HRAC's rule). info: "success" and "distance"."""

    metadata: ClassVar[dict] = {"render_modes": ["rgb_array"], "render_fps": 10}
    frame_skip = 5

    def __init__(self, env_id: str, evaluate: bool = False, render_mode: str | None = None, segment: int = 10):
        self.env_id, self.evaluate, self.render_mode, self.segment = env_id, evaluate, render_mode, segment
        self.model = mujoco.MjModel.from_xml_string(hiro_ant_xml(env_id))
        self.data = mujoco.MjData(self.model)
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (50 if env_id == "AntGather" else 30,), np.float64)
        self.action_space = gym.spaces.Box(-30.0, 30.0, (8,), np.float32)
        self.goal = None if env_id == "AntGather" else np.array(EVAL_GOALS[env_id])
        self.steps, self.succeeded = 0, False
        self.objects, self.kinds = np.zeros((0, 2)), np.zeros(0)  # AntGather's: their xy, +1 apple or -1 bomb
        self._renderer = None
        if env_id == "AntMazeSparse":
            scaling, structure = STRUCTURES[env_id]
            cells = [(i, j) for i, row in enumerate(structure) for j, c in enumerate(row) if c == "r"]
            self.starts = np.array([cell_centre(i, j, scaling, cells[0]) for i, j in cells])  # cells[0]: the origin

    def _observe(self) -> np.ndarray:
        obs = np.concatenate([self.data.qpos[:15], self.data.qvel[:14], [self.steps * 0.001]])
        if self.env_id == "AntGather":
            q = self.data.qpos
            yaw = np.arctan2(2 * (q[3] * q[6] + q[4] * q[5]), 1 - 2 * (q[5] ** 2 + q[6] ** 2))
            apples, bombs = self.objects[self.kinds > 0], self.objects[self.kinds < 0]
            readings = [gather_readings(q[:2], yaw, apples), gather_readings(q[:2], yaw, bombs)]
            obs = np.concatenate([obs[:29], *readings, [self.steps * 0.01]])
        return obs

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        mujoco.mj_resetData(self.model, self.data)
        self.data.qpos[:] += self.np_random.uniform(-0.1, 0.1, self.model.nq)
        self.data.qvel[:] += 0.1 * self.np_random.standard_normal(self.model.nv)
        if self.env_id == "AntMazeSparse":
            self.data.qpos[:2] += self.starts[self.np_random.integers(len(self.starts))]
        if self.env_id == "AntMaze" and not self.evaluate:
            self.goal = self.np_random.uniform((-4.0, -4.0), (20.0, 20.0))
        elif self.env_id in EVAL_GOALS:
            self.goal = np.array(EVAL_GOALS[self.env_id])
        if self.env_id == "AntGather":
            free = [(x, y) for x in range(-10, 11, 2) for y in range(-10, 11, 2) if x * x + y * y >= 4]
            picks = self.np_random.choice(len(free), GATHER["apples"] + GATHER["bombs"], replace=False)
            self.objects = np.array(free, dtype=np.float64)[picks]
            self.kinds = np.array([1.0] * GATHER["apples"] + [-1.0] * GATHER["bombs"])
        self.steps, self.succeeded = 0, False
        mujoco.mj_forward(self.model, self.data)
        return self._observe(), {}

    def step(self, action):
        self.data.ctrl[:] = np.clip(action, -30.0, 30.0)
        mujoco.mj_step(self.model, self.data, nstep=self.frame_skip)
        self.steps += 1
        xy = self.data.qpos[:2].copy()
        if self.env_id == "AntGather":
            caught = np.linalg.norm(self.objects - xy, axis=1) < GATHER["catch"]
            reward, info = float(self.kinds[caught].sum()), {"success": False}
            self.objects, self.kinds = self.objects[~caught], self.kinds[~caught]
        else:
            position = self.data.qpos[:3] if self.env_id == "AntFall" else xy
            distance = float(np.linalg.norm(position - self.goal))
            success = distance < SUCCESS_DISTANCE[self.env_id]
            reward = float(success) if self.env_id == "AntMazeSparse" else -distance
            info = {"success": success, "distance": distance}
            self.succeeded |= success
        stops = self.env_id == "AntMazeSparse" and not self.evaluate and self.succeeded  # HRAC's envs/__init__.py:114
        terminated = stops and self.steps % self.segment == 0
        return self._observe(), reward, terminated, self.steps >= EPISODE_STEPS, info

    def state_dict(self) -> dict:
        """For --resume: MuJoCo's integration state (time, qpos, qvel, warm start, ctrl, forces) and the env's own."""
        spec = mujoco.mjtState.mjSTATE_INTEGRATION
        physics = np.empty(mujoco.mj_stateSize(self.model, spec))
        mujoco.mj_getState(self.model, self.data, physics, spec)
        state = {"physics": physics, "steps": self.steps, "succeeded": self.succeeded, "goal": copy.copy(self.goal)}
        state |= {"objects": self.objects.copy(), "kinds": self.kinds.copy()}
        return state | {"np_random": self.np_random.bit_generator.state}

    def load_state_dict(self, state: dict) -> None:
        mujoco.mj_setState(self.model, self.data, state["physics"], mujoco.mjtState.mjSTATE_INTEGRATION)
        mujoco.mj_forward(self.model, self.data)  # the derived quantities (positions of bodies, contacts) for renders
        self.steps, self.succeeded, self.goal = state["steps"], state["succeeded"], state["goal"]
        self.objects, self.kinds = state["objects"], state["kinds"]
        self.np_random.bit_generator.state = state["np_random"]

    def render(self):
        if self._renderer is None:  # no shadows or reflections: 3x faster under software EGL on a CPU
            self.model.vis.quality.shadowsize = 0  # a visual setting only; the physics is unchanged
            self._renderer = mujoco.Renderer(self.model, 240, 240)
            self._renderer.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0
        self._renderer.update_scene(self.data, camera="top")
        # Markers in the scene only (no physics): AntGather's apples and bombs, else the goal's success-radius disc.
        if self.env_id == "AntGather":
            shape = mujoco.mjtGeom.mjGEOM_SPHERE
            colours = [(0.1, 0.8, 0.1, 1) if kind > 0 else (0.9, 0.1, 0.1, 1) for kind in self.kinds]
            markers = [((x, y, 0.5), (0.5, 0.5, 0.5), rgba) for (x, y), rgba in zip(self.objects, colours, strict=True)]
        else:
            shape, radius = mujoco.mjtGeom.mjGEOM_CYLINDER, SUCCESS_DISTANCE[self.env_id]
            z = self.goal[2] if len(self.goal) == 3 else 0.05
            markers = [((*self.goal[:2], z), (radius, 0.05, 0.0), (0.1, 0.8, 0.1, 0.35))]
        scene = self._renderer.scene
        for pos, size, rgba in markers[: scene.maxgeom - scene.ngeom]:
            geom = (np.array(size, dtype=np.float64), np.array(pos, dtype=np.float64), np.eye(3).ravel())
            mujoco.mjv_initGeom(scene.geoms[scene.ngeom], shape, *geom, np.array(rgba, dtype=np.float32))
            scene.ngeom += 1
        return self._renderer.render()

    def close(self):
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


# --- Resume: the state a stopped run continues from -------------------------------------------------------------------


@dataclass
class LoopState:
    """The variables the training loop carries from one step to the next (saved whole for --resume)."""

    next_eval: int
    next_adjacency: int
    state: np.ndarray
    seg_states: np.ndarray  # the segment in progress: its k + 1 states and k actions
    seg_actions: np.ndarray
    step: int = 0
    episodes: int = 0
    evaluations: int = 0
    adjacency_due: bool = False  # the work an episode end calls for, and the epochs done of the adjacency training
    adjacency_epochs: int = 0
    eval_due: bool = False
    result: dict = field(default_factory=lambda: dict.fromkeys(("success", "distance", "return"), float("nan")))
    recent: dict = field(default_factory=lambda: {"final_distance": [], "subgoal_distance": [], "return": []})
    episode_steps: int = 0  # the episode in progress, from here on (set at its step 0)
    goal: np.ndarray | None = None
    positions: list = field(default_factory=list)
    remaining: list = field(default_factory=list)
    proposals: list = field(default_factory=list)
    episode_return: float = 0.0
    ctrl_rewards: float = 0.0
    subgoal: np.ndarray | None = None
    proposed: np.ndarray | None = None
    seg_reward: float = 0.0


def training_state(loop: LoopState, agent: Agent, stores: dict, rng: np.random.Generator) -> dict:
    """Everything a resumed run needs but the global random states (save_resume adds them)."""
    state = {"agent": agent.state_dicts(training=True)} | {name: store.state_dict() for name, store in stores.items()}
    return state | {"numpy_rng": rng.bit_generator.state, "loop": copy.deepcopy(vars(loop))}


def restore_training_state(saved: dict, agent: Agent, stores: dict, rng: np.random.Generator) -> LoopState:
    """Load what training_state saved into the agent, the stores and the generators; return the loop's state."""
    agent.load_state_dicts(saved["agent"], training=True)
    for name, store in stores.items():
        store.load_state_dict(saved[name])
    rng.bit_generator.state = saved["numpy_rng"]
    rng_states(restore=saved["rng"])  # last: building the agent and the envs drew from them
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
    """Reject bad flags before any work (exit status 2), naming the flag and the valid choices."""
    errors = common_errors(args)
    if args.env_id not in ENV_IDS:
        errors.append(f"--env-id {args.env_id!r} is unknown: use one of {', '.join(ENV_IDS)}")
    if args.groups < 0 or (args.groups and args.embed_dim >= 1 and args.embed_dim % args.groups):
        divisors = [g for g in range(1, args.embed_dim + 1) if args.embed_dim % g == 0]
        wanted = f"0 (HRAC) or divide --embed-dim {args.embed_dim}: one of {divisors}"
        errors.append(f"--groups must be {wanted}; got {args.groups}")
    errors += range_errors(args, "ctrl_updates man_updates correction_samples adj_weight critic_weight_decay", 0)
    errors += range_errors(args, "man_reward_scale policy_noise noise_clip ctrl_noise man_noise", 0)
    errors += range_errors(args, "total_timesteps buffer_size batch_size hidden_dim adj_frequency adj_epochs", 1)
    errors += range_errors(args, "adj_batch_size eval_frequency eval_episodes embed_dim encoder_hidden_dim", 1)
    errors += range_errors(args, "k", 2)  # a one-step segment has no pair of cells k - 1 steps apart to label adjacent
    errors += range_errors(args, "actor_lr critic_lr encoder_lr adj_lr adj_margin_pos adj_margin_neg", 0, low_open=True)
    errors += range_errors(args, "subgoal_scale", 0, 100, low_open=True)  # metres; the largest arena is 48 m across
    errors += range_errors(args, "tau ctrl_gamma man_gamma", 0, 1, low_open=True)  # gamma 1 is safe: episodes terminate
    if args.k >= 1 and EPISODE_STEPS % args.k:
        divisors = [k for k in range(2, EPISODE_STEPS + 1) if EPISODE_STEPS % k == 0]
        errors.append(f"--k must divide the episode length {EPISODE_STEPS}: one of {divisors}; got {args.k}")
    if args.adj_margin_neg < args.adj_margin_pos:
        errors.append(f"--adj-margin-neg ({args.adj_margin_neg}) must be >= --adj-margin-pos ({args.adj_margin_pos})")
    if args.k >= 1 and args.total_timesteps < args.k:  # the manager learns from whole segments
        errors.append(f"--total-timesteps ({args.total_timesteps}) must be >= --k ({args.k}): one whole segment")
    if args.batch_size > args.buffer_size:
        errors.append(f"--batch-size ({args.batch_size}) must be <= --buffer-size ({args.buffer_size})")
    if args.checkpoint is not None and args.save_model:
        errors.append("--save-model does nothing with --checkpoint (which evaluates a saved agent, without training)")
    exit_on_errors(errors)


if __name__ == "__main__":
    main(tyro.cli(Args))
