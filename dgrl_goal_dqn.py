"""DGRL on a goal-conditioned DQN in pixel mazes: learning to reach diverse and novel goals.

Paper: Islam et al. 2022, "Discrete Factorial Representations as an Abstraction for Goal Conditioned RL", section 5
"Learning to Reach Diverse and Novel Goals" and appendix "Visual MazeWorlds". A goal-conditioned DQN acts on the
embeddings of an 80x80x3 observation and of a goal observation (the maze with the agent drawn at the goal), from an
encoder pre-trained on random-walk transitions with Deep InfoMax (DRIML's InfoNCE) or an autoencoder. DGRL
(`--groups G`) discretizes both embeddings with the shared-codebook bottleneck of vq.py and adds an exploration bonus
equal to the fraction of the G factors whose codes match between state and goal. The baseline (`--groups 0`) is the
same agent on continuous embeddings, with a bonus equal to their cosine similarity.

    python dgrl_goal_dqn.py --env-id LoopWorld --n-train-goals 4 --groups 16       # paper setting, DGRL (about 1 min)
    python dgrl_goal_dqn.py --env-id LoopWorld --n-train-goals 4 --groups 0        # the continuous goal-DQN
    python dgrl_goal_dqn.py --env-id SpiralWorld --n-train-goals 8 --groups 8      # then tested on 4 novel goals
    python dgrl_goal_dqn.py --total-timesteps 2000 --rep-steps 50                  # a quick CPU smoke run

The whole study: benchmark/goal_dqn.sh. Docs: docs/dgrl_goal_dqn.md.
"""

import os
import random
import time
from collections import deque
from dataclasses import dataclass
from typing import ClassVar, Literal

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
    exp_name: str = os.path.basename(__file__)[: -len(".py")]
    """the name of this experiment"""
    seed: int = 1
    """seed of the experiment"""
    torch_deterministic: bool = True
    """if toggled, `torch.backends.cudnn.deterministic=True`"""
    cuda: bool = True
    """if toggled, cuda will be enabled when available"""
    track: bool = False
    """if toggled, this experiment will be tracked with Weights and Biases"""
    wandb_project_name: str = "dgrl"
    """the wandb's project name"""
    wandb_entity: str | None = None
    """the entity (team) of wandb's project"""
    capture_video: bool = False
    """whether to capture videos of the agent's episodes (env 0, saved in `videos/`)"""
    save_model: bool = False
    """whether to save a checkpoint (encoder, codebook, Q-network) at every evaluation and at the end"""
    checkpoint: str | None = None
    """path of a saved checkpoint: evaluate it on the train and novel goals, then exit (no training)"""

    # Environment
    env_id: Literal["SpiralWorld", "LoopWorld", "EmptyWorld"] = "SpiralWorld"
    """the maze layout"""
    n_train_goals: int = 8
    """K: the number of training goal cells (the 4 novel test cells are the same for every K)"""
    goal_seed: int = 0
    """seed of the train/novel goal split; keep it fixed so that every run sees the same goals"""
    random_start: bool = False
    """start each training episode in a random cell instead of the paper's fixed corner (evaluation always starts there)"""
    noise: float = 0.0
    """amplitude in [0, 1] of fresh per-pixel noise drawn on the maze floor for every observation (0 = clean)"""
    max_episode_steps: int = 100
    """episode step limit (truncation, bootstrapped through)"""

    # Algorithm: DQN
    total_timesteps: int = 20000
    """total environment steps of the DQN phase"""
    learning_rate: float = 1e-3
    """Adam learning rate of the Q-network"""
    buffer_size: int = 20000
    """replay memory size"""
    gamma: float = 0.99
    """discount factor"""
    target_network_frequency: int = 50
    """training steps between hard copies of the target network (codebook included)"""
    batch_size: int = 128
    """replay batch size"""
    start_e: float = 1.0
    """starting epsilon"""
    end_e: float = 0.05
    """final epsilon"""
    exploration_fraction: float = 0.5
    """fraction of total_timesteps over which epsilon decays linearly"""
    learning_starts: int = 1000
    """environment steps before learning starts"""
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
    """pre-training gradient steps"""
    rep_batch_size: int = 128
    """pre-training batch size"""
    rep_learning_rate: float = 1e-3
    """pre-training Adam learning rate"""
    embed_dim: int = 64
    """size of the embedding (m); must be divisible by groups"""
    finetune: bool = False
    """keep training the encoder (and codebook) with the TD loss during RL instead of freezing it"""

    # DGRL
    groups: int = 16
    """G: factors per embedding; 0 runs the continuous baseline"""
    n_embed: int = 64
    """L: codes in the shared codebook"""
    vq_beta: float = 0.25
    """commitment-loss weight"""
    vq_decay: float = 0.99
    """EMA decay of the codebook"""
    vq_dead_code_steps: int = 50
    """restart a code unused for this many pre-training updates at a random current segment (0 = off, as in the paper;
    without it G=4 and G=8 collapse to 1 and 3 active codes here, see the docs)"""


# --- Environment ------------------------------------------------------------------------------------------------------

# 6x6 mazes as (2*6+1) x (2*6+1) characters: odd/odd positions are cells, '#' a wall, anything else an opening.
LAYOUTS = {
    "SpiralWorld": (
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
    ),
    "LoopWorld": (
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
        "# ####### # #",
        "#. . . . . .#",
        "#############",
    ),
    "EmptyWorld": ("#############",) + ("#. . . . . .#", "#           #") * 5 + ("#. . . . . .#", "#############"),
}
MOVES = ((0, -1), (0, 1), (-1, 0), (1, 0))  # left, right, up, down as (row, column) steps
PIXELS_PER_CHAR, BORDER = 6, 1  # 13 characters x 6 px + 2 px of border = 80 px
WALL_RGB, FLOOR_RGB, AGENT_RGB = (128, 128, 128), (0, 0, 0), (255, 0, 0)
START_CELL = 0  # the top-left corner: one end of the spiral, a corner of the loop


class MazeLayout:
    """A maze's static structure: its transition table, its clean images, the shortest-path distances."""

    def __init__(self, name: str):
        rows = LAYOUTS[name]
        self.name, self.size = name, (len(rows) - 1) // 2
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
            top, left = (
                BORDER + (2 * (cell // self.size) + 1) * PIXELS_PER_CHAR,
                BORDER + (2 * (cell % self.size) + 1) * PIXELS_PER_CHAR,
            )
            self.images[cell, top : top + PIXELS_PER_CHAR, left : left + PIXELS_PER_CHAR] = AGENT_RGB
        self.agent_mask = (self.images != background[None]).any(-1)
        self.distances = self._all_pairs_distances()

    def _all_pairs_distances(self) -> np.ndarray:
        """Shortest-path lengths between all pairs of cells, by breadth-first search from every cell."""
        distances = np.full((self.n_cells, self.n_cells), -1, dtype=np.int64)
        for source in range(self.n_cells):
            distances[source, source], frontier = 0, [source]
            while frontier:
                following = []
                for cell in frontier:
                    for neighbour in self.next_cell[cell]:
                        if distances[source, neighbour] < 0:
                            distances[source, neighbour] = distances[source, cell] + 1
                            following.append(neighbour)
                frontier = following
        return distances

    def render(self, cells: np.ndarray, noise: float, rng: np.random.Generator) -> np.ndarray:
        """uint8 images (len(cells), 80, 80, 3) of the agent in `cells`; with noise, fresh random floor pixels."""
        images = self.images[cells]
        if noise > 0:
            floor = self.floor[None] & ~self.agent_mask[cells]
            speckle = rng.integers(0, int(noise * 255) + 1, size=images.shape, dtype=np.uint8)
            images = np.where(floor[..., None], images + speckle, images)
        return images


def goal_split(layout: MazeLayout, n_train: int, goal_seed: int, n_novel: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Disjoint (train, novel) goal cells, never the start cell. The novel cells depend only on goal_seed, and the train
    cells are the first n_train of one seeded order, so K=4 goals are a subset of K=8, which are a subset of K=16."""
    candidates = np.array([cell for cell in range(layout.n_cells) if cell != START_CELL])
    order = np.random.default_rng(goal_seed).permutation(candidates)
    return np.sort(order[n_novel : n_novel + n_train]), np.sort(order[:n_novel])


class VisualMazeEnv(gym.Env):
    """Reach the goal cell of a 6x6 maze from pixels. Observation: {"observation", "desired_goal"}, both 80x80x3 uint8
    (the goal is the maze with the agent drawn at the goal). Reward -1 per step, +5 on the step that reaches the goal,
    which terminates. info carries the agent's "cell" and the "goal_cell"."""

    metadata: ClassVar[dict] = {"render_modes": ["rgb_array"], "render_fps": 8}

    def __init__(self, layout: MazeLayout, goal_cells: np.ndarray, random_start: bool, noise: float, render_mode=None):
        self.layout, self.goal_cells, self.random_start, self.noise = layout, np.asarray(goal_cells), random_start, noise
        self.render_mode = render_mode
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


def make_env(layout: MazeLayout, goal_cells: np.ndarray, args: Args, idx: int, run_name: str):
    def thunk():
        render_mode = "rgb_array" if args.capture_video and idx == 0 else None
        env = VisualMazeEnv(layout, goal_cells, args.random_start, args.noise, render_mode=render_mode)
        env = gym.wrappers.TimeLimit(env, args.max_episode_steps)
        env = gym.wrappers.RecordEpisodeStatistics(env)
        if render_mode is not None:
            env = gym.wrappers.RecordVideo(env, f"videos/{run_name}", episode_trigger=lambda episode: episode % 100 == 0)
        return env

    return thunk


# --- Networks ---------------------------------------------------------------------------------------------------------


class Representation(nn.Module):
    """phi: 80x80x3 uint8 -> R^embed_dim, with the heads of its self-supervised objective and, for DGRL, the bottleneck."""

    def __init__(
        self, embed_dim: int, rep: str, groups: int, n_embed: int, vq_beta: float, vq_decay: float, dead_code_steps: int = 0
    ):
        super().__init__()
        self.encoder = nn.Sequential(
            nn.Conv2d(3, 16, 8, stride=4),
            nn.ReLU(),
            nn.Conv2d(16, 32, 4, stride=2),
            nn.ReLU(),
            nn.Conv2d(32, 32, 3, stride=1),
            nn.ReLU(),
            nn.Flatten(),
            nn.Linear(32 * 6 * 6, embed_dim),
        )
        if rep == "infomax":  # psi_t(phi(s_t), a_t) and psi_t+1(phi(s_t+1)) of DRIML's score
            self.psi_state_action = nn.Sequential(nn.Linear(embed_dim + len(MOVES), 128), nn.ReLU(), nn.Linear(128, 64))
            self.psi_next = nn.Linear(embed_dim, 64)
        else:
            self.decoder = nn.Sequential(nn.Linear(embed_dim, 256), nn.ReLU(), nn.Linear(256, 80 * 80 * 3))
        self.vq = (  # DGRL
            VectorQuantizerEMA(
                embed_dim, n_embed, groups, beta=vq_beta, decay=vq_decay, dead_code_steps=dead_code_steps
            )  # DGRL
            if groups  # DGRL
            else None  # DGRL
        )  # DGRL

    def embed(self, images: torch.Tensor) -> torch.Tensor:
        return self.encoder(images.permute(0, 3, 1, 2).float() / 255.0)

    def forward(self, z: torch.Tensor, update: bool = False) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """(features the agent sees, commitment loss, code indices) of embeddings z."""
        if self.vq is None:
            return z, z.new_zeros(()), None
        return self.vq(z, update=update)  # DGRL


class QNetwork(nn.Module):
    """The paper's simple 2-layer goal-conditioned value network: Q(s, g, .) from [features(s), features(g)]."""

    def __init__(self, embed_dim: int, hidden_dim: int):
        super().__init__()
        self.network = nn.Sequential(nn.Linear(2 * embed_dim, hidden_dim), nn.ReLU(), nn.Linear(hidden_dim, len(MOVES)))

    def forward(self, state_features: torch.Tensor, goal_features: torch.Tensor) -> torch.Tensor:
        return self.network(torch.cat([state_features, goal_features], dim=-1))


# --- Losses, data, evaluation -----------------------------------------------------------------------------------------


def infonce_loss(anchors: torch.Tensor, positives: torch.Tensor, clip: float = 20.0) -> torch.Tensor:
    """InfoNCE with in-batch negatives: row i of `anchors` must pick row i of `positives` among all rows.

    Scores are dot products over sqrt(dim), soft-clipped to (-clip, clip) by clip * tanh(x / clip), as in DRIML.
    """
    scores = anchors @ positives.t() / anchors.shape[1] ** 0.5
    scores = clip * torch.tanh(scores / clip)
    return F.cross_entropy(scores, torch.arange(len(anchors), device=anchors.device))


def intrinsic_bonus(
    z_state: torch.Tensor, z_goal: torch.Tensor, codes_state: torch.Tensor | None, codes_goal: torch.Tensor | None
) -> torch.Tensor:
    """DGRL: fraction of the G factors whose codes match. Baseline: cosine similarity of the continuous embeddings."""
    if codes_state is not None:
        return factor_match(codes_state, codes_goal)  # DGRL
    return F.cosine_similarity(z_state, z_goal, dim=-1)


def bonus_quality(bonus: np.ndarray, layout: MazeLayout) -> tuple[float, float]:
    """How well a (cell, goal) bonus matrix tracks the maze: its correlation with minus the shortest-path distance over
    all pairs of distinct cells, and the fraction of moves one step closer to a goal that strictly raise the bonus."""
    off_diagonal = ~np.eye(layout.n_cells, dtype=bool)
    flat_bonus = bonus[off_diagonal]
    correlation = 0.0 if flat_bonus.std() == 0 else float(np.corrcoef(flat_bonus, -layout.distances[off_diagonal])[0, 1])
    closer = layout.distances[layout.next_cell] < layout.distances[:, None, :]  # (cell, action, goal)
    raised = bonus[layout.next_cell] > bonus[:, None, :]
    return correlation, float(raised[closer].mean())


def random_walks(layout: MazeLayout, n_transitions: int, walk_length: int, rng: np.random.Generator):
    """(cells, actions, next cells) of uniform random walks, each from a uniformly random cell, vectorised over walks."""
    n_walks = -(-n_transitions // walk_length)
    cell = rng.integers(layout.n_cells, size=n_walks)
    cells, actions, next_cells = [], [], []
    for _ in range(walk_length):
        action = rng.integers(len(MOVES), size=n_walks)
        following = layout.next_cell[cell, action]
        cells.append(cell)
        actions.append(action)
        next_cells.append(following)
        cell = following
    return tuple(np.stack(column, axis=1).reshape(-1)[:n_transitions] for column in (cells, actions, next_cells))


class CellEmbedder:
    """Embeddings of the observations of given cells, computed as cheaply as exactness allows.

    With --noise 0 an observation is a function of the agent's cell alone, so the encoder runs once on the 36 distinct
    images and the batch gathers from them: the same values and gradients as encoding the batch, at a fraction of the
    cost. With noise, the batch's images are rendered with fresh noise and encoded.
    """

    def __init__(self, layout: MazeLayout, noise: float, device: torch.device, rng: np.random.Generator):
        self.layout, self.noise, self.device, self.rng = layout, noise, device, rng
        self.all_images = torch.as_tensor(layout.images, device=device)

    def __call__(self, rep: Representation, cells: torch.Tensor) -> torch.Tensor:
        if self.noise == 0:
            return rep.embed(self.all_images)[cells]
        images = self.layout.render(cells.cpu().numpy(), self.noise, self.rng)
        return rep.embed(torch.as_tensor(images, device=self.device))


@torch.no_grad()
def evaluate(rep, q_network, embedder, layout: MazeLayout, goal_cells: np.ndarray, max_steps: int):
    """Greedy episodes from the start cell to every goal at once. Returns (reached, steps) per goal; steps is max_steps
    for a goal not reached."""
    device = embedder.device
    goals = torch.as_tensor(goal_cells, device=device)
    next_cell = torch.as_tensor(layout.next_cell, device=device)

    def cell_features(cells: torch.Tensor) -> torch.Tensor:
        return rep(embedder(rep, cells))[0]

    if embedder.noise == 0:  # every observation is one of the maze's distinct images: encode them once, then look up
        table = cell_features(torch.arange(layout.n_cells, device=device))

        def cell_features(cells: torch.Tensor) -> torch.Tensor:
            return table[cells]

    goal_features = cell_features(goals)
    cells = torch.full_like(goals, START_CELL)
    steps = torch.full_like(goals, max_steps)
    reached = torch.zeros_like(goals, dtype=torch.bool)
    for t in range(max_steps):
        actions = q_network(cell_features(cells), goal_features).argmax(1)
        cells = torch.where(reached, cells, next_cell[cells, actions])
        arrived = (cells == goals) & ~reached
        steps[arrived] = t + 1
        reached |= arrived
        if reached.all():
            break
    return reached.cpu().numpy(), steps.cpu().numpy()


def save_checkpoint(path: str, rep: Representation, q_network: QNetwork, args: Args) -> None:
    """Write atomically, so that a crash mid-write never destroys the previous checkpoint."""
    payload = {"representation": rep.state_dict(), "q_network": q_network.state_dict(), "args": vars(args)}
    torch.save(payload, path + ".tmp")
    os.replace(path + ".tmp", path)


def validate(args: Args) -> None:
    """Reject bad flags before any work, naming the flag and the valid choices."""
    errors = []
    if args.groups < 0 or (args.groups and args.embed_dim % args.groups):
        divisors = [g for g in range(1, args.embed_dim + 1) if args.embed_dim % g == 0]
        errors.append(
            f"--groups must be 0 (baseline) or divide --embed-dim {args.embed_dim}: one of {divisors}; got {args.groups}"
        )
    n_free = len(LAYOUTS[args.env_id]) // 2 * (len(LAYOUTS[args.env_id]) // 2) - 1 - 4
    if not 1 <= args.n_train_goals <= n_free:
        errors.append(
            f"--n-train-goals must be in [1, {n_free}] (cells other than the start and the 4 novel goals); "
            f"got {args.n_train_goals}"
        )
    if not 0.0 <= args.noise <= 1.0:
        errors.append(f"--noise must be in [0, 1]; got {args.noise}")
    for flag in (
        "total_timesteps",
        "buffer_size",
        "batch_size",
        "max_episode_steps",
        "eval_frequency",
        "target_network_frequency",
        "train_frequency",
        "rep_transitions",
        "rep_batch_size",
        "embed_dim",
        "n_embed",
        "hidden_dim",
    ):
        if getattr(args, flag) < 1:
            errors.append(f"--{flag.replace('_', '-')} must be >= 1; got {getattr(args, flag)}")
    if args.rep_steps < 0 or args.learning_starts < 0:
        errors.append("--rep-steps and --learning-starts must be >= 0")
    if args.vq_dead_code_steps < 0:
        errors.append(f"--vq-dead-code-steps must be >= 0; got {args.vq_dead_code_steps}")
    if not 0.0 <= args.vq_decay < 1.0:
        errors.append(f"--vq-decay must be in [0, 1); got {args.vq_decay}")
    if args.checkpoint is not None and not os.path.isfile(args.checkpoint):
        errors.append(f"--checkpoint {args.checkpoint} is not a file")
    if errors:
        raise SystemExit("error: " + "\n       ".join(errors))


if __name__ == "__main__":
    args = tyro.cli(Args)
    validate(args)
    dgrl = args.groups > 0
    run_name = f"{args.env_id}__K{args.n_train_goals}__G{args.groups}__{args.exp_name}__{args.seed}__{int(time.time())}"

    random.seed(args.seed)
    torch.manual_seed(args.seed)
    torch.backends.cudnn.deterministic = args.torch_deterministic
    device = torch.device("cuda" if torch.cuda.is_available() and args.cuda else "cpu")
    rng = np.random.default_rng(args.seed)

    layout = MazeLayout(args.env_id)
    train_goals, novel_goals = goal_split(layout, args.n_train_goals, args.goal_seed)
    embedder = CellEmbedder(layout, args.noise, device, rng)
    rep = Representation(
        args.embed_dim, args.rep, args.groups, args.n_embed, args.vq_beta, args.vq_decay, args.vq_dead_code_steps
    ).to(device)
    q_network = QNetwork(args.embed_dim, args.hidden_dim).to(device)

    def report(tag: str, reached: np.ndarray, steps: np.ndarray, goals: np.ndarray) -> str:
        optimal = layout.distances[START_CELL, goals].sum()
        return f"{tag} {reached.mean():.2f} success, {steps.sum()} total steps (optimal {optimal})"

    if args.checkpoint is not None:
        saved = torch.load(args.checkpoint, map_location=device)
        rep.load_state_dict(saved["representation"])
        q_network.load_state_dict(saved["q_network"])
        rep.eval()
        for tag, goals in (("train goals", train_goals), ("novel goals", novel_goals)):
            print(report(tag, *evaluate(rep, q_network, embedder, layout, goals, args.max_episode_steps), goals))
        raise SystemExit(0)

    if args.track:
        import wandb

        wandb.init(
            project=args.wandb_project_name,
            entity=args.wandb_entity,
            sync_tensorboard=True,
            config=vars(args),
            name=run_name,
            monitor_gym=True,
            save_code=True,
        )
    writer = SummaryWriter(f"runs/{run_name}")
    table = "\n".join(f"|{key}|{value}|" for key, value in vars(args).items())
    writer.add_text("hyperparameters", f"|param|value|\n|-|-|\n{table}")
    print(f"{run_name}: train goals {train_goals.tolist()}, novel goals {novel_goals.tolist()}, device {device}")
    start_time = time.time()

    # Phase 1: pre-train phi (and, for DGRL, the codebook on its embeddings) on random-walk transitions.
    walk_cells, walk_actions, walk_next = (
        torch.as_tensor(column, device=device)
        for column in random_walks(layout, args.rep_transitions, args.max_episode_steps, rng)
    )
    rep_optimizer = torch.optim.Adam(rep.parameters(), lr=args.rep_learning_rate, fused=True)
    for rep_step in range(args.rep_steps):
        batch = torch.as_tensor(rng.integers(args.rep_transitions, size=args.rep_batch_size), device=device)
        z = embedder(rep, torch.cat([walk_cells[batch], walk_next[batch]]))
        _, vq_loss, codes = rep(z, update=True)  # DGRL: one pooled update for s and s', the mean of their commitment losses
        z_state, z_next = z.chunk(2)
        if args.rep == "infomax":
            anchors = rep.psi_state_action(torch.cat([z_state, F.one_hot(walk_actions[batch], len(MOVES)).float()], 1))
            rep_loss = infonce_loss(anchors, rep.psi_next(z_next))
        else:  # with --noise, the clean image is the target: a denoising autoencoder
            clean_images = embedder.all_images[walk_cells[batch]].flatten(1).float() / 255.0
            rep_loss = F.mse_loss(torch.sigmoid(rep.decoder(z_state)), clean_images)
        rep_optimizer.zero_grad()
        (rep_loss + vq_loss).backward()  # DGRL: vq_loss is 0 for the baseline
        rep_optimizer.step()
        if rep_step % 100 == 0 or rep_step == args.rep_steps - 1:
            writer.add_scalar("losses/rep_loss", rep_loss.item(), rep_step)
            if dgrl:
                writer.add_scalar("vq/commit_loss", vq_loss.item(), rep_step)  # DGRL
                writer.add_scalar("vq/perplexity", perplexity(codes, args.n_embed).item(), rep_step)  # DGRL

    # Phase 2: goal-conditioned DQN on the (frozen, unless --finetune) representation.
    rep.eval()
    rep.requires_grad_(args.finetune)
    with torch.no_grad():
        all_z = rep.embed(embedder.all_images)
        all_features, _, all_codes = rep(all_z)
    if dgrl:
        distinct = len(torch.unique(all_codes, dim=0))  # DGRL
        writer.add_scalar("vq/distinct_cells", distinct, 0)  # DGRL
        n_active = active_codes(all_codes, args.n_embed).item()  # DGRL
        writer.add_scalar("vq/active_codes", n_active, 0)  # DGRL
        print(f"codebook: {n_active} active codes; {distinct} of {layout.n_cells} cells have distinct codes")  # DGRL
    pairs = torch.cartesian_prod(torch.arange(layout.n_cells), torch.arange(layout.n_cells)).to(device)
    pair_codes = (None, None) if all_codes is None else (all_codes[pairs[:, 0]], all_codes[pairs[:, 1]])
    all_bonus = intrinsic_bonus(all_z[pairs[:, 0]], all_z[pairs[:, 1]], *pair_codes).view(layout.n_cells, -1)
    correlation, step_closer = bonus_quality(all_bonus.cpu().numpy(), layout)
    writer.add_scalar("charts/bonus_distance_corr", correlation, 0)
    writer.add_scalar("charts/bonus_step_closer", step_closer, 0)
    print(
        f"pre-training: {args.rep_steps} steps, {args.rep} loss {rep_loss.item():.3f}, {time.time() - start_time:.1f} s; "
        f"bonus vs maze distance: correlation {correlation:.2f}, raised by {step_closer:.0%} of steps closer"
    )
    if args.finetune:
        rep.train()
        target_rep = make_target(rep)
    q_optimizer = torch.optim.Adam(
        list(q_network.parameters()) + (list(rep.encoder.parameters()) if args.finetune else []),
        lr=args.learning_rate,
        fused=True,
    )
    target_network = make_target(q_network)

    lookup = not args.finetune and args.noise == 0  # frozen phi, noiseless images: features are a 36-row table

    def features(model: Representation, cells: torch.Tensor, update: bool = False):
        """(features, continuous embedding, commitment loss, codes) of the observations of `cells` under `model`."""
        if lookup:
            return all_features[cells], all_z[cells], all_z.new_zeros(()), None if all_codes is None else all_codes[cells]
        z = embedder(model, cells)
        features_, vq_loss_, codes_ = model(z, update=update)
        return features_, z, vq_loss_, codes_

    envs = gym.vector.SyncVectorEnv(
        [make_env(layout, train_goals, args, 0, run_name)], autoreset_mode=gym.vector.AutoresetMode.SAME_STEP
    )
    envs.action_space.seed(args.seed)
    cells_buffer = np.zeros((args.buffer_size, 3), dtype=np.int64)  # cell, next cell, goal cell: they fix the raw images
    actions_buffer = np.zeros(args.buffer_size, dtype=np.int64)
    rewards_buffer = np.zeros(args.buffer_size, dtype=np.float32)
    terminated_buffer = np.zeros(args.buffer_size, dtype=np.float32)
    recent_success = deque(maxlen=100)
    observations, infos = envs.reset(seed=args.seed)
    dqn_start, train_steps = time.time(), 0
    for global_step in range(args.total_timesteps):
        # Act: epsilon-greedy on the features of the actual observation and goal (the codebook never updates here).
        epsilon = max(
            args.end_e,
            args.start_e - (args.start_e - args.end_e) * global_step / (args.exploration_fraction * args.total_timesteps),
        )
        if random.random() < epsilon:
            actions = envs.action_space.sample()
        else:
            with torch.no_grad():
                if lookup:
                    state_features, goal_features = all_features[infos["cell"]], all_features[infos["goal_cell"]]
                else:
                    images = torch.as_tensor(
                        np.concatenate([observations["observation"], observations["desired_goal"]]), device=device
                    )
                    state_features, goal_features = rep(rep.embed(images), update=False)[0].chunk(2)
                actions = q_network(state_features, goal_features).argmax(1).cpu().numpy()
        next_observations, rewards, terminations, truncations, next_infos = envs.step(actions)

        # Store: the true final cell of a finished episode comes from final_info (same-step autoreset).
        done = terminations | truncations
        real_next_cells = (
            np.where(done, next_infos["final_info"]["cell"], next_infos["cell"]) if done.any() else next_infos["cell"]
        )
        slot = global_step % args.buffer_size
        cells_buffer[slot] = (infos["cell"][0], real_next_cells[0], infos["goal_cell"][0])
        actions_buffer[slot], rewards_buffer[slot], terminated_buffer[slot] = actions[0], rewards[0], terminations[0]
        if done[0]:
            episode = next_infos["final_info"]["episode"]
            recent_success.append(float(terminations[0]))
            writer.add_scalar("charts/episodic_return", episode["r"][0], global_step)
            writer.add_scalar("charts/episodic_length", episode["l"][0], global_step)
            writer.add_scalar("charts/success_rate", np.mean(recent_success), global_step)
        observations, infos = next_observations, next_infos

        # Learn
        if global_step >= args.learning_starts and global_step % args.train_frequency == 0:
            batch = rng.integers(min(global_step + 1, args.buffer_size), size=args.batch_size)
            cells = torch.as_tensor(cells_buffer[batch], device=device)
            actions_t = torch.as_tensor(actions_buffer[batch], device=device)
            with torch.no_grad():
                target_model = target_rep if args.finetune else rep
                next_goal_cells = torch.cat([cells[:, 1], cells[:, 2]])
                next_goal_features, next_goal_z, _, next_goal_codes = features(target_model, next_goal_cells)
                next_codes, goal_codes = (None, None) if next_goal_codes is None else next_goal_codes.chunk(2)
                bonus = intrinsic_bonus(*next_goal_z.chunk(2), next_codes, goal_codes)
                rewards_t = torch.as_tensor(rewards_buffer[batch], device=device) + args.bonus_coef * bonus
                target_q = target_network(*next_goal_features.chunk(2))
                if args.double_dqn:
                    online_features = features(rep, next_goal_cells)[0] if args.finetune else next_goal_features
                    next_actions = q_network(*online_features.chunk(2)).argmax(1, keepdim=True)
                    next_values = target_q.gather(1, next_actions).squeeze(1)
                else:
                    next_values = target_q.max(1).values
                td_target = (
                    rewards_t + args.gamma * (1 - torch.as_tensor(terminated_buffer[batch], device=device)) * next_values
                )
            # State and goal in one call: one pooled codebook update, and the mean of their commitment losses.
            state_goal_features, _, vq_loss, _ = features(rep, torch.cat([cells[:, 0], cells[:, 2]]), update=args.finetune)
            state_features, goal_features = state_goal_features.chunk(2)
            q_values = q_network(state_features, goal_features).gather(1, actions_t.unsqueeze(1)).squeeze(1)
            td_loss = F.smooth_l1_loss(q_values, td_target)
            loss = td_loss + vq_loss  # DGRL: zero unless the codebook is fine-tuned
            q_optimizer.zero_grad()
            loss.backward()
            q_optimizer.step()
            train_steps += 1
            if train_steps % args.target_network_frequency == 0:
                update_target(target_network, q_network)
                if args.finetune:
                    update_target(target_rep, rep)  # the codebook buffers are copied too
            if train_steps % 100 == 0:
                writer.add_scalar("losses/td_loss", td_loss.item(), global_step)
                writer.add_scalar("losses/q_values", q_values.mean().item(), global_step)
                writer.add_scalar("charts/intrinsic_bonus", bonus.mean().item(), global_step)
                writer.add_scalar("charts/epsilon", epsilon, global_step)
                if dgrl:
                    writer.add_scalar("vq/factor_match", bonus.mean().item(), global_step)  # DGRL
                    if args.finetune:
                        writer.add_scalar("vq/commit_loss", vq_loss.item(), global_step)  # DGRL

        # Evaluate greedily on every train goal and every novel goal; log, print progress, checkpoint.
        if (global_step + 1) % args.eval_frequency == 0 or global_step + 1 == args.total_timesteps:
            rep.eval()
            results = {}
            for split, goals in (("train", train_goals), ("novel", novel_goals)):
                reached, steps = evaluate(rep, q_network, embedder, layout, goals, args.max_episode_steps)
                results[split] = (reached, steps)
                writer.add_scalar(f"eval/{split}_success_rate", reached.mean(), global_step)
                writer.add_scalar(f"eval/{split}_mean_steps", steps.mean(), global_step)
                writer.add_scalar(f"eval/{split}_total_steps", steps.sum(), global_step)
            rep.train(args.finetune)
            sps = int((global_step + 1) / (time.time() - dqn_start))
            writer.add_scalar("charts/SPS", sps, global_step)
            elapsed = time.time() - start_time
            remaining = (args.total_timesteps - global_step - 1) / max(sps, 1)
            print(
                f"step {global_step + 1:>7}/{args.total_timesteps}  {report('train', *results['train'], train_goals)}  "
                f"{report('novel', *results['novel'], novel_goals)}  SPS {sps}  {elapsed:.0f}s elapsed, {remaining:.0f}s left"
            )
            if args.save_model:
                save_checkpoint(f"runs/{run_name}/{args.exp_name}.cleanrl_model", rep, q_network, args)

    envs.close()
    writer.close()
    if args.save_model:
        print(f"checkpoint: runs/{run_name}/{args.exp_name}.cleanrl_model")
