"""DGRL on RIS in the vision-based Sawyer push-and-reach task: discretized goal and subgoal embeddings from pixels.

Paper: Islam et al. 2022, "Discrete Factorial Representations as an Abstraction for Goal Conditioned RL", section "Vision
Based Robotic Manipulation", appendix "Robotic Manipulation Task", Algorithm 1 and the code snippet's image branch. The agent
is RIS (Chane-Sane et al., ICML 2021) in its vision variant: a conv encoder maps 84x84 images of states and goals to 16-d
features (random-translate augmentation; trained by the critic's loss); a goal-conditioned actor and twin critics act on
the features; a high-level policy proposes subgoal features halfway to the goal; the actor's loss replaces SAC's entropy
term by a KL divergence to the target actor averaged over imagined subgoals. The encoder is also trained by DRIML's
local-global InfoNCE loss on (s_t, a_t, s_t+1) (Mazoure et al. 2020), as in the paper's snippet. DGRL (`--groups G`)
discretizes the encoder's embeddings with the shared-codebook bottleneck of vq.py and conditions the actor, the critics
and the prior on the discrete goal and subgoal embeddings. `--groups 0` is RIS (with the DRIML loss) from the same file.

The task: multiworld's `SawyerPushAndReachXYEnv` in its "TrainEnvBig" / "TestEnvBig" configurations, rebuilt on the
modern `mujoco` bindings with an MJCF scene generated in code (a table, four low walls around the arena, a puck and an end
effector driven by a mocap body; the original Sawyer arm meshes ship with no installable package, so the arm is left out).
Training resets everywhere in the arena; evaluation on the test configuration, where hand and puck cross the arena.

    MUJOCO_GL=egl python dgrl_ris_sawyer.py --groups 16     # paper setting (G=16, batch 256, one update per step): a GPU job
    MUJOCO_GL=egl python dgrl_ris_sawyer.py --groups 0      # RIS
    MUJOCO_GL=egl python dgrl_ris_sawyer.py --total-timesteps 30000 --batch-size 32 --start-timesteps 2000 \
        --eval-frequency 2000 --eval-episodes 10            # the CPU preset (30 min on a CPU core, 16-19 SPS)
    MUJOCO_GL=egl python dgrl_ris_sawyer.py --total-timesteps 600 --start-timesteps 300 --batch-size 16 \
        --eval-frequency 600 --eval-episodes 2              # 1-minute smoke run

Env frames/s and a picture of state and goal images: benchmark/sawyer_env.py; update times: benchmark/bench_ris_sawyer.py;
the CPU study: benchmark/ris_sawyer.sh. Docs, deviations and results: docs/dgrl_ris_sawyer.md.
"""

import math
import os
import random
import signal
import time
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from typing import ClassVar

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
    exp_name: str = os.path.basename(__file__)[: -len(".py")]
    """the name of this experiment"""
    seed: int = 1
    """seed of the experiment"""
    torch_deterministic: bool = True
    """if toggled, `torch.backends.cudnn.deterministic=True`"""
    cuda: bool = True
    """if toggled, cuda will be enabled when available (batch 256 of images at one update per step needs a GPU)"""
    track: bool = False
    """if toggled, this experiment will be tracked with Weights and Biases"""
    wandb_project_name: str = "dgrl"
    """the wandb's project name"""
    wandb_entity: str | None = None
    """the entity (team) of wandb's project"""
    capture_video: bool = False
    """whether to record the first episode of every 10th evaluation (state | goal images, saved in `videos/`)"""
    save_model: bool = False
    """whether to save a checkpoint (actor, critics, high level, encoder, DRIML heads, codebook) at every evaluation"""
    checkpoint: str | None = None
    """path of a saved checkpoint: evaluate it over --eval-episodes episodes on the test configuration, then exit"""
    threads: int = 1
    """torch CPU threads"""

    # Environment
    num_envs: int = 1
    """environments stepped together; each env step is followed by one update, as in RIS"""

    # Algorithm: RIS from pixels
    total_timesteps: int = 1_000_000
    """total environment steps (the reference gives no Sawyer budget; 1M is this script's choice)"""
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
    """random-translate augmentation: pad by this many pixels (edge replication), crop back at a random offset"""

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
    groups: int = 16
    """G: factors of the 16-d embedding; 0 runs RIS"""
    n_embed: int = 64
    """L: codes in the shared codebook"""
    vq_beta: float = 0.25
    """commitment-loss weight"""
    vq_decay: float = 0.99
    """EMA decay of the codebook"""
    vq_dead_code_steps: int = 0
    """restart a code unused for this many updates at a random current segment (0 = off, as in the paper)"""


# --- Environments -----------------------------------------------------------------------------------------------------

ARENA_LOW, ARENA_HIGH = np.array((-0.2, 0.5)), np.array((0.2, 0.7))  # bounds of the hand's and the puck's centres (xy)
HAND_Z, HAND_RADIUS = 0.06, 0.015  # the end effector moves at this fixed height
PUCK_RADIUS, PUCK_HALF_HEIGHT = 0.04, 0.015
WALL_HALF_THICKNESS, WALL_HALF_HEIGHT = 0.01, 0.02
PUCK_RING = (0.055, 0.075)  # training resets put the puck at this distance from the hand
GOAL_CLEARANCE = PUCK_RADIUS + HAND_RADIUS  # training goals keep the hand and the puck this far apart (0.055)
TEST_BOXES = {  # (low xy, high xy) of the test configuration's uniform draws
    "hand_start": ((0.15, 0.65), (0.20, 0.70)),
    "puck_start": ((-0.15, 0.55), (-0.10, 0.60)),
    "hand_goal": ((-0.20, 0.50), (-0.15, 0.55)),
    "puck_goal": ((0.15, 0.65), (0.20, 0.70)),
}
SUCCESS_DISTANCE = 0.05
EPISODE_STEPS = 100
TIMESTEP, FRAME_SKIP = 0.002, 50  # 0.1 s per env step
CAMERA_HEIGHT = 0.65  # the top camera's height: its 45-degree field of view spans 0.54 m, the arena and its walls


def sawyer_xml() -> str:
    """The scene: a table plane at z = 0, walls whose inner faces stop the puck's centre at the arena's bounds, a puck
    with two slide joints, an end effector with two slide joints welded to a mocap body, and a camera over the arena.

    qpos is (hand x, hand y, puck x, puck y): both bodies sit at the world origin in xy, so a slide joint's position is
    the world coordinate. The puck has no z or tilt freedom (it cannot tip over or fly) and does not touch the table;
    dry friction on its slide joints (`frictionloss`) stands in for table friction, so it stops when no longer pushed.
    The end effector is a vertical capsule whose top is at the hand height and whose shaft reaches down to the puck."""
    root = ET.Element("mujoco", model="sawyer_push_and_reach")
    ET.SubElement(root, "option", timestep=str(TIMESTEP))
    visual = ET.SubElement(root, "visual")
    ET.SubElement(visual, "quality", shadowsize="0")  # no shadows: 3x faster software rendering
    ET.SubElement(visual, "headlight", ambient="0.5 0.5 0.5", diffuse="0.5 0.5 0.5", specular="0 0 0")
    # Contacts and the hand's joint limits much stiffer than the hand's weld: the puck yields to the hand, the walls hold
    # the puck (the default softness let a hand pressing the puck into a wall push its centre 1 cm past the arena), and
    # the limits hold a hand shoved by a puck that is pressed against a wall.
    default = ET.SubElement(root, "default")
    ET.SubElement(default, "geom", solref="0.004 1", solimp="0.99 0.999 0.001")
    ET.SubElement(default, "joint", solreflimit="0.004 1", solimplimit="0.99 0.999 0.001")
    world = ET.SubElement(root, "worldbody")
    (x0, y0), (x1, y1) = ARENA_LOW, ARENA_HIGH
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    inner_x, inner_y = (x1 - x0) / 2 + PUCK_RADIUS, (y1 - y0) / 2 + PUCK_RADIUS  # half-extents inside the walls
    ET.SubElement(world, "geom", name="table", type="plane", pos=f"{cx} {cy} 0", size=f"{inner_x + 0.2} {inner_y + 0.2} 0.01",
                  rgba="0.9 0.88 0.82 1", contype="0", conaffinity="0")  # fmt: skip
    t, h = WALL_HALF_THICKNESS, WALL_HALF_HEIGHT
    walls = {
        "left": (cx - inner_x - t, cy, t, inner_y + 2 * t), "right": (cx + inner_x + t, cy, t, inner_y + 2 * t),
        "near": (cx, cy - inner_y - t, inner_x, t), "far": (cx, cy + inner_y + t, inner_x, t),
    }  # fmt: skip
    for name, (x, y, hx, hy) in walls.items():
        ET.SubElement(world, "geom", name=f"wall_{name}", type="box", pos=f"{x} {y} {h}", size=f"{hx} {hy} {h}",
                      rgba="0.45 0.45 0.5 1")  # fmt: skip
    ET.SubElement(world, "camera", name="top", pos=f"{cx} {cy} {CAMERA_HEIGHT}", xyaxes="1 0 0 0 1 0")
    ET.SubElement(world, "body", name="hand_target", mocap="true", pos=f"{cx} {cy} {HAND_Z}")
    hand = ET.SubElement(world, "body", name="hand", pos=f"0 0 {HAND_Z}")
    for axis, name in enumerate(("hand_x", "hand_y")):
        ET.SubElement(hand, "joint", name=name, type="slide", axis=("1 0 0", "0 1 0")[axis], limited="true",
                      range=f"{ARENA_LOW[axis]} {ARENA_HIGH[axis]}")  # fmt: skip
    ET.SubElement(hand, "geom", name="hand", type="capsule", fromto=f"0 0 {PUCK_HALF_HEIGHT - HAND_Z} 0 0 0",
                  size=str(HAND_RADIUS), mass="0.1", rgba="0.85 0.1 0.1 1")  # fmt: skip
    puck = ET.SubElement(world, "body", name="puck", pos=f"0 0 {PUCK_HALF_HEIGHT}")
    for axis, name in enumerate(("puck_x", "puck_y")):
        ET.SubElement(puck, "joint", name=name, type="slide", axis=("1 0 0", "0 1 0")[axis], frictionloss="0.3",
                      damping="0.5")  # fmt: skip
    ET.SubElement(puck, "geom", name="puck", type="cylinder", size=f"{PUCK_RADIUS} {PUCK_HALF_HEIGHT}", mass="0.1",
                  rgba="0.1 0.35 0.9 1")  # fmt: skip
    # relpose is given (identity), so the compiler does not take it from where the two bodies sit in the file
    ET.SubElement(ET.SubElement(root, "equality"), "weld", name="hand_to_target", body1="hand_target", body2="hand",
                  relpose="0 0 0 1 0 0 0", solref="0.02 1")  # fmt: skip
    return ET.tostring(root, encoding="unicode")


class SawyerPushAndReachEnv(gym.Env):
    """multiworld's Sawyer push-and-reach (xy) task on the modern `mujoco` bindings (reference ris.md).

    The Sawyer arm is replaced by its end effector: a capsule of radius 0.015 at the fixed height z = 0.06, on two slide
    joints, welded to a mocap body; as in the original, an action in [-1, 1]^2 moves the mocap target by
    action * action_scale (clipped to the arena) and 50 physics steps of 0.002 s follow, so the hand tracks the target
    and pushes the puck by contact. The puck (radius 0.04, half-height 0.015) slides in x and y inside four walls that
    keep its centre in the arena x in [-0.2, 0.2], y in [0.5, 0.7]; the clipping and two joint limits keep the hand's
    centre there too. Camera: the original one (distance 0.26, look-at (0, 0.88, 0.30), elevation -55, azimuth 270, tuned
    for the Sawyer scene) sees the arena at a slant and, at 84 x 84, cuts off its side walls and corners, so images come
    from a fixed camera `top` straight above the arena's centre that shows all of it (x to the right, y up).

    Observation: Dict(image = the current state rendered at image_size x image_size (uint8 RGB), state = (hand xy, puck
    xy), goal_image = the goal configuration rendered the same way (once per reset), goal = the 4-d goal state).
    Reward -1 per step (RIS); terminated on success, max(||hand - hand goal||, ||puck - puck goal||) < 0.05; truncated
    after 100 steps. `info` holds `success`, `hand_distance` and `puck_distance`.
    Training resets (`test=False`): the hand uniform in the arena, the puck at U(0.055, 0.075) from it in a uniform
    direction (redrawn until its centre lies in the arena); the goal's hand and puck uniform in the arena, redrawn until
    they are more than 0.055 (puck radius + hand radius) apart. Test resets draw from the fixed boxes of TEST_BOXES.
    """

    metadata: ClassVar[dict] = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, test: bool = False, image_size: int = 84, action_scale: float = 0.02, render_mode: str | None = None):
        self.test, self.image_size, self.action_scale, self.render_mode = test, image_size, action_scale, render_mode
        self.model = mujoco.MjModel.from_xml_string(sawyer_xml())
        self.data = mujoco.MjData(self.model)
        image = gym.spaces.Box(0, 255, (image_size, image_size, 3), np.uint8)
        walls = np.tile(ARENA_LOW - PUCK_RADIUS, 2), np.tile(ARENA_HIGH + PUCK_RADIUS, 2)  # no centre gets past them
        state = gym.spaces.Box(walls[0].astype(np.float32), walls[1].astype(np.float32), (4,), np.float32)
        self.observation_space = gym.spaces.Dict(image=image, state=state, goal_image=image, goal=state)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
        self._saved = np.empty(mujoco.mj_stateSize(self.model, mujoco.mjtState.mjSTATE_INTEGRATION))
        self.goal = np.zeros(4, np.float32)
        self.goal_image = np.zeros((image_size, image_size, 3), np.uint8)
        self.steps = 0
        self._renderer = None

    def set_state4(self, state4: np.ndarray) -> None:
        """Put the hand and the puck at rest at (hand xy, puck xy), with the mocap target on the hand."""
        self.data.qpos[:4] = state4
        self.data.qvel[:] = 0.0
        self.data.mocap_pos[0] = (state4[0], state4[1], HAND_Z)
        mujoco.mj_forward(self.model, self.data)

    def render_state(self, state4: np.ndarray) -> np.ndarray:
        """An image of the configuration state4; the simulation state (qpos, qvel, act, mocap, time, warm start) is
        restored exactly afterwards."""
        spec = mujoco.mjtState.mjSTATE_INTEGRATION
        mujoco.mj_getState(self.model, self.data, self._saved, spec)
        self.set_state4(state4)
        image = self.render()
        mujoco.mj_setState(self.model, self.data, self._saved, spec)
        mujoco.mj_forward(self.model, self.data)
        return image

    def _uniform(self, box: tuple) -> np.ndarray:
        return self.np_random.uniform(box[0], box[1])

    def _training_start(self) -> np.ndarray:
        hand = self._uniform((ARENA_LOW, ARENA_HIGH))
        while True:
            angle, radius = self.np_random.uniform(0.0, 2 * np.pi), self.np_random.uniform(*PUCK_RING)
            puck = hand + radius * np.array((np.cos(angle), np.sin(angle)))
            if np.all(puck >= ARENA_LOW) and np.all(puck <= ARENA_HIGH):
                return np.concatenate((hand, puck))

    def _training_goal(self) -> np.ndarray:
        while True:
            hand, puck = self._uniform((ARENA_LOW, ARENA_HIGH)), self._uniform((ARENA_LOW, ARENA_HIGH))
            if np.linalg.norm(hand - puck) > GOAL_CLEARANCE:
                return np.concatenate((hand, puck))

    def _info(self, state: np.ndarray) -> dict:
        hand_distance = float(np.linalg.norm(state[:2] - self.goal[:2]))
        puck_distance = float(np.linalg.norm(state[2:] - self.goal[2:]))
        success = max(hand_distance, puck_distance) < SUCCESS_DISTANCE
        return {"success": success, "hand_distance": hand_distance, "puck_distance": puck_distance}

    def _observe(self) -> dict:
        state = self.data.qpos[:4].astype(np.float32)
        return {"image": self.render(), "state": state, "goal_image": self.goal_image.copy(), "goal": self.goal.copy()}

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        mujoco.mj_resetData(self.model, self.data)
        if self.test:
            box = TEST_BOXES
            start = np.concatenate((self._uniform(box["hand_start"]), self._uniform(box["puck_start"])))
            goal = np.concatenate((self._uniform(box["hand_goal"]), self._uniform(box["puck_goal"])))
        else:
            start, goal = self._training_start(), self._training_goal()
        self.goal = goal.astype(np.float32)
        self.set_state4(start)
        self.goal_image = self.render_state(self.goal)
        self.steps = 0
        observation = self._observe()
        return observation, self._info(observation["state"])

    def step(self, action):
        delta = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0) * self.action_scale
        self.data.mocap_pos[0, :2] = np.clip(self.data.mocap_pos[0, :2] + delta, ARENA_LOW, ARENA_HIGH)
        mujoco.mj_step(self.model, self.data, nstep=FRAME_SKIP)
        self.steps += 1
        observation = self._observe()
        info = self._info(observation["state"])
        return observation, -1.0, info["success"], self.steps >= EPISODE_STEPS, info

    def render(self) -> np.ndarray:
        """The current state as an image_size x image_size RGB array."""
        if self._renderer is None:
            try:
                self._renderer = mujoco.Renderer(self.model, self.image_size, self.image_size)
            except mujoco.FatalError as error:
                raise RuntimeError("off-screen rendering failed: on a machine without a display set MUJOCO_GL=egl") from error
            self._renderer.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0
        self._renderer.update_scene(self.data, camera="top")
        return self._renderer.render()

    def close(self):
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


def reached(states: np.ndarray, goals: np.ndarray) -> np.ndarray:
    """The success test on (..., 4) arrays of (hand xy, puck xy): max(hand distance, puck distance) < 0.05."""
    hand = np.linalg.norm(states[..., :2] - goals[..., :2], axis=-1)
    puck = np.linalg.norm(states[..., 2:] - goals[..., 2:], axis=-1)
    return np.maximum(hand, puck) < SUCCESS_DISTANCE


def make_env(seed: int, test: bool):
    def thunk():
        env = gym.wrappers.RecordEpisodeStatistics(SawyerPushAndReachEnv(test=test))
        env.action_space.seed(seed)
        return env

    return thunk


def make_vector_env(n: int, seed: int, test: bool) -> gym.vector.SyncVectorEnv:
    thunks = [make_env(seed + i, test) for i in range(n)]
    return gym.vector.SyncVectorEnv(thunks, autoreset_mode=gym.vector.AutoresetMode.SAME_STEP)


# --- Networks ---------------------------------------------------------------------------------------------------------

LOG_STD_MIN, LOG_STD_MAX = -20.0, 2.0


def mlp(in_dim: int, hidden_dim: int, out_dim: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Linear(in_dim, hidden_dim), nn.ReLU(), nn.Linear(hidden_dim, hidden_dim), nn.ReLU(), nn.Linear(hidden_dim, out_dim)
    )


class Actor(nn.Module):
    """pi(a | z_s, z_g): a Gaussian over pre-tanh actions; the action is tanh(u)."""

    def __init__(self, feature_dim: int, action_dim: int, hidden_dim: int):
        super().__init__()
        self.net = mlp(2 * feature_dim, hidden_dim, 2 * action_dim)

    def forward(self, states: torch.Tensor, goal_inputs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        mean, log_std = self.net(torch.cat((states, goal_inputs), -1)).chunk(2, -1)
        return mean, log_std.clamp(LOG_STD_MIN, LOG_STD_MAX).exp()

    def sample(self, states: torch.Tensor, goal_inputs: torch.Tensor) -> torch.Tensor:
        mean, std = self(states, goal_inputs)
        return torch.tanh(mean + std * torch.randn_like(mean))


class TwinCritic(nn.Module):
    """Two Q-networks on (z_s, a, z_g); returns Q values of shape (2, batch)."""

    def __init__(self, feature_dim: int, action_dim: int, hidden_dim: int):
        super().__init__()
        self.q1 = mlp(2 * feature_dim + action_dim, hidden_dim, 1)
        self.q2 = mlp(2 * feature_dim + action_dim, hidden_dim, 1)

    def forward(self, states: torch.Tensor, actions: torch.Tensor, goal_inputs: torch.Tensor) -> torch.Tensor:
        inputs = torch.cat((states, actions, goal_inputs), -1)
        return torch.stack((self.q1(inputs).squeeze(-1), self.q2(inputs).squeeze(-1)))


class HighLevelPolicy(nn.Module):
    """pi_H(z_sg | z_s, z_g): a Laplace distribution over subgoal features, on the (continuous) state and goal features."""

    def __init__(self, feature_dim: int, hidden_dim: int):
        super().__init__()
        self.net = mlp(2 * feature_dim, hidden_dim, 2 * feature_dim)

    def forward(self, states: torch.Tensor, goals: torch.Tensor) -> torch.distributions.Laplace:
        loc, log_scale = self.net(torch.cat((states, goals), -1)).chunk(2, -1)
        return torch.distributions.Laplace(loc, log_scale.clamp(LOG_STD_MIN, LOG_STD_MAX).exp(), validate_args=False)


def orthogonal_init(module: nn.Module) -> None:
    """Delta-orthogonal convolutions (an orthogonal matrix at the kernel's centre, zeros elsewhere, ReLU gain), orthogonal
    linear layers, zero biases."""
    if isinstance(module, nn.Conv2d):
        nn.init.zeros_(module.weight)
        middle = module.kernel_size[0] // 2
        nn.init.orthogonal_(module.weight.data[:, :, middle, middle], nn.init.calculate_gain("relu"))
        nn.init.zeros_(module.bias)
    elif isinstance(module, nn.Linear):
        nn.init.orthogonal_(module.weight)
        nn.init.zeros_(module.bias)


class ImageEncoder(nn.Module):
    """RIS's image encoder: 3 x 84 x 84 in [0, 1] -> four Conv2d(., 32, 3) with strides 2, 2, 2, 1 and a ReLU after each
    -> the 32 x 7 x 7 map -> Linear(1568, feature_dim). The conv map is exposed for the DRIML loss."""

    channels = 32

    def __init__(self, feature_dim: int, image_size: int = 84):
        super().__init__()
        layers, in_channels, side = [], 3, image_size
        for stride in (2, 2, 2, 1):
            layers += [nn.Conv2d(in_channels, self.channels, 3, stride), nn.ReLU(inplace=True)]
            in_channels, side = self.channels, (side - 3) // stride + 1
        self.convs = nn.Sequential(*layers)
        self.linear = nn.Linear(self.channels * side * side, feature_dim)
        self.apply(orthogonal_init)

    def conv_map(self, images: torch.Tensor) -> torch.Tensor:
        return self.convs(images)

    def head(self, conv_map: torch.Tensor) -> torch.Tensor:
        return self.linear(conv_map.flatten(1))

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.head(self.convs(images))


class DrimlHeads(nn.Module):
    """The DRIML loss's projections to a common size: local (one position of s_t's conv map, with a_t) and global (the
    features of s_t+1)."""

    def __init__(self, channels: int, action_dim: int, feature_dim: int, dim: int):
        super().__init__()
        self.local = nn.Sequential(nn.Linear(channels + action_dim, dim), nn.ReLU(), nn.Linear(dim, dim))
        self.globl = nn.Sequential(nn.Linear(feature_dim, dim), nn.ReLU(), nn.Linear(dim, dim))


def goal_input(vq: VectorQuantizerEMA | None, features: torch.Tensor) -> torch.Tensor:
    """What the actor and critics see of a goal or subgoal: its features (RIS) or their discrete embedding (DGRL), with the
    codebook untouched."""
    if vq is None:
        return features
    return vq(features, update=False)[0]  # DGRL


# --- Augmentation and replay ------------------------------------------------------------------------------------------


def image_batch(images: np.ndarray | torch.Tensor, device) -> torch.Tensor:
    """(N, H, W, 3) uint8 -> (N, 3, H, W) float in [0, 1], a channels-last view (the faster layout for CPU convolutions)."""
    return torch.as_tensor(images, device=device).permute(0, 3, 1, 2).float().div_(255.0)


def translate(images: torch.Tensor, shifts: torch.Tensor) -> torch.Tensor:
    """Move the content of each (N, H, W, 3) uint8 image by its (rows, columns) offset in `shifts` (N, 2), filling the
    uncovered border with the edge pixels: padding with edge replication and cropping back, in one gather. Returns (N, 3,
    H, W) floats in [0, 1] like image_batch."""
    n, height, width, _ = images.shape
    rows = (torch.arange(height, device=images.device) - shifts[:, :1]).clamp(0, height - 1)  # output row i reads i - dy
    columns = (torch.arange(width, device=images.device) - shifts[:, 1:]).clamp(0, width - 1)
    samples = torch.arange(n, device=images.device)[:, None, None]
    return image_batch(images[samples, rows[:, :, None], columns[:, None, :]], images.device)


def random_translate(images: torch.Tensor, pad: int) -> torch.Tensor:
    """RIS's augmentation: each image shifted by its own offset, uniform in [-pad, pad]^2 (pad, then a random crop)."""
    return translate(images, torch.randint(-pad, pad + 1, (len(images), 2), device=images.device))


class ImageEpisodeReplay:
    """Whole episodes of uint8 images and 4-d states in one ring of rows, in host memory.

    An episode of L transitions takes L + 2 consecutive rows: its observations o_0..o_L (image and state), then its goal
    (image and state). Transition t lives in the row of o_t, which also holds a_t, the row of the episode's last transition
    and the row of its goal; s_t+1 is the next row. So every image is stored once: 21 KB a row, 2.1 GB for 1e5 rows.
    Episodes are written contiguously (a write that would cross the end starts again at row 0), goal last, so whatever
    survives of an overwritten episode is a suffix of it with its goal and its stored rows intact.
    """

    def __init__(self, capacity: int, image_shape: tuple[int, ...], action_dim: int):
        self.capacity = capacity
        self.images = np.zeros((capacity, *image_shape), np.uint8)
        self.states = np.zeros((capacity, 4), np.float32)
        self.actions = np.zeros((capacity, action_dim), np.float32)
        self.episode_end = np.zeros(capacity, np.int64)  # row of the episode's last transition
        self.goal_row = np.zeros(capacity, np.int64)
        self.is_transition = np.zeros(capacity, bool)  # False for the o_L and goal rows
        self.position, self.size = 0, 0

    def add_episode(
        self, images: np.ndarray, states: np.ndarray, actions: np.ndarray, goal_image: np.ndarray, goal_state: np.ndarray
    ) -> None:
        """images, states: o_0..o_L (L + 1 rows); actions: a_0..a_L-1."""
        length = len(actions)
        if self.position + length + 2 > self.capacity:
            self.position = 0
        start, goal = self.position, self.position + length + 1
        self.images[start:goal], self.images[goal] = images, goal_image
        self.states[start:goal], self.states[goal] = states, goal_state
        self.actions[start : start + length] = actions
        self.is_transition[start : goal + 1] = False
        self.is_transition[start : start + length] = True
        self.episode_end[start : goal + 1] = start + length - 1
        self.goal_row[start : goal + 1] = goal
        self.position = goal + 1
        self.size = max(self.size, self.position)

    def transitions(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """Rows of n transitions, uniform over the stored ones."""
        rows = rng.integers(self.size, size=n)
        while not (valid := self.is_transition[rows]).all():
            rows[~valid] = rng.integers(self.size, size=int((~valid).sum()))
        return rows

    def sample(self, batch_size: int, goal_frac: float, random_frac: float, rng: np.random.Generator) -> dict:
        """A HER batch: images of (s, s', g, s_g) stacked in one (4B, H, W, 3) uint8 array, actions, and the 4-d states of
        s, s' and g; g relabelled, rewards and done recomputed.

        The first `goal_frac` of the batch keeps the rollout goal, the next `random_frac` gets a random replay state, the
        rest a future state of the same episode, uniform over s'_t..s'_end. Rewards are -1; done marks the success test
        between s' and g. s_g: random replay states, the high level's subgoal candidates.
        """
        index = self.transitions(batch_size, rng)
        n_keep, n_random = round(goal_frac * batch_size), round(random_frac * batch_size)
        future = index[n_keep + n_random :]
        offsets = (rng.random(len(future)) * (self.episode_end[future] - future + 1)).astype(np.int64)
        goal_rows = np.concatenate((self.goal_row[index[:n_keep]], self.transitions(n_random, rng), future + 1 + offsets))
        subgoal_rows = self.transitions(batch_size, rng)
        next_states, goal_states = self.states[index + 1], self.states[goal_rows]
        rows = np.concatenate((index, index + 1, goal_rows, subgoal_rows))
        return dict(
            images=self.images[rows], actions=self.actions[index], rewards=-np.ones(batch_size, np.float32),
            done=reached(next_states, goal_states).astype(np.float32), states=self.states[index], next_states=next_states,
            goal_states=goal_states,
        )  # fmt: skip


# --- Losses -----------------------------------------------------------------------------------------------------------


def local_global_infonce(local: torch.Tensor, global_: torch.Tensor) -> torch.Tensor:
    """InfoNCE between each local vector of sample b (local: (B, P, D)) and the global vectors of the batch (global_: (B,
    D)): scores are dot products; (b, b) is the positive pair, the B - 1 other samples the negatives; the cross-entropy
    is averaged over the B samples and P positions. log B when the features say nothing; 0 at best."""
    batch, positions, _ = local.shape
    scores = torch.einsum("bpd,kd->bpk", local, global_).reshape(batch * positions, batch)
    return F.cross_entropy(scores, torch.arange(batch, device=local.device).repeat_interleave(positions))


def driml_loss(heads: DrimlHeads, conv_map: torch.Tensor, actions: torch.Tensor, next_features: torch.Tensor) -> torch.Tensor:
    """DRIML's local-global loss: each position of s_t's conv map (B, C, H, W), with a_t, must pick out the features of
    its own s_t+1 among the batch's."""
    local = conv_map.flatten(2).transpose(1, 2)  # (B, H * W, C)
    local = torch.cat((local, actions.unsqueeze(1).expand(-1, local.shape[1], -1)), -1)
    return local_global_infonce(heads.local(local), heads.globl(next_features))


def advantage_weights(distance_proposed: torch.Tensor, distance_candidates: torch.Tensor, temperature: float) -> torch.Tensor:
    """softmax over the batch of (D(proposed subgoal) - D(candidate)) / lambda: candidates better than the proposal
    (a smaller cost to go through them) get the larger weights."""
    return F.softmax((distance_proposed - distance_candidates) / temperature, dim=0)


def subgoal_cost(values_to_subgoal: torch.Tensor, values_from_subgoal: torch.Tensor) -> torch.Tensor:
    """D(s_g) = max(|clip(V(s, s_g), -100, 0)|, |clip(V(s_g, g), -100, 0)|): the longer of the two halves."""
    return torch.maximum(values_to_subgoal.clamp(-100.0, 0.0).abs(), values_from_subgoal.clamp(-100.0, 0.0).abs())


def prior_kl(
    actions_pre_tanh: torch.Tensor,
    mean: torch.Tensor,
    std: torch.Tensor,
    prior_mean: torch.Tensor,
    prior_std: torch.Tensor,
    epsilon: float,
) -> torch.Tensor:
    """Single-sample KL(pi || prior) at u: log N(u; mu, sigma) - log(mean_k N(u; mu_k, sigma_k) + epsilon).

    u: (B, A); mean, std: (B, A); prior_mean, prior_std: (K, B, A) from the target actor at K imagined subgoals. The
    log of the mixture density plus epsilon is computed with logsumexp, so a tiny density does not underflow to 0.
    """
    log_policy = torch.distributions.Normal(mean, std, validate_args=False).log_prob(actions_pre_tanh).sum(-1)
    log_prior_k = (
        torch.distributions.Normal(prior_mean, prior_std, validate_args=False).log_prob(actions_pre_tanh.unsqueeze(0)).sum(-1)
    )
    n_subgoals = log_prior_k.shape[0]
    log_terms = torch.cat((log_prior_k - math.log(n_subgoals), torch.full_like(log_prior_k[:1], math.log(epsilon))))
    return log_policy - torch.logsumexp(log_terms, dim=0)


def make_agent(args: Args, image_size: int, action_dim: int, device) -> tuple[dict, dict]:
    """The networks (with the actor and critic targets and, under DGRL, the codebook) and their optimizers. The critic's
    optimizer also trains the encoder (at --encoder-lr) and the DRIML heads (at --q-lr: at --encoder-lr the DRIML loss
    stayed at log(batch) for the first thousand updates); the codebook moves by EMA, in no optimizer."""
    actor = Actor(args.feature_dim, action_dim, args.hidden_dim).to(device)
    critic = TwinCritic(args.feature_dim, action_dim, args.hidden_dim).to(device)
    encoder = ImageEncoder(args.feature_dim, image_size).to(device)
    heads = DrimlHeads(ImageEncoder.channels, action_dim, args.feature_dim, args.driml_dim).to(device)
    nets = dict(
        actor=actor, critic=critic, high=HighLevelPolicy(args.feature_dim, args.hidden_dim).to(device), encoder=encoder,
        driml=heads, vq=None, actor_target=make_target(actor), critic_target=make_target(critic),
    )  # fmt: skip
    if args.groups > 0:  # DGRL
        nets["vq"] = VectorQuantizerEMA(  # DGRL
            args.feature_dim, args.n_embed, args.groups, args.vq_beta, args.vq_decay, dead_code_steps=args.vq_dead_code_steps
        ).to(device)  # DGRL
    fused = device.type in ("cpu", "cuda")
    critic_groups = [
        {"params": [*critic.parameters(), *heads.parameters()], "lr": args.q_lr},
        {"params": encoder.parameters(), "lr": args.encoder_lr},
    ]
    optimizers = {
        "critic": torch.optim.Adam(critic_groups, fused=fused),
        "actor": torch.optim.Adam(actor.parameters(), lr=args.actor_lr, fused=fused),
        "high": torch.optim.Adam(nets["high"].parameters(), lr=args.h_lr, fused=fused),
    }
    return nets, optimizers


def ris_update(nets: dict, optimizers: dict, batch: dict, args: Args) -> dict[str, torch.Tensor]:
    """One RIS update from pixels (encoder + critic with the DRIML loss, high level, actor, targets) with DGRL's bottleneck;
    returns detached metrics."""
    actor, critic, high, encoder, heads = nets["actor"], nets["critic"], nets["high"], nets["encoder"], nets["driml"]
    actor_target, critic_target, vq = nets["actor_target"], nets["critic_target"], nets["vq"]
    device = next(critic.parameters()).device
    actions = torch.as_tensor(batch["actions"], device=device)
    rewards, done = torch.as_tensor(batch["rewards"], device=device), torch.as_tensor(batch["done"], device=device)
    batch_size = len(actions)
    metrics = {}

    # Features of the augmented s, s', g, s_g: only s passes through the encoder with gradient (RIS); the target critic
    # and the DRIML loss's global side see the online encoder's features of s' (no target encoder, as in RIS).
    images = random_translate(torch.as_tensor(batch["images"], device=device), args.image_pad)
    conv_map = encoder.conv_map(images[:batch_size])
    state_z = encoder.head(conv_map)
    with torch.no_grad():
        next_z, goal_z, subgoal_z = encoder(images[batch_size:]).chunk(3)
    driml = driml_loss(heads, conv_map, actions, next_z)
    representation_loss = args.driml_coef * driml
    if vq is not None:  # DGRL
        z_q, vq_loss, codes = vq(torch.cat((state_z, next_z, goal_z, subgoal_z)), update=True)  # DGRL: one EMA step, four
        goal_in = z_q[2 * batch_size : 3 * batch_size].detach()  # DGRL: the nets see the discrete goal embedding
        representation_loss = representation_loss + vq_loss  # DGRL: the mean of the four commitment losses
        metrics.update(vq_loss=vq_loss, codes=codes)  # DGRL
    else:
        goal_in = goal_z

    # Critic (policy evaluation); its loss also trains the encoder, the DRIML heads (and, under DGRL, commits to codes).
    with torch.no_grad():
        next_actions = actor.sample(next_z, goal_in)
        next_q = critic_target(next_z, next_actions, goal_in).min(0).values
        target_q = rewards + (1.0 - done) * args.gamma * next_q
    q_values = critic(state_z, actions, goal_in)
    critic_loss = 0.5 * (q_values - target_q).pow(2).sum(0).mean()
    optimizers["critic"].zero_grad(set_to_none=True)
    (critic_loss + representation_loss).backward()
    optimizers["critic"].step()
    state_z = state_z.detach()

    # High level: advantage-weighted regression onto the features of random replay states.
    subgoal_distribution = high(state_z, goal_z)
    proposed = subgoal_distribution.loc.detach()
    with torch.no_grad():
        value_states = torch.cat((state_z, subgoal_z, state_z, proposed))
        value_goals = goal_input(vq, torch.cat((subgoal_z, goal_z, proposed, goal_z)))  # DGRL: V(x, y) sees y discretized
        value_actions = torch.tanh(actor(value_states, value_goals)[0])
        values = critic(value_states, value_actions, value_goals).min(0).values.view(4, batch_size)
        weights = advantage_weights(subgoal_cost(values[2], values[3]), subgoal_cost(values[0], values[1]), args.h_lambda)
    high_loss = -(weights * subgoal_distribution.log_prob(subgoal_z).sum(-1)).mean()
    optimizers["high"].zero_grad(set_to_none=True)
    high_loss.backward()
    optimizers["high"].step()

    # Actor: maximise Q with a KL penalty towards the target actor averaged over imagined subgoals.
    with torch.no_grad():
        imagined = goal_input(vq, high(state_z, goal_z).sample((args.n_subgoals,)))  # DGRL: the prior sees discrete subgoals
        prior_mean, prior_std = actor_target(state_z.expand(args.n_subgoals, -1, -1), imagined)
    mean, std = actor(state_z, goal_in)
    actions_pre_tanh = mean + std * torch.randn_like(mean)
    kl = prior_kl(actions_pre_tanh, mean, std, prior_mean, prior_std, args.prior_epsilon)
    actor_q = critic(state_z, torch.tanh(actions_pre_tanh), goal_in).min(0).values
    actor_loss = (args.alpha * kl - actor_q).mean()
    optimizers["actor"].zero_grad(set_to_none=True)
    actor_loss.backward()
    optimizers["actor"].step()

    update_target(critic_target, critic, args.tau)
    update_target(actor_target, actor, args.tau)
    metrics.update(
        critic_loss=critic_loss, driml_loss=driml, high_loss=high_loss, actor_loss=actor_loss, kl=kl.mean(),
        q_values=q_values.mean(), high_weight_max=weights.max(),
    )  # fmt: skip
    return {name: value.detach() for name, value in metrics.items()}


# --- Acting, evaluation, checkpoints, flags ---------------------------------------------------------------------------


@torch.no_grad()
def act(actor: Actor, encoder: ImageEncoder, vq, observations: dict, device, deterministic: bool) -> np.ndarray:
    """Actions for a batch of observations: the un-augmented state and goal images through the encoder."""
    n = len(observations["image"])
    features = encoder(image_batch(np.concatenate((observations["image"], observations["goal_image"])), device))
    state_z, goal_in = features[:n], goal_input(vq, features[n:])  # DGRL: the goal quantized, no codebook update
    if deterministic:
        return torch.tanh(actor(state_z, goal_in)[0]).cpu().numpy()
    return actor.sample(state_z, goal_in).cpu().numpy()


def video_frame(image: np.ndarray, goal_image: np.ndarray, scale: int = 3) -> np.ndarray:
    """The state image beside the goal image, upscaled (nearest neighbour)."""
    return np.concatenate((image, goal_image), 1).repeat(scale, 0).repeat(scale, 1)


def evaluate(envs: gym.vector.SyncVectorEnv, actor, encoder, vq, device, deterministic: bool, frames=None) -> dict:
    """One episode per env on the test configuration: success rate, hand-only success rate (the hand within 0.05 of its
    goal at the end), mean final hand and puck distances to their goals."""
    observations, _ = envs.reset()
    finished = np.zeros(envs.num_envs, dtype=bool)
    success, hand, puck = np.zeros(envs.num_envs), np.zeros(envs.num_envs), np.zeros(envs.num_envs)
    while not finished.all():
        if frames is not None and not finished[0]:
            frames.append(video_frame(observations["image"][0], observations["goal_image"][0]))
        actions = act(actor, encoder, vq, observations, device, deterministic)
        observations, _, terminations, truncations, infos = envs.step(actions)
        ended = (terminations | truncations) & ~finished
        for env in np.flatnonzero(ended):
            hand[env], puck[env] = infos["final_info"]["hand_distance"][env], infos["final_info"]["puck_distance"][env]
            success[env] = terminations[env]
        finished |= ended
    return {
        "success_rate": success.mean(), "hand_success_rate": (hand < SUCCESS_DISTANCE).mean(),
        "final_hand_distance": hand.mean(), "final_puck_distance": puck.mean(),
    }  # fmt: skip


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
    if args.feature_dim >= 1 and (args.groups < 0 or (args.groups and args.feature_dim % args.groups)):
        divisors = [g for g in range(1, args.feature_dim + 1) if args.feature_dim % g == 0]
        errors.append(
            f"--groups must be 0 (RIS) or divide --feature-dim {args.feature_dim}: one of {divisors}; got {args.groups}"
        )
    for flag in (
        "total_timesteps", "num_envs", "buffer_size", "batch_size", "hidden_dim", "n_subgoals", "eval_frequency",
        "eval_episodes", "n_embed", "feature_dim", "driml_dim", "threads",
    ):  # fmt: skip
        if getattr(args, flag) < 1:
            errors.append(f"--{flag.replace('_', '-')} must be >= 1; got {getattr(args, flag)}")
    for flag in ("start_timesteps", "vq_dead_code_steps", "image_pad", "driml_coef", "vq_beta"):
        if getattr(args, flag) < 0:
            errors.append(f"--{flag.replace('_', '-')} must be >= 0; got {getattr(args, flag)}")
    for flag in ("alpha", "h_lambda", "prior_epsilon", "tau", "q_lr", "actor_lr", "h_lr", "encoder_lr"):
        if getattr(args, flag) <= 0:
            errors.append(f"--{flag.replace('_', '-')} must be > 0; got {getattr(args, flag)}")
    if not 0 <= args.gamma <= 1:
        errors.append(f"--gamma must be in [0, 1]; got {args.gamma}")
    if not 0 <= args.vq_decay < 1:
        errors.append(f"--vq-decay must be in [0, 1); got {args.vq_decay}")
    if not (0 <= args.her_goal_frac and 0 <= args.her_random_frac and args.her_goal_frac + args.her_random_frac <= 1):
        errors.append(
            f"--her-goal-frac ({args.her_goal_frac}) and --her-random-frac ({args.her_random_frac}) must be >= 0 with a "
            "sum <= 1 (the rest are future goals)"
        )
    if args.buffer_size < args.batch_size:
        errors.append(f"--buffer-size ({args.buffer_size}) must be >= --batch-size ({args.batch_size})")
    if args.buffer_size < EPISODE_STEPS + 2:  # the replay writes whole episodes, with their last observation and goal
        errors.append(f"--buffer-size ({args.buffer_size}) must hold one whole episode: >= {EPISODE_STEPS + 2} rows")
    if args.checkpoint is not None and not os.path.isfile(args.checkpoint):
        errors.append(f"--checkpoint {args.checkpoint}: no such file")
    if errors:
        raise SystemExit("dgrl_ris_sawyer.py: invalid arguments:\n  " + "\n  ".join(errors))


if __name__ == "__main__":
    args = tyro.cli(Args)
    validate(args)
    dgrl = args.groups > 0
    run_name = f"SawyerPushAndReach__G{args.groups}__{args.exp_name}__{args.seed}__{int(time.time())}"

    random.seed(args.seed)
    torch.manual_seed(args.seed)
    torch.backends.cudnn.deterministic = args.torch_deterministic
    torch.set_num_threads(args.threads)
    device = torch.device("cuda" if torch.cuda.is_available() and args.cuda else "cpu")
    rng = np.random.default_rng(args.seed)  # replay sampling

    envs = make_vector_env(args.num_envs, args.seed, test=False)
    eval_envs = make_vector_env(args.eval_episodes, args.seed + 10_000, test=True)
    eval_envs.reset(seed=args.seed + 10_000)  # one evaluation stream per run, continued across evaluations
    image_shape = envs.single_observation_space["image"].shape
    action_dim = envs.single_action_space.shape[0]

    nets, optimizers = make_agent(args, image_shape[0], action_dim, device)
    actor, encoder, vq = nets["actor"], nets["encoder"], nets["vq"]
    modules = {name: nets[name] for name in ("actor", "critic", "high", "encoder", "driml", "vq")}

    if args.checkpoint is not None:
        saved = torch.load(args.checkpoint, map_location=device)
        architecture = ("groups", "n_embed", "feature_dim", "hidden_dim", "driml_dim")
        differ = [
            f"--{key.replace('_', '-')} {saved['args'][key]}" for key in architecture if saved["args"][key] != vars(args)[key]
        ]
        if differ:
            raise SystemExit(f"--checkpoint {args.checkpoint} was saved with other settings: pass {' '.join(differ)}")
        for name, module in modules.items():
            if module is not None:
                module.load_state_dict(saved[name])
        result = evaluate(eval_envs, actor, encoder, vq, device, args.eval_deterministic)
        print(
            f"{args.eval_episodes} test episodes: success {result['success_rate']:.0%}, hand success "
            f"{result['hand_success_rate']:.0%}, final hand distance {result['final_hand_distance']:.3f}, "
            f"final puck distance {result['final_puck_distance']:.3f}"
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
    print(f"{run_name}: {image_shape} images, {args.feature_dim}-d features, {args.total_timesteps} steps, device {device}")
    if device.type == "cpu" and args.batch_size >= 128:
        print(f"note: --batch-size {args.batch_size} takes 0.5 to 1 s per update on a CPU; see the docstring's CPU preset")

    replay = ImageEpisodeReplay(args.buffer_size, image_shape, action_dim)
    n_envs = args.num_envs
    episode = {key: [[] for _ in range(n_envs)] for key in ("images", "states", "actions")}
    stop = []  # Ctrl-C or SIGTERM ends the run after the current step, with the checkpoint saved and the logs flushed

    def request_stop(number, frame):
        stop.append(number)
        signal.signal(number, signal.SIG_DFL)  # a second Ctrl-C or SIGTERM stops at once

    for signal_number in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signal_number, request_stop)

    observations, _ = envs.reset(seed=args.seed)
    start_time, step, updates, evaluations, next_eval, next_log = time.time(), 0, 0, 0, args.eval_frequency, 1
    last_eval_step, last_eval_time = 0, 0.0  # for the time left: the rate since the last evaluation
    last_print = start_time  # a heartbeat line at least every 60 s, so that a slow run never looks hung
    recent_success, metrics = [], {}
    result = dict.fromkeys(("success_rate", "hand_success_rate", "final_hand_distance", "final_puck_distance"), float("nan"))
    while step < args.total_timesteps and not stop:
        if step < args.start_timesteps:
            actions = envs.action_space.sample()
        else:
            actions = act(actor, encoder, vq, observations, device, deterministic=False)
        next_observations, _, terminations, truncations, infos = envs.step(actions)
        step += n_envs

        # Stage each env's transitions; a finished episode goes to the replay whole, with its true last observation
        # (final_obs) and its goal.
        for env in range(n_envs):
            episode["images"][env].append(observations["image"][env])
            episode["states"][env].append(observations["state"][env])
            episode["actions"][env].append(actions[env])
            if terminations[env] or truncations[env]:
                last, final_info = infos["final_obs"][env], infos["final_info"]
                replay.add_episode(
                    np.stack([*episode["images"][env], last["image"]]), np.stack([*episode["states"][env], last["state"]]),
                    np.stack(episode["actions"][env]), observations["goal_image"][env], observations["goal"][env],
                )  # fmt: skip
                for key in episode:
                    episode[key][env] = []
                recent_success.append(float(terminations[env]))
                writer.add_scalar("charts/episodic_return", final_info["episode"]["r"][env], step)
                writer.add_scalar("charts/episodic_length", final_info["episode"]["l"][env], step)
                writer.add_scalar("charts/success_rate", float(terminations[env]), step)
                writer.add_scalar("charts/hand_distance", final_info["hand_distance"][env], step)
                writer.add_scalar("charts/puck_distance", final_info["puck_distance"][env], step)
        observations = next_observations

        # Train: one update per environment step once the random phase is over.
        if step >= max(args.start_timesteps, args.batch_size) and replay.size >= args.batch_size:
            for _ in range(n_envs):
                batch = replay.sample(args.batch_size, args.her_goal_frac, args.her_random_frac, rng)
                metrics = ris_update(nets, optimizers, batch, args)
                updates += 1
            if updates >= next_log:  # every 100 updates, from the first
                next_log += 100
                for name in ("critic_loss", "actor_loss", "high_loss", "driml_loss", "kl", "q_values", "high_weight_max"):
                    writer.add_scalar(f"losses/{name}", metrics[name].item(), step)
                if dgrl:  # DGRL
                    writer.add_scalar("vq/commit_loss", metrics["vq_loss"].item(), step)  # DGRL
                    writer.add_scalar("vq/perplexity", perplexity(metrics["codes"], args.n_embed).item(), step)  # DGRL
                    writer.add_scalar("vq/active_codes", active_codes(metrics["codes"], args.n_embed).item(), step)  # DGRL

        if time.time() - last_print > 60:
            last_print = time.time()
            print(f"step {step:>8}/{args.total_timesteps}  {updates} updates  SPS {int(step / (last_print - start_time))}")

        # Evaluate on the test configuration, log, print progress, checkpoint.
        if step >= next_eval or step >= args.total_timesteps:
            last_print = time.time()
            next_eval += args.eval_frequency
            video = [] if args.capture_video and evaluations % 10 == 0 else None
            result = evaluate(eval_envs, actor, encoder, vq, device, args.eval_deterministic, video)
            evaluations += 1
            elapsed = time.time() - start_time
            sps = int(step / elapsed)
            # The time left from the rate since the last evaluation: the random phase steps 10x faster than training
            recent_sps = (step - last_eval_step) / max(elapsed - last_eval_time, 1e-9)
            last_eval_step, last_eval_time = step, elapsed
            for name, value in result.items():
                writer.add_scalar(f"eval/{name}", value, step)
            writer.add_scalar("charts/SPS", sps, step)
            train_success = f"{np.mean(recent_success):4.0%}" if recent_success else "   -"  # no episode ended since
            recent_success = []
            print(
                f"step {step:>8}/{args.total_timesteps}  eval success {result['success_rate']:4.0%} hand "
                f"{result['hand_success_rate']:4.0%}  distance hand {result['final_hand_distance']:.3f} puck "
                f"{result['final_puck_distance']:.3f}  train success {train_success}  SPS {sps}  {elapsed:.0f}s elapsed, "
                f"{(args.total_timesteps - step) / max(recent_sps, 1e-9):.0f}s left"
            )
            if video:
                write_video(f"videos/{run_name}/eval_{step}.mp4", video)
            if args.save_model:
                save_checkpoint(f"runs/{run_name}/{args.exp_name}.cleanrl_model", modules, args)

    if args.save_model:
        save_checkpoint(f"runs/{run_name}/{args.exp_name}.cleanrl_model", modules, args)
        print(f"checkpoint: runs/{run_name}/{args.exp_name}.cleanrl_model")
    print(
        f"{'stopped' if stop else 'done'}: {step} steps, {updates} updates, last eval success {result['success_rate']:.0%} "
        f"(hand {result['hand_success_rate']:.0%}), {time.time() - start_time:.0f} s"
    )
    envs.close()
    eval_envs.close()
    writer.close()
