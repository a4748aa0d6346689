"""DGRL on RIS in the Ant mazes: discretized goal and subgoal embeddings for RL with Imagined Subgoals.

Paper: Islam et al. 2022, "Discrete Factorial Representations as an Abstraction for Goal Conditioned RL", section "Ant
Navigation Maze Tasks", appendix "Ant Navigation Tasks", Algorithm 1 (RIS with DGRL) and the code snippet. RIS
(Chane-Sane et al., ICML 2021): a goal-conditioned SAC-style actor and twin critics trained with hindsight relabelling,
a high-level policy proposing subgoal states halfway to the goal (advantage-weighted over replay states) and, in place
of SAC's entropy term, a KL divergence to a prior: the target actor averaged over imagined subgoals. DGRL (`--groups G`)
embeds goals, subgoals and states with an MLP autoencoder, discretizes them with vq.py's shared-codebook bottleneck and
conditions the actor, the critics and the prior on the discrete goals and subgoals; the encoder's loss takes the mean of
the commitment losses of s, s', g and s_g (the paper's text; the snippet's sum: `--vq-loss-reduction sum`).

    python dgrl_ris.py --env-id AntMaze --groups 16   # the paper's setting (Pi maze): 5M steps at batch 2048, a GPU job
    python dgrl_ris.py --env-id AntU --groups 0       # RIS on the U maze
    python dgrl_ris.py --env-id PointMaze_UMaze-v3 --total-timesteps 30000 --batch-size 128 --start-timesteps 2000 \
        --eval-frequency 2000 --eval-episodes 10 --vq-loss-reduction sum   # the CPU preset (20 min; --groups 0: 10 min)
    python dgrl_ris.py --env-id AntU --total-timesteps 3000 --start-timesteps 500 --batch-size 64   # 1-minute smoke run
    python dgrl_ris.py --env-id AntU --checkpoint runs/<run>/dgrl_ris.cleanrl_model   # evaluate a --save-model file
    python dgrl_ris.py --env-id AntMaze --groups 16 --resume runs/<run>   # continue a stopped run exactly (its flags)

Environments: RIS's four Ant mazes (`AntU`, `AntFb`, `AntMaze`, `AntFg`; gymnasium's Ant) and every gymnasium-robotics
maze id. CPU studies: python benchmark/launch.py --preset ris-pointmaze (or ris-antu-cpu). Docs: docs/dgrl_ris.md.
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
from functools import cache, partial
from typing import ClassVar, Literal

if sys.platform.startswith("linux") and not os.environ.get("DISPLAY"):
    os.environ.setdefault("MUJOCO_GL", "egl")  # headless rendering (videos) with no display; set MUJOCO_GL to override

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
    # Environment
    env_id: str = "AntMaze"
    """AntU, AntFb (S), AntMaze (Pi), AntFg (omega), or a gymnasium-robotics maze id (PointMaze_UMaze-v3, ...)"""
    max_episode_steps: int = 0
    """episode step limit (0 = 600 for the four Ant mazes, the registered limit for gymnasium-robotics ids)"""
    num_envs: int = 1
    """environments stepped together; each env step is followed by one update, as in RIS"""

    # Algorithm: RIS
    total_timesteps: int = 5_000_000
    """total environment steps"""
    buffer_size: int = 1_000_000
    """replay capacity in transitions"""
    batch_size: int = 2048
    """transitions per update (the paper's 2048 needs a GPU: 0.2-0.5 s per update on a CPU core)"""
    start_timesteps: int = 10_000
    """steps of uniform random actions before the first update"""
    gamma: float = 0.99
    """discount, in (0, 1]"""
    tau: float = 0.005
    """Polyak rate of the critic and actor targets, in (0, 1]"""
    q_lr: float = 1e-3
    """Adam learning rate of the twin critics"""
    actor_lr: float = 1e-3
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
    prior_epsilon: float = 1e-16
    """added to the prior density inside the log"""
    her_goal_frac: float = 0.2
    """fraction of each batch keeping the rollout goal"""
    her_random_frac: float = 0.4
    """fraction relabelled with a random replay state (the rest: a future state of the same episode)"""
    goal_threshold: float = 0.0
    """success radius on the xy distance (0 = 0.5 for the four Ant mazes, 0.45 for gymnasium-robotics ids)"""

    # Evaluation
    eval_frequency: int = 1000
    """environment steps between evaluations (also the checkpoint cadence with --save-model)"""
    eval_episodes: int = 5
    """episodes per evaluation on the test configuration (--capture-video records the first of every 10th evaluation)"""
    eval_deterministic: bool = False
    """act with the mean action during evaluation (RIS samples actions, as in training)"""

    # DGRL
    groups: int = 16  # DGRL
    """G: factors of the goal embedding; 0 runs RIS"""
    n_embed: int = 64
    """L: codes in the shared codebook"""
    vq_beta: float = 0.25
    """commitment-loss weight"""
    vq_decay: float = 0.99
    """EMA decay of the codebook, in [0, 1)"""
    vq_dead_code_steps: int = 0
    """restart a code unused for this many updates at a random current segment (0 = off, as in the paper)"""
    vq_loss_reduction: str = "mean"
    """how the commitment losses of s, s', g and s_g combine: mean (the paper's text) or sum (its code snippet)"""
    embed_dim: int = 64
    """size of the goal embedding (m); must be divisible by groups"""
    encoder_lr: float = 1e-4
    """Adam learning rate of the goal encoder and decoder (a parameter group of the critic optimizer)"""

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


# --- Networks, and acting with them -----------------------------------------------------------------------------------

LOG_STD_MIN, LOG_STD_MAX = -20.0, 2.0


def mlp(in_dim: int, hidden_dim: int, out_dim: int) -> nn.Sequential:
    hidden = (nn.Linear(in_dim, hidden_dim), nn.ReLU(), nn.Linear(hidden_dim, hidden_dim), nn.ReLU())
    return nn.Sequential(*hidden, nn.Linear(hidden_dim, out_dim))


class Actor(nn.Module):
    """pi(a | s, g): a Gaussian over pre-tanh actions; the action is tanh(u)."""

    def __init__(self, state_dim: int, goal_input_dim: int, action_dim: int, hidden_dim: int):
        super().__init__()
        self.net = mlp(state_dim + goal_input_dim, hidden_dim, 2 * action_dim)

    def forward(self, states: torch.Tensor, goal_inputs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        mean, log_std = self.net(torch.cat((states, goal_inputs), -1)).chunk(2, -1)
        return mean, log_std.clamp(LOG_STD_MIN, LOG_STD_MAX).exp()

    def sample(self, states: torch.Tensor, goal_inputs: torch.Tensor) -> torch.Tensor:
        mean, std = self(states, goal_inputs)
        return torch.tanh(mean + std * torch.randn_like(mean))


class TwinCritic(nn.Module):
    """Two Q-networks on (s, a, g); returns Q values of shape (2, batch)."""

    def __init__(self, state_dim: int, goal_input_dim: int, action_dim: int, hidden_dim: int):
        super().__init__()
        self.q1, self.q2 = (mlp(state_dim + action_dim + goal_input_dim, hidden_dim, 1) for _ in range(2))

    def forward(self, states: torch.Tensor, actions: torch.Tensor, goal_inputs: torch.Tensor) -> torch.Tensor:
        inputs = torch.cat((states, actions, goal_inputs), -1)
        return torch.stack((self.q1(inputs).squeeze(-1), self.q2(inputs).squeeze(-1)))


class HighLevelPolicy(nn.Module):
    """pi_H(s_g | s, g): a Laplace distribution over subgoal states, on raw states and goals."""

    def __init__(self, state_dim: int, goal_dim: int, hidden_dim: int):
        super().__init__()
        self.net = mlp(state_dim + goal_dim, hidden_dim, 2 * state_dim)

    def forward(self, states: torch.Tensor, goals: torch.Tensor) -> torch.distributions.Laplace:
        loc, log_scale = self.net(torch.cat((states, goals), -1)).chunk(2, -1)
        return torch.distributions.Laplace(loc, log_scale.clamp(LOG_STD_MIN, LOG_STD_MAX).exp(), validate_args=False)


class GoalEncoder(nn.Module):  # DGRL
    """The paper snippet's Ant branch on goal-space points: MLP encoder, shared codebook, MLP decoder (for its loss)."""

    def __init__(self, goal_dim: int, args: Args):
        super().__init__()
        self.encoder = mlp(goal_dim, args.hidden_dim, args.embed_dim)  # DGRL
        self.decoder = mlp(args.embed_dim, args.hidden_dim, goal_dim)  # DGRL
        codebook = args.embed_dim, args.n_embed, args.groups, args.vq_beta, args.vq_decay  # DGRL
        self.vq = VectorQuantizerEMA(*codebook, dead_code_steps=args.vq_dead_code_steps)  # DGRL

    def forward(self, goals: torch.Tensor, update: bool = False) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(z_q, commitment loss, code indices); the codebook moves only with update=True."""
        return self.vq(self.encoder(goals), update=update)  # DGRL


def combined_commitment_loss(pooled: torch.Tensor, n_embeddings: int, reduction: str) -> torch.Tensor:
    """n embeddings' commitment loss from one pooled call (their mean): it (the paper's text) or n x it (snippet)."""
    return pooled if reduction == "mean" else n_embeddings * pooled  # DGRL


def goal_input(goal_encoder: GoalEncoder | None, goals: torch.Tensor) -> torch.Tensor:
    """What the actor and critics see of a goal: itself (RIS) or its discrete embedding (DGRL), codebook untouched."""
    return goals if goal_encoder is None else goal_encoder(goals, update=False)[0]  # DGRL


@torch.no_grad()
def act(actor: Actor, goal_encoder: GoalEncoder | None, observations: dict, device, deterministic: bool) -> np.ndarray:
    states = torch.as_tensor(observations["state"], device=device)
    goal_z = goal_input(goal_encoder, torch.as_tensor(observations["goal"], device=device))  # DGRL: z_q(g)
    actions = torch.tanh(actor(states, goal_z)[0]) if deterministic else actor.sample(states, goal_z)  # DGRL
    return actions.cpu().numpy()


@dataclass
class Agent:
    """RIS's networks with their targets and optimizers, and the DGRL goal encoder (None for --groups 0)."""

    actor: Actor
    critic: TwinCritic
    high: HighLevelPolicy
    goal_encoder: GoalEncoder | None  # trained with the critic, by its optimizer
    actor_target: Actor
    critic_target: TwinCritic
    actor_optimizer: torch.optim.Optimizer
    critic_optimizer: torch.optim.Optimizer
    high_optimizer: torch.optim.Optimizer

    EVALUATED = ("actor", "critic", "high", "goal_encoder")  # what a --save-model checkpoint holds (with the codebook)

    def state_dicts(self) -> dict:
        return {name: None if (part := getattr(self, name)) is None else part.state_dict() for name in self.EVALUATED}

    def load_state_dicts(self, saved: dict) -> None:
        for name in self.EVALUATED:
            if getattr(self, name) is not None:
                getattr(self, name).load_state_dict(saved[name])


def make_agent(state_dim: int, goal_dim: int, action_dim: int, args: Args, device: torch.device) -> Agent:
    """The agent of a run (the networks are created in this order, so a seed gives the same weights)."""
    goal_input_dim = args.embed_dim if args.groups else goal_dim  # DGRL: the networks take z_q(g) instead of g
    actor = Actor(state_dim, goal_input_dim, action_dim, args.hidden_dim).to(device)
    critic = TwinCritic(state_dim, goal_input_dim, action_dim, args.hidden_dim).to(device)
    high = HighLevelPolicy(state_dim, goal_dim, args.hidden_dim).to(device)
    goal_encoder = GoalEncoder(goal_dim, args).to(device) if args.groups else None  # DGRL
    critic_groups = [{"params": critic.parameters(), "lr": args.q_lr}]
    if goal_encoder is not None:  # DGRL: the encoder learns with the critic (the codebook moves by EMA)
        critic_groups.append({"params": goal_encoder.parameters(), "lr": args.encoder_lr})
    adam = partial(torch.optim.Adam, fused=device.type in ("cpu", "cuda"))
    optimizers = adam(actor.parameters(), lr=args.actor_lr), adam(critic_groups), adam(high.parameters(), lr=args.h_lr)
    return Agent(actor, critic, high, goal_encoder, make_target(actor), make_target(critic), *optimizers)


# --- Replay with hindsight relabelling --------------------------------------------------------------------------------

EPISODE_KEYS = ("states", "actions", "next_states", "goals")  # what the loop stages of each env's unfinished episode


class EpisodeReplay:
    """A ring of whole, contiguous episodes (back to 0 at the end): an overwritten one's suffix keeps a valid end."""

    STORED = (*EPISODE_KEYS, "episode_end")

    def __init__(self, capacity: int, state_dim: int, action_dim: int, goal_dim: int, device: torch.device):
        self.capacity, self.device = capacity, device
        self.states = torch.zeros(capacity, state_dim, device=device)
        self.actions = torch.zeros(capacity, action_dim, device=device)
        self.next_states = torch.zeros(capacity, state_dim, device=device)
        self.goals = torch.zeros(capacity, goal_dim, device=device)
        self.episode_end = torch.zeros(capacity, dtype=torch.long, device=device)
        self.position, self.size = 0, 0

    def add_episode(self, states: np.ndarray, actions: np.ndarray, next_states: np.ndarray, goals: np.ndarray) -> None:
        length = len(states)
        if self.position + length > self.capacity:
            self.position = 0
        rows = slice(self.position, self.position + length)
        for name, values in zip(EPISODE_KEYS, (states, actions, next_states, goals), strict=True):
            getattr(self, name)[rows] = torch.as_tensor(values, device=self.device)
        self.episode_end[rows] = self.position + length - 1
        self.position += length
        self.size = max(self.size, self.position)

    def state_dict(self) -> dict:
        """The filled rows (copies on the CPU, so the file holds only them) and the write position."""
        rows = {name: getattr(self, name)[: self.size].to("cpu", copy=True) for name in self.STORED}
        return {"position": self.position, "size": self.size, **rows}

    def load_state_dict(self, saved: dict) -> None:
        self.position, self.size = saved["position"], saved["size"]
        for name in self.STORED:
            getattr(self, name)[: self.size] = saved[name].to(self.device)

    def sample(self, batch_size: int, goal_dim: int, threshold: float, goal_frac: float, random_frac: float):
        """HER batch (s, a, s', g, r = -1, done: xy of s' within `threshold` of g, s_g: random states): g is the rollout
        goal (first `goal_frac`), a random state's (next `random_frac`) or a uniform future s' of the episode."""
        index = torch.randint(self.size, (batch_size,), device=self.device)
        n_keep, n_random = round(goal_frac * batch_size), round(random_frac * batch_size)
        future = index[n_keep + n_random :]
        offset = (torch.rand(len(future), device=self.device) * (self.episode_end[future] - future + 1)).long()
        random_goals = self.states[torch.randint(self.size, (n_random,), device=self.device), :goal_dim]
        goals = torch.cat((self.goals[index[:n_keep]], random_goals, self.next_states[future + offset, :goal_dim]))
        next_states = self.next_states[index]
        done = (torch.linalg.vector_norm(next_states[:, :2] - goals[:, :2], dim=-1) < threshold).float()
        subgoals = self.states[torch.randint(self.size, (batch_size,), device=self.device)]
        return self.states[index], self.actions[index], next_states, goals, -torch.ones_like(done), done, subgoals


# --- Losses -----------------------------------------------------------------------------------------------------------


def advantage_weights(proposed_cost: torch.Tensor, candidate_cost: torch.Tensor, temperature: float) -> torch.Tensor:
    """softmax over the batch of (D(proposed subgoal) - D(candidate)) / lambda: the cheaper candidates weigh more."""
    return F.softmax((proposed_cost - candidate_cost) / temperature, dim=0)


def subgoal_cost(values_to_subgoal: torch.Tensor, values_from_subgoal: torch.Tensor) -> torch.Tensor:
    """D(s_g) = max(|clip(V(s, s_g), -100, 0)|, |clip(V(s_g, g), -100, 0)|): the longer of the two halves."""
    return torch.maximum(values_to_subgoal.clamp(-100.0, 0.0).abs(), values_from_subgoal.clamp(-100.0, 0.0).abs())


def prior_kl(actions_pre_tanh, mean, std, prior_mean, prior_std, epsilon: float) -> torch.Tensor:
    """Single-sample KL(pi || prior) at u (B, A): log N(u; mu, sigma) - log(mean_k N(u; mu_k, sigma_k) + epsilon), the
    prior's (K, B, A) from the target actor at K imagined subgoals; logsumexp keeps a 1e-40 density from reaching 0."""
    normal = partial(torch.distributions.Normal, validate_args=False)
    log_policy = normal(mean, std).log_prob(actions_pre_tanh).sum(-1)
    log_prior_k = normal(prior_mean, prior_std).log_prob(actions_pre_tanh[None]).sum(-1)
    log_epsilon = torch.full_like(log_prior_k[:1], math.log(epsilon))
    log_terms = torch.cat((log_prior_k - math.log(len(log_prior_k)), log_epsilon))
    return log_policy - torch.logsumexp(log_terms, dim=0)


def learn(optimizer: torch.optim.Optimizer, loss: torch.Tensor, max_grad_norm: float | None = None) -> None:
    """One step on `loss`: clear the gradients, backpropagate, clip their norm to `max_grad_norm` if given, step."""
    optimizer.zero_grad()
    loss.backward()
    if max_grad_norm is not None:
        params = [param for group in optimizer.param_groups for param in group["params"]]
        torch.nn.utils.clip_grad_norm_(params, max_grad_norm, foreach=True)
    optimizer.step()


def ris_update(agent: Agent, batch: tuple, args: Args) -> dict[str, torch.Tensor]:
    """One RIS update (critic, high level, actor, targets) with DGRL's representation loss; returns detached metrics."""
    actor, critic, high, goal_encoder = agent.actor, agent.critic, agent.high, agent.goal_encoder
    states, actions, next_states, goals, rewards, done, subgoals = batch
    batch_size, goal_dim = goals.shape  # a state's goal-space projection: its first goal_dim entries

    # Critic (policy evaluation); under DGRL also the representation: autoencoder + commitment losses of s, s', g, s_g.
    if goal_encoder is not None:  # DGRL
        points = torch.cat((states[:, :goal_dim], next_states[:, :goal_dim], goals, subgoals[:, :goal_dim]))  # DGRL
        z_q, vq_loss, codes = goal_encoder(points, update=True)  # DGRL: one pooled EMA step over the four embeddings
        reconstruction_loss = F.mse_loss(goal_encoder.decoder(z_q[:batch_size]), points[:batch_size])  # DGRL
        goal_z = z_q[2 * batch_size : 3 * batch_size]  # DGRL: straight-through, so the critic loss shapes the encoder
        representation_loss = reconstruction_loss + combined_commitment_loss(vq_loss, 4, args.vq_loss_reduction)  # DGRL
        metrics = dict(reconstruction_loss=reconstruction_loss, vq_loss=vq_loss, codes=codes)
    else:
        goal_z, representation_loss, metrics = goals, 0.0, {}
    with torch.no_grad():
        next_actions = actor.sample(next_states, goal_z.detach())  # DGRL: z_q(g), detached
        next_q = agent.critic_target(next_states, next_actions, goal_z.detach()).min(0).values  # DGRL: z_q(g), detached
        target_q = rewards + (1.0 - done) * args.gamma * next_q
    q_values = critic(states, actions, goal_z)  # DGRL: z_q(g), straight-through to the encoder
    critic_loss = 0.5 * (q_values - target_q).pow(2).sum(0).mean()
    learn(agent.critic_optimizer, critic_loss + representation_loss)  # DGRL: + the representation loss
    goal_z = goal_z.detach()  # DGRL: the high level's values and the actor see z_q(g) without gradient

    # High level: advantage-weighted regression onto random replay states.
    subgoal_distribution = high(states, goals)
    proposed = subgoal_distribution.loc.detach()
    with torch.no_grad():
        value_states = torch.cat((states, subgoals, states, proposed))
        value_goals = torch.cat((subgoals[:, :goal_dim], goals, proposed[:, :goal_dim], goals))
        value_goal_z = goal_input(goal_encoder, value_goals)  # DGRL: V(x, y) sees y's discrete embedding
        value_actions = torch.tanh(actor(value_states, value_goal_z)[0])  # DGRL: z_q(y)
        values = critic(value_states, value_actions, value_goal_z).min(0).values.view(4, batch_size)  # DGRL: z_q(y)
        proposed_cost, candidate_cost = subgoal_cost(values[2], values[3]), subgoal_cost(values[0], values[1])
        weights = advantage_weights(proposed_cost, candidate_cost, args.h_lambda)
    high_loss = -(weights * subgoal_distribution.log_prob(subgoals).sum(-1)).mean()
    learn(agent.high_optimizer, high_loss)

    # Actor: maximise Q with a KL penalty towards the target actor averaged over imagined subgoals.
    with torch.no_grad():
        imagined = high(states, goals).sample((args.n_subgoals,))  # (K, B, state_dim)
        imagined_z = goal_input(goal_encoder, imagined[..., :goal_dim])  # DGRL: the prior sees discrete subgoals
        prior_mean, prior_std = agent.actor_target(states.expand(args.n_subgoals, -1, -1), imagined_z)  # DGRL: z_q(s_g)
    mean, std = actor(states, goal_z)  # DGRL: z_q(g), detached
    actions_pre_tanh = mean + std * torch.randn_like(mean)
    kl = prior_kl(actions_pre_tanh, mean, std, prior_mean, prior_std, args.prior_epsilon)
    actor_q = critic(states, torch.tanh(actions_pre_tanh), goal_z).min(0).values  # DGRL: z_q(g), detached
    actor_loss = (args.alpha * kl - actor_q).mean()
    learn(agent.actor_optimizer, actor_loss)

    update_target(agent.critic_target, critic, args.tau)
    update_target(agent.actor_target, actor, args.tau)
    subgoal_distance = torch.linalg.vector_norm(proposed[:, :2] - states[:, :2], dim=-1).mean()
    metrics |= dict(critic_loss=critic_loss, high_loss=high_loss, actor_loss=actor_loss, kl=kl.mean())
    metrics |= dict(q_values=q_values.mean(), high_weight_max=weights.max(), subgoal_distance=subgoal_distance)
    return {name: value.detach() for name, value in metrics.items()}


# --- The run: setup, the training loop, the end; its evaluations ------------------------------------------------------

# A checkpoint is evaluated only under the flags that shape its networks, its env and what success means.
MUST_MATCH = ("env_id", "max_episode_steps", "goal_threshold", "groups", "embed_dim", "n_embed", "hidden_dim")
LOSS_LOG_UPDATES = 1000  # losses and codebook statistics are logged every this many updates


def main(args: Args) -> None:
    """Train RIS (--groups 0) or DGRL in a maze, or evaluate a --checkpoint and exit."""
    validate(args)
    args.goal_threshold = args.goal_threshold or (ANT_THRESHOLD if args.env_id in ANT_MAZES else ROBOTICS_THRESHOLD)
    run_name = f"{args.env_id}__G{args.groups}__{args.exp_name}__{args.seed}__{int(time.time())}"
    if args.resume is not None:  # the stopped run's folder and videos; if it still runs elsewhere, exit 2 at once
        run_name = os.path.basename(os.path.normpath(args.resume))
        hold_run_folder(run_name, check_only=True)
    saved = load_resume(args) if args.resume is not None else None  # after the threshold is resolved, as it was saved
    device = seed_and_device(args)

    # Environments: training (random starts and goals) and evaluation (the test configuration, one seeded stream)
    limits = (args.max_episode_steps, args.goal_threshold)
    envs = make_vector_env(args.env_id, args.num_envs, args.seed, False, *limits)
    eval_seed = args.seed + 10_000  # one evaluation stream per run, continued across evaluations
    eval_envs = make_vector_env(args.env_id, args.eval_episodes, eval_seed, True, *limits, render=args.capture_video)
    eval_envs.reset(seed=eval_seed)
    state_dim, goal_dim = (envs.single_observation_space[key].shape[0] for key in ("state", "goal"))
    action_dim = envs.single_action_space.shape[0]
    if not (np.all(envs.single_action_space.low == -1) and np.all(envs.single_action_space.high == 1)):
        exit_on_errors([f"--env-id {args.env_id}: RIS's tanh policy expects actions in [-1, 1]"])
    agent = make_agent(state_dim, goal_dim, action_dim, args, device)

    stop = stop_on_signals()  # from here on Ctrl-C or SIGTERM ends the run cleanly
    if args.checkpoint is not None:
        return evaluate_checkpoint(args, agent, eval_envs, device, stop)

    try:
        replay = EpisodeReplay(args.buffer_size, state_dim, action_dim, goal_dim, device)
    except RuntimeError as error:  # out of memory (torch.OutOfMemoryError on a GPU is a RuntimeError too)
        too_large = f"the replay does not fit in {device.type} memory ({type(error).__name__})"
        exit_on_errors([f"--buffer-size {args.buffer_size}: {too_large}"])
    checkpoint_path = f"runs/{run_name}/{args.exp_name}.cleanrl_model"
    episode = {key: [[] for _ in range(args.num_envs)] for key in EPISODE_KEYS}  # each env's unfinished episode
    observations, _ = envs.reset(seed=args.seed)
    loop = LoopState(observations, episode, next_eval=args.eval_frequency, next_loss_log=LOSS_LOG_UPDATES)
    if saved is not None:  # continue the stopped run: its networks, replay, envs mid-episode and loop variables
        loop = restore_training_state(saved, agent, replay, envs, eval_envs)
    diverged = False

    _lock = hold_run_folder(run_name)  # one process writes a run folder, from its first write to its end
    writer = make_writer(args, run_name, purge_step=None if saved is None else loop.step + 1)  # logs so far: <= step
    print(f"{run_name}: state {state_dim}-d, goal {goal_dim}-d, {args.total_timesteps} steps, device {device}")
    if saved is not None:
        print(f"resumed at step {loop.step} ({loop.updates} updates) from {args.resume}/{RESUME_FILE}")
    if device.type == "cpu" and args.batch_size >= 1024:
        print(f"note: --batch-size {args.batch_size} on a CPU: 0.2-0.5 s per update; see docs/dgrl_ris.md's CPU preset")
    update = fast_update(ris_update, args.fast, [agent.critic_optimizer, agent.high_optimizer, agent.actor_optimizer])
    progress = Progress(args.total_timesteps, start_step=loop.step)
    her = (args.goal_threshold, args.her_goal_frac, args.her_random_frac)  # HER: success radius, goal fractions
    if saved is not None:
        rng_states(restore=saved["rng"])  # last: building the envs and networks above drew from them
    while loop.step < args.total_timesteps and not stop:
        # Act: uniform random actions during the warm-up, then the actor's samples.
        if loop.step < args.start_timesteps:
            actions = envs.action_space.sample()
        else:
            actions = act(agent.actor, agent.goal_encoder, loop.observations, device, deterministic=False)
        next_observations, _, terminations, truncations, infos = envs.step(actions)
        loop.step += args.num_envs

        # Stage each env's transitions; a finished episode goes to the replay whole (the true last state: final_obs).
        for env in range(args.num_envs):
            ended = terminations[env] or truncations[env]
            next_state = infos["final_obs"][env]["state"] if ended else next_observations["state"][env]
            row = loop.observations["state"][env], actions[env], next_state, loop.observations["goal"][env]
            for key, value in zip(EPISODE_KEYS, row, strict=True):
                loop.episode[key][env].append(value)
            if ended:
                replay.add_episode(*(np.stack(loop.episode[key][env]) for key in EPISODE_KEYS))
                for key in EPISODE_KEYS:
                    loop.episode[key][env] = []
                loop.recent_success.append(float(terminations[env]))
                writer.add_scalar("charts/episodic_return", infos["final_info"]["episode"]["r"][env], loop.step)
                writer.add_scalar("charts/episodic_length", infos["final_info"]["episode"]["l"][env], loop.step)
                writer.add_scalar("charts/success_rate", float(terminations[env]), loop.step)
        loop.observations = next_observations

        # Train: one update per environment step once the random phase is over and the replay holds a batch.
        if loop.step >= max(args.start_timesteps, args.batch_size) and replay.size >= args.batch_size:
            for _ in range(args.num_envs):
                metrics = update(agent, replay.sample(args.batch_size, goal_dim, *her), args)
                loop.updates += 1
            if loop.updates >= loop.next_loss_log:
                loop.next_loss_log += LOSS_LOG_UPDATES
                names = ("critic_loss", "actor_loss", "high_loss", "kl", "q_values")
                losses = {name: metrics[name].item() for name in names}
                for name, value in losses.items():
                    writer.add_scalar(f"losses/{name}", value, loop.step)
                writer.add_scalar("losses/high_weight_max", metrics["high_weight_max"].item(), loop.step)
                writer.add_scalar("charts/subgoal_distance", metrics["subgoal_distance"].item(), loop.step)
                if args.groups:  # the representation and the codebook (DGRL)
                    writer.add_scalar("losses/reconstruction", metrics["reconstruction_loss"].item(), loop.step)
                    writer.add_scalar("vq/commit_loss", metrics["vq_loss"].item(), loop.step)
                    writer.add_scalar("vq/perplexity", perplexity(metrics["codes"], args.n_embed).item(), loop.step)
                    writer.add_scalar("vq/active_codes", active_codes(metrics["codes"], args.n_embed).item(), loop.step)
                diverged = not all(map(math.isfinite, losses.values()))
                if diverged:  # every later update would be NaN too: stop rather than train garbage
                    problem = f"training diverged: non-finite losses {losses} at step {loop.step}"
                    print(f"{problem}; lower the learning rates or --alpha", file=sys.stderr)
                    break
        progress.line(loop.step, f"{loop.updates} updates", heartbeat=True)

        # Evaluate on the test configuration, log, print progress, checkpoint (a stop signal waits for the evaluation).
        if loop.step >= loop.next_eval or loop.step >= args.total_timesteps:
            loop.next_eval += args.eval_frequency
            video = [] if args.capture_video and loop.evaluations % 10 == 0 else None
            loop.eval_success, loop.eval_distance = evaluate(eval_envs, agent, device, args.eval_deterministic, video)
            loop.evaluations += 1
            writer.add_scalar("eval/success_rate", loop.eval_success, loop.step)
            writer.add_scalar("eval/final_distance", loop.eval_distance, loop.step)
            writer.add_scalar("charts/SPS", progress.sps(loop.step), loop.step)
            train_success = f"{np.mean(loop.recent_success):4.0%}" if loop.recent_success else "   -"  # none ended
            loop.recent_success = []
            eval_figures = f"eval success {loop.eval_success:4.0%} distance {loop.eval_distance:5.2f}"
            progress.line(loop.step, f"{eval_figures}  train success {train_success}")
            if video:
                write_video(f"videos/{run_name}/eval_{loop.step}.mp4", video, fps=15)
            if args.save_model:
                save_checkpoint(checkpoint_path, agent.state_dicts(), args)
        if progress.resume_due(loop.step, args.checkpoint_every, args.checkpoint_every_steps):
            save_resume(run_name, training_state(agent, replay, envs, eval_envs, loop), args)

    if not diverged:  # a diverged run broke off mid-step, with NaN networks: its last periodic resume file stays
        save_resume(run_name, training_state(agent, replay, envs, eval_envs, loop), args)
    if args.save_model:
        save_checkpoint(checkpoint_path, agent.state_dicts(), args)
        print(f"checkpoint: {checkpoint_path}")
    stopped = bool(stop) and loop.step < args.total_timesteps
    summary = f"{loop.step} steps, {loop.updates} updates, last eval success {loop.eval_success:.0%}"
    progress.finish(stopped or diverged, run_name, summary)
    envs.close()
    eval_envs.close()
    writer.close()
    if diverged:
        raise SystemExit(1)


def evaluate(envs, agent: Agent, device, deterministic: bool, frames: list | None = None, stop=None) -> tuple | None:
    """One episode per env: (success rate, mean final xy distance to the goal), None if `stop` gets a signal first."""
    observations, _ = envs.reset()
    finished, (success, distance) = np.zeros(envs.num_envs, dtype=bool), np.zeros((2, envs.num_envs))
    while not finished.all():
        if stop:
            return None
        if frames is not None and not finished[0]:
            frames.append(envs.envs[0].render())
        actions = act(agent.actor, agent.goal_encoder, observations, device, deterministic)
        observations, _, terminations, truncations, infos = envs.step(actions)
        ended = (terminations | truncations) & ~finished
        for env in np.flatnonzero(ended):
            last = infos["final_obs"][env]
            distance[env] = np.linalg.norm(last["state"][:2] - last["goal"][:2])
            success[env] = terminations[env]
        finished |= ended
    return success.mean(), distance.mean()


def evaluate_checkpoint(args: Args, agent: Agent, eval_envs, device: torch.device, stop: list[int]) -> None:
    """--checkpoint: load a --save-model checkpoint into the agent, evaluate it on the test configuration, print."""
    agent.load_state_dicts(load_checkpoint(args.checkpoint, args, MUST_MATCH, device))
    result = evaluate(eval_envs, agent, device, args.eval_deterministic, stop=stop)
    figures = result and f"{args.eval_episodes} test episodes: success {result[0]:.0%}, final distance {result[1]:.2f}"
    print(figures or "stopped: the evaluation was interrupted")


def write_video(path: str, frames: list[np.ndarray], fps: int) -> None:
    """Frames (H, W, 3) uint8 to an mp4 (moviepy loaded only here), one encoder thread: with more, the bytes vary."""
    os.makedirs(os.path.dirname(path), exist_ok=True)
    importlib.import_module("moviepy").ImageSequenceClip(frames, fps=fps).write_videofile(path, logger=None, threads=1)


# --- Environments -----------------------------------------------------------------------------------------------------

ANT_MAZES = {  # RIS's four mazes (its multiworld code): interior bounds, inner walls as (cx, cy, hx, hy), test boxes
    "AntU": dict(interior=((-3.75, 3.75), (-9.0, 9.0)), walls=((0.0, 1.5, 0.75, 7.5),),
                 test_start=((-2.5, -2.0), (7.25, 7.75)), test_goal=((2.0, 2.5), (7.25, 7.75))),
    "AntFb": dict(interior=((-6.0, 6.0), (-6.0, 6.0)), walls=((-2.25, 1.5, 0.75, 4.5), (2.25, -1.5, 0.75, 4.5)),
                  test_start=((-4.75, -4.25), (4.25, 4.75)), test_goal=((4.25, 4.75), (-4.75, -4.25))),
    "AntMaze": dict(interior=((-8.0, 8.0), (-8.0, 8.0)),
                    walls=((-2.375, 3.25, 1.625, 0.75), (2.375, 3.25, 1.625, 0.75), (0.0, 2.0, 0.75, 6.0),
                           (-6.0, -2.25, 2.0, 0.75), (6.0, -2.25, 2.0, 0.75)),
                    test_start=((-2.5, -2.0), (6.25, 6.75)), test_goal=((2.0, 2.5), (6.25, 6.75))),
    "AntFg": dict(interior=((-8.0, 8.0), (-8.0, 8.0)),
                  walls=((0.0, -3.25, 3.0, 0.75), (-3.75, 0.0, 0.75, 4.0), (3.75, 0.0, 0.75, 4.0),
                         (0.0, -6.0, 0.75, 2.0)),
                  test_start=((-2.5, -2.0), (-6.75, -6.25)), test_goal=((2.0, 2.5), (-6.75, -6.25))),
}  # fmt: skip
ANT_JOINT_POSE = np.array((0.0, 1.0, 0.0, -1.0, 0.0, -1.0, 0.0, 1.0))  # hips and ankles at rest (gymnasium's init_qpos)
ANT_EPISODE_STEPS = 600
YAWS = np.array((0.0, np.pi, np.pi / 2, -np.pi / 2))
WALL_CLEARANCE = 0.75  # training starts and goals keep at least this far from every wall
ANT_THRESHOLD, ROBOTICS_THRESHOLD = 0.5, 0.45  # success radii (RIS; gymnasium-robotics' own)
ROBOTICS_PREFIXES = ("AntMaze_", "PointMaze_")


def maze_boxes(name: str) -> np.ndarray:
    """Every wall of a maze as (cx, cy, hx, hy) rows: the inner walls, then four outer walls of half-thickness 1."""
    (x0, x1), (y0, y1) = ANT_MAZES[name]["interior"]
    cx, cy, hx, hy = (x0 + x1) / 2, (y0 + y1) / 2, (x1 - x0) / 2, (y1 - y0) / 2
    outer = ((cx, y1 + 1, hx + 2, 1), (cx, y0 - 1, hx + 2, 1), (x0 - 1, cy, 1, hy), (x1 + 1, cy, 1, hy))
    return np.array(ANT_MAZES[name]["walls"] + outer, dtype=np.float64)


def wall_distance(points: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """Distance from each xy point (N, 2) to the nearest wall box (0 inside a wall)."""
    gap = np.abs(points[:, None, :] - boxes[None, :, :2]) - boxes[None, :, 2:]
    return np.linalg.norm(np.maximum(gap, 0.0), axis=-1).min(1)


def quat_to_euler(quat: np.ndarray) -> np.ndarray:
    """(w, x, y, z) unit quaternion to (roll, pitch, yaw)."""
    w, x, y, z = quat
    roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = math.asin(min(1.0, max(-1.0, 2 * (w * y - z * x))))
    yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return np.array((roll, pitch, yaw))


def ant_state(qpos: np.ndarray, qvel: np.ndarray) -> np.ndarray:
    """RIS's 31-d observation: torso xyz, (cos, sin) of roll, pitch and yaw, 8 joint angles, 14 velocities."""
    euler = quat_to_euler(qpos[3:7])
    angles = np.stack((np.cos(euler), np.sin(euler)), 1).ravel()
    return np.concatenate((qpos[:3], angles, qpos[7:15], qvel[:14])).astype(np.float32)


def rest_qpos(xy: np.ndarray, yaw: float) -> np.ndarray:
    """Positions of the ant at rest at `xy` facing `yaw`: torso at z 0.565, upright, joints at their rest pose."""
    return np.concatenate((xy, (0.565, math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)), ANT_JOINT_POSE))


def goal_state(xy: np.ndarray, yaw: float) -> np.ndarray:
    """A full 31-d goal state: the ant at rest (zero velocities) at `xy` facing `yaw`."""
    return ant_state(rest_qpos(xy, yaw), np.zeros(14))


@cache
def ant_maze_xml(name: str) -> str:
    """Gymnasium's Ant edited for RIS: gear 10, timestep 0.03 (RK4), the maze's walls, a goal marker, a top camera."""
    root = ET.parse(os.path.join(os.path.dirname(gym.__file__), "envs/mujoco/assets/ant.xml")).getroot()
    root.find("option").set("timestep", "0.03")
    for motor in root.iter("motor"):
        motor.set("gear", "10")
    world = root.find("worldbody")
    (x0, x1), (y0, y1) = ANT_MAZES[name]["interior"]
    extent = max(x1 - x0, y1 - y0) + 2
    world.find("geom[@name='floor']").set("size", f"{extent} {extent} 40")
    for index, (cx, cy, hx, hy) in enumerate(maze_boxes(name)):
        wall = dict(pos=f"{cx} {cy} 0.75", size=f"{hx} {hy} 0.75", conaffinity="1", contype="1", rgba="0.55 0.55 0.6 1")
        ET.SubElement(world, "geom", name=f"wall_{index}", type="box", **wall)
    marker = ET.SubElement(world, "body", name="goal", mocap="true", pos="0 0 0.3")
    ET.SubElement(marker, "geom", type="sphere", size="0.3", contype="0", conaffinity="0", rgba="0.9 0.2 0.2 0.7")
    height = 1.25 * extent  # the whole maze in a 45-degree field of view
    ET.SubElement(world, "camera", name="top", pos=f"{(x0 + x1) / 2} {(y0 + y1) / 2} {height}", xyaxes="1 0 0 0 1 0")
    return ET.tostring(root, encoding="unicode")


class AntMazeEnv(gym.Env):
    """One of RIS's four Ant mazes (multiworld) on `mujoco`: Dict(state, goal) of 31-d ant states, 8 motors in [-1, 1],
    0.15 s a step, reward -1 (RIS relabels it), done when the torso's xy is within `threshold` of the goal's."""

    metadata: ClassVar[dict] = {"render_modes": ["rgb_array"], "render_fps": 7}
    frame_skip = 5

    def __init__(self, name: str, test: bool = False, threshold: float = ANT_THRESHOLD, render_mode: str | None = None):
        self.name, self.test, self.threshold, self.render_mode = name, test, threshold, render_mode
        self.model, self.walls = mujoco.MjModel.from_xml_string(ant_maze_xml(name)), maze_boxes(name)
        self.data = mujoco.MjData(self.model)
        box = gym.spaces.Box(-np.inf, np.inf, (31,), np.float32)
        self.observation_space = gym.spaces.Dict(state=box, goal=box)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (8,), np.float32)
        self.goal, self._renderer = np.zeros(31, np.float32), None

    def _draw_xy(self, box_key: str) -> np.ndarray:
        """Uniform over a test box, or over the interior without the points within WALL_CLEARANCE of a wall."""
        (x0, x1), (y0, y1) = ANT_MAZES[self.name][box_key if self.test else "interior"]
        if self.test:
            return self.np_random.uniform((x0, y0), (x1, y1))
        while True:
            points = self.np_random.uniform((x0, y0), (x1, y1), size=(64, 2))
            free = points[wall_distance(points, self.walls) >= WALL_CLEARANCE]
            if len(free):
                return free[0]

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        mujoco.mj_resetData(self.model, self.data)
        self.data.qpos[:] = rest_qpos(self._draw_xy("test_start"), self.np_random.choice(YAWS))  # zero velocities
        self.goal = goal_state(self._draw_xy("test_goal"), self.np_random.choice(YAWS))
        self.data.mocap_pos[0, :2] = self.goal[:2]
        mujoco.mj_forward(self.model, self.data)
        return {"state": ant_state(self.data.qpos, self.data.qvel), "goal": self.goal.copy()}, {}

    def step(self, action):
        self.data.ctrl[:] = np.clip(action, -1.0, 1.0)
        mujoco.mj_step(self.model, self.data, nstep=self.frame_skip)
        state = ant_state(self.data.qpos, self.data.qvel)
        success = bool(np.linalg.norm(state[:2] - self.goal[:2]) < self.threshold)
        return {"state": state, "goal": self.goal.copy()}, -1.0, success, False, {"success": success}

    def render(self):
        if self._renderer is None:
            self._renderer = mujoco.Renderer(self.model, 240, 240)
        self._renderer.update_scene(self.data, camera="top")
        return self._renderer.render()

    def close(self):
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


class RoboticsMaze(gym.ObservationWrapper, gym.utils.RecordConstructorArgs):
    """A gymnasium-robotics maze as Dict(state = (achieved xy, observation), goal = desired xy)."""

    def __init__(self, env: gym.Env, test: bool):
        gym.utils.RecordConstructorArgs.__init__(self, test=test)  # so gymnasium can re-create the wrapper
        gym.ObservationWrapper.__init__(self, env)
        spaces = env.observation_space
        state_dim = spaces["achieved_goal"].shape[0] + spaces["observation"].shape[0]
        box = partial(gym.spaces.Box, -np.inf, np.inf, dtype=np.float32)
        self.observation_space = gym.spaces.Dict(state=box((state_dim,)), goal=box(spaces["desired_goal"].shape))
        u_maze = test and "UMaze" in str(env.spec.id)  # test resets run from end to end of the U (RIS's test setup)
        self.options = {"reset_cell": np.array((1, 1)), "goal_cell": np.array((3, 1))} if u_maze else None

    @staticmethod
    def observation(observation: dict) -> dict:  # what ObservationWrapper's reset and step return
        state = np.concatenate((observation["achieved_goal"], observation["observation"])).astype(np.float32)
        return {"state": state, "goal": observation["desired_goal"].astype(np.float32)}

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        return super().reset(seed=seed, options=options or self.options)


def robotics_ids() -> list[str]:
    import gymnasium_robotics

    gym.register_envs(gymnasium_robotics)
    return sorted(env_id for env_id in gym.registry if env_id.startswith(ROBOTICS_PREFIXES))


def episode_limit(env_id: str, max_episode_steps: int) -> int:
    """The episode step limit a run uses: --max-episode-steps, else 600 (Ant mazes) or the id's registered limit."""
    if env_id in ANT_MAZES:
        return max_episode_steps or ANT_EPISODE_STEPS
    robotics_ids()  # registers the ids (for make_env's gym.make too)
    return max_episode_steps or gym.spec(env_id).max_episode_steps


def make_env(env_id: str, seed: int, test: bool, max_episode_steps: int, threshold: float, render: bool = False):
    def thunk():
        render_mode, limit = "rgb_array" if render else None, episode_limit(env_id, max_episode_steps)
        if env_id in ANT_MAZES:
            env = gym.wrappers.TimeLimit(AntMazeEnv(env_id, test, threshold, render_mode), limit)
        else:
            ant_v5 = env_id.startswith("AntMaze_") and "-v5" in env_id  # the v5 Ant's contact forces stay out
            kwargs = {"include_cfrc_ext_in_observation": False} if ant_v5 else {}
            env = gym.make(env_id, continuing_task=False, render_mode=render_mode, max_episode_steps=limit, **kwargs)
            env = RoboticsMaze(env, test)
        env = gym.wrappers.RecordEpisodeStatistics(env)
        env.action_space.seed(seed)
        return env

    return thunk


def make_vector_env(env_id: str, n: int, seed: int, test: bool, max_episode_steps: int, threshold: float, render=False):
    """n envs seeded seed, seed + 1, ...; with `render`, env 0 renders frames (videos)."""
    thunks = [make_env(env_id, seed + i, test, max_episode_steps, threshold, render and i == 0) for i in range(n)]
    return gym.vector.SyncVectorEnv(thunks, autoreset_mode=gym.vector.AutoresetMode.SAME_STEP)


# --- Resume: the whole training state (--resume) ---------------------------------------------------------------------

# What a make_env env's layers carry between steps besides MuJoCo's state (pickled envs would come back fresh).
ENV_CARRIED = ("_elapsed_steps", "episode_returns", "episode_lengths", "episode_count", "_has_reset", "_np_random")
ENV_CARRIED += ("goal", "reset_pos", "init_qpos")
MUJOCO_STATE = mujoco.mjtState.mjSTATE_INTEGRATION  # all mj_step reads: time, qpos, qvel, act, ctrl, mocap, warmstart


def env_layers(env: gym.Env) -> list:
    """A make_env env's wrappers, the env itself and, inside a gymnasium-robotics maze, its MuJoCo robot env."""
    layers = [env]
    while inner := [vars(layers[-1])[name] for name in ("env", "point_env", "ant_env") if name in vars(layers[-1])]:
        layers += inner
    return layers


def env_state(env: gym.Env) -> dict:
    """One env's state: ENV_CARRIED by layer, MuJoCo's state (with the target marker, a model field), the action rng."""
    layers = []
    for layer in env_layers(env):
        carried = {name: copy.deepcopy(value) for name, value in vars(layer).items() if name in ENV_CARRIED}
        if isinstance(vars(layer).get("data"), mujoco.MjData):
            physics = np.empty(mujoco.mj_stateSize(layer.model, MUJOCO_STATE))
            mujoco.mj_getState(layer.model, layer.data, physics, MUJOCO_STATE)
            carried["mujoco"] = (physics, layer.model.site_pos.copy())
        layers.append(carried)
    return {"layers": layers, "action_rng": copy.deepcopy(env.action_space.np_random)}


def restore_env(env: gym.Env, saved: dict) -> None:
    for layer, carried in zip(env_layers(env), saved["layers"], strict=True):
        for name, value in carried.items():
            if name == "mujoco":
                mujoco.mj_setState(layer.model, layer.data, value[0], MUJOCO_STATE)
                layer.model.site_pos[:] = value[1]
                mujoco.mj_forward(layer.model, layer.data)  # positions of bodies and sites, for rendering
            else:
                setattr(layer, name, copy.deepcopy(value))
    env.action_space._np_random = copy.deepcopy(saved["action_rng"])


@dataclass
class LoopState:
    """The variables the training loop carries from one step to the next (saved as a plain dict, restored whole)."""

    observations: dict
    episode: dict  # EPISODE_KEYS -> one list per env of the unfinished episode's rows
    next_eval: int
    next_loss_log: int
    step: int = 0
    updates: int = 0
    evaluations: int = 0
    recent_success: list = field(default_factory=list)  # successes of the episodes ended since the last evaluation
    eval_success: float = float("nan")
    eval_distance: float = float("nan")


def training_state(agent: Agent, replay: EpisodeReplay, envs, eval_envs, loop: LoopState) -> dict:
    """What a run needs to continue exactly, but the random states (save_resume adds them); the agent's codebook too."""
    return {
        "agent": {name: part.state_dict() for name, part in vars(agent).items() if part is not None},
        "replay": replay.state_dict(),
        "envs": [env_state(env) for env in envs.envs],
        "eval_envs": [env_state(env) for env in eval_envs.envs],
        "action_rng": copy.deepcopy(envs.action_space.np_random),
        "loop": copy.deepcopy(vars(loop)),
    }


def restore_training_state(saved: dict, agent: Agent, replay: EpisodeReplay, envs, eval_envs) -> LoopState:
    """Load training_state's pieces into a freshly built agent, replay and envs; returns the loop's variables."""
    for name, state in saved["agent"].items():
        getattr(agent, name).load_state_dict(state)
    replay.load_state_dict(saved["replay"])
    for env, state in zip(envs.envs + eval_envs.envs, saved["envs"] + saved["eval_envs"], strict=True):
        restore_env(env, state)
    envs.action_space._np_random = saved["action_rng"]
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
    """Reject bad flags before any work, naming the flag and the valid choices; exit with status 2."""
    errors = common_errors(args)
    if args.env_id not in ANT_MAZES and not args.env_id.startswith(ROBOTICS_PREFIXES):
        robotics = "a gymnasium-robotics maze id (AntMaze_* or PointMaze_*, e.g. PointMaze_UMaze-v3, AntMaze_UMaze-v5)"
        errors.append(f"--env-id {args.env_id!r} is unknown: use one of {', '.join(ANT_MAZES)} or {robotics}")
    elif args.env_id not in ANT_MAZES and args.env_id not in (ids := robotics_ids()):
        errors.append(f"--env-id {args.env_id!r} is not a registered gymnasium-robotics id; choices: {', '.join(ids)}")
    if args.groups < 0 or (args.groups and args.embed_dim > 0 and args.embed_dim % args.groups):
        divisors = [g for g in range(1, args.embed_dim + 1) if args.embed_dim % g == 0]
        choices = f"0 (RIS) or divide --embed-dim {args.embed_dim}: one of {divisors}"
        errors.append(f"--groups must be {choices}; got {args.groups}")
    counts = "total_timesteps num_envs buffer_size batch_size hidden_dim n_subgoals eval_frequency eval_episodes"
    errors += range_errors(args, counts + " embed_dim", 1)
    errors += range_errors(args, "max_episode_steps start_timesteps goal_threshold her_goal_frac her_random_frac", 0)
    errors += range_errors(args, "alpha h_lambda prior_epsilon q_lr actor_lr h_lr encoder_lr", 0, low_open=True)
    if args.vq_loss_reduction not in ("mean", "sum"):
        choices = "mean (the paper's text) or sum (the paper's snippet)"
        errors.append(f"--vq-loss-reduction must be {choices}; got {args.vq_loss_reduction!r}")
    errors += range_errors(args, "gamma tau", 0, 1, low_open=True)
    if args.her_goal_frac + args.her_random_frac > 1:
        fracs = f"--her-goal-frac ({args.her_goal_frac}) and --her-random-frac ({args.her_random_frac})"
        errors.append(f"{fracs} must sum to <= 1 (the rest are future goals)")
    if args.buffer_size < args.batch_size:
        errors.append(f"--buffer-size ({args.buffer_size}) must be >= --batch-size ({args.batch_size})")
    if args.total_timesteps <= max(args.start_timesteps, args.batch_size):
        first = f"--start-timesteps ({args.start_timesteps}) and --batch-size ({args.batch_size})"
        errors.append(f"--total-timesteps ({args.total_timesteps}) must exceed {first}: updates start after both")
    if not errors:  # the replay is written one whole episode at a time: an episode, and a batch of them, must fit
        limit = episode_limit(args.env_id, args.max_episode_steps)
        warm_up = max(args.start_timesteps, args.batch_size + args.num_envs * (limit - 1))
        buffer = f"--buffer-size ({args.buffer_size})"
        if args.buffer_size < limit:
            errors.append(f"{buffer} must hold one whole episode: >= {limit} (--max-episode-steps)")
        elif args.buffer_size // limit * limit < args.batch_size:
            held = f"holds {args.buffer_size // limit} whole {limit}-step episodes, fewer transitions than --batch-size"
            errors.append(f"{buffer} {held} ({args.batch_size}): raise --buffer-size")
        elif args.total_timesteps <= warm_up:
            needed = f"--total-timesteps ({args.total_timesteps}) must exceed {warm_up}"
            wait = f"updates wait for --batch-size ({args.batch_size}) transitions of whole {limit}-step episodes"
            errors.append(f"{needed}: {wait}, with --num-envs {args.num_envs}")
    exit_on_errors(errors)


if __name__ == "__main__":
    main(tyro.cli(Args))
