"""DGRL on a goal-conditioned DQN in pixel mazes: learning to reach diverse and novel goals.

Paper: Islam et al. 2022, "Discrete Factorial Representations as an Abstraction for Goal Conditioned RL", section 5
"Learning to Reach Diverse and Novel Goals" and appendix "Visual MazeWorlds". A goal-conditioned DQN acts on the
embeddings of an 80x80x3 observation and of a goal observation (the maze with the agent drawn at the goal), from an
encoder pre-trained on random-walk transitions with Deep InfoMax (DRIML's InfoNCE) or an autoencoder. DGRL
(`--groups G`) discretizes both embeddings with the shared-codebook bottleneck of vq.py and adds an exploration bonus
equal to the fraction of the G factors whose codes match between state and goal. The baseline (`--groups 0`) is the
same agent on continuous embeddings, with a bonus equal to their cosine similarity.

The paper's experiments (LoopWorld trained on 4 or 8 goals; SpiralWorld on 8 or 16, tested on 4 novel goals) at a
CPU-sized budget (the paper gives neither budget nor DQN hyper-parameters): the defaults take about 1 min on one core:

    python dgrl_goal_dqn.py --env-id LoopWorld --n-train-goals 4 --groups 16     # LoopWorld, 4 training goals, G=16
    python dgrl_goal_dqn.py --env-id LoopWorld --n-train-goals 4 --groups 0      # the same with the continuous goal-DQN
    python dgrl_goal_dqn.py --env-id SpiralWorld --n-train-goals 16 --groups 8   # SpiralWorld, then the 4 novel goals
    python dgrl_goal_dqn.py --total-timesteps 2000 --rep-steps 50                # a quick CPU smoke run (seconds)
    python dgrl_goal_dqn.py <the same flags> --resume runs/<run_name>           # continue a stopped run exactly

The whole study (5 seeds; the paper has 3): python benchmark/launch.py --preset goal-dqn. Docs: docs/dgrl_goal_dqn.md.
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
from collections import deque
from dataclasses import dataclass, field
from typing import ClassVar, Literal, NamedTuple

import gymnasium as gym
import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
import tyro
from torch.utils.tensorboard import SummaryWriter

from vq import VectorQuantizerEMA, active_codes, factor_match, make_target, perplexity, update_target


@dataclass
class Args:
    # Environment
    env_id: Literal["SpiralWorld", "LoopWorld", "EmptyWorld"] = "SpiralWorld"
    """the maze layout"""
    n_train_goals: int = 8
    """K: the number of training goal cells (the 4 novel test cells are the same for every K)"""
    goal_seed: int = 0
    """seed of the train/novel goal split; keep it fixed so that every run sees the same goals"""
    random_start: bool = False
    """start training episodes in a random cell, not the paper's fixed corner (evaluation always starts there)"""
    noise: float = 0.0
    """amplitude in [0, 1] of fresh per-pixel noise drawn on the maze floor for every observation (0 = clean)"""
    max_episode_steps: int = 100
    """step limit of training episodes (truncation, bootstrapped through) and of evaluation episodes"""

    # Algorithm: DQN
    total_timesteps: int = 20000
    """total environment steps of the DQN phase"""
    learning_rate: float = 1e-3
    """Adam learning rate of the Q-network"""
    buffer_size: int = 20000
    """replay memory size"""
    gamma: float = 0.99
    """discount factor, in (0, 1]"""
    target_network_frequency: int = 50
    """training steps between hard copies of the target network (codebook included)"""
    batch_size: int = 128
    """replay batch size"""
    start_e: float = 1.0
    """starting epsilon"""
    end_e: float = 0.05
    """final epsilon"""
    exploration_fraction: float = 0.5
    """fraction of total_timesteps, in (0, 1], over which epsilon decays linearly"""
    learning_starts: int = 1000
    """environment steps before learning starts (fewer than total_timesteps)"""
    train_frequency: int = 1
    """environment steps between training steps"""
    double_dqn: bool = True
    """Double DQN targets (the online network picks the next action, the target network values it)"""
    hidden_dim: int = 256
    """hidden units of the 2-layer Q-network"""
    bonus_coef: float = 0.5
    """lambda: weight of the intrinsic bonus (factor match with DGRL, cosine similarity without)"""
    eval_frequency: int = 1000
    """environment steps between greedy evaluations on the train and novel goals"""

    # Representation (pre-trained on random walks, then frozen unless --finetune)
    rep: Literal["infomax", "autoencoder"] = "infomax"
    """self-supervised objective: Deep InfoMax (DRIML InfoNCE on (s_t, a_t) -> s_t+1) or an autoencoder"""
    rep_transitions: int = 20000
    """random-walk transitions collected for pre-training"""
    rep_steps: int = 1000
    """pre-training gradient steps (0 leaves phi and the codebook at their random initialisation)"""
    rep_batch_size: int = 128
    """pre-training batch size"""
    rep_learning_rate: float = 1e-3
    """pre-training Adam learning rate"""
    embed_dim: int = 64
    """size of the embedding (m); must be divisible by groups"""
    finetune: bool = False
    """keep training the encoder (and codebook) with the TD loss during RL instead of freezing it"""

    # The discrete factorial bottleneck (DGRL)
    groups: int = 16
    """G: factors per embedding; 0 runs the continuous baseline"""
    n_embed: int = 64
    """L: codes in the shared codebook"""
    vq_beta: float = 0.25
    """commitment-loss weight"""
    vq_decay: float = 0.99
    """EMA decay of the codebook"""
    vq_dead_code_steps: int = 50
    """restart a code unused for this many pre-training updates at a random segment (0 = off, as in the paper)"""

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


class Representation(nn.Module):
    """phi: 80x80x3 uint8 -> R^embed_dim, with the heads of its self-supervised objective and (DGRL) the bottleneck."""

    def __init__(self, embed_dim: int, objective: str, groups: int, n_embed: int, beta, decay, dead_steps=0):
        super().__init__()
        self.objective = objective
        convolutions = (nn.Conv2d(3, 16, 8, stride=4), nn.Conv2d(16, 32, 4, stride=2), nn.Conv2d(32, 32, 3, stride=1))
        layers = [layer for convolution in convolutions for layer in (convolution, nn.ReLU())]  # a ReLU after each
        self.encoder = nn.Sequential(*layers, nn.Flatten(), nn.Linear(32 * 6 * 6, embed_dim))
        if objective == "infomax":  # psi_t(phi(s_t), a_t) and psi_t+1(phi(s_t+1)) of DRIML's score
            self.psi_state_action = nn.Sequential(nn.Linear(embed_dim + len(MOVES), 128), nn.ReLU(), nn.Linear(128, 64))
            self.psi_next = nn.Linear(embed_dim, 64)
        else:
            self.decoder = nn.Sequential(nn.Linear(embed_dim, 256), nn.ReLU(), nn.Linear(256, 80 * 80 * 3))
        self.vq = None  # the baseline: no bottleneck
        if groups:
            self.vq = VectorQuantizerEMA(embed_dim, n_embed, groups, beta, decay, dead_code_steps=dead_steps)  # DGRL

    def embed(self, images: torch.Tensor) -> torch.Tensor:
        return self.encoder(images.permute(0, 3, 1, 2).float() / 255.0)

    def forward(self, z: torch.Tensor, update: bool = False) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """(features the agent sees, commitment loss, code indices) of embeddings z."""
        if self.vq is not None:
            return self.vq(z, update=update)  # DGRL: the agent sees the quantized factors
        return z, z.new_zeros(()), None


class QNetwork(nn.Module):
    """The paper's simple 2-layer goal-conditioned value network: Q(s, g, .) from [features(s), features(g)]."""

    def __init__(self, embed_dim: int, hidden_dim: int):
        super().__init__()
        self.network = nn.Sequential(nn.Linear(2 * embed_dim, hidden_dim), nn.ReLU(), nn.Linear(hidden_dim, len(MOVES)))

    def forward(self, state_features: torch.Tensor, goal_features: torch.Tensor) -> torch.Tensor:
        return self.network(torch.cat([state_features, goal_features], dim=-1))


@dataclass
class Agent:
    """Everything that learns. The DGRL bottleneck is `rep.vq`, inside phi, so that a target copy of phi carries it."""

    rep: Representation  # phi with its pre-training heads and the bottleneck
    q_network: QNetwork
    target_q_network: QNetwork
    target_rep: Representation | None  # only with --finetune: phi and its codebook as the TD targets see them
    rep_optimizer: torch.optim.Optimizer  # pre-training: phi, its heads (the codebook moves by EMA)
    q_optimizer: torch.optim.Optimizer  # the DQN phase: the Q-network, and phi's encoder with --finetune


def make_agent(args: Args, device: torch.device) -> Agent:
    """phi (with the bottleneck for --groups > 0), the Q-network, their targets and the two Adam optimizers."""
    dgrl_flags = (args.groups, args.n_embed, args.vq_beta, args.vq_decay, args.vq_dead_code_steps)
    rep = Representation(args.embed_dim, args.rep, *dgrl_flags).to(device)  # DGRL: phi with the bottleneck
    q_network = QNetwork(args.embed_dim, args.hidden_dim).to(device)
    q_parameters = list(q_network.parameters()) + (list(rep.encoder.parameters()) if args.finetune else [])
    target_q_network, target_rep = make_target(q_network), make_target(rep) if args.finetune else None
    rep_optimizer = torch.optim.Adam(rep.parameters(), lr=args.rep_learning_rate, fused=True)
    q_optimizer = torch.optim.Adam(q_parameters, lr=args.learning_rate, fused=True)
    return Agent(rep, q_network, target_q_network, target_rep, rep_optimizer, q_optimizer)


# --- Losses, data, updates --------------------------------------------------------------------------------------------


def infonce_loss(anchors: torch.Tensor, positives: torch.Tensor, clip: float = 20.0) -> torch.Tensor:
    """InfoNCE with in-batch negatives: row i of `anchors` must pick row i of `positives`; DRIML's clipped scores."""
    scores = clip * torch.tanh(anchors @ positives.t() / anchors.shape[1] ** 0.5 / clip)
    return F.cross_entropy(scores, torch.arange(len(anchors), device=anchors.device))


def intrinsic_bonus(z_state: torch.Tensor, z_goal: torch.Tensor, codes_state, codes_goal) -> torch.Tensor:
    """DGRL: fraction of the G factors whose codes match. Baseline (codes None): cosine similarity of the embeddings."""
    if codes_state is not None:
        return factor_match(codes_state, codes_goal)  # DGRL
    return F.cosine_similarity(z_state, z_goal, dim=-1)


def random_walks(layout: "MazeLayout", n_transitions: int, walk_length: int, rng: np.random.Generator):
    """(cells, actions, next cells) of uniform random walks from uniformly random cells, vectorised over walks."""
    n_walks = -(-n_transitions // walk_length)
    cells, actions = [rng.integers(layout.n_cells, size=n_walks)], []
    for _ in range(walk_length):
        actions.append(rng.integers(len(MOVES), size=n_walks))
        cells.append(layout.next_cell[cells[-1], actions[-1]])
    return tuple(np.stack(column, axis=1).reshape(-1)[:n_transitions] for column in (cells[:-1], actions, cells[1:]))


class CellEmbedder:
    """Embeddings of the observations of given cells. With --noise 0 an observation depends on its cell alone: the
    encoder runs once on the 36 distinct images and the batch gathers rows (same values and gradients, far cheaper)."""

    def __init__(self, layout: "MazeLayout", noise: float, device: torch.device, rng: np.random.Generator):
        self.layout, self.noise, self.device, self.rng = layout, noise, device, rng
        self.all_images = torch.as_tensor(layout.images, device=device)

    def inputs(self, cells: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """(images, rows) for embed_images: the 36 images and `cells`; with noise, fresh host-drawn images and None."""
        if self.noise == 0:
            return self.all_images, cells
        images = self.layout.render(cells.cpu().numpy(), self.noise, self.rng)
        return torch.as_tensor(images, device=self.device), None

    def __call__(self, rep: Representation, cells: torch.Tensor) -> torch.Tensor:
        return embed_images(rep, *self.inputs(cells))


def embed_images(rep: Representation, images: torch.Tensor, rows: torch.Tensor | None) -> torch.Tensor:
    z = rep.embed(images)
    return z if rows is None else z[rows]


@dataclass
class CellTable:  # phi's embeddings, the agent's features and (DGRL) the codes of the maze's noiseless cell images
    z: torch.Tensor
    features: torch.Tensor
    codes: torch.Tensor | None  # None for the baseline


@torch.no_grad()
def cell_table(rep: Representation, embedder: CellEmbedder) -> CellTable:
    z = rep.embed(embedder.all_images)
    features, _, codes = rep(z)  # DGRL: z_q of the cells; the codebook does not update
    return CellTable(z, features, codes)


def cell_features(rep: Representation, cells: torch.Tensor, table: CellTable | None, observed, update=False):
    """(features, z, commitment loss, codes) of `cells`: `table`'s rows if any, else `rep` on `observed` (inputs())."""
    if table is not None:
        codes = None if table.codes is None else table.codes[cells]
        return table.features[cells], table.z[cells], table.z.new_zeros(()), codes
    z = embed_images(rep, *observed)
    features, vq_loss, codes = rep(z, update=update)  # DGRL: z_q; an EMA step only with update
    return features, z, vq_loss, codes


class Batch(NamedTuple):  # a pytree: CudaGraphUpdate copies its tensors
    cells: torch.Tensor  # (batch, 3): cell, next cell, goal cell
    actions: torch.Tensor
    rewards: torch.Tensor
    terminated: torch.Tensor


class ReplayBuffer:
    """Transitions (cell, next cell, goal cell, action, reward, terminated) on the device: cells, never code indices."""

    FIELDS = ("cells", "actions", "rewards", "terminated")

    def __init__(self, size: int, device: torch.device):
        self.device, self.position, self.count = device, 0, 0
        self.cells = torch.zeros((size, 3), dtype=torch.int64, device=device)
        self.actions = torch.zeros(size, dtype=torch.int64, device=device)
        self.rewards = torch.zeros(size, dtype=torch.float32, device=device)
        self.terminated = torch.zeros(size, dtype=torch.float32, device=device)

    def add(self, cell: int, next_cell: int, goal_cell: int, action: int, reward: float, terminated: bool) -> None:
        row = self.position  # Python numbers written in place: on a GPU, fills without a copy from the host or a wait
        self.cells[row, 0], self.cells[row, 1], self.cells[row, 2] = int(cell), int(next_cell), int(goal_cell)
        self.actions[row], self.rewards[row], self.terminated[row] = int(action), float(reward), float(terminated)
        self.position = (self.position + 1) % len(self.actions)
        self.count = min(self.count + 1, len(self.actions))

    def sample(self, batch_size: int, rng: np.random.Generator) -> Batch:
        rows = torch.as_tensor(rng.integers(self.count, size=batch_size), device=self.device)
        return Batch(self.cells[rows], self.actions[rows], self.rewards[rows], self.terminated[rows])

    def state_dict(self) -> dict:
        """The filled rows [0, count) (a CPU copy) and the write position."""
        stored = {name: getattr(self, name)[: self.count].to("cpu", copy=True) for name in self.FIELDS}
        return stored | {"position": self.position, "count": self.count}

    def load_state_dict(self, state: dict) -> None:
        self.position, self.count = state["position"], state["count"]
        for name in self.FIELDS:
            getattr(self, name)[: self.count] = torch.as_tensor(state[name], device=self.device)


def pretrain_inputs(embedder: CellEmbedder, walks: tuple[torch.Tensor, ...], rows: torch.Tensor, objective: str):
    """pretrain_step's inputs for transitions `rows`: s then s' as (images, rows), actions, s's autoencoder targets."""
    cells, actions, next_cells = walks
    images, image_rows = embedder.inputs(torch.cat([cells[rows], next_cells[rows]]))
    clean_images = embedder.all_images[cells[rows]] if objective == "autoencoder" else None
    return images, image_rows, actions[rows], clean_images


def learn(optimizer: torch.optim.Optimizer, loss: torch.Tensor, max_grad_norm: float | None = None) -> None:
    """One step on `loss`: clear the gradients, backpropagate, clip their norm to `max_grad_norm` if given, step."""
    optimizer.zero_grad()
    loss.backward()
    if max_grad_norm is not None:
        params = [param for group in optimizer.param_groups for param in group["params"]]
        torch.nn.utils.clip_grad_norm_(params, max_grad_norm, foreach=True)
    optimizer.step()


def pretrain_step(agent: Agent, images: torch.Tensor, image_rows, actions: torch.Tensor, clean_images) -> dict:
    """One Adam step of phi's objective, plus (DGRL) the commitment loss and a codebook EMA update; detached metrics."""
    rep = agent.rep
    z = embed_images(rep, images, image_rows)
    _, vq_loss, codes = rep(z, update=True)  # DGRL: one pooled update for s and s', the mean of their commitment losses
    z_state, z_next = z.chunk(2)
    if rep.objective == "infomax":
        # Not F.one_hot: it reads back its largest index on a CPU.
        one_hot = (actions.unsqueeze(1) == torch.arange(len(MOVES), device=actions.device)).float()
        anchors = rep.psi_state_action(torch.cat([z_state, one_hot], 1))
        rep_loss = infonce_loss(anchors, rep.psi_next(z_next))
    else:  # with --noise, the clean image is the target: a denoising autoencoder
        rep_loss = F.mse_loss(torch.sigmoid(rep.decoder(z_state)), clean_images.flatten(1).float() / 255.0)
    learn(agent.rep_optimizer, rep_loss + vq_loss)  # DGRL: vq_loss is 0 for the baseline
    metrics = {"rep_loss": rep_loss.detach(), "vq_loss": vq_loss.detach()}
    if codes is not None:
        metrics["perplexity"] = perplexity(codes, rep.vq.n_embed)  # DGRL
    return metrics


def td_inputs(embedder: CellEmbedder, batch: Batch, table: CellTable | None, finetune: bool, double_dqn: bool):
    """td_update's observations when it has no table, in the order it encodes them: (next state, goal) for the targets,
    again for the online network's Double DQN choice with --finetune (else None), (state, goal) for the loss."""
    if table is not None:
        return None
    next_goal_cells = torch.cat([batch.cells[:, 1], batch.cells[:, 2]])
    next_goal = embedder.inputs(next_goal_cells)
    online_next_goal = embedder.inputs(next_goal_cells) if finetune and double_dqn else None
    return next_goal, online_next_goal, embedder.inputs(torch.cat([batch.cells[:, 0], batch.cells[:, 2]]))


def td_update(agent: Agent, batch: Batch, table: CellTable | None, observed: tuple | None, args: Args) -> dict:
    """One DQN step: smooth-L1 between Q(s, g, a) and r + bonus_coef * bonus(s', g) + gamma * Q_target(s', g, a') (a' by
    Double DQN or the max). With --finetune the TD loss also trains phi's encoder and the codebook. Detached metrics."""
    finetune = agent.target_rep is not None
    next_goal, online_next_goal, state_goal = (None, None, None) if observed is None else observed
    with torch.no_grad():
        target_rep = agent.target_rep if finetune else agent.rep
        next_goal_cells = torch.cat([batch.cells[:, 1], batch.cells[:, 2]])
        next_goal_features, next_goal_z, _, codes = cell_features(target_rep, next_goal_cells, table, next_goal)
        next_codes, goal_codes = (None, None) if codes is None else codes.chunk(2)
        bonus = intrinsic_bonus(*next_goal_z.chunk(2), next_codes, goal_codes)  # DGRL: factor match of s' and g
        rewards = batch.rewards + args.bonus_coef * bonus
        target_q = agent.target_q_network(*next_goal_features.chunk(2))  # DGRL: z_q(s'), z_q(g), no gradient
        if args.double_dqn:
            online_features = next_goal_features
            if finetune:
                online_features = cell_features(agent.rep, next_goal_cells, table, online_next_goal)[0]
            next_actions = agent.q_network(*online_features.chunk(2)).argmax(1, keepdim=True)  # DGRL: z_q(s'), z_q(g)
            next_values = target_q.gather(1, next_actions).squeeze(1)
        else:
            next_values = target_q.max(1).values
        td_target = rewards + args.gamma * (1 - batch.terminated) * next_values
    state_goal_cells = torch.cat([batch.cells[:, 0], batch.cells[:, 2]])  # one call: one pooled codebook update
    features, _, vq_loss, _ = cell_features(agent.rep, state_goal_cells, table, state_goal, update=finetune)  # DGRL
    q_values = agent.q_network(*features.chunk(2)).gather(1, batch.actions.unsqueeze(1)).squeeze(1)  # DGRL
    td_loss = F.smooth_l1_loss(q_values, td_target)
    learn(agent.q_optimizer, td_loss + vq_loss)  # DGRL: vq_loss is zero unless the codebook is fine-tuned
    metrics = {"td_loss": td_loss, "q_values": q_values.mean(), "bonus": bonus.mean(), "vq_loss": vq_loss}
    return {name: value.detach() for name, value in metrics.items()}


# --- Acting: greedy actions on the goal -------------------------------------------------------------------------------


@torch.no_grad()
def greedy_actions(agent: Agent, table: CellTable | None, observations: dict, infos: dict) -> np.ndarray:
    """The Q-network's actions on the features of the observations and their goals (the codebook does not update)."""
    if table is not None:
        state_features, goal_features = table.features[infos["cell"]], table.features[infos["goal_cell"]]
    else:
        images = np.concatenate([observations["observation"], observations["desired_goal"]])
        z = agent.rep.embed(torch.as_tensor(images, device=next(agent.q_network.parameters()).device))
        state_features, goal_features = agent.rep(z, update=False)[0].chunk(2)  # DGRL: z_q, no EMA step
    return agent.q_network(state_features, goal_features).argmax(1).cpu().numpy()  # DGRL: z_q(s), z_q(g)


# --- The run: setup, the training loop, the end -----------------------------------------------------------------------


def main(args: Args) -> None:
    """Pre-train phi, then train the goal-conditioned DQN (--groups 0: the baseline); or evaluate a --checkpoint."""
    validate(args)
    run_name = f"{args.env_id}__K{args.n_train_goals}__G{args.groups}__{args.exp_name}__{args.seed}__{int(time.time())}"
    if args.resume is not None:  # a run still running elsewhere: exit 2 at once, touching nothing
        run_name = os.path.basename(os.path.normpath(args.resume))
        hold_run_folder(run_name, check_only=True)
    saved = load_resume(args) if args.resume is not None else None  # another script's file or other flags: exit 2
    dgrl = args.groups > 0
    device = seed_and_device(args)
    rng = np.random.default_rng(args.seed)  # random walks, replay batches and image noise

    layout = MazeLayout(args.env_id)
    goals = dict(zip(("train", "novel"), goal_split(layout, args.n_train_goals, args.goal_seed), strict=True))
    optimal_steps = {split: layout.distances[START_CELL, cells].sum() for split, cells in goals.items()}
    embedder = CellEmbedder(layout, args.noise, device, rng)
    agent = make_agent(args, device)

    stop = stop_on_signals()  # from here on Ctrl-C or SIGTERM ends the run cleanly
    if args.checkpoint is not None:
        evaluate_checkpoint(args, agent, embedder, layout, goals, optimal_steps)
        return

    # A resumed run's TensorBoard drops what the stopped run logged from the first step (of the phase it stopped in)
    # that its resume file has not logged. Step 0 always stays: a file saved at step 0 follows all that step 0 logs.
    first_unlogged, resumed = None, ""
    if saved is not None:
        phase, step_key = ("DQN", "global_step") if saved["loop"]["dqn_phase"] else ("pre-training", "rep_step")
        first_unlogged = max(saved["loop"][step_key], 1)
        resumed = f", resumed at {phase} step {saved['loop'][step_key]}"
    _lock = hold_run_folder(run_name)  # one process writes a run folder, from its first write to its end
    writer = make_writer(args, run_name, purge_step=first_unlogged)
    goal_text = ", ".join(f"{split} goals {cells.tolist()}" for split, cells in goals.items())
    print(f"{run_name}: {goal_text}, device {device}{resumed}")

    # The data of both phases: random-walk transitions to pre-train on; the maze env and the replay memory of the DQN.
    columns = random_walks(layout, args.rep_transitions, args.max_episode_steps, rng)
    walks = tuple(torch.as_tensor(column, device=device) for column in columns)
    maze = VisualMazeEnv(layout, goals["train"], args.random_start, args.noise)
    env = gym.wrappers.RecordEpisodeStatistics(gym.wrappers.TimeLimit(maze, args.max_episode_steps))
    envs = gym.vector.SyncVectorEnv([lambda: env], autoreset_mode=gym.vector.AutoresetMode.SAME_STEP)
    envs.action_space.seed(args.seed)
    loop = LoopState(*envs.reset(seed=args.seed), next_eval=args.eval_frequency)  # the first observations and infos
    replay = ReplayBuffer(args.buffer_size, device)
    exploration_steps = args.exploration_fraction * args.total_timesteps

    def write_resume() -> None:  # TensorBoard first: after a kill -9, every point up to the file's step is on disk
        writer.flush()
        save_resume(run_name, training_state(agent, rng, envs, replay, loop), args)

    if saved is not None:
        loop = restore_training_state(saved, agent, rng, envs, replay)
        for tag, value, step in loop.pretraining_log:  # purged too: the two phases share TensorBoard's steps
            if step >= first_unlogged:
                writer.add_scalar(tag, value, step)
        rng_states(restore=saved["rng"])  # last: building the agent drew; nothing draws before or between the two loops

    pretrain = fast_update(pretrain_step, args.fast, [agent.rep_optimizer])  # as --fast asks, each made once
    td = fast_update(td_update, args.fast, [agent.q_optimizer])

    # Phase 1: pre-train phi (and, for DGRL, the codebook on its embeddings) on random-walk transitions.
    pretraining = Progress(args.rep_steps, unit="pre-training step", start_step=loop.rep_step)
    while loop.rep_step < args.rep_steps and not stop:
        rows = torch.as_tensor(rng.integers(args.rep_transitions, size=args.rep_batch_size), device=device)
        rep_metrics = pretrain(agent, *pretrain_inputs(embedder, walks, rows, args.rep))
        loop.rep_loss = rep_metrics["rep_loss"]
        if loop.rep_step >= loop.next_rep_log or loop.rep_step == args.rep_steps - 1:
            loop.next_rep_log += 100
            add_kept_scalar(writer, loop.pretraining_log, "losses/rep_loss", loop.rep_loss.item(), loop.rep_step)
            if dgrl:
                for tag, key in (("vq/commit_loss", "vq_loss"), ("vq/perplexity", "perplexity")):
                    add_kept_scalar(writer, loop.pretraining_log, tag, rep_metrics[key].item(), loop.rep_step)  # DGRL
            pretraining.line(loop.rep_step + 1, f"{args.rep} loss {loop.rep_loss.item():.3f}")
        loop.rep_step += 1
        pretraining.line(loop.rep_step, heartbeat=True)
        if pretraining.resume_due(loop.rep_step, args.checkpoint_every, args.checkpoint_every_steps):
            write_resume()

    # Freeze phi (unless --finetune) and encode the maze's cells once.
    agent.rep.eval().requires_grad_(args.finetune)
    pretrained = cell_table(agent.rep, embedder)
    if loop.rep_step == args.rep_steps and not loop.dqn_phase:  # pre-training has just ended (a stop skips this)
        report_pretraining(writer, loop, pretrained, layout, args, pretraining.start_time)
        if args.finetune:
            update_target(agent.target_rep, agent.rep)  # DGRL: the target starts from the pre-trained phi and codebook
        loop.dqn_phase = True
        write_resume()  # the phases share TensorBoard's steps: a pre-training file must not stay
    agent.rep.train(args.finetune)
    lookup = None if args.finetune or args.noise > 0 else pretrained  # frozen phi, noiseless images: a 36-row table

    # Phase 2: goal-conditioned DQN on the (frozen, unless --finetune) representation.
    progress = Progress(args.total_timesteps, start_step=loop.global_step)
    while loop.global_step < args.total_timesteps and not stop:
        # Act: epsilon-greedy on the features of the actual observation and goal.
        epsilon = max(args.end_e, args.start_e - (args.start_e - args.end_e) * loop.global_step / exploration_steps)
        if random.random() < epsilon:
            actions = envs.action_space.sample()
        else:
            actions = greedy_actions(agent, lookup, loop.observations, loop.infos)
        next_observations, rewards, terminations, truncations, next_infos = envs.step(actions)

        # Store: the true final cell of a finished episode comes from final_info (same-step autoreset).
        done = terminations | truncations
        next_cell = (next_infos["final_info"] if done[0] else next_infos)["cell"][0]
        cell, goal_cell = loop.infos["cell"][0], loop.infos["goal_cell"][0]
        replay.add(cell, next_cell, goal_cell, actions[0], rewards[0], terminations[0])
        if done[0]:
            episode = next_infos["final_info"]["episode"]
            loop.recent_success.append(float(terminations[0]))
            writer.add_scalar("charts/episodic_return", episode["r"][0], loop.global_step)
            writer.add_scalar("charts/episodic_length", episode["l"][0], loop.global_step)
            writer.add_scalar("charts/success_rate", np.mean(loop.recent_success), loop.global_step)
        loop.observations, loop.infos = next_observations, next_infos

        # Learn
        if loop.global_step >= args.learning_starts and loop.global_step % args.train_frequency == 0:
            batch = replay.sample(args.batch_size, rng)
            observed = td_inputs(embedder, batch, lookup, args.finetune, args.double_dqn)
            metrics = td(agent, batch, lookup, observed, args)
            loop.train_steps += 1
            if loop.train_steps % args.target_network_frequency == 0:
                update_target(agent.target_q_network, agent.q_network)
                if agent.target_rep is not None:
                    update_target(agent.target_rep, agent.rep)  # DGRL: the codebook buffers are copied too
            if loop.train_steps >= loop.next_train_log:
                loop.next_train_log += 100
                writer.add_scalar("losses/td_loss", metrics["td_loss"].item(), loop.global_step)
                writer.add_scalar("losses/q_values", metrics["q_values"].item(), loop.global_step)
                writer.add_scalar("charts/intrinsic_bonus", metrics["bonus"].item(), loop.global_step)
                writer.add_scalar("charts/epsilon", epsilon, loop.global_step)
                if dgrl:
                    writer.add_scalar("vq/factor_match", metrics["bonus"].item(), loop.global_step)  # DGRL
                    if args.finetune:
                        writer.add_scalar("vq/commit_loss", metrics["vq_loss"].item(), loop.global_step)

        # Evaluate greedily on every train goal and every novel goal; log, print progress, record the episodes.
        steps_done = loop.global_step + 1
        if steps_done >= loop.next_eval or steps_done == args.total_timesteps:
            loop.next_eval += args.eval_frequency
            agent.rep.eval()
            texts, frames = [], []
            for split, cells in goals.items():
                episodes = evaluate(agent.rep, agent.q_network, embedder, layout, cells, args.max_episode_steps)
                reached, steps, visited = episodes
                texts.append(evaluation_text(split, reached, steps, optimal_steps[split]))
                writer.add_scalar(f"eval/{split}_success_rate", reached.mean(), loop.global_step)
                writer.add_scalar(f"eval/{split}_mean_steps", steps.mean(), loop.global_step)
                writer.add_scalar(f"eval/{split}_total_steps", steps.sum(), loop.global_step)
                if args.capture_video:
                    frames += episode_frames(layout, visited, steps, cells)
            agent.rep.train(args.finetune)
            loop.last_evaluation = "  ".join(texts)
            writer.add_scalar("charts/SPS", progress.sps(steps_done), loop.global_step)
            progress.line(steps_done, loop.last_evaluation)
            if args.capture_video:
                write_video(f"videos/{run_name}/eval_step{steps_done}.mp4", frames, fps=maze.metadata["render_fps"])
        loop.global_step = steps_done
        progress.line(loop.global_step, heartbeat=True)
        if progress.resume_due(loop.global_step, args.checkpoint_every, args.checkpoint_every_steps):
            write_resume()

    write_resume()  # stopped or done: --resume runs/{run_name} goes on from here
    if args.save_model:
        path = f"runs/{run_name}/{args.exp_name}.cleanrl_model"  # phi (with the codebook) and the Q-network
        networks = {"representation": agent.rep.state_dict(), "q_network": agent.q_network.state_dict()}
        split = {f"{name}_goals": cells.tolist() for name, cells in goals.items()}
        save_checkpoint(path, networks | split | {"pretraining_steps": loop.rep_step, "steps": loop.global_step}, args)
        print(f"checkpoint: {path}")
    summary = f"{loop.rep_step} pre-training steps, {loop.global_step} DQN steps; {loop.last_evaluation}"
    progress.finish(bool(stop), run_name, summary)
    envs.close()
    writer.close()


# --- Evaluation -------------------------------------------------------------------------------------------------------


@torch.no_grad()
def evaluate(rep, q_network, embedder, layout: "MazeLayout", goal_cells: np.ndarray, max_steps: int):
    """Greedy episodes from START_CELL to all goals at once: reached, steps (max_steps if not), path (time, goal)."""
    device = embedder.device
    goals = torch.as_tensor(goal_cells, device=device)
    next_cell = torch.as_tensor(layout.next_cell, device=device)
    table = None

    def features(cells: torch.Tensor) -> torch.Tensor:
        return rep(embedder(rep, cells))[0] if table is None else table[cells]  # DGRL: z_q

    if embedder.noise == 0:  # every observation is one of the maze's distinct images: encode them once, then look up
        table = features(torch.arange(layout.n_cells, device=device))
    goal_features = features(goals)
    cells, steps = torch.full_like(goals, START_CELL), torch.full_like(goals, max_steps)
    reached = torch.zeros_like(goals, dtype=torch.bool)
    path = [cells]
    for t in range(max_steps):
        actions = q_network(features(cells), goal_features).argmax(1)  # DGRL: z_q(s), z_q(g)
        cells = torch.where(reached, cells, next_cell[cells, actions])
        path.append(cells)
        arrived = (cells == goals) & ~reached
        steps[arrived] = t + 1
        reached |= arrived
        if reached.all():
            break
    return reached.cpu().numpy(), steps.cpu().numpy(), torch.stack(path).cpu().numpy()


def evaluation_text(tag: str, reached: np.ndarray, steps: np.ndarray, optimal: int) -> str:
    return f"{tag} {reached.mean():.2f} success, {steps.sum()} total steps (optimal {optimal})"


def episode_frames(layout: "MazeLayout", path: np.ndarray, steps: np.ndarray, goal_cells: np.ndarray) -> list:
    """Video frames of evaluate()'s episodes, one goal after another: the noiseless observation beside the goal, 2x."""
    gap = np.full((layout.images.shape[1], 2, 3), 255, dtype=np.uint8)
    frames = []
    for index, goal in enumerate(goal_cells):
        for cell in path[: steps[index] + 1, index]:
            frame = np.concatenate([layout.images[cell], gap, layout.images[goal]], axis=1)
            frames.append(frame.repeat(2, 0).repeat(2, 1))
    return frames


def bonus_quality(bonus: np.ndarray, layout: "MazeLayout") -> tuple[float, float]:
    """How well a (cell, goal) bonus matrix tracks the maze: its correlation with minus the shortest-path distance over
    all pairs of distinct cells, and the fraction of moves one step closer to a goal that strictly raise the bonus."""
    off_diagonal = ~np.eye(layout.n_cells, dtype=bool)
    bonuses, closeness = bonus[off_diagonal], -layout.distances[off_diagonal]
    correlation = 0.0 if bonuses.std() == 0 else float(np.corrcoef(bonuses, closeness)[0, 1])
    closer = layout.distances[layout.next_cell] < layout.distances[:, None, :]  # (cell, action, goal)
    raised = bonus[layout.next_cell] > bonus[:, None, :]
    return correlation, float(raised[closer].mean())


def report_pretraining(writer, loop: "LoopState", table: CellTable, layout: "MazeLayout", args: Args, start_time):
    """Log and print, once pre-training ends, the codebook's health and how well the bonus tracks maze distance."""
    if table.codes is not None:
        distinct = len(torch.unique(table.codes, dim=0))  # DGRL
        add_kept_scalar(writer, loop.pretraining_log, "vq/distinct_cells", distinct, 0)
        n_active = active_codes(table.codes, args.n_embed).item()  # DGRL
        add_kept_scalar(writer, loop.pretraining_log, "vq/active_codes", n_active, 0)
        print(f"codebook: {n_active} active codes; {distinct} of {layout.n_cells} cells have distinct codes")
    cells = torch.arange(layout.n_cells, device=table.z.device)
    rows, columns = torch.cartesian_prod(cells, cells).T
    pair_codes = (None, None) if table.codes is None else (table.codes[rows], table.codes[columns])
    all_bonus = intrinsic_bonus(table.z[rows], table.z[columns], *pair_codes)  # DGRL
    correlation, step_closer = bonus_quality(all_bonus.view(layout.n_cells, -1).cpu().numpy(), layout)
    add_kept_scalar(writer, loop.pretraining_log, "charts/bonus_distance_corr", correlation, 0)
    add_kept_scalar(writer, loop.pretraining_log, "charts/bonus_step_closer", step_closer, 0)
    loss_text = "not trained" if loop.rep_loss is None else f"loss {loop.rep_loss.item():.3f}"
    quality = f"bonus vs maze distance: correlation {correlation:.2f}, raised by {step_closer:.0%} of steps closer"
    print(f"pre-training: {loop.rep_step} steps, {args.rep} {loss_text}, {time.time() - start_time:.1f} s; {quality}")


def evaluate_checkpoint(args: Args, agent: Agent, embedder: CellEmbedder, layout: "MazeLayout", goals, optimal):
    """--checkpoint: load a --save-model checkpoint into the agent, evaluate it on the train and novel goals, print."""
    saved = load_checkpoint(args.checkpoint, args, MUST_MATCH, embedder.device)
    wanted = {f"{name}_goals": cells.tolist() for name, cells in goals.items()}
    saved_split = {key: saved.get(key) for key in wanted}
    if saved_split != wanted:
        refusal = f"was trained on the goal split {saved_split}, but these flags give {wanted}"
        exit_on_errors([f"--checkpoint {args.checkpoint} {refusal}"])
    agent.rep.load_state_dict(saved["representation"])
    agent.q_network.load_state_dict(saved["q_network"])
    agent.rep.eval()
    for split, cells in goals.items():
        reached, steps, _ = evaluate(agent.rep, agent.q_network, embedder, layout, cells, args.max_episode_steps)
        print(evaluation_text(f"{split} goals", reached, steps, optimal[split]))


def write_video(path: str, frames: list[np.ndarray], fps: int) -> None:
    """Frames (H, W, 3) uint8 to an mp4 (moviepy loaded only here), one encoder thread: with more, the bytes vary."""
    os.makedirs(os.path.dirname(path), exist_ok=True)
    importlib.import_module("moviepy").ImageSequenceClip(frames, fps=fps).write_videofile(path, logger=None, threads=1)


# --- Environment ------------------------------------------------------------------------------------------------------

# 6x6 mazes as (2*6+1) x (2*6+1) characters: odd/odd positions are cells, '#' a wall, anything else an opening.
SPIRAL_WORLD = (
    "#############",
    "#.#. . . . .#",
    "# # ####### #",
    "#.#.#. . .#.#",
    "# # # ### # #",
    "#.#.#.#.#.#.#",
    "# # # # # # #",
    "#.#.#. .#.#.#",
    "# # ##### # #",
    "#.#. . . .#.#",
    "# ######### #",
    "#. . . . . .#",
    "#############",
)
LAYOUTS = {
    "SpiralWorld": SPIRAL_WORLD,
    "LoopWorld": (*SPIRAL_WORLD[:10], "# ####### # #", *SPIRAL_WORLD[11:]),  # one more opening: the spiral is a loop
    "EmptyWorld": ("#############",) + ("#. . . . . .#", "#           #") * 5 + ("#. . . . . .#", "#############"),
}
MOVES = ((0, -1), (0, 1), (-1, 0), (1, 0))  # left, right, up, down as (row, column) steps
PIXELS_PER_CHAR, BORDER = 6, 1  # 13 characters x 6 px + 2 px of border = 80 px
WALL_RGB, FLOOR_RGB, AGENT_RGB = (128, 128, 128), (0, 0, 0), (255, 0, 0)  # grey walls, a black floor, a red agent
START_CELL = 0  # the top-left corner: one end of the spiral, a corner of the loop
N_NOVEL_GOALS = 4  # the paper's test set: 4 goals never trained on


class MazeLayout:
    """A maze's static structure: its transition table, its clean images, the shortest-path distances."""

    def __init__(self, name: str):
        rows = LAYOUTS[name]
        self.size = (len(rows) - 1) // 2
        self.n_cells = self.size * self.size
        self.next_cell = np.empty((self.n_cells, len(MOVES)), dtype=np.int64)
        for row in range(self.size):
            for col in range(self.size):
                for action, (d_row, d_col) in enumerate(MOVES):
                    blocked = rows[2 * row + 1 + d_row][2 * col + 1 + d_col] == "#"
                    target = row * self.size + col if blocked else (row + d_row) * self.size + col + d_col
                    self.next_cell[row * self.size + col, action] = target
        wall_chars = np.array([[char == "#" for char in line] for line in rows])
        side = len(rows) * PIXELS_PER_CHAR + 2 * BORDER
        self.floor = np.zeros((side, side), dtype=bool)
        self.floor[BORDER:-BORDER, BORDER:-BORDER] = ~wall_chars.repeat(PIXELS_PER_CHAR, 0).repeat(PIXELS_PER_CHAR, 1)
        background = np.where(self.floor[..., None], np.array(FLOOR_RGB, np.uint8), np.array(WALL_RGB, np.uint8))
        self.images = np.repeat(background[None], self.n_cells, axis=0)
        for cell in range(self.n_cells):
            top = BORDER + (2 * (cell // self.size) + 1) * PIXELS_PER_CHAR
            left = BORDER + (2 * (cell % self.size) + 1) * PIXELS_PER_CHAR
            self.images[cell, top : top + PIXELS_PER_CHAR, left : left + PIXELS_PER_CHAR] = AGENT_RGB
        self.agent_mask = (self.images != background[None]).any(-1)
        # Shortest-path lengths between all pairs of cells (-1: unreachable): breadth-first, from every cell at once.
        adjacent = np.zeros((self.n_cells, self.n_cells), dtype=bool)
        adjacent[np.arange(self.n_cells)[:, None], self.next_cell] = True
        reached = np.eye(self.n_cells, dtype=bool)
        self.distances = np.where(reached, 0, -1)
        for step in range(1, self.n_cells):
            frontier = (reached @ adjacent) & ~reached
            self.distances[frontier] = step
            reached |= frontier

    def render(self, cells: np.ndarray, noise: float, rng: np.random.Generator) -> np.ndarray:
        """uint8 images (len(cells), 80, 80, 3) of the agent in `cells`; with noise, fresh random floor pixels."""
        images = self.images[cells]
        if noise > 0:
            floor = self.floor[None] & ~self.agent_mask[cells]
            speckle = rng.integers(0, int(noise * 255) + 1, size=images.shape, dtype=np.uint8)
            images = np.where(floor[..., None], images + speckle, images)
        return images


def goal_split(layout: MazeLayout, n_train: int, goal_seed: int, n_novel: int = N_NOVEL_GOALS) -> tuple:
    """Disjoint (train, novel) goals, never START_CELL; train: the first n_train of a seeded order (K=4 within K=8)."""
    candidates = np.array([cell for cell in range(layout.n_cells) if cell != START_CELL])
    order = np.random.default_rng(goal_seed).permutation(candidates)
    return np.sort(order[n_novel : n_novel + n_train]), np.sort(order[:n_novel])


class VisualMazeEnv(gym.Env):
    """Reach the goal cell of a 6x6 maze from pixels: "observation" and "desired_goal" (the agent drawn at the goal),
    both 80x80x3 uint8. Reward -1 per step, +5 on reaching the goal, which terminates; info has "cell", "goal_cell"."""

    metadata: ClassVar[dict] = {"render_modes": ["rgb_array"], "render_fps": 8}

    def __init__(self, layout: MazeLayout, goal_cells: np.ndarray, random_start: bool, noise: float, render_mode=None):
        self.layout, self.goal_cells, self.random_start = layout, np.asarray(goal_cells), random_start
        self.noise, self.render_mode = noise, render_mode
        image_space = gym.spaces.Box(0, 255, layout.images.shape[1:], np.uint8)
        self.observation_space = gym.spaces.Dict({"observation": image_space, "desired_goal": image_space})
        self.action_space = gym.spaces.Discrete(len(MOVES))

    def _observe(self):
        images = self.layout.render(np.array([self.cell, self.goal_cell]), self.noise, self.np_random)
        self._frame = images[0]
        return {"observation": images[0], "desired_goal": images[1]}, {"cell": self.cell, "goal_cell": self.goal_cell}

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.goal_cell = int(self.np_random.choice(self.goal_cells))
        self.cell = START_CELL
        if self.random_start:
            self.cell = int(self.np_random.choice([c for c in range(self.layout.n_cells) if c != self.goal_cell]))
        return self._observe()

    def step(self, action):
        self.cell = int(self.layout.next_cell[self.cell, int(action)])
        reached = self.cell == self.goal_cell
        observation, info = self._observe()
        return observation, 5.0 if reached else -1.0, reached, False, info

    def render(self):
        return self._frame.repeat(4, 0).repeat(4, 1)


# --- Resume: the whole training state (--resume) ----------------------------------------------------------------------


@dataclass
class LoopState:
    """The variables the training loop carries from one step to the next (saved whole in resume.pt under "loop")."""

    observations: dict  # the env's current observation and info (the vector env's buffers are rewritten every step)
    infos: dict
    next_eval: int
    rep_step: int = 0
    next_rep_log: int = 0
    rep_loss: torch.Tensor | None = None
    pretraining_log: list = field(default_factory=list)  # every scalar logged before the DQN phase: see add_kept_scalar
    dqn_phase: bool = False  # True once pre-training's results are logged and the DQN phase wrote its first resume file
    global_step: int = 0
    train_steps: int = 0
    next_train_log: int = 100
    last_evaluation: str = "no evaluation"
    recent_success: deque = field(default_factory=lambda: deque(maxlen=100))


def add_kept_scalar(writer: SummaryWriter, kept: list, tag: str, value: float, step: int) -> None:
    """writer.add_scalar, keeping (tag, value, step) in `kept`: a run resumed in the DQN phase logs them again."""
    writer.add_scalar(tag, value, step)
    kept.append((tag, value, step))


def agent_networks(agent: Agent) -> dict[str, nn.Module]:
    """The agent's networks by name (their state dicts hold the codebook and its EMA buffers)."""
    networks = {"rep": agent.rep, "q_network": agent.q_network, "target_q_network": agent.target_q_network}
    return networks | ({} if agent.target_rep is None else {"target_rep": agent.target_rep})


def env_state(envs: gym.vector.SyncVectorEnv) -> dict:
    """What the maze env in its wrappers and the vector env need to go on with the episode in progress."""
    statistics = envs.envs[0]
    time_limit, maze = statistics.env, statistics.env.env
    return {
        "cell": maze.cell,
        "goal_cell": maze.goal_cell,
        "frame": maze._frame,
        "generator": maze.np_random.bit_generator.state,  # goal draws, random starts, image noise
        "elapsed_steps": time_limit._elapsed_steps,
        "episode_return": statistics.episode_returns,
        "episode_length": statistics.episode_lengths,
        "episode_time": time.perf_counter() - statistics.episode_start_time,
        "episode_count": statistics.episode_count,
        "queues": (statistics.return_queue, statistics.length_queue, statistics.time_queue),
        "autoreset": envs._autoreset_envs.copy(),
        "action_generator": envs.action_space.np_random.bit_generator.state,  # epsilon's random actions
    }


def restore_env_state(envs: gym.vector.SyncVectorEnv, state: dict) -> None:
    statistics = envs.envs[0]
    time_limit, maze = statistics.env, statistics.env.env
    maze.cell, maze.goal_cell, maze._frame = state["cell"], state["goal_cell"], state["frame"]
    maze.np_random.bit_generator.state = state["generator"]
    time_limit._elapsed_steps = state["elapsed_steps"]
    statistics.episode_returns, statistics.episode_lengths = state["episode_return"], state["episode_length"]
    statistics.episode_start_time = time.perf_counter() - state["episode_time"]
    statistics.episode_count = state["episode_count"]
    statistics.return_queue, statistics.length_queue, statistics.time_queue = state["queues"]
    envs._autoreset_envs = state["autoreset"]
    envs.action_space.np_random.bit_generator.state = state["action_generator"]


def training_state(agent: Agent, rng: np.random.Generator, envs, replay: ReplayBuffer, loop: LoopState) -> dict:
    """Everything a stopped run needs to continue exactly, but the global random states (save_resume adds them)."""
    return {
        "networks": {name: network.state_dict() for name, network in agent_networks(agent).items()},
        "optimizers": {"rep": agent.rep_optimizer.state_dict(), "q": agent.q_optimizer.state_dict()},
        "generator": rng.bit_generator.state,  # random walks, replay batches, image noise
        "env": env_state(envs),
        "replay": replay.state_dict(),
        "loop": copy.deepcopy(vars(loop)),  # a plain dict: a run started as __main__ resumes when imported too
    }


def restore_training_state(saved: dict, agent: Agent, rng: np.random.Generator, envs, replay: ReplayBuffer):
    """Put back what training_state saved into objects built as a new run builds them; returns the loop's variables."""
    for name, network in agent_networks(agent).items():
        network.load_state_dict(saved["networks"][name])
    agent.rep_optimizer.load_state_dict(saved["optimizers"]["rep"])
    agent.q_optimizer.load_state_dict(saved["optimizers"]["q"])
    rng.bit_generator.state = saved["generator"]
    restore_env_state(envs, saved["env"])
    replay.load_state_dict(saved["replay"])
    return LoopState(**saved["loop"])


# --- The script's constants: the flags a checkpoint must match --------------------------------------------------------

MUST_MATCH = ("env_id", "n_train_goals", "goal_seed", "noise", "max_episode_steps")  # the maze, the goals, evaluation
MUST_MATCH += ("rep", "embed_dim", "hidden_dim", "groups", "n_embed")  # the architecture


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
    """Refuse bad flags before any work (exit status 2), naming each flag and what it accepts."""
    errors = common_errors(args)
    errors += range_errors(args, "total_timesteps buffer_size batch_size max_episode_steps eval_frequency embed_dim", 1)
    errors += range_errors(args, "target_network_frequency train_frequency rep_transitions rep_batch_size", 1)
    errors += range_errors(args, "hidden_dim", 1)
    errors += range_errors(args, "goal_seed learning_starts rep_steps bonus_coef", 0)
    errors += range_errors(args, "learning_rate rep_learning_rate", 0, low_open=True)
    errors += range_errors(args, "gamma exploration_fraction", 0, 1, low_open=True)
    errors += range_errors(args, "start_e end_e noise", 0, 1)
    errors += range_errors(args, "n_train_goals", 1, MazeLayout(args.env_id).n_cells - 1 - N_NOVEL_GOALS)  # free cells
    if args.start_e < args.end_e:
        errors.append(f"--start-e {args.start_e} must be >= --end-e {args.end_e}: epsilon decays from one to the other")
    if args.groups < 0 or (args.groups and args.embed_dim % args.groups):  # 0 is the baseline
        divisors = [g for g in range(1, args.embed_dim + 1) if args.embed_dim % g == 0]
        wanted = f"0 (baseline) or divide --embed-dim {args.embed_dim}: one of {divisors}"
        errors.append(f"--groups must be {wanted}; got {args.groups}")
    if args.batch_size > args.buffer_size:
        errors.append(f"--batch-size {args.batch_size} must be <= --buffer-size {args.buffer_size}")
    if args.rep_batch_size > args.rep_transitions:
        errors.append(f"--rep-batch-size {args.rep_batch_size} must be <= --rep-transitions {args.rep_transitions}")
    if args.rep == "infomax" and args.rep_steps and args.rep_batch_size < 2:
        errors.append("--rep-batch-size must be >= 2 with --rep infomax (InfoNCE needs in-batch negatives)")
    if args.train_frequency >= 1 and args.learning_starts >= 0:
        first_update = -(-args.learning_starts // args.train_frequency) * args.train_frequency
        if first_update >= args.total_timesteps:
            steps = f"--total-timesteps {args.total_timesteps} must exceed --learning-starts {args.learning_starts}"
            why = f"the first update is at step {first_update} with --train-frequency {args.train_frequency}"
            errors.append(f"{steps} ({why}): no DQN update would run")
    exit_on_errors(errors)


if __name__ == "__main__":
    main(tyro.cli(Args))
