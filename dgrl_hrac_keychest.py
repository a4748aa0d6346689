"""DGRL on HRAC in the Key-Chest grid: discretized subgoals for a two-level agent.

Paper: Islam et al. 2022, "Discrete Factorial Representations as an Abstraction for Goal Conditioned RL", section "Goal
Grounding in KeyChest Maze Navigation Domain" and appendix "KeyChest Domain". The agent is HRAC (Zhang et al., NeurIPS
2020): every k = 10 steps a TD3 high level proposes a cell (row, col), kept within k-step reach by an adjacency network
trained contrastively; an A2C low level is rewarded for reaching it (Euclidean distance below 0.5, the paper's test).
DGRL (`--groups G`) passes each subgoal through an encoder, vq.py's shared-codebook bottleneck and a decoder whose
reconstruction grounds the codes; as in the paper, the low level sees the discrete embedding and is rewarded for
reaching the raw subgoal (`--dgrl-goal decoded`, ours: the decoded one for both). Docs: docs/dgrl_hrac_keychest.md.

    python dgrl_hrac_keychest.py --groups 16    # the paper's DGRL G=16: 2M frames (about 28 min on a CPU core)
    python dgrl_hrac_keychest.py --groups 0     # HRAC
    python dgrl_hrac_keychest.py --groups 16 --resume runs/<run>   # continue a stopped run exactly (its flags)
    python dgrl_hrac_keychest.py --total-timesteps 20000 --adj-init-steps 5000 --man-buffer-size 400 \
        --eval-frequency 5000                   # smoke run (about 30 s)

The study: python benchmark/launch.py --preset keychest; update times: benchmark/speed/bench_hrac_keychest.py.
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
from typing import ClassVar, Literal

import gymnasium as gym
import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
import tyro
from torch.utils.tensorboard import SummaryWriter

from vq import VectorQuantizerEMA, active_codes, make_target, perplexity, update_target


@dataclass
class Args:
    # Environment
    env_id: Literal["KeyChest"] = "KeyChest"
    """the environment (HRAC's Key-Chest grid)"""
    total_timesteps: int = 2_000_000
    """total environment frames, adjacency pre-training included (as the original counts them)"""
    num_envs: int = 8
    """parallel environments stepped in one batch (the original runs 1; see the docs)"""
    max_episode_steps: int = 500
    """episode step limit (truncation, bootstrapped through)"""
    random_action_prob: float = 0.25
    """probability that the environment replaces the chosen action by a uniformly random one"""

    # Algorithm: HRAC high level (TD3 over absolute cells)
    k: int = 10
    """steps between two subgoals (the high level's action repeat)"""
    man_actor_lr: float = 1e-4
    """Adam learning rate of the high-level actor"""
    man_critic_lr: float = 1e-3
    """Adam learning rate of the high-level twin critics"""
    man_gamma: float = 0.99
    """high-level discount (one high-level step = k frames)"""
    man_tau: float = 0.001
    """Polyak rate of the high-level target networks"""
    man_policy_delay: int = 2
    """the critic term of the actor loss is applied every this many updates (the adjacency term every update)"""
    man_buffer_size: int = 20_000
    """high-level replay capacity (k-step transitions); training starts when it is half full"""
    man_batch_size: int = 64
    """high-level batch size"""
    man_noise: float = 5.0
    """std of the Gaussian exploration noise on the high level's subgoals, in cells"""
    man_reward_scale: float = 1.0
    """scale of the environment reward summed over a k-step segment"""
    n_noisy_goals: int = 20
    """noisy candidate subgoals drawn per decision; one deemed k-step reachable is picked (0 = plain Gaussian noise)"""
    adj_weight: float = 20.0
    """weight of the adjacency loss in the high level's actor loss"""
    hidden_dim: int = 300
    """hidden units of both levels' 2-layer networks"""

    # Algorithm: HRAC low level (A2C)
    ctrl_lr: float = 1e-4
    """Adam learning rate of the low-level actor-critic"""
    ctrl_gamma: float = 0.99
    """low-level discount; returns are truncated at the end of each k-step segment"""
    ctrl_entropy: float = 0.01
    """entropy bonus coefficient"""
    ctrl_reward_scale: float = 1.0
    """low-level reward for a step that ends on its subgoal (--reach-rule, --goal-threshold)"""
    goal_threshold: float = 0.5
    """reach radius, in cells (see --reach-rule)"""
    reach_rule: Literal["euclidean", "box"] = "euclidean"
    """reached: Euclidean distance below --goal-threshold (the paper), or within it in both coordinates (HRAC's box)"""

    # Algorithm: adjacency network
    adj_lr: float = 2e-4
    """Adam learning rate of the adjacency network"""
    adj_margin_pos: float = 1.0
    """contrastive margin for k-step adjacent pairs"""
    adj_margin_neg: float = 1.2
    """contrastive margin for non-adjacent pairs; (pos + neg) / 2 is the reachability threshold"""
    adj_init_steps: int = 50_000
    """frames of random-subgoal exploration (the chest does not end episodes) before the first adjacency training"""
    adj_init_epochs: int = 50
    """epochs of the first adjacency training"""
    adj_frequency: int = 50_000
    """env steps (frames) between two adjacency retrainings, counted from the end of the exploration"""
    adj_epochs: int = 25
    """epochs of each retraining"""
    adj_batch_size: int = 64
    """adjacency batch size (pairs of visited cells)"""
    adj_hidden_dim: int = 128
    """hidden units of the 4-layer adjacency network"""
    adj_embed_dim: int = 32
    """output size of the adjacency network"""

    # Evaluation and logging
    eval_frequency: int = 25_000
    """frames between evaluations, at its multiples after the exploration (25,000 = 50 full episodes of 8 envs)"""
    eval_episodes: int = 50
    """episodes per evaluation (random starts, deterministic subgoals, sampled low-level actions)"""
    log_frequency: int = 5_000
    """env steps (frames) between two logs of the latest update's losses"""

    # Algorithm: DGRL subgoal bottleneck
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
    dgrl_goal: Literal["embedding", "decoded"] = "embedding"
    """the low level's input under DGRL: the discrete embedding (the paper) or the decoded discretized subgoal (ours)"""
    ae_hidden_dim: int = 128
    """hidden units of the subgoal encoder and decoder"""
    ae_lr: float = 1e-3
    """Adam learning rate of the subgoal autoencoder"""
    ae_init_steps: int = 2000
    """autoencoder steps on uniform random subgoals during adjacency pre-training"""
    ae_batch_size: int = 256
    """batch size of those steps"""

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
    widths = [in_dim] + [hidden_dim] * n_hidden  # the inputs of the n_hidden ReLU layers, then of the output layer
    layers = [module for width in widths[:-1] for module in (nn.Linear(width, hidden_dim), nn.ReLU())]
    return nn.Sequential(*layers, nn.Linear(widths[-1], out_dim))


class ManagerActor(nn.Module):
    """High-level TD3 actor: state -> absolute subgoal cell, sigmoid x (13, 17)."""

    def __init__(self, hidden_dim: int):
        super().__init__()
        self.net = mlp(3, hidden_dim, 2)
        self.register_buffer("scale", torch.as_tensor(GOAL_SCALE))

    def forward(self, states: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(self.net(states)) * self.scale


class TwinCritic(nn.Module):
    """High-level TD3 twin critics Q(state, subgoal)."""

    def __init__(self, hidden_dim: int):
        super().__init__()
        self.q1, self.q2 = mlp(5, hidden_dim, 1), mlp(5, hidden_dim, 1)

    def forward(self, states: torch.Tensor, goals: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = torch.cat([states, goals], 1)
        return self.q1(x).squeeze(1), self.q2(x).squeeze(1)


class Controller(nn.Module):
    """Low-level A2C: separate policy and value networks on (state, subgoal input)."""

    def __init__(self, goal_input_dim: int, hidden_dim: int):
        super().__init__()
        self.policy = mlp(3 + goal_input_dim, hidden_dim, len(MOVES))
        self.value = mlp(3 + goal_input_dim, hidden_dim, 1)

    def forward(self, states: torch.Tensor, goal_inputs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = torch.cat([states, goal_inputs], 1)
        return self.policy(x), self.value(x).squeeze(1)


class AdjacencyNet(nn.Module):
    """phi: cell -> embedding whose distances tell k-step reachability (HRAC)."""

    def __init__(self, hidden_dim: int, embed_dim: int):
        super().__init__()
        self.net = mlp(2, hidden_dim, embed_dim, n_hidden=3)

    def forward(self, cells: torch.Tensor) -> torch.Tensor:
        return self.net(cells)


class GoalAutoencoder(nn.Module):  # DGRL
    """Subgoal -> encoder -> grouped VQ (shared EMA codebook) -> decoder -> subgoal (paper appendix "KeyChest")."""

    def __init__(self, args: Args):
        super().__init__()
        self.encoder = mlp(2, args.ae_hidden_dim, args.embed_dim, n_hidden=1)  # DGRL
        vq_flags = {"beta": args.vq_beta, "decay": args.vq_decay, "dead_code_steps": args.vq_dead_code_steps}
        self.vq = VectorQuantizerEMA(args.embed_dim, args.n_embed, args.groups, **vq_flags)  # DGRL
        self.decoder = mlp(args.embed_dim, args.ae_hidden_dim, 2, n_hidden=1)  # DGRL
        self.register_buffer("scale", torch.as_tensor(GOAL_SCALE))

    def forward(self, goals: torch.Tensor, update: bool = False):
        """(discrete embedding, commitment loss, code indices, reconstruction in [0, 1]^2 units) of raw subgoals."""
        quantized, vq_loss, indices = self.vq(self.encoder(goals / self.scale), update=update)  # DGRL
        return quantized, vq_loss, indices, self.decoder(quantized)  # DGRL


@dataclass
class Agent:
    """HRAC's two levels and adjacency network, DGRL's subgoal autoencoder (codebook moved by EMA); Adam for each."""

    actor: ManagerActor
    critic: TwinCritic
    actor_target: ManagerActor
    critic_target: TwinCritic
    controller: Controller
    adjacency: AdjacencyNet
    goal_ae: GoalAutoencoder | None  # None for --groups 0
    dgrl_goal: str  # what the low level gets of a subgoal under DGRL, "decoded" or "embedding" (see Args)
    actor_optimizer: torch.optim.Optimizer
    critic_optimizer: torch.optim.Optimizer
    controller_optimizer: torch.optim.Optimizer
    adjacency_optimizer: torch.optim.Optimizer
    ae_optimizer: torch.optim.Optimizer | None

    def state_dicts(self) -> dict:
        """What evaluation needs, as checkpoint entries (the autoencoder's with the codebook and its EMA buffers)."""
        entries = {name: getattr(self, name).state_dict() for name in ("actor", "critic", "controller", "adjacency")}
        return entries | {"goal_autoencoder": None if self.goal_ae is None else self.goal_ae.state_dict()}


def make_agent(args: Args, device: torch.device) -> Agent:
    """The agent of a run, on `device` (networks built in a fixed order, so a seed gives the same weights)."""
    dgrl = args.groups > 0
    actor, critic = ManagerActor(args.hidden_dim).to(device), TwinCritic(args.hidden_dim).to(device)
    goal_ae = GoalAutoencoder(args).to(device) if dgrl else None  # DGRL
    goal_input_dim = args.embed_dim if dgrl and args.dgrl_goal == "embedding" else 2  # DGRL: the embedding as input
    controller = Controller(goal_input_dim, args.hidden_dim).to(device)
    adjacency = AdjacencyNet(args.adj_hidden_dim, args.adj_embed_dim).to(device).requires_grad_(False)  # trained apart

    def adam(network: nn.Module, lr: float) -> torch.optim.Optimizer:
        return torch.optim.Adam(network.parameters(), lr=lr, fused=True)

    return Agent(
        actor=actor, critic=critic, actor_target=make_target(actor), critic_target=make_target(critic),
        controller=controller, adjacency=adjacency, goal_ae=goal_ae, dgrl_goal=args.dgrl_goal,
        actor_optimizer=adam(actor, args.man_actor_lr), critic_optimizer=adam(critic, args.man_critic_lr),
        controller_optimizer=adam(controller, args.ctrl_lr), adjacency_optimizer=adam(adjacency, args.adj_lr),
        ae_optimizer=adam(goal_ae, args.ae_lr) if dgrl else None,
    )  # fmt: skip


# --- Buffers, losses, updates -----------------------------------------------------------------------------------------


class ManagerReplay:
    """Ring buffer of k-step high-level transitions (state, subgoal, reward, next state, terminal) on the device."""

    COLUMNS = ("states", "goals", "rewards", "next_states", "terminals")

    def __init__(self, capacity: int, rng: np.random.Generator, device: torch.device | str = "cpu"):
        self.capacity, self.rng, self.size, self.pointer = capacity, rng, 0, 0
        for name, row_shape in zip(self.COLUMNS, ((3,), (2,), (), (3,), ()), strict=True):
            setattr(self, name, torch.zeros((capacity, *row_shape), device=device))

    def add(self, *columns: np.ndarray) -> None:
        """Append host rows of the five columns (one copy to the device per column)."""
        slots = torch.as_tensor((self.pointer + np.arange(len(columns[0]))) % self.capacity, device=self.states.device)
        for name, rows in zip(self.COLUMNS, columns, strict=True):
            getattr(self, name)[slots] = torch.as_tensor(np.asarray(rows, dtype=np.float32), device=self.states.device)
        self.pointer = int((self.pointer + len(slots)) % self.capacity)
        self.size = min(self.size + len(slots), self.capacity)

    def started(self) -> bool:
        return self.size >= self.capacity // 2

    def state(self) -> dict:
        columns = {name: getattr(self, name)[: self.size].cpu() for name in self.COLUMNS}
        return {"size": self.size, "pointer": self.pointer, "columns": columns}

    def load_state(self, state: dict) -> None:
        self.size, self.pointer = state["size"], state["pointer"]
        for name, column in state["columns"].items():
            getattr(self, name)[: self.size] = torch.as_tensor(column)

    def sample(self, batch_size: int, device: torch.device) -> tuple[torch.Tensor, ...]:
        """Distinct transitions, as the original; redrawing a rare repeat is 5x faster than choice(replace=False)."""
        if self.size < 16 * batch_size:
            batch = self.rng.choice(self.size, batch_size, replace=False)
        else:
            batch = self.rng.integers(self.size, size=batch_size)
            while len(np.unique(batch)) < batch_size:
                batch = self.rng.integers(self.size, size=batch_size)
        batch = torch.as_tensor(batch, device=self.states.device)
        return tuple(getattr(self, name).index_select(0, batch).to(device) for name in self.COLUMNS)


def segment_discounts(gamma: float, k: int, device: torch.device | str = "cpu") -> torch.Tensor:
    """(k, k) float64: [i, j] = gamma^(j - i) for j >= i, else 0; numpy's powers (torch.pow differs in the last bit)."""
    offsets = np.arange(k)[None, :] - np.arange(k)[:, None]  # offsets[i, j] = j - i
    return torch.as_tensor(np.where(offsets >= 0, gamma ** np.maximum(offsets, 0), 0.0), device=device)


def by_segment(values: torch.Tensor, k: int) -> torch.Tensor:
    """Steps 0..k-1, k..2k-1, ... as the rows of a (segments, k) matrix, the last one padded with zeros."""
    return F.pad(values, (0, -len(values) % k)).view(-1, k)


def segment_returns(rewards: torch.Tensor, discounts: torch.Tensor) -> torch.Tensor:
    """HRAC's low-level A2C target (float64): discounted returns that stop, unbootstrapped, at each segment's end."""
    return (by_segment(rewards.double(), len(discounts)) @ discounts.T).reshape(-1)[: len(rewards)]


def goal_reached(next_states: torch.Tensor, goals: torch.Tensor, threshold: float, rule: str) -> torch.Tensor:
    """1 where the next cell reaches the goal: nearer than `threshold` ("euclidean", paper) or in both axes ("box")."""
    offsets = next_states[:, :2] - goals
    return (offsets.norm(dim=1) < threshold if rule == "euclidean" else (offsets.abs() <= threshold).all(1)).float()


def a2c_loss(logits, values, actions, returns, entropy_coef: float) -> tuple[torch.Tensor, ...]:
    """HRAC's A2C loss: mean of -A log pi(a) + A^2 - c H(pi), A = return - V (the original's unhalved value loss)."""
    log_probs, advantages = F.log_softmax(logits, 1), returns - values
    policy_loss = -(advantages.detach() * log_probs.gather(1, actions.unsqueeze(1)).squeeze(1)).mean()
    value_loss, entropy = advantages.pow(2).mean(), -(log_probs.exp() * log_probs).sum(1).mean()
    return policy_loss + value_loss - entropy_coef * entropy, policy_loss, value_loss, entropy


def contrastive_loss(emb_a, emb_b, labels, margin_pos: float, margin_neg: float) -> torch.Tensor:
    """HRAC's adjacency loss: mean(l * max(0, d - m+)) + mean((1 - l) * max(0, m- - d)), d = ||phi_a - phi_b||."""
    distances = torch.sqrt((emb_a - emb_b).pow(2).sum(1) + 1e-12)
    adjacent_term = (labels * (distances - margin_pos).clamp(min=0)).mean()
    return adjacent_term + ((1 - labels) * (margin_neg - distances).clamp(min=0)).mean()


def mark_adjacent(adjacency: np.ndarray, visited: np.ndarray, cells: np.ndarray, k: int) -> None:
    """Mark cells t and t+j of one trajectory (flat indices) adjacent in the (H*W, H*W) matrix, for 1 <= j < k."""
    visited[cells] = True
    for offset in range(1, min(k, len(cells))):
        adjacency[cells[:-offset], cells[offset:]] = adjacency[cells[offset:], cells[:-offset]] = True


def learn(optimizer: torch.optim.Optimizer, loss: torch.Tensor, max_grad_norm: float | None = None) -> None:
    """One step on `loss`: clear the gradients, backpropagate, clip their norm to `max_grad_norm` if given, step."""
    optimizer.zero_grad()
    loss.backward()
    if max_grad_norm is not None:
        params = [param for group in optimizer.param_groups for param in group["params"]]
        torch.nn.utils.clip_grad_norm_(params, max_grad_norm, foreach=True)
    optimizer.step()


def train_adjacency(agent: Agent, adjacency: np.ndarray, visited: np.ndarray, epochs: int, args: Args, rng) -> float:
    """`epochs` passes over all pairs of visited cells in shuffled batches; the last epoch's mean loss (NaN if none)."""
    anet, device, cells = agent.adjacency, next(agent.adjacency.parameters()).device, np.flatnonzero(visited)
    first, second = np.triu_indices(len(cells), 1)
    coordinates = torch.as_tensor(np.stack(np.divmod(cells, WIDTH), 1), dtype=torch.float32, device=device)
    labels_all = torch.as_tensor(adjacency[cells[first], cells[second]], dtype=torch.float32, device=device)
    first, second = torch.as_tensor(first, device=device), torch.as_tensor(second, device=device)
    anet.requires_grad_(True)
    losses = []
    for _ in range(epochs):
        losses = []
        for batch in torch.as_tensor(rng.permutation(len(first)), device=device).split(args.adj_batch_size):
            embeddings = anet(coordinates[first[batch]]), anet(coordinates[second[batch]])
            loss = contrastive_loss(*embeddings, labels_all[batch], args.adj_margin_pos, args.adj_margin_neg)
            learn(agent.adjacency_optimizer, loss)
            losses.append(loss.detach())
    anet.requires_grad_(False)  # the high-level actor's adjacency loss must not train it
    return torch.stack(losses).mean().item() if losses else float("nan")


def controller_goals(goal_ae: GoalAutoencoder | None, goals: torch.Tensor, mode: str, update: bool = False):
    """(what the low level sees of raw subgoals g, the cells its reward is measured to; both detached), plus DGRL's
    (commitment loss, codes, reconstruction). HRAC: (g, g); DGRL "embedding": (embedding, g); "decoded": (g', g')."""
    if goal_ae is None:
        return goals, goals, None
    quantized, vq_loss, codes, reconstruction = goal_ae(goals, update=update)  # DGRL
    if mode == "embedding":
        return quantized.detach(), goals, (vq_loss, codes, reconstruction)  # DGRL: the low level sees the embedding
    decoded = (reconstruction * goal_ae.scale).detach()  # DGRL
    return decoded, decoded, (vq_loss, codes, reconstruction)  # DGRL: it sees, and is rewarded for, the decoded subgoal


def goal_autoencoder_step(agent: Agent, goals: torch.Tensor, reconstruction, vq_loss) -> dict[str, torch.Tensor]:
    """One Adam step of the subgoal autoencoder on reconstruction (MSE in [0, 1]^2 units) + the commitment loss."""
    reconstruction_loss = F.mse_loss(reconstruction, goals / agent.goal_ae.scale)  # DGRL
    learn(agent.ae_optimizer, reconstruction_loss + vq_loss)  # DGRL
    return {"losses/goal_reconstruction": reconstruction_loss.detach(), "vq/commit_loss": vq_loss.detach()}


def goal_autoencoder_update(agent: Agent, goals: torch.Tensor) -> dict[str, torch.Tensor]:
    """The autoencoder's pre-training update on raw subgoals: the codebook's EMA step, then Adam's."""
    _, vq_loss, _, reconstruction = agent.goal_ae(goals, update=True)  # DGRL
    return goal_autoencoder_step(agent, goals, reconstruction, vq_loss)


def controller_update(agent: Agent, states, goals, actions, next_states, discounts, args: Args) -> dict:
    """HRAC's low-level A2C update on one episode of raw subgoals; detached figures (--fast: a dynamic length). Under
    DGRL the current autoencoder recomputes the goals and takes its training step; the A2C loss never shapes codes."""
    goal_inputs, target_goals, ae_outputs = controller_goals(agent.goal_ae, goals, agent.dgrl_goal, update=True)  # DGRL
    figures = {}
    if agent.goal_ae is not None:
        (vq_loss, codes, reconstruction), n_embed = ae_outputs, agent.goal_ae.vq.n_embed
        figures = goal_autoencoder_step(agent, goals, reconstruction, vq_loss)  # DGRL
        figures |= {"vq/perplexity": perplexity(codes, n_embed), "vq/active_codes": active_codes(codes, n_embed)}
    intrinsic = args.ctrl_reward_scale * goal_reached(next_states, target_goals, args.goal_threshold, args.reach_rule)
    returns = segment_returns(intrinsic, discounts).float()
    logits, values = agent.controller(states, goal_inputs)  # DGRL: the embedding or the decoded subgoal, detached
    loss, policy_loss, value_loss, entropy = a2c_loss(logits, values, actions, returns, args.ctrl_entropy)
    learn(agent.controller_optimizer, loss)
    figures |= {"losses/ctrl_policy_loss": policy_loss.detach(), "losses/ctrl_value_loss": value_loss.detach()}
    figures |= {"losses/ctrl_entropy": entropy.detach(), "charts/intrinsic_reward": intrinsic.mean()}
    reached_segments = by_segment(intrinsic, len(discounts)).sum(1) > 0  # segments with a reaching step
    return figures | {"charts/subgoal_reach_rate": reached_segments.double().mean()}


def manager_update(agent: Agent, batch: tuple, args: Args, threshold: float, policy_term) -> dict[str, torch.Tensor]:
    """One HRAC high-level TD3 update: twin critics on r + gamma * min Q'(s', pi'(s')) (no target-policy noise), the
    actor on -Q1(s, pi(s)) (if `policy_term`: TD3's delay) + adj_weight x the adjacency loss hinged at `threshold`,
    Polyak targets; detached figures. `policy_term`: a bool, or under cudagraphs a 0-d tensor 1.0 or 0.0 (no branch)."""
    states, goals, rewards, next_states, terminals = batch
    with torch.no_grad():
        next_q = torch.min(*agent.critic_target(next_states, agent.actor_target(next_states)))
        td_target = rewards + args.man_gamma * (1 - terminals) * next_q
    q1, q2 = agent.critic(states, goals)
    critic_loss = F.mse_loss(q1, td_target) + F.mse_loss(q2, td_target)
    learn(agent.critic_optimizer, critic_loss)
    proposed = agent.actor(states)
    q_term = 0.0 if policy_term is False else -agent.critic.q1(torch.cat([states, proposed], 1)).mean() * policy_term
    state_embeddings = agent.adjacency(states[:, :2])  # no gradient: the adjacency network is frozen (trained apart)
    goal_loss = ((agent.adjacency(proposed) - state_embeddings).norm(dim=1) - threshold).clamp(min=0).mean()
    learn(agent.actor_optimizer, q_term + args.adj_weight * goal_loss)
    update_target(agent.actor_target, agent.actor, args.man_tau)
    update_target(agent.critic_target, agent.critic, args.man_tau)
    figures = {"losses/man_critic_loss": critic_loss.detach(), "losses/man_goal_loss": goal_loss.detach()}
    return figures | {"losses/man_q_values": q1.detach().mean()}


# --- Acting: the high level's subgoals and the low level's roll-out ---------------------------------------------------


def uniform_subgoals(count: int, device: torch.device) -> torch.Tensor:
    """`count` uniformly random points of [0, 13] x [0, 17]: HRAC's subgoals before the high level trains."""
    return torch.rand(count, 2, device=device) * torch.as_tensor(GOAL_SCALE, device=device)


@torch.no_grad()
def propose_subgoals(actor, anet, states, *, threshold: float, explore: bool, n_noisy_goals: int, noise: float):
    """HRAC's subgoal choice: the actor's output; exploring, a uniform pick among n_noisy_goals Gaussian candidates
    around it (std `noise` cells, clipped to the grid) that the adjacency network deems k-step reachable, else it."""
    raw = actor(states)
    if not explore:
        return raw
    candidates = raw.unsqueeze(1) + noise * torch.randn((len(states), max(n_noisy_goals, 1), 2), device=raw.device)
    noisy = torch.minimum(candidates.clamp(min=0), actor.scale)
    if n_noisy_goals == 0:
        return noisy[:, 0]
    reachable = (anet(noisy) - anet(states[:, :2]).unsqueeze(1)).norm(dim=2) < threshold
    pick = torch.where(reachable, torch.rand(reachable.shape, device=raw.device), -1.0).argmax(1)
    return torch.where(reachable.any(1, keepdim=True), noisy[torch.arange(len(states)), pick], raw)


class ControllerRollout:
    """The low level acting on subgoals from `choose_subgoals(states)`, new every k steps of an episode. `step()` gives
    (observations, t_episode, raw subgoals, actions, true next observations, rewards, terminations, done, infos)."""

    def __init__(self, envs, observations: np.ndarray, agent: Agent, choose_subgoals, k: int):
        self.envs, self.agent, self.choose_subgoals, self.k = envs, agent, choose_subgoals, k
        self.observations, self.t_episode = observations, np.zeros(envs.num_envs, dtype=np.int64)
        self.goals = torch.zeros(envs.num_envs, 2, device=next(agent.controller.parameters()).device)
        self.goal_inputs = controller_goals(agent.goal_ae, self.goals, agent.dgrl_goal)[0]  # DGRL

    def step(self):
        agent = self.agent
        states = torch.as_tensor(self.observations, device=self.goals.device)
        new_segment = self.t_episode % self.k == 0
        if new_segment.any():
            index = torch.as_tensor(np.flatnonzero(new_segment), device=self.goals.device)
            self.goals[index] = self.choose_subgoals(states[index])
            self.goal_inputs[index] = controller_goals(agent.goal_ae, self.goals[index], agent.dgrl_goal)[0]  # DGRL
        with torch.no_grad():
            logits, _ = agent.controller(states, self.goal_inputs)  # DGRL: z_q or the decoded subgoal
            actions = torch.multinomial(F.softmax(logits, 1), 1).squeeze(1).cpu().numpy()
        next_observations, rewards, terminations, truncations, infos = self.envs.step(actions)
        done = terminations | truncations
        real_next = np.where(done[:, None], infos["final_obs"], next_observations) if done.any() else next_observations
        goals = self.goals.cpu().numpy().copy()
        step = (self.observations, self.t_episode.copy(), goals, actions, real_next, rewards, terminations, done, infos)
        self.t_episode, self.observations = np.where(done, 0, self.t_episode + 1), next_observations
        return step

    def state(self) -> dict:  # goal_inputs: as the autoencoder of the time the subgoals were chosen computed them
        return {key: getattr(self, key) for key in ("observations", "t_episode", "goals", "goal_inputs")}

    def load_state(self, state: dict) -> None:
        for key, value in state.items():
            setattr(self, key, value.to(self.goals.device) if isinstance(value, torch.Tensor) else value)


# --- The run: setup, the training loop, the end -----------------------------------------------------------------------


def main(args: Args) -> None:
    """One run: build the envs and agent, explore to pre-train adjacency, then train both levels; or --checkpoint."""
    validate(args)
    run_name = f"{args.env_id}__G{args.groups}__{args.exp_name}__{args.seed}__{int(time.time())}"
    run_name = run_name if args.resume is None else os.path.basename(os.path.normpath(args.resume))
    if args.resume is not None:  # a run still running elsewhere: exit 2 at once, touching nothing
        hold_run_folder(run_name, check_only=True)
    saved = load_resume(args) if args.resume is not None else None
    dgrl = args.groups > 0
    device = seed_and_device(args)
    rng = np.random.default_rng(args.seed)  # the replay's and the adjacency training's draws
    threshold = (args.adj_margin_pos + args.adj_margin_neg) / 2  # embedding distance deemed "k-step reachable"
    agent = make_agent(args, device)
    eval_envs = KeyChestVecEnv(args.eval_episodes, args.max_episode_steps, args.random_action_prob)
    eval_envs.reset(seed=args.seed + 100)  # one evaluation stream per run, continued across evaluations

    stop = stop_on_signals()  # from here on Ctrl-C or SIGTERM ends the run cleanly

    if args.checkpoint is not None:
        evaluate_checkpoint(args, agent, eval_envs, device)
        return

    # The exploration and the training envs, each acting through the low level, and the high level's replay.
    distances_bfs = shortest_path_lengths()
    n_envs, max_steps, rows = args.num_envs, args.max_episode_steps, np.arange(args.num_envs)
    explore_envs = KeyChestVecEnv(n_envs, max_steps, args.random_action_prob, terminate_at_chest=False)
    starts = explore_envs.reset(seed=args.seed + 200)[0]
    explore_rollout = ControllerRollout(explore_envs, starts, agent, lambda x: uniform_subgoals(len(x), device), args.k)
    replay = ManagerReplay(args.man_buffer_size, rng, device)
    envs = gym.wrappers.vector.RecordEpisodeStatistics(KeyChestVecEnv(n_envs, max_steps, args.random_action_prob))

    def high_level_subgoals(states: torch.Tensor) -> torch.Tensor:  # uniform until the replay is half full
        if not replay.started():
            return uniform_subgoals(len(states), device)
        noise = {"n_noisy_goals": args.n_noisy_goals, "noise": args.man_noise}
        return propose_subgoals(agent.actor, agent.adjacency, states, threshold=threshold, explore=True, **noise)

    rollout = ControllerRollout(envs, envs.reset(seed=args.seed)[0], agent, high_level_subgoals, args.k)
    loop = new_loop_state(args)
    if saved is not None:  # continue the stopped run: its networks, replay, envs mid-episode and loop variables
        loop = restore_training_state(saved, agent, rng, replay, explore_rollout, rollout, eval_envs)
        rng_states(restore=saved["rng"])  # last: building the agent and the envs above drew from them

    # The updates under --fast, after the restore (under cudagraphs the A2C update, of varying length, stays compiled).
    ctrl_optimizers = [agent.controller_optimizer] + ([agent.ae_optimizer] if dgrl else [])  # the autoencoder's too
    update_controller = fast_update(controller_update, args.fast.replace("cudagraphs", "compile"), ctrl_optimizers)
    update_manager = fast_update(manager_update, args.fast, [agent.critic_optimizer, agent.actor_optimizer])
    update_goal_ae = fast_update(goal_autoencoder_update, args.fast, [agent.ae_optimizer]) if dgrl else None
    policy_terms = torch.arange(2.0, device=device).unbind() if args.fast == "cudagraphs" else (False, True)
    discounts = segment_discounts(args.ctrl_gamma, args.k, device)

    # Every save follows all logging of its frame, so a resumed run logs from the next frame on.
    _lock = hold_run_folder(run_name)  # one process writes a run folder, from its first write to its end
    writer = make_writer(args, run_name, purge_step=None if saved is None else loop.frames + 1)
    progress = Progress(args.total_timesteps, unit="frame", start_step=loop.frames)
    resumed = "" if saved is None else f", resumed at frame {loop.frames}"
    print(f"{run_name}: {args.num_envs} envs, {args.total_timesteps} frames, device {device}{resumed}")

    # Phase 1: random-subgoal exploration (the chest ends no episode) to learn k-step adjacency, as HRAC does first.
    while loop.frames < args.adj_init_steps and not stop:
        observations, t_episode, _, _, real_next, _, _, done, _ = explore_rollout.step()
        loop.trajectories[rows, t_episode] = observations[:, 0] * WIDTH + observations[:, 1]
        loop.trajectories[rows, t_episode + 1] = real_next[:, 0] * WIDTH + real_next[:, 1]
        loop.frames += n_envs
        for env in np.flatnonzero(done):
            mark_adjacent(loop.adjacency, loop.visited, loop.trajectories[env, : t_episode[env] + 2], args.k)
            loop.episodes += 1
        progress.line(loop.frames, "exploring", heartbeat=True)
        exploring = loop.frames < args.adj_init_steps  # not at the last step: the pre-training below logs at its frame
        if exploring and progress.resume_due(loop.frames, args.checkpoint_every, args.checkpoint_every_steps):
            writer.flush()  # a run killed later resumes from here: what it logged before must be on disk
            save_resume(run_name, training_state(loop, agent, rng, replay, explore_rollout, rollout, eval_envs), args)
    if loop.frames >= args.adj_init_steps and not loop.pretrained:  # the exploration just ended (a stop waits for this)
        steps = explore_rollout.t_episode  # the episodes still running count too
        for env in np.flatnonzero(steps > 0):
            mark_adjacent(loop.adjacency, loop.visited, loop.trajectories[env, : steps[env] + 1], args.k)
        adj_loss = train_adjacency(agent, loop.adjacency, loop.visited, args.adj_init_epochs, args, rng)
        loop.adj_accuracy = adjacency_accuracy(agent.adjacency, distances_bfs, args.k, threshold)
        writer.add_scalar("losses/adjacency_loss", adj_loss, loop.frames)
        writer.add_scalar("charts/adjacency_accuracy", loop.adj_accuracy, loop.frames)
        for _ in range(args.ae_init_steps if dgrl else 0):  # DGRL: ground the codes on subgoals all over the grid first
            update_goal_ae(agent, uniform_subgoals(args.ae_batch_size, device))  # DGRL
        loop.pretrained = True
        cells = f"{loop.visited.sum()} cells visited, accuracy {loop.adj_accuracy:.3f} (loss {adj_loss:.3f})"
        print(f"adjacency pre-training: {loop.frames} frames, {cells}, {time.time() - progress.start_time:.1f} s")

    # Phase 2: HRAC. Uniform subgoals and no learning until the replay is half full, then adjacency-filtered noise.
    while loop.frames < args.total_timesteps and not stop:
        # Act: one vector step of the low level; the raw subgoals are stored, never their codes.
        observations, t_episode, goals, actions, real_next, rewards, terminations, done, infos = rollout.step()
        episode = (loop.episode_states, loop.episode_goals, loop.episode_actions, loop.episode_next)
        for column, values in zip(episode, (observations, goals, actions, real_next), strict=True):
            column[rows, t_episode] = values
        loop.frames += n_envs

        # High-level transitions: one per k-step segment, or per shorter last segment; termination only at the chest.
        new_segment = t_episode % args.k == 0
        loop.chosen_subgoals.append(goals[new_segment])  # tested for reachability at the next evaluation
        loop.segment_start = np.where(new_segment[:, None], observations, loop.segment_start)
        loop.segment_reward = np.where(new_segment, 0.0, loop.segment_reward) + args.man_reward_scale * rewards
        ends = ((t_episode + 1) % args.k == 0) | done
        if ends.any():
            segments = (loop.segment_start, goals, loop.segment_reward, real_next, terminations)
            replay.add(*(column[ends] for column in segments))

        # Episode ends: adjacency labels, then (replay half full) HRAC's A2C update and max(length // k, 1) TD3 updates.
        for env in np.flatnonzero(done):
            length = int(t_episode[env]) + 1
            loop.episodes += 1
            loop.recent_returns.append(float(infos["episode"]["r"][env]))
            writer.add_scalar("charts/episodic_return", infos["episode"]["r"][env], loop.frames)
            writer.add_scalar("charts/episodic_length", length, loop.frames)
            writer.add_scalar("charts/success_rate", float(terminations[env]), loop.frames)
            trajectory = np.vstack([loop.episode_states[env, :length, :2], real_next[env, :2]]).astype(np.int64)
            mark_adjacent(loop.adjacency, loop.visited, trajectory @ (WIDTH, 1), args.k)  # flat cell indices
            if not replay.started():
                continue
            columns = [torch.as_tensor(column[env, :length], device=device) for column in episode]
            loop.figures = dict(update_controller(agent, *columns, discounts, args))  # a copy (the update's dict stays)
            for _ in range(max(length // args.k, 1)):
                policy_term = policy_terms[loop.man_updates % args.man_policy_delay == 0]
                batch = replay.sample(args.man_batch_size, device)
                loop.figures |= update_manager(agent, batch, args, threshold, policy_term)
                loop.man_updates += 1

        if loop.frames >= loop.next_adjacency:  # retrain the adjacency network on every pair of cells seen so far
            loop.next_adjacency += args.adj_frequency
            adj_loss = train_adjacency(agent, loop.adjacency, loop.visited, args.adj_epochs, args, rng)
            loop.adj_accuracy = adjacency_accuracy(agent.adjacency, distances_bfs, args.k, threshold)
            writer.add_scalar("losses/adjacency_loss", adj_loss, loop.frames)
            writer.add_scalar("charts/adjacency_accuracy", loop.adj_accuracy, loop.frames)

        if loop.frames >= loop.next_log:
            loop.next_log += args.log_frequency
            for tag, value in loop.figures.items():
                writer.add_scalar(tag, float(value), loop.frames)

        if loop.frames >= loop.next_eval:
            loop.next_eval += args.eval_frequency
            video = [] if args.capture_video and loop.evaluations % 10 == 0 else None
            mean_return, distance, reach = evaluate(eval_envs, agent, args, frames=video)
            random_return = evaluate(eval_envs, agent, args, random_subgoals=True)[0]
            distinct = ""
            if dgrl:
                with torch.no_grad():
                    cell_codes = agent.goal_ae(torch.as_tensor(FREE_CELLS, dtype=torch.float32, device=device))[2]
                distinct_cells = len(torch.unique(cell_codes, dim=0))  # cells with a code tuple of their own
                writer.add_scalar("vq/distinct_cells", distinct_cells, loop.frames)
                distinct = f"  distinct cells {distinct_cells:3d}"
            loop.evaluations += 1
            writer.add_scalar("eval/return", mean_return, loop.frames)
            writer.add_scalar("eval/return_random_subgoals", random_return, loop.frames)
            writer.add_scalar("eval/subgoal_distance", distance, loop.frames)
            writer.add_scalar("eval/subgoal_reach_rate", reach, loop.frames)
            writer.add_scalar("charts/SPS", progress.sps(loop.frames), loop.frames)
            chosen, loop.chosen_subgoals = np.concatenate(loop.chosen_subgoals or [np.zeros((0, 2))]), []
            for rule in ("euclidean", "box"):  # of the subgoals chosen since the last evaluation
                share = unreachable_subgoals(chosen, args.goal_threshold, rule).mean() if len(chosen) else 0.0
                writer.add_scalar(f"charts/unreachable_subgoals_{rule}", share, loop.frames)
            train, loop.recent_returns = (np.mean(loop.recent_returns) if loop.recent_returns else float("nan")), []
            text = f"eval return {mean_return:5.2f} (random subgoals {random_return:4.2f})  train return {train:5.2f}"
            text += f"  subgoal dist {distance:5.2f} reached {reach:4.0%}  adjacency acc {loop.adj_accuracy:.3f}"
            progress.line(loop.frames, text + distinct)
            if video is not None:
                write_video(f"videos/{run_name}/eval_{loop.frames}.mp4", video, fps=10)
            if args.save_model:
                save_checkpoint(f"runs/{run_name}/{args.exp_name}.cleanrl_model", agent.state_dicts(), args)
        progress.line(loop.frames, heartbeat=True)
        if progress.resume_due(loop.frames, args.checkpoint_every, args.checkpoint_every_steps):
            writer.flush()
            save_resume(run_name, training_state(loop, agent, rng, replay, explore_rollout, rollout, eval_envs), args)

    writer.flush()
    save_resume(run_name, training_state(loop, agent, rng, replay, explore_rollout, rollout, eval_envs), args)
    if args.save_model:
        save_checkpoint(f"runs/{run_name}/{args.exp_name}.cleanrl_model", agent.state_dicts(), args)
        print(f"checkpoint: runs/{run_name}/{args.exp_name}.cleanrl_model")
    progress.finish(bool(stop), run_name, f"{loop.frames} frames, {loop.episodes} episodes")
    envs.close()
    writer.close()


# --- Evaluation -------------------------------------------------------------------------------------------------------


@torch.no_grad()
def evaluate(envs, agent: Agent, args: Args, frames: list | None = None, random_subgoals: bool = False):
    """One episode per env: deterministic subgoals every k steps, sampled actions (as the original). Returns (mean
    return, mean distance from a segment's last cell to its subgoal, fraction of segments reaching it); env 0's frames
    go to `frames`. `random_subgoals` replaces the high level by uniform ones: the reference for what it adds."""
    device, n = next(agent.controller.parameters()).device, envs.num_envs
    observations, _ = envs.reset()
    returns, running = np.zeros(n), np.ones(n, dtype=bool)
    reached_in_segment = torch.zeros(n, dtype=torch.bool, device=device)
    distances, reached = [], []
    for step in range(args.max_episode_steps):
        states = torch.as_tensor(observations, device=device)
        if step % args.k == 0:
            raw_goals = uniform_subgoals(n, device) if random_subgoals else agent.actor(states)
            goal_inputs, goals, _ = controller_goals(agent.goal_ae, raw_goals, agent.dgrl_goal)  # DGRL (acting)
            reached_in_segment.zero_()
        if frames is not None and running[0]:
            frames.append(envs.frame(0, goals[0].cpu().numpy()))
        logits, _ = agent.controller(states, goal_inputs)  # DGRL: z_q or the decoded subgoal
        actions = torch.multinomial(F.softmax(logits, 1), 1).squeeze(1)
        observations, rewards, terminations, truncations, infos = envs.step(actions.cpu().numpy())
        done = terminations | truncations
        real_next = np.where(done[:, None], infos["final_obs"], observations) if done.any() else observations
        next_states = torch.as_tensor(real_next, device=device)
        reached_in_segment |= goal_reached(next_states, goals, args.goal_threshold, args.reach_rule).bool()
        returns += rewards * running
        if (step + 1) % args.k == 0:  # a complete segment: score it for the envs still in their first episode
            mask = torch.as_tensor(running, device=device)
            distances.append((next_states[:, :2] - goals).norm(dim=1)[mask])
            reached.append(reached_in_segment[mask].float())
        running &= ~done
        if not running.any():
            break
    distances, reached = torch.cat(distances), torch.cat(reached)
    return returns.mean(), distances.mean().item() if len(distances) else float("nan"), reached.mean().item()


def unreachable_subgoals(goals: np.ndarray, threshold: float, rule: str) -> np.ndarray:
    """True where no free cell reaches the subgoal point under `rule` (e.g. corners between cells, Euclidean at 0.5)."""
    cells = torch.as_tensor(FREE_CELLS, dtype=torch.float32).repeat(len(goals), 1)
    points = torch.as_tensor(goals, dtype=torch.float32).repeat_interleave(len(FREE_CELLS), 0)
    return (goal_reached(cells, points, threshold, rule).view(len(goals), -1).amax(1) == 0).numpy()


@torch.no_grad()
def adjacency_accuracy(anet: AdjacencyNet, distances: np.ndarray, k: int, threshold: float) -> float:
    """Agreement of `||phi_i - phi_j|| < threshold` with `BFS distance <= k` over all pairs of free cells."""
    embeddings = anet(torch.as_tensor(FREE_CELLS, dtype=torch.float32, device=next(anet.parameters()).device))
    predicted = (torch.cdist(embeddings, embeddings) < threshold).cpu().numpy()
    first, second = np.triu_indices(len(FREE_CELLS), 1)
    return float((predicted[first, second] == (distances[first, second] <= k)).mean())


# What a checkpoint must have been saved with to be evaluated: the task, what evaluation measures (the k-step segments,
# the reach test) and the networks' shapes; under DGRL also the autoencoder's and the low level's input.
MUST_MATCH = ("env_id", "max_episode_steps", "random_action_prob", "k", "goal_threshold", "reach_rule", "hidden_dim")
MUST_MATCH += ("adj_hidden_dim", "adj_embed_dim", "groups")
DGRL_MUST_MATCH = ("embed_dim", "n_embed", "ae_hidden_dim", "dgrl_goal")


def evaluate_checkpoint(args: Args, agent: Agent, eval_envs: "KeyChestVecEnv", device: torch.device) -> None:
    """--checkpoint: load the saved networks, evaluate them (and uniform random subgoals), print the results."""
    must_match = MUST_MATCH + (DGRL_MUST_MATCH if args.groups else ())  # the autoencoder's flags only matter under DGRL
    saved = load_checkpoint(args.checkpoint, args, must_match, device)
    for name in ("actor", "critic", "controller", "adjacency"):
        getattr(agent, name).load_state_dict(saved[name])
    if agent.goal_ae is not None:
        agent.goal_ae.load_state_dict(saved["goal_autoencoder"])
    for label, random_subgoals in (("", False), (" with uniform random subgoals", True)):
        mean_return, distance, reach = evaluate(eval_envs, agent, args, random_subgoals=random_subgoals)
        figures = f"return {mean_return:.2f}, subgoal distance {distance:.2f}, reached {reach:.0%}"
        print(f"{args.eval_episodes} episodes{label}: {figures}")


def write_video(path: str, frames: list[np.ndarray], fps: int) -> None:
    """Frames (H, W, 3) uint8 to an mp4 (moviepy loaded only here), one encoder thread: with more, the bytes vary."""
    os.makedirs(os.path.dirname(path), exist_ok=True)
    importlib.import_module("moviepy").ImageSequenceClip(frames, fps=fps).write_videofile(path, logger=None, threads=1)


# --- Environment ------------------------------------------------------------------------------------------------------

LAYOUT = """\
wwwwwwwwwwwwwwwww
w               w
wB              w
wwwwwwwwwwwwww  w
w               w
w               w
wK wwwwwwwwwww  w
w               w
w               w
wwwwwwwwwwwwww  w
w               w
w      S        w
wwwwwwwwwwwwwwwww""".splitlines()
MOVES = np.array(((-1, 0), (1, 0), (0, -1), (0, 1)))  # up, down, left, right as (row, col) steps
WALLS = np.array([[char == "w" for char in line] for line in LAYOUT])
HEIGHT, WIDTH = WALLS.shape
GOAL_SCALE = np.array((HEIGHT, WIDTH), dtype=np.float32)  # the high level proposes cells in [0, 13] x [0, 17]
KEY_CELL, CHEST_CELL = (6, 1), (2, 1)  # K and B above
FREE_CELLS = np.argwhere(~WALLS)  # (128, 2) in row-major order
KEY_REWARD, CHEST_REWARD = 1.0, 5.0
# What gymnasium's vector RecordEpisodeStatistics accumulates (its episode start times measure wall clock, not the run).
EPISODE_STATISTICS = "episode_count episode_returns episode_lengths prev_dones return_queue length_queue".split()


class KeyChestVecEnv(gym.vector.VectorEnv):
    """`num_envs` Key-Chest grids stepped together in numpy (HRAC's task: the 13 x 17 layout above, key K, chest B).

    Observation (row, col, has_key) as float32. Actions 0 up, 1 down, 2 left, 3 right, replaced with probability
    `random_action_prob` by a random one; walls block moves. The key cell gives +1 the first time; the chest cell with
    the key gives +5 and terminates (unless `terminate_at_chest` is False, HRAC's pure exploration). Episodes truncate
    after `max_episode_steps` and start on a uniformly random free cell; autoreset SAME_STEP (`infos["final_obs"]`)."""

    metadata: ClassVar[dict] = {"autoreset_mode": gym.vector.AutoresetMode.SAME_STEP}

    def __init__(self, num_envs: int, max_episode_steps=500, random_action_prob=0.25, terminate_at_chest=True):
        self.num_envs, self.max_episode_steps, self.terminate_at_chest = num_envs, max_episode_steps, terminate_at_chest
        self.random_action_prob, self.rng = random_action_prob, np.random.default_rng()
        self.single_observation_space = gym.spaces.Box(0, max(HEIGHT, WIDTH) - 1, (3,), np.float32)
        self.single_action_space = gym.spaces.Discrete(len(MOVES))
        self.observation_space = gym.vector.utils.batch_space(self.single_observation_space, num_envs)
        self.action_space = gym.vector.utils.batch_space(self.single_action_space, num_envs)
        self.position = np.zeros((num_envs, 2), dtype=np.int64)
        self.has_key, self.elapsed = np.zeros(num_envs, dtype=bool), np.zeros(num_envs, dtype=np.int64)

    def _observe(self) -> np.ndarray:
        return np.concatenate([self.position, self.has_key[:, None]], 1).astype(np.float32)

    def _reset_envs(self, mask: np.ndarray) -> None:
        self.position[mask] = FREE_CELLS[self.rng.integers(len(FREE_CELLS), size=int(mask.sum()))]
        self.has_key[mask], self.elapsed[mask] = False, 0

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        if seed is not None:
            self.rng = np.random.default_rng(seed)
            self.action_space.seed(seed)
        self._reset_envs(np.ones(self.num_envs, dtype=bool))
        return self._observe(), {}

    def step(self, actions):
        actions = np.asarray(actions)
        if actions.shape != (self.num_envs,) or actions.dtype.kind not in "iu" or not np.isin(actions, range(4)).all():
            wanted = f"expected {self.num_envs} integer actions in [0, 3] (up, down, left, right)"
            raise ValueError(f"KeyChestVecEnv.step: {wanted}; got {actions.tolist()!r} of dtype {actions.dtype}")
        replaced = self.rng.random(self.num_envs) < self.random_action_prob
        actions = np.where(replaced, self.rng.integers(len(MOVES), size=self.num_envs), actions)
        target = self.position + MOVES[actions]
        moved = ~WALLS[target[:, 0], target[:, 1]]
        self.position[moved] = target[moved]
        got_key = moved & ~self.has_key & (self.position == KEY_CELL).all(1)
        self.has_key |= got_key
        opened = moved & self.has_key & (self.position == CHEST_CELL).all(1)
        rewards = KEY_REWARD * got_key + CHEST_REWARD * opened
        self.elapsed += 1
        terminations = opened & self.terminate_at_chest
        truncations = (self.elapsed >= self.max_episode_steps) & ~terminations
        done = terminations | truncations
        infos = {}
        if done.any():
            infos = {"final_obs": np.where(done[:, None], self._observe(), 0.0).astype(np.float32), "_final_obs": done}
            self._reset_envs(done)
        return self._observe(), rewards, terminations, truncations, infos

    def frame(self, index: int, subgoal: np.ndarray | None = None, pixels: int = 16) -> np.ndarray:
        """Env `index` as RGB: walls grey, key yellow, chest brown, agent red (blue with the key), subgoal green."""
        image = np.where(WALLS[..., None], np.uint8(110), np.uint8(0)).repeat(3, 2)
        if not self.has_key[index]:
            image[KEY_CELL] = (230, 200, 0)
        image[CHEST_CELL] = (140, 80, 20)
        image[tuple(self.position[index])] = (40, 90, 255) if self.has_key[index] else (230, 30, 30)
        image = image.repeat(pixels, 0).repeat(pixels, 1)
        if subgoal is not None:
            row, col = np.clip(np.round(subgoal).astype(int), 0, (HEIGHT - 1, WIDTH - 1))
            cell = image[row * pixels : (row + 1) * pixels, col * pixels : (col + 1) * pixels]
            cell[:2] = cell[-2:] = cell[:, :2] = cell[:, -2:] = (0, 220, 0)  # a green border
        return image

    def state(self) -> dict:
        """Everything the next steps depend on (for --resume): cells, keys, step counts and the random generators."""
        cells = {"position": self.position.copy(), "has_key": self.has_key.copy(), "elapsed": self.elapsed.copy()}
        action_rng = self.action_space.np_random.bit_generator.state
        return cells | {"rng": self.rng.bit_generator.state, "action_rng": action_rng}

    def load_state(self, state: dict) -> None:
        self.position[:], self.has_key[:], self.elapsed[:] = state["position"], state["has_key"], state["elapsed"]
        self.rng.bit_generator.state = state["rng"]
        self.action_space.np_random.bit_generator.state = state["action_rng"]


def shortest_path_lengths() -> np.ndarray:
    """(128, 128) BFS distances between free cells (FREE_CELLS order), ignoring the action noise."""
    neighbours = np.abs(FREE_CELLS[:, None] - FREE_CELLS[None]).sum(2) == 1
    reached = np.eye(len(FREE_CELLS), dtype=bool)
    distances = np.where(reached, 0, -1).astype(np.int64)
    for distance in range(1, len(FREE_CELLS)):
        frontier = (reached @ neighbours) & ~reached  # one step further than every cell reached so far
        distances[frontier] = distance
        reached |= frontier
    return distances


# --- Resume: the loop's state, and everything a run continues from ----------------------------------------------------


@dataclass
class LoopState:
    """The variables the training loop carries from one step to the next (saved as a plain dict, restored whole)."""

    trajectories: np.ndarray  # flat cell indices of each exploring env's current episode
    adjacency: np.ndarray  # (H*W, H*W) over flat cell indices: cells seen within k steps of each other, all run long
    visited: np.ndarray
    episode_states: np.ndarray  # each training env's episode so far: states, raw subgoals, actions, true next states
    episode_goals: np.ndarray
    episode_actions: np.ndarray
    episode_next: np.ndarray
    segment_start: np.ndarray  # each training env's state at the start of its k-step segment
    segment_reward: np.ndarray  # and the segment's summed reward so far
    next_adjacency: int  # the next frames of each cadence
    next_log: int
    next_eval: int
    frames: int = 0
    episodes: int = 0
    pretrained: bool = False  # whether the first adjacency training (and the autoencoder's) is done
    man_updates: int = 0
    evaluations: int = 0
    adj_accuracy: float = float("nan")
    recent_returns: list = field(default_factory=list)  # of the episodes ended since the last evaluation
    chosen_subgoals: list = field(default_factory=list)  # the training subgoals chosen since the last evaluation
    figures: dict = field(default_factory=dict)  # the latest update's losses, logged every --log-frequency frames


def new_loop_state(args: Args) -> LoopState:
    """A new run's loop state: empty episodes, no adjacency, the cadences counted from the end of the exploration."""
    n_envs, max_steps, cells = args.num_envs, args.max_episode_steps, HEIGHT * WIDTH
    steps = (n_envs, max_steps)  # each training env's episode, step by step
    explored = -(-args.adj_init_steps // n_envs) * n_envs  # the frame at which the exploration ends
    return LoopState(
        trajectories=np.zeros((n_envs, max_steps + 1), dtype=np.int64),
        adjacency=np.zeros((cells, cells), dtype=bool), visited=np.zeros(cells, dtype=bool),
        episode_states=np.zeros((*steps, 3), dtype=np.float32), episode_goals=np.zeros((*steps, 2), dtype=np.float32),
        episode_actions=np.zeros(steps, dtype=np.int64), episode_next=np.zeros((*steps, 3), dtype=np.float32),
        segment_start=np.zeros((n_envs, 3), dtype=np.float32), segment_reward=np.zeros(n_envs, dtype=np.float32),
        next_adjacency=explored + args.adj_frequency,
        next_log=(explored // args.log_frequency + 1) * args.log_frequency,
        next_eval=(explored // args.eval_frequency + 1) * args.eval_frequency,
    )  # fmt: skip


def training_state(loop: LoopState, agent: Agent, rng, replay, explore_rollout, rollout, eval_envs) -> dict:
    """Everything the run continues from (save_resume adds the global random states), episode statistics included."""
    return {
        "agent": {name: part.state_dict() for name, part in vars(agent).items() if hasattr(part, "state_dict")},
        "numpy_rng": rng.bit_generator.state,
        "envs": {"explore": explore_rollout.envs.state(), "train": rollout.envs.env.state(), "eval": eval_envs.state()},
        "episode_statistics": {name: getattr(rollout.envs, name) for name in EPISODE_STATISTICS},
        "rollouts": {"explore": explore_rollout.state(), "train": rollout.state()},
        "replay": replay.state(),
        "variables": copy.deepcopy(vars(loop)),
    }


def restore_training_state(saved: dict, agent: Agent, rng, replay, explore_rollout, rollout, eval_envs) -> LoopState:
    """Load training_state() into the freshly built objects; returns the loop's variables."""
    for name, state_dict in saved["agent"].items():  # every network, the targets included, and every optimizer
        getattr(agent, name).load_state_dict(state_dict)
    rng.bit_generator.state = saved["numpy_rng"]
    explore_rollout.envs.load_state(saved["envs"]["explore"])
    rollout.envs.env.load_state(saved["envs"]["train"])
    eval_envs.load_state(saved["envs"]["eval"])
    for name, value in saved["episode_statistics"].items():
        setattr(rollout.envs, name, value)
    explore_rollout.load_state(saved["rollouts"]["explore"])
    rollout.load_state(saved["rollouts"]["train"])
    replay.load_state(saved["replay"])
    return LoopState(**saved["variables"])


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
    """Reject bad flags before any work (exit status 2), naming the flag and the valid values."""
    errors = common_errors(args)
    counts = "total_timesteps num_envs max_episode_steps k man_buffer_size man_batch_size man_policy_delay hidden_dim "
    counts += "adj_init_steps adj_frequency adj_batch_size adj_hidden_dim adj_embed_dim eval_frequency eval_episodes "
    errors += range_errors(args, counts + "log_frequency embed_dim ae_hidden_dim ae_batch_size", 1)
    zero_or_more = "n_noisy_goals adj_init_epochs adj_epochs ae_init_steps man_noise adj_weight ctrl_entropy"
    positive = "man_actor_lr man_critic_lr ctrl_lr adj_lr ae_lr man_reward_scale ctrl_reward_scale goal_threshold"
    errors += range_errors(args, zero_or_more + " adj_margin_pos", 0)
    errors += range_errors(args, positive + " adj_margin_neg", 0, low_open=True)
    errors += range_errors(args, "man_gamma ctrl_gamma man_tau", 0, 1, low_open=True)
    errors += range_errors(args, "random_action_prob", 0, 1)
    exit_on_errors(errors)  # the checks below combine flags and assume each is in range
    if args.groups < 0 or (args.groups and args.embed_dim % args.groups):
        divisors = [g for g in range(1, args.embed_dim + 1) if args.embed_dim % g == 0]
        wanted = f"0 (HRAC) or divide --embed-dim {args.embed_dim}: one of {divisors}"
        errors.append(f"--groups must be {wanted}; got {args.groups}")
    if args.k > args.max_episode_steps:
        errors.append(f"--k ({args.k}) must be <= --max-episode-steps ({args.max_episode_steps}): k steps per subgoal")
    if args.man_batch_size > args.man_buffer_size // 2:
        buffer = f"--man-buffer-size ({args.man_buffer_size})"
        errors.append(f"--man-batch-size ({args.man_batch_size}) must be <= half of {buffer}: training starts then")
    if args.adj_margin_pos > args.adj_margin_neg:
        errors.append(f"--adj-margin-pos ({args.adj_margin_pos}) must be <= --adj-margin-neg ({args.adj_margin_neg})")
    # Frames when exploration ends, and when the high level's replay is half full: one transition per k-step segment.
    explored = -(-args.adj_init_steps // args.num_envs) * args.num_envs
    warm_up = math.ceil(args.man_buffer_size // 2 * args.max_episode_steps / -(-args.max_episode_steps // args.k))
    if args.total_timesteps < explored + warm_up:
        wanted = f"--total-timesteps ({args.total_timesteps}) must be >= {explored + warm_up}, or no update runs"
        exploring = f"--adj-init-steps ({args.adj_init_steps}) of exploration"
        errors.append(f"{wanted}: {exploring}, then {warm_up} frames to fill half of --man-buffer-size, one per --k")
    first_evaluation = (explored // args.eval_frequency + 1) * args.eval_frequency
    if first_evaluation > args.total_timesteps:
        first = f"the first would be at frame {first_evaluation}, after --total-timesteps ({args.total_timesteps})"
        errors.append(f"--eval-frequency ({args.eval_frequency}) leaves no evaluation: {first}")
    exit_on_errors(errors)


if __name__ == "__main__":
    main(tyro.cli(Args))
