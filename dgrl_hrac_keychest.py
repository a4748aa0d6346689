"""DGRL on HRAC in the Key-Chest grid: discretized subgoals for a two-level agent.

Paper: Islam et al. 2022, "Discrete Factorial Representations as an Abstraction for Goal Conditioned RL", section
"Goal Grounding in KeyChest Maze Navigation Domain" and appendix "KeyChest Domain". The agent is HRAC's discrete
agent (Zhang et al., NeurIPS 2020): a TD3 high level proposes an absolute cell (row, col) every k = 10 steps, kept
within k-step reach by an adjacency network trained with a contrastive loss; an on-policy A2C low level is rewarded
for reaching the proposed cell. DGRL (`--groups G`) passes each subgoal through an encoder, the shared-codebook
bottleneck of vq.py and a decoder back to the grid; the low level is conditioned on (and rewarded for reaching) the
decoded discretized subgoal instead of the raw one, or with `--dgrl-goal embedding` sees the discrete embedding
itself. `--groups 0` is plain HRAC from the same file.

    python dgrl_hrac_keychest.py --groups 16            # paper setting, DGRL G=16: 2M frames (about 28 min on a CPU core)
    python dgrl_hrac_keychest.py --groups 0             # HRAC
    python dgrl_hrac_keychest.py --total-timesteps 20000 --adj-init-steps 5000 --man-buffer-size 400   # smoke run

The study: benchmark/hrac_keychest.sh. Docs: docs/dgrl_hrac_keychest.md.
"""

import os
import random
import signal
import time
from dataclasses import dataclass
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
    """whether to record the first evaluation episode of every 10th evaluation (saved in `videos/`)"""
    save_model: bool = False
    """whether to save a checkpoint (both levels, adjacency network, goal autoencoder with its codebook) at every
    evaluation and at the end"""
    checkpoint: str | None = None
    """path of a saved checkpoint: evaluate it over --eval-episodes episodes, then exit (no training)"""
    threads: int = 1
    """torch CPU threads (one is fastest for these 300-unit networks; two runs then fit side by side on 2 cores)"""

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
    man_noise_sigma: float = 5.0
    """Gaussian exploration noise on the subgoal, in cells"""
    man_reward_scale: float = 1.0
    """scale of the environment reward summed over a k-step segment"""
    n_noisy_goals: int = 20
    """noisy candidate subgoals drawn per decision; one deemed k-step reachable is picked (0 = plain Gaussian noise)"""
    goal_loss_coef: float = 20.0
    """weight of the adjacency loss in the high-level actor loss"""
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
    """low-level reward for a step that ends within --goal-threshold of the subgoal in both coordinates"""
    goal_threshold: float = 0.5
    """the subgoal counts as reached when |s' - g| <= this in both coordinates"""

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
    adj_training_freq: int = 50_000
    """frames between two adjacency retrainings"""
    adj_training_epochs: int = 25
    """epochs of each retraining"""
    adj_batch_size: int = 64
    """adjacency batch size (pairs of visited cells)"""
    adj_hidden_dim: int = 128
    """hidden units of the 4-layer adjacency network"""
    adj_embed_dim: int = 32
    """output size of the adjacency network"""

    # Evaluation
    eval_frequency: int = 50
    """training episodes between evaluations"""
    eval_episodes: int = 50
    """episodes per evaluation (random starts, deterministic subgoals, sampled low-level actions)"""

    # DGRL
    groups: int = 16
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
    dgrl_goal: Literal["decoded", "embedding"] = "decoded"
    """what the low level gets under DGRL: the decoded discretized subgoal, a point of the grid that it is rewarded for
    reaching (the paper appendix's encoder-bottleneck-decoder), or the discrete embedding itself, rewarded for reaching
    the raw subgoal"""
    ae_hidden_dim: int = 128
    """hidden units of the subgoal encoder and decoder"""
    ae_lr: float = 1e-3
    """Adam learning rate of the subgoal autoencoder"""
    ae_init_steps: int = 2000
    """autoencoder steps on uniform random subgoals during adjacency pre-training"""
    ae_batch_size: int = 256
    """batch size of those steps"""


# --- Environment ------------------------------------------------------------------------------------------------------

LAYOUT = (
    "wwwwwwwwwwwwwwwww",
    "w               w",
    "wB              w",
    "wwwwwwwwwwwwww  w",
    "w               w",
    "w               w",
    "wK wwwwwwwwwww  w",
    "w               w",
    "w               w",
    "wwwwwwwwwwwwww  w",
    "w               w",
    "w      S        w",
    "wwwwwwwwwwwwwwwww",
)
MOVES = np.array(((-1, 0), (1, 0), (0, -1), (0, 1)))  # up, down, left, right as (row, col) steps
WALLS = np.array([[char == "w" for char in line] for line in LAYOUT])
HEIGHT, WIDTH = WALLS.shape
GOAL_SCALE = np.array((HEIGHT, WIDTH), dtype=np.float32)  # the high level proposes cells in [0, 13] x [0, 17]
KEY_CELL, CHEST_CELL = (6, 1), (2, 1)
FREE_CELLS = np.argwhere(~WALLS)  # (128, 2) in row-major order
KEY_REWARD, CHEST_REWARD = 1.0, 5.0


class KeyChestVecEnv(gym.vector.VectorEnv):
    """`num_envs` Key-Chest grids stepped together in numpy (HRAC's task, reference hrac-keychest.md).

    Observation (row, col, has_key) as float32. Actions: 0 up, 1 down, 2 left, 3 right; with probability
    `random_action_prob` the action is replaced by a uniformly random one; walls block moves. Entering the key cell
    gives +1 the first time (has_key becomes 1); entering the chest cell with the key gives +5 and terminates (unless
    `terminate_at_chest` is False, HRAC's pure-exploration mode). Episodes truncate after `max_episode_steps` and
    start on a uniformly random free cell. Autoreset is SAME_STEP: a finished env is reset in the step that ends it,
    its last observation in `infos["final_obs"]` (mask `infos["_final_obs"]`) and its return and length in
    `infos["episode"]["r"]` / `["l"]` (mask `infos["_episode"]`).
    """

    metadata: ClassVar[dict] = {"autoreset_mode": gym.vector.AutoresetMode.SAME_STEP, "render_modes": ["rgb_array"]}

    def __init__(
        self,
        num_envs: int,
        max_episode_steps: int = 500,
        random_action_prob: float = 0.25,
        terminate_at_chest: bool = True,
        render_mode: str | None = None,
    ):
        self.num_envs = num_envs
        self.max_episode_steps, self.random_action_prob = max_episode_steps, random_action_prob
        self.terminate_at_chest, self.render_mode = terminate_at_chest, render_mode
        self.single_observation_space = gym.spaces.Box(0, max(HEIGHT, WIDTH) - 1, (3,), np.float32)
        self.single_action_space = gym.spaces.Discrete(len(MOVES))
        self.observation_space = gym.vector.utils.batch_space(self.single_observation_space, num_envs)
        self.action_space = gym.vector.utils.batch_space(self.single_action_space, num_envs)
        self.rng = np.random.default_rng()
        self.position = np.zeros((num_envs, 2), dtype=np.int64)
        self.has_key = np.zeros(num_envs, dtype=bool)
        self.elapsed = np.zeros(num_envs, dtype=np.int64)
        self.episode_return = np.zeros(num_envs, dtype=np.float64)

    def _observe(self) -> np.ndarray:
        return np.concatenate([self.position, self.has_key[:, None]], 1).astype(np.float32)

    def _reset_envs(self, mask: np.ndarray) -> None:
        self.position[mask] = FREE_CELLS[self.rng.integers(len(FREE_CELLS), size=int(mask.sum()))]
        self.has_key[mask], self.elapsed[mask], self.episode_return[mask] = False, 0, 0.0

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        if seed is not None:
            self.rng = np.random.default_rng(seed)
            self.action_space.seed(seed)
        self._reset_envs(np.ones(self.num_envs, dtype=bool))
        return self._observe(), {}

    def step(self, actions):
        actions = np.asarray(actions, dtype=np.int64)
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
        self.episode_return += rewards
        terminations = opened & self.terminate_at_chest
        truncations = (self.elapsed >= self.max_episode_steps) & ~terminations
        done = terminations | truncations
        infos = {}
        if done.any():
            infos = {
                "final_obs": np.where(done[:, None], self._observe(), 0.0).astype(np.float32),
                "_final_obs": done,
                "episode": {"r": np.where(done, self.episode_return, 0.0), "l": np.where(done, self.elapsed, 0)},
                "_episode": done,
            }
            self._reset_envs(done)
        return self._observe(), rewards, terminations, truncations, infos

    def frame(self, index: int, subgoal: np.ndarray | None = None, pixels: int = 16) -> np.ndarray:
        """RGB image of env `index`: walls grey, key yellow (until taken), chest brown, agent red (blue with the key),
        and the current subgoal's cell outlined in green."""
        image = np.where(WALLS[..., None], np.uint8(110), np.uint8(0)).repeat(3, 2)
        if not self.has_key[index]:
            image[KEY_CELL] = (230, 200, 0)
        image[CHEST_CELL] = (140, 80, 20)
        image[tuple(self.position[index])] = (40, 90, 255) if self.has_key[index] else (230, 30, 30)
        image = image.repeat(pixels, 0).repeat(pixels, 1)
        if subgoal is not None:
            row, col = np.clip(np.round(subgoal).astype(int), 0, (HEIGHT - 1, WIDTH - 1))
            cell = image[row * pixels : (row + 1) * pixels, col * pixels : (col + 1) * pixels]
            cell[:2], cell[-2:], cell[:, :2], cell[:, -2:] = (0, 220, 0), (0, 220, 0), (0, 220, 0), (0, 220, 0)
        return image

    def render(self):
        return tuple(self.frame(index) for index in range(self.num_envs))


def shortest_path_lengths() -> np.ndarray:
    """(128, 128) BFS distances between free cells (FREE_CELLS order), ignoring the action noise."""
    index = -np.ones((HEIGHT, WIDTH), dtype=np.int64)
    index[FREE_CELLS[:, 0], FREE_CELLS[:, 1]] = np.arange(len(FREE_CELLS))
    distances = np.full((len(FREE_CELLS), len(FREE_CELLS)), -1, dtype=np.int64)
    for source in range(len(FREE_CELLS)):
        distances[source, source], frontier = 0, [source]
        while frontier:
            following = []
            for cell in frontier:
                for move in MOVES:
                    row, col = FREE_CELLS[cell] + move
                    neighbour = index[row, col]
                    if neighbour >= 0 and distances[source, neighbour] < 0:
                        distances[source, neighbour] = distances[source, cell] + 1
                        following.append(neighbour)
            frontier = following
    return distances


# --- Networks ---------------------------------------------------------------------------------------------------------


def mlp(in_dim: int, hidden_dim: int, out_dim: int, n_hidden: int = 2) -> nn.Sequential:
    layers, width = [], in_dim
    for _ in range(n_hidden):
        layers += [nn.Linear(width, hidden_dim), nn.ReLU()]
        width = hidden_dim
    return nn.Sequential(*layers, nn.Linear(width, out_dim))


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

    def __init__(self, embed_dim: int, hidden_dim: int, groups: int, n_embed: int, beta: float, decay: float, dead: int):
        super().__init__()
        self.encoder = mlp(2, hidden_dim, embed_dim, n_hidden=1)
        self.vq = VectorQuantizerEMA(embed_dim, n_embed, groups, beta=beta, decay=decay, dead_code_steps=dead)
        self.decoder = mlp(embed_dim, hidden_dim, 2, n_hidden=1)
        self.register_buffer("scale", torch.as_tensor(GOAL_SCALE))

    def forward(self, goals: torch.Tensor, update: bool = False):
        """(discrete embedding, commitment loss, code indices, reconstruction in [0, 1]^2 units) of raw subgoals."""
        quantized, vq_loss, indices = self.vq(self.encoder(goals / self.scale), update=update)
        return quantized, vq_loss, indices, self.decoder(quantized)


# --- Buffers, losses, evaluation --------------------------------------------------------------------------------------


class ManagerReplay:
    """Preallocated ring buffer of k-step high-level transitions (state, subgoal, summed reward, next state, terminal)."""

    def __init__(self, capacity: int, rng: np.random.Generator):
        self.capacity, self.rng, self.size, self.pointer = capacity, rng, 0, 0
        self.states = np.zeros((capacity, 3), dtype=np.float32)
        self.goals = np.zeros((capacity, 2), dtype=np.float32)
        self.rewards = np.zeros(capacity, dtype=np.float32)
        self.next_states = np.zeros((capacity, 3), dtype=np.float32)
        self.terminals = np.zeros(capacity, dtype=np.float32)

    def add(self, states, goals, rewards, next_states, terminals) -> None:
        slots = (self.pointer + np.arange(len(states))) % self.capacity
        self.states[slots], self.goals[slots], self.rewards[slots] = states, goals, rewards
        self.next_states[slots], self.terminals[slots] = next_states, terminals
        self.pointer = int((self.pointer + len(states)) % self.capacity)
        self.size = min(self.size + len(states), self.capacity)

    def started(self) -> bool:
        return self.size >= self.capacity // 2

    def sample(self, batch_size: int, device: torch.device) -> tuple[torch.Tensor, ...]:
        """A uniform batch of distinct transitions (as the original). From a large buffer, redrawing the rare batch with a
        repeat is 5x faster than rng.choice(replace=False), which the small-buffer case uses."""
        if self.size < 16 * batch_size:
            batch = self.rng.choice(self.size, batch_size, replace=False)
        else:
            batch = self.rng.integers(self.size, size=batch_size)
            while len(np.unique(batch)) < batch_size:
                batch = self.rng.integers(self.size, size=batch_size)
        columns = (self.states, self.goals, self.rewards, self.next_states, self.terminals)
        return tuple(torch.as_tensor(column[batch], device=device) for column in columns)


def segment_returns(rewards: np.ndarray, gamma: float, k: int) -> np.ndarray:
    """Discounted returns that stop at the end of each k-step segment (steps 0..k-1, k..2k-1, ...), with no bootstrap:
    HRAC's low-level A2C target, one subgoal per segment."""
    n_segments = -(-len(rewards) // k)
    padded = np.zeros(n_segments * k, dtype=np.float64)
    padded[: len(rewards)] = rewards
    offsets = np.arange(k)[None, :] - np.arange(k)[:, None]  # offsets[i, j] = j - i
    discount = np.where(offsets >= 0, gamma ** np.maximum(offsets, 0), 0.0)
    return (padded.reshape(n_segments, k) @ discount.T).reshape(-1)[: len(rewards)]


def goal_reached(next_states: torch.Tensor, goals: torch.Tensor, threshold: float) -> torch.Tensor:
    """1 where the next cell is within `threshold` of the subgoal in both coordinates (the low level's reward)."""
    return ((next_states[:, :2] - goals).abs() <= threshold).all(1).float()


def a2c_loss(logits: torch.Tensor, values: torch.Tensor, actions: torch.Tensor, returns: torch.Tensor, entropy_coef: float):
    """HRAC's A2C loss: mean of -A log pi(a) + A^2 - c H(pi), A = return - V (the original's unhalved value loss)."""
    log_probs = F.log_softmax(logits, 1)
    advantages = returns - values
    policy_loss = -(advantages.detach() * log_probs.gather(1, actions.unsqueeze(1)).squeeze(1)).mean()
    value_loss = advantages.pow(2).mean()
    entropy = -(log_probs.exp() * log_probs).sum(1).mean()
    return policy_loss + value_loss - entropy_coef * entropy, policy_loss, value_loss, entropy


def contrastive_loss(emb_a: torch.Tensor, emb_b: torch.Tensor, labels: torch.Tensor, margin_pos: float, margin_neg: float):
    """HRAC's adjacency loss: mean(l * max(0, d - m+)) + mean((1 - l) * max(0, m- - d)), d = ||phi_a - phi_b||."""
    distances = torch.sqrt((emb_a - emb_b).pow(2).sum(1) + 1e-12)
    return (labels * (distances - margin_pos).clamp(min=0)).mean() + (
        (1 - labels) * (margin_neg - distances).clamp(min=0)
    ).mean()


def mark_adjacent(adjacency: np.ndarray, visited: np.ndarray, cells: np.ndarray, k: int) -> None:
    """Record in the (H*W, H*W) matrix that cells t and t+j of one trajectory (flat indices) are adjacent, 1 <= j < k."""
    visited[cells] = True
    for offset in range(1, min(k, len(cells))):
        adjacency[cells[:-offset], cells[offset:]] = True
        adjacency[cells[offset:], cells[:-offset]] = True


def train_adjacency(anet, optimizer, adjacency, visited, epochs, batch_size, margin_pos, margin_neg, rng, device) -> float:
    """`epochs` passes over every pair of visited cells in shuffled batches; returns the last epoch's mean loss."""
    cells = np.flatnonzero(visited)
    first, second = np.triu_indices(len(cells), 1)
    coordinates = torch.as_tensor(np.stack(np.divmod(cells, WIDTH), 1), dtype=torch.float32, device=device)
    labels_all = torch.as_tensor(adjacency[cells[first], cells[second]], dtype=torch.float32, device=device)
    first, second = torch.as_tensor(first, device=device), torch.as_tensor(second, device=device)
    anet.requires_grad_(True)
    losses = [torch.tensor(float("nan"))]
    for _ in range(epochs):
        order = torch.as_tensor(rng.permutation(len(first)), device=device)
        losses = []
        for batch in order.split(batch_size):
            loss = contrastive_loss(
                anet(coordinates[first[batch]]), anet(coordinates[second[batch]]), labels_all[batch], margin_pos, margin_neg
            )
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            losses.append(loss.detach())
    anet.requires_grad_(False)  # the high-level actor's adjacency loss must not train it
    return torch.stack(losses).mean().item()


@torch.no_grad()
def adjacency_accuracy(anet: AdjacencyNet, distances: np.ndarray, k: int, threshold: float) -> float:
    """Agreement of `||phi_i - phi_j|| < threshold` with `BFS distance <= k` over all pairs of free cells."""
    embeddings = anet(torch.as_tensor(FREE_CELLS, dtype=torch.float32, device=next(anet.parameters()).device))
    predicted = (torch.cdist(embeddings, embeddings) < threshold).cpu().numpy()
    first, second = np.triu_indices(len(FREE_CELLS), 1)
    return float((predicted[first, second] == (distances[first, second] <= k)).mean())


@torch.no_grad()
def propose_subgoals(actor, anet, states, args: Args, threshold: float, explore: bool) -> torch.Tensor:
    """HRAC's subgoal choice. Exploring: draw n_noisy_goals Gaussian candidates around the actor's output, clipped to the
    grid, and pick uniformly among those the adjacency network deems k-step reachable, else the noiseless output."""
    raw = actor(states)
    if not explore:
        return raw
    noise_shape = (len(states), max(args.n_noisy_goals, 1), 2)
    noise = args.man_noise_sigma * torch.randn(noise_shape, device=raw.device)
    noisy = torch.minimum((raw.unsqueeze(1) + noise).clamp(min=0), actor.scale)
    if args.n_noisy_goals == 0:
        return noisy[:, 0]
    distances = (anet(noisy) - anet(states[:, :2]).unsqueeze(1)).norm(dim=2)
    reachable = distances < threshold
    pick = torch.where(reachable, torch.rand(reachable.shape, device=raw.device), -1.0).argmax(1)
    chosen = noisy[torch.arange(len(states)), pick]
    return torch.where(reachable.any(1, keepdim=True), chosen, raw)


def controller_goals(goal_ae: GoalAutoencoder | None, goals: torch.Tensor, mode: str, update: bool = False):
    """(what the low level sees of a raw subgoal, the cell-space goal its reward and distances are measured to),
    plus the autoencoder's (commitment loss, codes, reconstruction) for DGRL. HRAC: (g, g). DGRL "decoded": the
    decoded discretized subgoal for both. DGRL "embedding": (discrete embedding, g). Both outputs are detached."""
    if goal_ae is None:
        return goals, goals, None
    quantized, vq_loss, codes, reconstruction = goal_ae(goals, update=update)  # DGRL
    if mode == "embedding":  # DGRL
        return quantized.detach(), goals, (vq_loss, codes, reconstruction)  # DGRL
    decoded = (reconstruction * goal_ae.scale).detach()  # DGRL
    return decoded, decoded, (vq_loss, codes, reconstruction)  # DGRL


@torch.no_grad()
def evaluate(envs: KeyChestVecEnv, actor, controller, goal_ae, args: Args, device, frames=None, random_subgoals=False):
    """One episode per env (random starts): deterministic subgoals every k steps, sampled low-level actions, as the
    original. Returns (mean return, mean distance from a segment's last cell to its subgoal, fraction of segments whose
    subgoal was reached). With `frames`, env 0's episode is appended to it as RGB images. With `random_subgoals`, the
    high level is replaced by uniform random subgoals: the reference that tells what the high level adds."""
    n = envs.num_envs
    observations, _ = envs.reset()
    returns, running = np.zeros(n), np.ones(n, dtype=bool)
    reached_in_segment = torch.zeros(n, dtype=torch.bool, device=device)
    distances, reached = [], []
    for step in range(args.max_episode_steps):
        states = torch.as_tensor(observations, device=device)
        if step % args.k == 0:
            raw_goals = torch.rand(n, 2, device=device) * actor.scale if random_subgoals else actor(states)
            goal_inputs, goals, _ = controller_goals(goal_ae, raw_goals, args.dgrl_goal)  # acting: update=False
            reached_in_segment.zero_()
        if frames is not None and running[0]:
            frames.append(envs.frame(0, goals[0].cpu().numpy()))
        logits, _ = controller(states, goal_inputs)
        actions = torch.multinomial(F.softmax(logits, 1), 1).squeeze(1)
        observations, rewards, terminations, truncations, infos = envs.step(actions.cpu().numpy())
        done = terminations | truncations
        real_next = np.where(done[:, None], infos["final_obs"], observations) if done.any() else observations
        next_states = torch.as_tensor(real_next, device=device)
        reached_in_segment |= goal_reached(next_states, goals, args.goal_threshold).bool()
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


def manager_update(
    actor,
    critic,
    actor_target,
    critic_target,
    actor_optimizer,
    critic_optimizer,
    anet,
    batch,
    args: Args,
    threshold: float,
    policy_term: bool,
):
    """One HRAC high-level TD3 update: twin critics on r + gamma * min Q'(s', pi'(s')) (no target-policy noise), then
    the actor on -Q1(s, pi(s)) (only when `policy_term`, TD3's delay) + goal_loss_coef x the adjacency loss, then
    Polyak targets. Returns (critic loss, adjacency loss, Q1 values)."""
    states, goals, rewards, next_states, terminals = batch
    with torch.no_grad():
        next_q = torch.min(*critic_target(next_states, actor_target(next_states)))
        td_target = rewards + args.man_gamma * (1 - terminals) * next_q
    q1, q2 = critic(states, goals)
    critic_loss = F.mse_loss(q1, td_target) + F.mse_loss(q2, td_target)
    critic_optimizer.zero_grad()
    critic_loss.backward()
    critic_optimizer.step()
    proposed = actor(states)
    actor_q_loss = -critic.q1(torch.cat([states, proposed], 1)).mean() if policy_term else 0.0
    with torch.no_grad():
        state_embeddings = anet(states[:, :2])
    goal_loss = ((anet(proposed) - state_embeddings).norm(dim=1) - threshold).clamp(min=0).mean()
    actor_optimizer.zero_grad()
    (actor_q_loss + args.goal_loss_coef * goal_loss).backward()
    actor_optimizer.step()
    update_target(actor_target, actor, args.man_tau)
    update_target(critic_target, critic, args.man_tau)
    return critic_loss, goal_loss, q1


def goal_autoencoder_step(optimizer, goals: torch.Tensor, reconstruction, vq_loss, goal_scale: torch.Tensor):  # DGRL
    """One Adam step of the subgoal autoencoder on reconstruction (MSE in [0, 1]^2 units) + the commitment loss."""
    reconstruction_loss = F.mse_loss(reconstruction, goals / goal_scale)
    optimizer.zero_grad()
    (reconstruction_loss + vq_loss).backward()
    optimizer.step()
    return reconstruction_loss


def save_checkpoint(path: str, modules: dict[str, nn.Module | None], args: Args) -> None:
    """Write atomically, so that a crash mid-write never destroys the previous checkpoint."""
    payload = {name: None if module is None else module.state_dict() for name, module in modules.items()}
    payload["args"] = vars(args)
    torch.save(payload, path + ".tmp")
    os.replace(path + ".tmp", path)


def write_video(path: str, frames: list[np.ndarray], fps: int = 10) -> None:
    from moviepy import ImageSequenceClip

    os.makedirs(os.path.dirname(path), exist_ok=True)
    ImageSequenceClip(frames, fps=fps).write_videofile(path, logger=None)


def validate(args: Args) -> None:
    """Reject bad flags before any work, naming the flag and the valid choices."""
    errors = []
    if args.groups < 0 or (args.groups and args.embed_dim % args.groups):
        divisors = [g for g in range(1, args.embed_dim + 1) if args.embed_dim % g == 0]
        errors.append(
            f"--groups must be 0 (HRAC) or divide --embed-dim {args.embed_dim}: one of {divisors}; got {args.groups}"
        )
    for flag in (
        "total_timesteps",
        "num_envs",
        "max_episode_steps",
        "k",
        "man_buffer_size",
        "man_batch_size",
        "man_policy_delay",
        "hidden_dim",
        "adj_init_steps",
        "adj_training_freq",
        "adj_batch_size",
        "adj_hidden_dim",
        "adj_embed_dim",
        "eval_frequency",
        "eval_episodes",
        "embed_dim",
        "n_embed",
        "ae_hidden_dim",
        "ae_batch_size",
        "threads",
    ):
        if getattr(args, flag) < 1:
            errors.append(f"--{flag.replace('_', '-')} must be >= 1; got {getattr(args, flag)}")
    for flag in ("n_noisy_goals", "adj_init_epochs", "adj_training_epochs", "ae_init_steps", "vq_dead_code_steps"):
        if getattr(args, flag) < 0:
            errors.append(f"--{flag.replace('_', '-')} must be >= 0; got {getattr(args, flag)}")
    if not 0.0 <= args.random_action_prob <= 1.0:
        errors.append(f"--random-action-prob must be in [0, 1]; got {args.random_action_prob}")
    if args.man_batch_size > args.man_buffer_size // 2:
        errors.append(
            f"--man-batch-size ({args.man_batch_size}) must be <= half of --man-buffer-size ({args.man_buffer_size}), "
            "the fill at which training starts"
        )
    if args.adj_margin_pos > args.adj_margin_neg:
        errors.append(f"--adj-margin-pos ({args.adj_margin_pos}) must be <= --adj-margin-neg ({args.adj_margin_neg})")
    if args.adj_init_steps >= args.total_timesteps:
        errors.append(f"--adj-init-steps ({args.adj_init_steps}) must be < --total-timesteps ({args.total_timesteps})")
    if args.checkpoint is not None and not os.path.isfile(args.checkpoint):
        errors.append(f"--checkpoint {args.checkpoint}: no such file")
    if errors:
        raise SystemExit("dgrl_hrac_keychest.py: invalid arguments:\n  " + "\n  ".join(errors))


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
    rng = np.random.default_rng(args.seed)
    threshold = (args.adj_margin_pos + args.adj_margin_neg) / 2  # embedding distance deemed "k-step reachable"

    actor = ManagerActor(args.hidden_dim).to(device)
    critic = TwinCritic(args.hidden_dim).to(device)
    goal_ae = (  # DGRL
        GoalAutoencoder(
            args.embed_dim, args.ae_hidden_dim, args.groups, args.n_embed, args.vq_beta, args.vq_decay, args.vq_dead_code_steps
        ).to(device)
        if dgrl
        else None
    )
    controller = Controller(args.embed_dim if dgrl and args.dgrl_goal == "embedding" else 2, args.hidden_dim).to(device)
    anet = AdjacencyNet(args.adj_hidden_dim, args.adj_embed_dim).to(device)
    eval_envs = KeyChestVecEnv(args.eval_episodes, args.max_episode_steps, args.random_action_prob)
    eval_envs.reset(seed=args.seed + 100)  # one evaluation stream per run, continued across evaluations
    modules = {"actor": actor, "critic": critic, "controller": controller, "adjacency": anet, "goal_autoencoder": goal_ae}

    if args.checkpoint is not None:
        saved = torch.load(args.checkpoint, map_location=device)
        architecture = ("groups", "dgrl_goal", "embed_dim", "n_embed", "hidden_dim", "adj_hidden_dim", "adj_embed_dim")
        differ = [
            f"--{key.replace('_', '-')} {saved['args'][key]}" for key in architecture if saved["args"][key] != vars(args)[key]
        ]
        if differ:
            raise SystemExit(f"--checkpoint {args.checkpoint} was saved with other networks: pass {' '.join(differ)}")
        for name, module in modules.items():
            if module is not None:
                module.load_state_dict(saved[name])
        for label, random_subgoals in (("", False), (" with uniform random subgoals", True)):
            mean_return, distance, reach = evaluate(
                eval_envs, actor, controller, goal_ae, args, device, random_subgoals=random_subgoals
            )
            print(
                f"{args.eval_episodes} episodes{label}: return {mean_return:.2f}, subgoal distance {distance:.2f}, "
                f"reached {reach:.0%}"
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
    print(f"{run_name}: {args.num_envs} envs, {args.total_timesteps} frames, device {device}")
    start_time = time.time()

    actor_target, critic_target = make_target(actor), make_target(critic)
    actor_optimizer = torch.optim.Adam(actor.parameters(), lr=args.man_actor_lr, fused=True)
    critic_optimizer = torch.optim.Adam(critic.parameters(), lr=args.man_critic_lr, fused=True)
    controller_optimizer = torch.optim.Adam(controller.parameters(), lr=args.ctrl_lr, fused=True)
    anet_optimizer = torch.optim.Adam(anet.parameters(), lr=args.adj_lr, fused=True)
    ae_optimizer = torch.optim.Adam(goal_ae.parameters(), lr=args.ae_lr, fused=True) if dgrl else None  # DGRL
    distances_bfs = shortest_path_lengths()
    adjacency = np.zeros((HEIGHT * WIDTH, HEIGHT * WIDTH), dtype=bool)  # over flat cell indices; persists all run long
    visited = np.zeros(HEIGHT * WIDTH, dtype=bool)
    goal_scale = torch.as_tensor(GOAL_SCALE, device=device)
    max_steps, n_envs = args.max_episode_steps, args.num_envs

    def controller_rollout(envs, observations, explore_goals):
        """Generator over vector steps of the low level acting on subgoals from `explore_goals(states)` every k steps.
        Yields (observations, each env's step in its episode, raw subgoals, actions, true next observations, rewards,
        terminations, terminations | truncations, infos)."""
        t_episode = np.zeros(n_envs, dtype=np.int64)
        goals = torch.zeros(n_envs, 2, device=device)
        goal_inputs = controller_goals(goal_ae, goals, args.dgrl_goal)[0]
        while True:
            states = torch.as_tensor(observations, device=device)
            new_segment = t_episode % args.k == 0
            if new_segment.any():
                index = torch.as_tensor(np.flatnonzero(new_segment), device=device)
                goals[index] = explore_goals(states[index])
                goal_inputs[index] = controller_goals(goal_ae, goals[index], args.dgrl_goal)[0]  # the codebook stays put
            with torch.no_grad():
                logits, _ = controller(states, goal_inputs)
                actions = torch.multinomial(F.softmax(logits, 1), 1).squeeze(1).cpu().numpy()
            next_observations, rewards, terminations, truncations, infos = envs.step(actions)
            done = terminations | truncations
            real_next = np.where(done[:, None], infos["final_obs"], next_observations) if done.any() else next_observations
            goals_np = goals.cpu().numpy().copy()
            yield observations, t_episode.copy(), goals_np, actions, real_next, rewards, terminations, done, infos
            t_episode = np.where(done, 0, t_episode + 1)
            observations = next_observations

    def random_goals(states: torch.Tensor) -> torch.Tensor:
        return torch.rand(len(states), 2, device=device) * goal_scale

    # Phase 1: random-subgoal exploration (the chest ends no episode) to learn k-step adjacency, as HRAC does first.
    frames, episodes = 0, 0
    explore_envs = KeyChestVecEnv(n_envs, max_steps, args.random_action_prob, terminate_at_chest=False)
    trajectories = np.zeros((n_envs, max_steps + 1), dtype=np.int64)  # flat cell indices of each env's current episode
    rollout = controller_rollout(explore_envs, explore_envs.reset(seed=args.seed + 200)[0], random_goals)
    while frames < args.adj_init_steps:
        observations, t_episode, _, _, real_next, _, _, done, _ = next(rollout)
        trajectories[np.arange(n_envs), t_episode] = observations[:, 0] * WIDTH + observations[:, 1]
        trajectories[np.arange(n_envs), t_episode + 1] = real_next[:, 0] * WIDTH + real_next[:, 1]
        frames += n_envs
        for env in np.flatnonzero(done):
            mark_adjacent(adjacency, visited, trajectories[env, : t_episode[env] + 2], args.k)
            episodes += 1
    for env in np.flatnonzero(~done):  # the episodes still running count too
        mark_adjacent(adjacency, visited, trajectories[env, : t_episode[env] + 2], args.k)
    adj_loss = train_adjacency(
        anet, anet_optimizer, adjacency, visited, args.adj_init_epochs, args.adj_batch_size,
        args.adj_margin_pos, args.adj_margin_neg, rng, device,
    )  # fmt: skip
    adj_accuracy = adjacency_accuracy(anet, distances_bfs, args.k, threshold)
    writer.add_scalar("losses/adjacency_loss", adj_loss, frames)
    writer.add_scalar("charts/adjacency_accuracy", adj_accuracy, frames)
    if dgrl:  # DGRL: ground the codebook on subgoals drawn over the whole grid before they condition the low level
        for _ in range(args.ae_init_steps):
            goals = torch.rand(args.ae_batch_size, 2, device=device) * goal_scale  # DGRL
            _, vq_loss, _, reconstruction = goal_ae(goals, update=True)  # DGRL
            goal_autoencoder_step(ae_optimizer, goals, reconstruction, vq_loss, goal_scale)  # DGRL
    print(
        f"adjacency pre-training: {frames} frames, {visited.sum()} cells visited, accuracy {adj_accuracy:.3f} "
        f"(loss {adj_loss:.3f}), {time.time() - start_time:.1f} s"
    )

    # Phase 2: HRAC. The high level explores with adjacency-filtered noise once its replay is half full; before that,
    # subgoals are uniform random and neither level learns.
    replay = ManagerReplay(args.man_buffer_size, rng)
    envs = KeyChestVecEnv(n_envs, max_steps, args.random_action_prob)

    def explore_goals(states: torch.Tensor) -> torch.Tensor:
        if not replay.started():
            return random_goals(states)
        return propose_subgoals(actor, anet, states, args, threshold, explore=True)

    episode_states = np.zeros((n_envs, max_steps, 3), dtype=np.float32)
    episode_goals = np.zeros((n_envs, max_steps, 2), dtype=np.float32)
    episode_actions = np.zeros((n_envs, max_steps), dtype=np.int64)
    episode_next = np.zeros((n_envs, max_steps, 3), dtype=np.float32)
    segment_start = np.zeros((n_envs, 3), dtype=np.float32)
    segment_reward = np.zeros(n_envs, dtype=np.float32)
    frames_since_adjacency, man_updates, evaluations = 0, 0, 0
    recent_returns = []
    rollout = controller_rollout(envs, envs.reset(seed=args.seed)[0], explore_goals)
    stop = []  # Ctrl-C or SIGTERM ends the run after the current step, with the checkpoint saved and the logs flushed

    def request_stop(number, frame):
        stop.append(number)
        signal.signal(number, signal.SIG_DFL)  # a second Ctrl-C or SIGTERM stops at once

    for signal_number in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signal_number, request_stop)
    while frames < args.total_timesteps and not stop:
        observations, t_episode, goals, actions, real_next, rewards, terminations, done, infos = next(rollout)
        rows = np.arange(n_envs)
        episode_states[rows, t_episode], episode_goals[rows, t_episode] = observations, goals
        episode_actions[rows, t_episode], episode_next[rows, t_episode] = actions, real_next
        # High-level transitions: one per k-step segment, or per shorter last segment; termination only at the chest.
        segment_start = np.where((t_episode % args.k == 0)[:, None], observations, segment_start)
        segment_reward = np.where(t_episode % args.k == 0, 0.0, segment_reward) + args.man_reward_scale * rewards
        segment_end = ((t_episode + 1) % args.k == 0) | done
        if segment_end.any():
            replay.add(
                segment_start[segment_end], goals[segment_end], segment_reward[segment_end],
                real_next[segment_end], terminations[segment_end],
            )  # fmt: skip
        frames += n_envs
        frames_since_adjacency += n_envs

        for env in np.flatnonzero(done):
            length = int(t_episode[env]) + 1
            episodes += 1
            recent_returns.append(float(infos["episode"]["r"][env]))
            writer.add_scalar("charts/episodic_return", infos["episode"]["r"][env], frames)
            writer.add_scalar("charts/episodic_length", length, frames)
            writer.add_scalar("charts/success_rate", float(terminations[env]), frames)
            trajectory = np.vstack([episode_states[env, :length, :2], real_next[env, :2]]).astype(np.int64)
            mark_adjacent(adjacency, visited, trajectory @ (WIDTH, 1), args.k)  # flat cell indices

            if replay.started():
                # Low level: one A2C update on this episode, returns truncated at each segment's end.
                states_t = torch.as_tensor(episode_states[env, :length], device=device)
                goals_t = torch.as_tensor(episode_goals[env, :length], device=device)
                next_t = torch.as_tensor(episode_next[env, :length], device=device)
                # DGRL: the low-level goals are recomputed from the stored raw subgoals by the current autoencoder, whose
                # training step this is (the codebook moves here); the low level's loss does not shape the codes.
                goal_inputs, target_goals, ae_outputs = controller_goals(goal_ae, goals_t, args.dgrl_goal, update=True)
                if dgrl:
                    vq_loss, codes, reconstruction = ae_outputs  # DGRL
                    reconstruction_loss = goal_autoencoder_step(
                        ae_optimizer, goals_t, reconstruction, vq_loss, goal_scale
                    )  # DGRL
                intrinsic = args.ctrl_reward_scale * goal_reached(next_t, target_goals, args.goal_threshold)
                returns_t = torch.as_tensor(
                    segment_returns(intrinsic.cpu().numpy(), args.ctrl_gamma, args.k), dtype=torch.float32, device=device
                )
                logits, values = controller(states_t, goal_inputs)
                ctrl_loss, policy_loss, value_loss, entropy = a2c_loss(
                    logits, values, torch.as_tensor(episode_actions[env, :length], device=device), returns_t,
                    args.ctrl_entropy,
                )  # fmt: skip
                controller_optimizer.zero_grad()
                ctrl_loss.backward()
                controller_optimizer.step()

                # High level: max(length // k, 1) TD3 updates, as HRAC does after every episode.
                for _ in range(max(length // args.k, 1)):
                    critic_loss, goal_loss, q1 = manager_update(
                        actor, critic, actor_target, critic_target, actor_optimizer, critic_optimizer, anet,
                        replay.sample(args.man_batch_size, device), args, threshold,
                        policy_term=man_updates % args.man_policy_delay == 0,
                    )  # fmt: skip
                    man_updates += 1

                if episodes % 10 == 0:
                    segment_reached = np.add.reduceat(intrinsic.cpu().numpy(), np.arange(0, length, args.k)) > 0
                    writer.add_scalar("losses/ctrl_policy_loss", policy_loss.item(), frames)
                    writer.add_scalar("losses/ctrl_value_loss", value_loss.item(), frames)
                    writer.add_scalar("losses/ctrl_entropy", entropy.item(), frames)
                    writer.add_scalar("losses/man_critic_loss", critic_loss.item(), frames)
                    writer.add_scalar("losses/man_goal_loss", goal_loss.item(), frames)
                    writer.add_scalar("losses/man_q_values", q1.mean().item(), frames)
                    writer.add_scalar("charts/intrinsic_reward", intrinsic.mean().item(), frames)
                    writer.add_scalar("charts/subgoal_reach_rate", segment_reached.mean(), frames)
                    if dgrl:
                        writer.add_scalar("losses/goal_reconstruction", reconstruction_loss.item(), frames)  # DGRL
                        writer.add_scalar("vq/commit_loss", vq_loss.item(), frames)  # DGRL
                        writer.add_scalar("vq/perplexity", perplexity(codes, args.n_embed).item(), frames)  # DGRL
                        writer.add_scalar("vq/active_codes", active_codes(codes, args.n_embed).item(), frames)  # DGRL

            # Adjacency: retrain on everything seen so far every adj_training_freq frames.
            if frames_since_adjacency >= args.adj_training_freq:
                adj_loss = train_adjacency(
                    anet, anet_optimizer, adjacency, visited, args.adj_training_epochs, args.adj_batch_size,
                    args.adj_margin_pos, args.adj_margin_neg, rng, device,
                )  # fmt: skip
                adj_accuracy = adjacency_accuracy(anet, distances_bfs, args.k, threshold)
                writer.add_scalar("losses/adjacency_loss", adj_loss, frames)
                writer.add_scalar("charts/adjacency_accuracy", adj_accuracy, frames)
                frames_since_adjacency = 0

            # Evaluate, log, print progress, checkpoint.
            if episodes % args.eval_frequency == 0:
                video = [] if args.capture_video and evaluations % 10 == 0 else None
                mean_return, distance, reach = evaluate(eval_envs, actor, controller, goal_ae, args, device, video)
                random_return = evaluate(eval_envs, actor, controller, goal_ae, args, device, random_subgoals=True)[0]
                if dgrl:
                    with torch.no_grad():
                        cell_codes = goal_ae(torch.as_tensor(FREE_CELLS, dtype=torch.float32, device=device))[2]  # DGRL
                    distinct = len(torch.unique(cell_codes, dim=0))  # DGRL
                    writer.add_scalar("vq/distinct_cells", distinct, frames)  # DGRL: cells with their own code tuple
                evaluations += 1
                sps = int(frames / (time.time() - start_time))
                writer.add_scalar("eval/return", mean_return, frames)
                writer.add_scalar("eval/return_random_subgoals", random_return, frames)
                writer.add_scalar("eval/subgoal_distance", distance, frames)
                writer.add_scalar("eval/subgoal_reach_rate", reach, frames)
                writer.add_scalar("charts/SPS", sps, frames)
                train_return = np.mean(recent_returns) if recent_returns else float("nan")
                recent_returns = []
                elapsed = time.time() - start_time
                print(
                    f"frames {frames:>8}/{args.total_timesteps}  eval return {mean_return:5.2f} (random subgoals "
                    f"{random_return:4.2f})  train return "
                    f"{train_return:5.2f}  subgoal dist {distance:5.2f} reached {reach:4.0%}  adjacency acc "
                    f"{adj_accuracy:.3f}" + (f"  distinct cells {distinct:3d}" if dgrl else "") + f"  SPS {sps}  "
                    f"{elapsed:.0f}s elapsed, {(args.total_timesteps - frames) / max(sps, 1):.0f}s left"
                )
                if video is not None:
                    write_video(f"videos/{run_name}/eval_{frames}.mp4", video)
                if args.save_model:
                    save_checkpoint(f"runs/{run_name}/{args.exp_name}.cleanrl_model", modules, args)

    if args.save_model:
        save_checkpoint(f"runs/{run_name}/{args.exp_name}.cleanrl_model", modules, args)
        print(f"checkpoint: runs/{run_name}/{args.exp_name}.cleanrl_model")
    print(f"{'stopped' if stop else 'done'}: {frames} frames, {episodes} episodes, {time.time() - start_time:.0f} s")
    envs.close()
    writer.close()
