"""DGRL on HRAC in the HIRO Ant suite (AntMaze, AntMazeSparse, AntPush, AntFall, AntGather): discretized subgoals.

Paper: Islam et al. 2022, "Discrete Factorial Representations as an Abstraction for Goal Conditioned RL", section "Ant
Manipulation Control Domains" and appendix "Ant Manipulation tasks". The agent is HRAC (Zhang et al., NeurIPS 2020): a
TD3 manager that proposes a relative xy subgoal every k = 10 steps, a TD3 controller rewarded for reaching it (the
subgoal re-targeted after every step), HIRO's off-policy correction of the manager's stored subgoals, and an adjacency
network over 1 m grid cells, retrained every 50k steps with a contrastive loss, whose k-step reachability constrains the
manager's subgoals through an extra actor loss. DGRL (`--groups G`) passes the manager's output (the subgoal) through an
encoder and the shared-codebook bottleneck of vq.py; the controller's actor and critic see the discrete subgoal
embedding z_q instead of the raw subgoal. `--groups 0` is plain HRAC from the same file.

The environments are the HIRO Ant suite as HRAC uses it (reference hrac-keychest.md): gymnasium's Ant model edited in
code (ctrl +-30, gear 1, timestep 0.02 with RK4, frame_skip 5) inside structures of fixed, sliding and elevated blocks
generated into MJCF at run time; AntGather adds apples, bombs and range sensors.

    python dgrl_hrac.py --env-id AntPush --groups 16      # DGRL G=16 on AntPush, the paper's 5M steps (a GPU job)
    python dgrl_hrac.py --env-id AntMaze --groups 0       # HRAC on AntMaze
    python dgrl_hrac.py --env-id AntMaze --groups 0 --total-timesteps 300000   # the short CPU run of docs/dgrl_hrac.md
    python dgrl_hrac.py --env-id AntFall --total-timesteps 2000 --ctrl-updates 50 --man-updates 5   # 15-second smoke run

The study: benchmark/hrac.sh; env speed and renders: benchmark/hrac_envs.py. Docs: docs/dgrl_hrac.md.
"""

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
    """if toggled, cuda will be enabled when available"""
    track: bool = False
    """if toggled, this experiment will be tracked with Weights and Biases"""
    wandb_project_name: str = "dgrl"
    """the wandb's project name"""
    wandb_entity: str | None = None
    """the entity (team) of wandb's project"""
    capture_video: bool = False
    """whether to record the first episode of every 10th evaluation (saved in `videos/`; set MUJOCO_GL=egl headless)"""
    save_model: bool = False
    """whether to save a checkpoint (both levels, targets excluded, the adjacency network and the subgoal encoder with
    its codebook) at every evaluation"""
    checkpoint: str | None = None
    """path of a saved checkpoint: evaluate it over --eval-episodes episodes, then exit"""
    threads: int = 1
    """torch CPU threads"""

    # Environment
    env_id: str = "AntMaze"
    """AntMaze, AntMazeSparse, AntPush, AntFall or AntGather"""

    # Algorithm: HRAC (reference hrac-keychest.md, "HRAC on the Ant tasks")
    total_timesteps: int = 5_000_000
    """total environment steps"""
    k: int = 10
    """controller steps per subgoal (the manager acts every k steps)"""
    buffer_size: int = 200_000
    """capacity of each level's replay (controller steps; manager k-step segments)"""
    batch_size: int = 128
    """transitions per update at both levels"""
    ctrl_updates: int = 0
    """controller updates at each episode end (0 = the episode's length, 500)"""
    man_updates: int = 0
    """manager updates at each episode end (0 = the episode's length / k, 50)"""
    ctrl_gamma: float = 0.95
    """controller discount"""
    man_gamma: float = 0.99
    """manager discount (per k-step segment)"""
    tau: float = 0.005
    """Polyak rate of the target networks at both levels"""
    actor_lr: float = 1e-4
    """Adam learning rate of both actors"""
    critic_lr: float = 1e-3
    """Adam learning rate of both twin critics"""
    critic_weight_decay: float = 1e-4
    """weight decay of both critic optimizers"""
    policy_noise: float = 0.2
    """std of the target-action noise (absolute units at both levels)"""
    noise_clip: float = 0.5
    """clip of the target-action noise"""
    ctrl_noise: float = 1.0
    """std of the Gaussian exploration noise on the controller's torques (max 30)"""
    man_noise: float = 1.0
    """std of the Gaussian exploration noise on the manager's subgoals"""
    man_reward_scale: float = 0.0
    """scale of the summed env reward the manager learns from (0 = 0.1, or 1.0 for AntMazeSparse and AntGather)"""
    subgoal_scale: float = 10.0
    """the manager proposes xy offsets in [-scale, scale] (AntFall's third, z, dimension: +-0.5)"""
    correction_samples: int = 10
    """Gaussian candidates of the off-policy correction (plus the stored subgoal and the achieved offset)"""
    hidden_dim: int = 300
    """hidden units of every actor and critic layer"""

    # Adjacency network
    adj_frequency: int = 50_000
    """environment steps between adjacency-network trainings (the labels persist over the run)"""
    adj_epochs: int = 25
    """epochs over all pairs of visited cells at each training"""
    adj_batch_size: int = 64
    """pairs per adjacency step"""
    adj_lr: float = 2e-4
    """Adam learning rate of the adjacency network"""
    adj_weight: float = 20.0
    """weight of the adjacency loss in the manager's actor loss"""
    margin_pos: float = 1.0
    """contrastive margin of adjacent pairs (the manager's adjacency threshold is the mean of the two margins)"""
    margin_neg: float = 1.2
    """contrastive margin of non-adjacent pairs"""

    # Evaluation
    eval_frequency: int = 5000
    """environment steps between evaluations (each at the end of an episode)"""
    eval_episodes: int = 5
    """deterministic evaluation episodes (AntMaze: on the fixed evaluation goal)"""

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
    encoder_hidden_dim: int = 128
    """hidden units of the subgoal encoder and decoder"""
    encoder_lr: float = 1e-4
    """Adam learning rate of the subgoal encoder and decoder (a parameter group of the controller's critic optimizer)"""


# --- Environments -----------------------------------------------------------------------------------------------------

# HIRO's structures, rows top to bottom: 1 fixed block, 0 free, r robot start (the first one is the origin; AntMazeSparse
# starts uniformly over all of them), XY a block sliding in x and y, YZ a block sliding in y and z, -1 a chasm.
SPARSE_ROWS = (
    "1 1 1 1 1 1 1 1 1 1", "1 r r r r r r r r 1", "1 r r r r r r r r 1", "1 1 1 1 1 1 1 r r 1", "1 0 r r r r r r r 1",
    "1 0 r r r r r r r 1", "1 1 1 1 1 1 1 r r 1", "1 r r r r r r r r 1", "1 r r r r r r r r 1", "1 1 1 1 1 1 1 1 1 1",
)  # fmt: skip
STRUCTURES = {
    "AntMaze": (8.0, ((1, 1, 1, 1, 1), (1, "r", 0, 0, 1), (1, 1, 1, 0, 1), (1, 0, 0, 0, 1), (1, 1, 1, 1, 1))),
    "AntPush": (8.0, ((1, 1, 1, 1, 1), (1, 0, "r", 1, 1), (1, 0, "XY", 0, 1), (1, 1, 0, 1, 1), (1, 1, 1, 1, 1))),
    "AntFall": (8.0, ((1, 1, 1, 1), (1, "r", 0, 1), (1, 0, "YZ", 1), (1, -1, -1, 1), (1, 0, 0, 1), (1, 1, 1, 1))),
    "AntMazeSparse": (2.0, tuple(tuple(int(c) if c in "01" else c for c in row.split()) for row in SPARSE_ROWS)),
}
MAZE_HEIGHT = 0.5  # walls are MAZE_HEIGHT * scaling tall
EVAL_GOALS = {"AntMaze": (0.0, 16.0), "AntMazeSparse": (2.0, 9.0), "AntPush": (0.0, 19.0), "AntFall": (0.0, 27.0, 4.5)}
SUCCESS_DISTANCE = {"AntMaze": 5.0, "AntMazeSparse": 1.0, "AntPush": 5.0, "AntFall": 5.0}
EPISODE_STEPS = 500
GATHER = {"apples": 8, "bombs": 8, "half_width": 10, "wall": 11.0, "catch": 1.0, "bins": 10, "range": 6.0, "span": 2 * np.pi}


def structure_origin(structure) -> tuple[int, int]:
    """(row, column) of the first robot cell: the world origin, where the ant starts."""
    for i, row in enumerate(structure):
        for j, cell in enumerate(row):
            if cell == "r":
                return i, j
    raise ValueError("structure without a robot cell")


def cell_centre(i: int, j: int, scaling: float, origin: tuple[int, int]) -> tuple[float, float]:
    """World xy of cell (row i, column j): x grows with the column, y with the row (HIRO's convention)."""
    return j * scaling - origin[1] * scaling, i * scaling - origin[0] * scaling


def structure_blocks(env_id: str) -> list[dict]:
    """The blocks of an env's structure as MuJoCo boxes: name, centre (x, y, z), half-sizes, the axes it slides along
    ("" for a fixed block) and its mass (movable blocks only). An elevated structure (one with a chasm) adds a platform
    under every non-chasm cell, and everything else sits on it."""
    scaling, structure = STRUCTURES[env_id]
    origin = structure_origin(structure)
    elevated = any(cell == -1 for row in structure for cell in row)
    offset = MAZE_HEIGHT * scaling if elevated else 0.0
    half = 0.5 * scaling
    wall_half_height = 0.5 * MAZE_HEIGHT * scaling
    blocks = []
    for i, row in enumerate(structure):
        for j, cell in enumerate(row):
            x, y = cell_centre(i, j, scaling, origin)
            if elevated and cell != -1:
                blocks.append(dict(name=f"platform_{i}_{j}", pos=(x, y, offset / 2), size=(half, half, offset / 2), axes=""))
            if cell == 1:
                pos, size = (x, y, offset + wall_half_height), (half, half, wall_half_height)
                blocks.append(dict(name=f"block_{i}_{j}", pos=pos, size=size, axes=""))
            elif cell in ("XY", "YZ"):
                shrink = 0.99 if "Z" in cell else 1.0  # the falling block fits through the chasm's gap
                mass = 0.001 if "Z" in cell else 0.0002
                blocks.append(
                    dict(
                        name=f"movable_{i}_{j}", pos=(x, y, offset + wall_half_height),
                        size=(half * shrink, half * shrink, wall_half_height), axes=cell.lower(), mass=mass,
                    )
                )  # fmt: skip
    return blocks


def hiro_ant_xml(env_id: str) -> str:
    """Gymnasium's Ant model edited as HIRO's (ctrl +-30 with gear 1, timestep 0.02, RK4) with the env's blocks; the
    ant keeps the first 15 qpos and 14 qvel entries (the blocks' slide joints come after it)."""
    root = ET.parse(os.path.join(os.path.dirname(gym.__file__), "envs/mujoco/assets/ant.xml")).getroot()
    root.find("option").set("timestep", "0.02")
    for motor in root.iter("motor"):
        motor.set("gear", "1")
        motor.set("ctrlrange", "-30 30")
    world = root.find("worldbody")
    world.find("geom[@name='floor']").set("size", "60 60 40")
    blocks = [] if env_id == "AntGather" else structure_blocks(env_id)
    scaling = STRUCTURES[env_id][0] if blocks else 0.0
    if any(block["name"].startswith("platform") for block in blocks):  # the ant starts on the platform
        world.find("body[@name='torso']").set("pos", f"0 0 {0.75 + MAZE_HEIGHT * scaling}")
    for block in blocks:
        pos, size = " ".join(map(str, block["pos"])), " ".join(map(str, block["size"]))
        if not block["axes"]:
            ET.SubElement(
                world, "geom", name=block["name"], type="box", pos=pos, size=size, conaffinity="1", contype="1",
                rgba="0.4 0.4 0.4 1",
            )  # fmt: skip
            continue
        body = ET.SubElement(world, "body", name=block["name"], pos=pos)
        ET.SubElement(
            body, "geom", name=block["name"] + "_geom", type="box", size=size, mass=str(block["mass"]), conaffinity="1",
            contype="1", rgba="0.9 0.1 0.1 1", solimp="0.995 0.995 0.01",
        )  # fmt: skip
        for axis in block["axes"]:
            direction = {"x": "1 0 0", "y": "0 1 0", "z": "0 0 1"}[axis]
            joint = dict(
                name=f"{block['name']}_{axis}", type="slide", axis=direction, pos="0 0 0", armature="0", damping="0.0"
            )
            if axis == "z":  # the falling block drops at most the platform's height
                joint.update(limited="true", range=f"{-MAZE_HEIGHT * scaling} 0")
            elif "z" in block["axes"]:
                joint.update(limited="true", range=f"{-scaling} {scaling}")
            else:
                joint.update(limited="false")
            ET.SubElement(body, "joint", **joint)
    if blocks:  # a camera over the middle of the structure that sees all of it (45-degree field of view)
        xs = [b["pos"][0] for b in blocks]
        ys = [b["pos"][1] for b in blocks]
        centre_x, centre_y = (min(xs) + max(xs)) / 2, (min(ys) + max(ys)) / 2
        extent = max(max(xs) - min(xs), max(ys) - min(ys)) + scaling
    else:
        centre_x, centre_y, extent = 0.0, 0.0, 2 * GATHER["wall"] + 1
    ET.SubElement(world, "camera", name="top", pos=f"{centre_x} {centre_y} {1.25 * extent}", xyaxes="1 0 0 0 1 0")
    if env_id == "AntGather":
        w = GATHER["wall"]
        walls = {"north": (0, w, w, 0.5), "south": (0, -w, w, 0.5), "east": (w, 0, 0.5, w), "west": (-w, 0, 0.5, w)}
        for name, (x, y, hx, hy) in walls.items():
            ET.SubElement(
                world, "geom", name=f"wall_{name}", type="box", pos=f"{x} {y} 0.5", size=f"{hx} {hy} 0.5", conaffinity="1",
                contype="1", rgba="0.4 0.4 0.4 1",
            )  # fmt: skip
    return ET.tostring(root, encoding="unicode")


def gather_readings(xy: np.ndarray, yaw: float, objects: np.ndarray) -> np.ndarray:
    """rllab's range sensor: `bins` bins over a 2*pi span centred on the ant's heading; each bin holds the largest
    1 - distance / range of the objects within range whose bearing falls in it."""
    readings = np.zeros(GATHER["bins"])
    offsets = objects - xy
    distance = np.linalg.norm(offsets, axis=1)
    bearing = (np.arctan2(offsets[:, 1], offsets[:, 0]) - yaw + GATHER["span"] / 2) % (2 * np.pi)
    bins = np.minimum((bearing / (GATHER["span"] / GATHER["bins"])).astype(int), GATHER["bins"] - 1)
    seen = distance < GATHER["range"]
    np.maximum.at(readings, bins[seen], 1.0 - distance[seen] / GATHER["range"])
    return readings


class HiroAntEnv(gym.Env):
    """One env of the HIRO Ant suite on the modern `mujoco` bindings (reference hrac-keychest.md).

    Observation: qpos[:15] + qvel[:14] of the ant and the time feature t * 0.001 (30-d); AntGather adds 10 apple and 10
    bomb range readings. Action: 8 motor torques in [-30, 30]. Reset: the model's initial state with qpos + U(-0.1,
    0.1) and qvel + 0.1 N(0, 1); AntMazeSparse starts on a uniformly drawn robot cell. Goals: AntMaze trains on
    U([-4, -4], [20, 20]) and evaluates on (0, 16); the others use their fixed goal (`goal`, None for AntGather).
    Reward: -||xy - g|| (AntFall: xyz), AntMazeSparse 1 within 1 of the goal, AntGather apples - bombs caught. Episodes
    are truncated after 500 steps; `info["success"]` applies the env's success test, `info["distance"]` is the distance
    to the goal (not for AntGather).
    """

    metadata: ClassVar[dict] = {"render_modes": ["rgb_array"], "render_fps": 10}
    frame_skip = 5

    def __init__(self, env_id: str, evaluate: bool = False, render_mode: str | None = None):
        self.env_id, self.evaluate, self.render_mode = env_id, evaluate, render_mode
        self.model = mujoco.MjModel.from_xml_string(hiro_ant_xml(env_id))
        self.data = mujoco.MjData(self.model)
        size = 50 if env_id == "AntGather" else 30
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (size,), np.float64)
        self.action_space = gym.spaces.Box(-30.0, 30.0, (8,), np.float32)
        self.goal = None if env_id == "AntGather" else np.array(EVAL_GOALS[env_id])
        self.steps = 0
        self.objects = np.zeros((0, 2))
        self.kinds = np.zeros(0)  # +1 apple, -1 bomb
        self._renderer = None
        if env_id == "AntMazeSparse":
            scaling, structure = STRUCTURES[env_id]
            origin = structure_origin(structure)
            cells = [(i, j) for i, row in enumerate(structure) for j, c in enumerate(row) if c == "r"]
            self.starts = np.array([cell_centre(i, j, scaling, origin) for i, j in cells])

    def _observe(self) -> np.ndarray:
        obs = np.concatenate([self.data.qpos[:15], self.data.qvel[:14], [self.steps * 0.001]])
        if self.env_id == "AntGather":
            yaw = np.arctan2(2 * (self.data.qpos[3] * self.data.qpos[6] + self.data.qpos[4] * self.data.qpos[5]),
                             1 - 2 * (self.data.qpos[5] ** 2 + self.data.qpos[6] ** 2))  # fmt: skip
            xy = self.data.qpos[:2]
            obs = np.concatenate([
                obs[:29],
                gather_readings(xy, yaw, self.objects[self.kinds > 0]),
                gather_readings(xy, yaw, self.objects[self.kinds < 0]),
                [self.steps * 0.01],
            ])  # fmt: skip
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
        self.steps = 0
        mujoco.mj_forward(self.model, self.data)
        return self._observe(), {}

    def step(self, action):
        self.data.ctrl[:] = np.clip(action, -30.0, 30.0)
        mujoco.mj_step(self.model, self.data, nstep=self.frame_skip)
        self.steps += 1
        xy = self.data.qpos[:2].copy()
        if self.env_id == "AntGather":
            caught = np.linalg.norm(self.objects - xy, axis=1) < GATHER["catch"]
            reward = float(self.kinds[caught].sum())
            self.objects, self.kinds = self.objects[~caught], self.kinds[~caught]
            success = False
        else:
            position = self.data.qpos[:3] if self.env_id == "AntFall" else xy
            distance = float(np.linalg.norm(position - self.goal))
            if self.env_id == "AntMazeSparse":
                reward = float(distance < SUCCESS_DISTANCE[self.env_id])
            else:
                reward = -distance
            success = distance < SUCCESS_DISTANCE[self.env_id]
        truncated = self.steps >= EPISODE_STEPS
        info = {"success": success} if self.env_id == "AntGather" else {"success": success, "distance": distance}
        return self._observe(), reward, False, truncated, info

    def render(self):
        if self._renderer is None:  # no shadows or reflections: 3x faster under software EGL on a CPU
            self.model.vis.quality.shadowsize = 0  # a visual setting only; the physics is unchanged
            self._renderer = mujoco.Renderer(self.model, 240, 240)
            self._renderer.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0
        self._renderer.update_scene(self.data, camera="top")
        # Markers drawn into the scene only (no bodies, so no physics): AntGather's apples (green) and bombs (red); the
        # goal of the other envs (a translucent green disc of the success radius, at the goal's height for AntFall).
        if self.env_id == "AntGather":
            markers = [((x, y, 0.5), 0.5, (0.1, 0.8, 0.1, 1) if kind > 0 else (0.9, 0.1, 0.1, 1))
                       for (x, y), kind in zip(self.objects, self.kinds, strict=True)]  # fmt: skip
        else:
            z = self.goal[2] if len(self.goal) == 3 else 0.05
            markers = [((*self.goal[:2], z), SUCCESS_DISTANCE[self.env_id], (0.1, 0.8, 0.1, 0.35))]
        scene = self._renderer.scene
        for pos, radius, rgba in markers[: scene.maxgeom - scene.ngeom]:
            shape = mujoco.mjtGeom.mjGEOM_SPHERE if self.env_id == "AntGather" else mujoco.mjtGeom.mjGEOM_CYLINDER
            size = np.array([radius, radius, radius]) if self.env_id == "AntGather" else np.array([radius, 0.05, 0])
            mujoco.mjv_initGeom(scene.geoms[scene.ngeom], shape, size, np.array(pos, dtype=np.float64), np.eye(3).ravel(),
                                np.array(rgba, dtype=np.float32))  # fmt: skip
            scene.ngeom += 1
        return self._renderer.render()

    def close(self):
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


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
    """DGRL's bottleneck on the manager's output: a relative subgoal (divided by the subgoal scale) -> MLP encoder ->
    the shared-codebook quantizer of vq.py -> z_q, the discrete subgoal embedding that the controller's actor and critic
    see instead of the raw subgoal. The decoder maps z_q back to the subgoal; its reconstruction loss keeps the codes
    informative about where the subgoal points."""

    def __init__(self, goal_dim: int, scale: np.ndarray, args: "Args"):
        super().__init__()
        self.encoder = mlp(goal_dim, args.encoder_hidden_dim, args.embed_dim)
        self.decoder = mlp(args.embed_dim, args.encoder_hidden_dim, goal_dim)
        self.vq = VectorQuantizerEMA(
            args.embed_dim, args.n_embed, args.groups, args.vq_beta, args.vq_decay, dead_code_steps=args.vq_dead_code_steps
        )
        self.register_buffer("scale", torch.as_tensor(scale, dtype=torch.float32))

    def forward(self, subgoals: torch.Tensor, update: bool = False) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(z_q, commitment loss, code indices); the codebook moves only with update=True."""
        return self.vq(self.encoder(subgoals / self.scale), update=update)


# --- HRAC's computations ----------------------------------------------------------------------------------------------


def controller_input(states: np.ndarray | torch.Tensor):
    """The controller's view of a state: xy zeroed (HRAC's controller is blind to where it is, only to where its
    relative subgoal points)."""
    masked = states.clone() if isinstance(states, torch.Tensor) else states.copy()
    masked[..., :2] = 0
    return masked


def subgoal_transition(states, subgoals, next_states):
    """The relative subgoal re-targeted after a step, so that it keeps pointing at the same place:
    g' = s[:d] + g - s'[:d] (d = the goal space's size)."""
    d = subgoals.shape[-1]
    return states[..., :d] + subgoals - next_states[..., :d]


def controller_reward(states, subgoals, next_states):
    """HRAC's low-level reward: -||s[:d] + g - s'[:d]||, the distance of the step's end from the subgoal's target."""
    d = subgoals.shape[-1]
    offset = states[..., :d] + subgoals - next_states[..., :d]
    return -np.linalg.norm(offset, axis=-1) if isinstance(offset, np.ndarray) else -offset.norm(dim=-1)


@torch.no_grad()
def off_policy_correction(controller: Actor, states: np.ndarray, actions: np.ndarray, subgoals: np.ndarray,
                          scale: np.ndarray, rng: np.random.Generator, n_samples: int = 10,
                          goal_encoder=None) -> np.ndarray:  # fmt: skip
    """HIRO's relabelling of stored manager transitions. `states` (B, k + 1, S), `actions` (B, k, A), `subgoals` (B, d):
    the candidates are the stored subgoal, the achieved offset s_k - s_0 and `n_samples` draws from
    N(s_k - s_0, (0.5 scale)^2) clipped to +-scale; each is rolled through the k stored states with the subgoal
    transition, and the one under which the current controller is most likely to have taken the stored actions,
    argmax of -0.5 sum_t ||pi(s_t, g_t) - a_t||^2, replaces the stored subgoal. Returns (B, d). Under DGRL the
    controller sees each candidate through `goal_encoder` (its discrete embedding), as it does when acting."""
    batch, k = actions.shape[:2]
    d = subgoals.shape[-1]
    achieved = states[:, -1, :d] - states[:, 0, :d]
    noise = rng.normal(0.0, 0.5 * scale, (batch, n_samples, d))
    candidates = np.concatenate(
        [subgoals[:, None], achieved[:, None], np.clip(achieved[:, None] + noise, -scale, scale)], 1
    )  # (B, 2 + n_samples, d)
    n = candidates.shape[1]
    goals = np.empty((batch, n, k, d))
    goals[:, :, 0] = candidates
    for t in range(1, k):
        goals[:, :, t] = subgoal_transition(states[:, None, t - 1], goals[:, :, t - 1], states[:, None, t])
    observed = np.broadcast_to(states[:, None, :k], (batch, n, k, states.shape[-1]))
    device = next(controller.parameters()).device
    goals_in = torch.as_tensor(goals, dtype=torch.float32, device=device)
    predicted = controller(
        torch.as_tensor(controller_input(observed), dtype=torch.float32, device=device),
        goals_in if goal_encoder is None else goal_encoder(goals_in)[0],  # DGRL: the candidates' discrete embeddings
    ).cpu().numpy()  # fmt: skip
    log_likelihood = -0.5 * ((predicted - actions[:, None]) ** 2).sum(-1).sum(-1)  # (B, n)
    return candidates[np.arange(batch), log_likelihood.argmax(1)]


def contrastive_loss(emb_a: torch.Tensor, emb_b: torch.Tensor, labels: torch.Tensor, margin_pos: float = 1.0,
                     margin_neg: float = 1.2) -> torch.Tensor:  # fmt: skip
    """HRAC's adjacency loss: mean(l * max(0, d - m+)) + mean((1 - l) * max(0, m- - d)), d = ||phi_a - phi_b||."""
    distances = torch.sqrt((emb_a - emb_b).pow(2).sum(-1) + 1e-12)
    positive = (labels * (distances - margin_pos).clamp(min=0)).mean()
    return positive + ((1 - labels) * (margin_neg - distances).clamp(min=0)).mean()


def adjacency_loss(anet: AdjacencyNet, positions: torch.Tensor, subgoals: torch.Tensor, threshold: float = 1.1):
    """The manager actor's adjacency term (before its weight 20): mean(max(0, ||phi(s_xy) - phi(s_xy + g)|| - 1.1))."""
    d = subgoals.shape[-1]
    distance = (anet(positions[..., :d]) - anet(positions[..., :d] + subgoals)).norm(dim=-1)
    return (distance - threshold).clamp(min=0).mean()


class AdjacencyMemory:
    """HRAC's adjacency labels over 1 m grid cells (round(s[:2])): cells t and t + j of one trajectory are adjacent for
    1 <= j <= k - 1. The matrix persists over the run and grows as new cells are visited."""

    def __init__(self, k: int = 10):
        self.k, self.index, self.edges = k, {}, set()

    def cell_ids(self, positions: np.ndarray) -> np.ndarray:
        ids = []
        for cell in map(tuple, np.round(positions[:, :2]).astype(np.int64)):
            ids.append(self.index.setdefault(cell, len(self.index)))
        return np.array(ids, dtype=np.int64)

    def add_trajectory(self, positions: np.ndarray) -> None:
        ids = self.cell_ids(positions)
        for offset in range(1, min(self.k, len(ids))):
            for a, b in zip(ids[:-offset], ids[offset:], strict=True):
                if a != b:
                    self.edges.add((min(a, b), max(a, b)))

    def labelled_pairs(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(cells_a (P, 2), cells_b (P, 2), labels (P,)) over every pair of distinct visited cells."""
        cells = np.array(sorted(self.index, key=self.index.get), dtype=np.float32).reshape(-1, 2)
        first, second = np.triu_indices(len(cells), 1)
        labels = np.array([(a, b) in self.edges for a, b in zip(first, second, strict=True)], dtype=np.float32)
        return cells[first], cells[second], labels


class Replay:
    """A ring of preallocated numpy arrays, one per field (shapes given at construction); `sample` draws uniformly."""

    def __init__(self, capacity: int, **shapes: tuple[int, ...]):
        self.capacity, self.size, self.position = capacity, 0, 0
        self.fields = {name: np.zeros((capacity, *shape), dtype=np.float32) for name, shape in shapes.items()}

    def add(self, **values) -> None:
        for name, array in self.fields.items():
            array[self.position] = values[name]
        self.position = (self.position + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)

    def sample(self, batch_size: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
        index = rng.integers(self.size, size=batch_size)
        return {name: array[index] for name, array in self.fields.items()}


def td3_update(nets: dict, optimizers: dict, batch: dict[str, torch.Tensor], gamma: float, max_action: float,
               tau: float = 0.005, policy_noise: float = 0.2, noise_clip: float = 0.5,
               actor_extra=None, critic_extra: torch.Tensor | float = 0.0) -> dict[str, torch.Tensor]:  # fmt: skip
    """One TD3 step as HRAC runs it at both levels: target actions with clipped Gaussian noise, the min of the target
    critics, a Huber critic loss (the critic optimizer carries the weight decay), the actor updated at every step (no
    policy delay) to maximise Q1, plus `actor_extra(actions)` if given (the manager's adjacency term), then Polyak
    targets. `batch`: states, goals, actions, rewards, next_states, next_goals, dones. `critic_extra` is added to the
    critic loss before its backward pass (DGRL: the subgoal encoder's losses, its parameters in the critic optimizer,
    with `goals` carrying the encoder's graph); the actor sees the goals detached."""
    with torch.no_grad():
        noise = (torch.randn_like(batch["actions"]) * policy_noise).clamp(-noise_clip, noise_clip)
        next_actions = (nets["actor_target"](batch["next_states"], batch["next_goals"]) + noise).clamp(-max_action, max_action)
        target_q = torch.min(*nets["critic_target"](batch["next_states"], batch["next_goals"], next_actions))
        target = batch["rewards"] + gamma * (1.0 - batch["dones"]) * target_q
    q1, q2 = nets["critic"](batch["states"], batch["goals"], batch["actions"])
    critic_loss = nn.functional.smooth_l1_loss(q1, target) + nn.functional.smooth_l1_loss(q2, target)
    optimizers["critic"].zero_grad(set_to_none=True)
    (critic_loss + critic_extra).backward()
    optimizers["critic"].step()
    goals = batch["goals"].detach()
    actions = nets["actor"](batch["states"], goals)
    actor_loss = -nets["critic"](batch["states"], goals, actions)[0].mean()
    if actor_extra is not None:
        actor_loss = actor_loss + actor_extra(actions)
    optimizers["actor"].zero_grad(set_to_none=True)
    actor_loss.backward()
    optimizers["actor"].step()
    update_target(nets["actor_target"], nets["actor"], tau)
    update_target(nets["critic_target"], nets["critic"], tau)
    metrics = {"critic_loss": critic_loss.detach(), "actor_loss": actor_loss.detach(), "q": q1.detach().mean()}
    return metrics | {"target_q": target_q.mean()}


# --- The agent: acting, updates, adjacency training, evaluation -------------------------------------------------------

ENV_IDS = ("AntMaze", "AntMazeSparse", "AntPush", "AntFall", "AntGather")
MANAGER_GOAL_DIMS = {"AntMaze": 2, "AntPush": 2, "AntFall": 3, "AntMazeSparse": 0, "AntGather": 0}


def subgoal_bounds(env_id: str, scale: float) -> np.ndarray:
    """The manager's output range per subgoal dimension: xy +-scale; AntFall's subgoals add z within +-0.5."""
    return np.array([scale, scale, 0.5]) if env_id == "AntFall" else np.array([scale, scale])


def manager_goal(env: HiroAntEnv) -> np.ndarray:
    """What the manager sees of the task: the goal's xy (AntFall xyz); AntMazeSparse and AntGather give it nothing."""
    return np.zeros(0) if MANAGER_GOAL_DIMS[env.env_id] == 0 else env.goal.astype(np.float32)


def controller_goal_input(goal_encoder: SubgoalEncoder | None, subgoals: torch.Tensor) -> torch.Tensor:
    """What the controller sees of its subgoal: the relative subgoal (HRAC) or its discrete embedding z_q (DGRL),
    codebook untouched."""
    return subgoals if goal_encoder is None else goal_encoder(subgoals)[0]  # DGRL


@torch.no_grad()
def propose_subgoal(nets: dict, state: np.ndarray, goal: np.ndarray, bounds: np.ndarray, noise: float,
                    rng: np.random.Generator) -> np.ndarray:  # fmt: skip
    """The manager's relative subgoal, with Gaussian exploration noise (std `noise`) clipped to the bounds."""
    device = nets["manager"]["actor"].max_action.device
    to = lambda x: torch.as_tensor(x, dtype=torch.float32, device=device)[None]  # noqa: E731
    subgoal = nets["manager"]["actor"](to(state), to(goal))[0].cpu().numpy().astype(np.float64)
    if noise > 0:
        subgoal = np.clip(subgoal + rng.normal(0.0, noise, subgoal.shape), -bounds, bounds)
    return subgoal


@torch.no_grad()
def controller_action(nets: dict, state: np.ndarray, subgoal: np.ndarray, noise: float,
                      rng: np.random.Generator) -> np.ndarray:  # fmt: skip
    """The controller's torques for the xy-masked state and its subgoal, with Gaussian noise (std `noise`) clipped to
    +-30."""
    actor = nets["controller"]["actor"]
    device = actor.max_action.device
    to = lambda x: torch.as_tensor(x, dtype=torch.float32, device=device)[None]  # noqa: E731
    action = actor(to(controller_input(state)), controller_goal_input(nets["encoder"], to(subgoal)))[0].cpu().numpy()
    if noise > 0:
        action = np.clip(action + rng.normal(0.0, noise, action.shape), -actor.max_action.item(), actor.max_action.item())
    return action


def controller_update(nets: dict, optimizer: dict, replay: Replay, args: "Args", rng: np.random.Generator, device):
    """One controller TD3 step on a replay batch. DGRL: the batch's subgoals and re-targeted next subgoals go through
    the encoder and the quantizer in one call (one EMA step of the codebook); the controller's critic and actor see z_q;
    the critic loss reaches the encoder through the straight-through estimator, with the reconstruction and commitment
    losses added."""
    batch = {name: torch.as_tensor(value, device=device) for name, value in replay.sample(args.batch_size, rng).items()}
    encoder, extra, metrics = nets["encoder"], 0.0, {}
    if encoder is not None:  # DGRL
        n = args.batch_size  # DGRL
        z_q, vq_loss, codes = encoder(torch.cat([batch["goals"], batch["next_goals"]]), update=True)  # DGRL
        reconstruction = nn.functional.mse_loss(encoder.decoder(z_q[:n]), batch["goals"] / encoder.scale)  # DGRL
        batch = batch | {"goals": z_q[:n], "next_goals": z_q[n:].detach()}  # DGRL
        extra = reconstruction + vq_loss  # DGRL: the mean commitment loss of the two embeddings
        metrics = {"reconstruction_loss": reconstruction.detach(), "vq_loss": vq_loss.detach(), "codes": codes}  # DGRL
    metrics |= td3_update(
        nets["controller"], optimizer, batch, args.ctrl_gamma, nets["controller"]["actor"].max_action, args.tau,
        args.policy_noise, args.noise_clip, critic_extra=extra,
    )  # fmt: skip
    return metrics


def manager_update(nets: dict, optimizer: dict, replay: Replay, args: "Args", bounds: np.ndarray,
                   rng: np.random.Generator, device) -> dict:  # fmt: skip
    """One manager TD3 step: the sampled subgoals are relabelled by HIRO's off-policy correction under the current
    controller, and the actor loss adds adj_weight x the adjacency loss of its subgoals (on their xy part)."""
    sample = replay.sample(args.batch_size, rng)
    sample["actions"] = off_policy_correction(
        nets["controller"]["actor"], sample["state_seq"], sample["action_seq"], sample["actions"], bounds, rng,
        args.correction_samples, nets["encoder"],
    ).astype(np.float32)  # fmt: skip
    names = ("states", "goals", "actions", "rewards", "next_states", "dones")
    batch = {name: torch.as_tensor(sample[name], device=device) for name in names}
    batch["next_goals"] = batch["goals"]
    threshold = (args.margin_pos + args.margin_neg) / 2

    def adjacency_term(subgoals: torch.Tensor) -> torch.Tensor:
        return args.adj_weight * adjacency_loss(nets["anet"], batch["states"][:, :2], subgoals[:, :2], threshold)

    metrics = td3_update(
        nets["manager"], optimizer, batch, args.man_gamma, nets["manager"]["actor"].max_action, args.tau,
        args.policy_noise, args.noise_clip, actor_extra=adjacency_term,
    )  # fmt: skip
    with torch.no_grad():
        metrics["adjacency_loss"] = adjacency_loss(nets["anet"], batch["states"][:, :2], batch["actions"][:, :2], threshold)
    return metrics


def train_adjacency(anet: AdjacencyNet, optimizer, memory: AdjacencyMemory, args: "Args", rng: np.random.Generator,
                    device) -> tuple[float, float]:  # fmt: skip
    """Train the adjacency network `adj_epochs` epochs over every pair of visited cells with the contrastive loss.
    Returns (mean loss of the last epoch, accuracy of the last epoch's embedding distances against the labels)."""
    cells_a, cells_b, labels = (torch.as_tensor(x, device=device) for x in memory.labelled_pairs())
    if len(labels) == 0:
        return float("nan"), float("nan")
    for _ in range(args.adj_epochs):
        order = torch.as_tensor(rng.permutation(len(labels)), device=device)
        losses = []
        for start in range(0, len(labels), args.adj_batch_size):
            index = order[start : start + args.adj_batch_size]
            loss = contrastive_loss(
                anet(cells_a[index]), anet(cells_b[index]), labels[index], args.margin_pos, args.margin_neg
            )
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            losses.append(loss.detach())
    with torch.no_grad():
        predicted = (anet(cells_a) - anet(cells_b)).norm(dim=-1) < (args.margin_pos + args.margin_neg) / 2
        accuracy = (predicted.float() == labels).float().mean().item()
    return torch.stack(losses).mean().item(), accuracy


@torch.no_grad()
def evaluate(env: HiroAntEnv, nets: dict, args: "Args", bounds: np.ndarray, rng: np.random.Generator, episodes: int,
             frames: list | None = None) -> dict[str, float]:  # fmt: skip
    """HRAC's evaluation: deterministic actions at both levels; an episode ends at the first step that passes the env's
    success test (distance < 5, AntMazeSparse reward > 0) or after 500 steps. Returns the success rate, the mean
    distance to the goal when the episodes ended and the mean return (AntGather's metric)."""
    successes, distances, returns = [], [], []
    for episode in range(episodes):
        state, _ = env.reset()
        goal, total, reached, info = manager_goal(env), 0.0, False, {}
        for t in range(EPISODE_STEPS):
            if t % args.k == 0:
                subgoal = propose_subgoal(nets, state, goal, bounds, 0.0, rng)
            next_state, reward, terminated, truncated, info = env.step(controller_action(nets, state, subgoal, 0.0, rng))
            subgoal = subgoal_transition(state, subgoal, next_state)
            state, total = next_state, total + reward
            if frames is not None and episode == 0:
                frames.append(env.render())
            reached = reward > 0 if env.env_id == "AntMazeSparse" else info["success"]
            if reached or terminated or truncated:
                break
        successes.append(float(reached))
        distances.append(info.get("distance", float("nan")))
        returns.append(total)
    return {"success": float(np.mean(successes)), "distance": float(np.mean(distances)), "return": float(np.mean(returns))}


def make_agent(args: "Args", state_dim: int, action_dim: int, device) -> tuple[dict, dict]:
    """Both levels (actor, twin critics and their targets), the adjacency network and, under DGRL, the subgoal encoder
    with its codebook; and their optimizers (critics with weight decay; the encoder a parameter group of the controller's
    critic optimizer, no weight decay; the codebook moves by EMA, in no optimizer)."""
    bounds = subgoal_bounds(args.env_id, args.subgoal_scale)
    goal_dim, man_goal_dim = len(bounds), MANAGER_GOAL_DIMS[args.env_id]
    ctrl_goal_input_dim = args.embed_dim if args.groups else goal_dim  # DGRL: the controller takes z_q(g) instead of g
    manager = {
        "actor": Actor(state_dim, man_goal_dim, goal_dim, bounds, args.hidden_dim).to(device),
        "critic": TwinCritic(state_dim, man_goal_dim, goal_dim, args.hidden_dim).to(device),
    }
    controller = {
        "actor": Actor(state_dim, ctrl_goal_input_dim, action_dim, 30.0, args.hidden_dim).to(device),
        "critic": TwinCritic(state_dim, ctrl_goal_input_dim, action_dim, args.hidden_dim).to(device),
    }
    anet = AdjacencyNet(2).to(device)  # over xy cells at every env (AntFall's z is not part of the grid)
    encoder = SubgoalEncoder(goal_dim, bounds, args).to(device) if args.groups else None  # DGRL
    for level in (manager, controller):
        level["actor_target"], level["critic_target"] = make_target(level["actor"]), make_target(level["critic"])
    fused = device.type in ("cpu", "cuda")

    def level_optimizers(level: dict, extra_groups: tuple = ()) -> dict:
        critic_groups = [{"params": level["critic"].parameters(), "weight_decay": args.critic_weight_decay}, *extra_groups]
        return {
            "actor": torch.optim.Adam(level["actor"].parameters(), lr=args.actor_lr, fused=fused),
            "critic": torch.optim.Adam(critic_groups, lr=args.critic_lr, fused=fused),
        }

    encoder_group = ({"params": encoder.parameters(), "lr": args.encoder_lr, "weight_decay": 0.0},) if encoder else ()  # DGRL
    optimizers = {
        "manager": level_optimizers(manager),
        "controller": level_optimizers(controller, encoder_group),
        "adjacency": torch.optim.Adam(anet.parameters(), lr=args.adj_lr, fused=fused),
    }
    return {"manager": manager, "controller": controller, "anet": anet, "encoder": encoder}, optimizers


# --- Checkpoints, videos, flags ---------------------------------------------------------------------------------------


def save_checkpoint(path: str, modules: dict[str, nn.Module | None], args: "Args") -> None:
    """Write atomically, so that a crash mid-write never destroys the previous checkpoint."""
    payload = {name: None if module is None else module.state_dict() for name, module in modules.items()}
    payload["args"] = vars(args)
    torch.save(payload, path + ".tmp")
    os.replace(path + ".tmp", path)


def write_video(path: str, frames: list[np.ndarray], fps: int = 10) -> None:
    from moviepy import ImageSequenceClip

    os.makedirs(os.path.dirname(path), exist_ok=True)
    ImageSequenceClip(frames, fps=fps).write_videofile(path, logger=None)


def validate(args: "Args") -> None:
    """Reject bad flags before any work, naming the flag and the valid choices."""
    errors = []
    if args.env_id not in ENV_IDS:
        errors.append(f"--env-id {args.env_id!r} is unknown: use one of {', '.join(ENV_IDS)}")
    if args.groups < 0 or (args.groups and args.embed_dim % args.groups):
        divisors = [g for g in range(1, args.embed_dim + 1) if args.embed_dim % g == 0]
        errors.append(
            f"--groups must be 0 (HRAC) or divide --embed-dim {args.embed_dim}: one of {divisors}; got {args.groups}"
        )
    for flag in (
        "total_timesteps", "k", "buffer_size", "batch_size", "hidden_dim", "adj_frequency", "adj_epochs", "adj_batch_size",
        "eval_frequency", "eval_episodes", "n_embed", "embed_dim", "encoder_hidden_dim", "threads",
    ):  # fmt: skip
        if getattr(args, flag) < 1:
            errors.append(f"--{flag.replace('_', '-')} must be >= 1; got {getattr(args, flag)}")
    for flag in (
        "ctrl_updates", "man_updates", "man_reward_scale", "correction_samples", "policy_noise", "noise_clip", "ctrl_noise",
        "man_noise", "critic_weight_decay", "adj_weight", "vq_dead_code_steps",
    ):  # fmt: skip
        if getattr(args, flag) < 0:
            errors.append(f"--{flag.replace('_', '-')} must be >= 0; got {getattr(args, flag)}")
    for flag in ("tau", "actor_lr", "critic_lr", "adj_lr", "encoder_lr", "subgoal_scale", "margin_pos", "margin_neg"):
        if getattr(args, flag) <= 0:
            errors.append(f"--{flag.replace('_', '-')} must be > 0; got {getattr(args, flag)}")
    for flag in ("ctrl_gamma", "man_gamma"):
        if not 0 <= getattr(args, flag) < 1:
            errors.append(f"--{flag.replace('_', '-')} must be in [0, 1); got {getattr(args, flag)}")
    if EPISODE_STEPS % args.k:
        divisors = [k for k in range(1, EPISODE_STEPS + 1) if EPISODE_STEPS % k == 0]
        errors.append(f"--k must divide the episode length {EPISODE_STEPS} (whole segments): one of {divisors}; got {args.k}")
    if args.margin_neg < args.margin_pos:
        errors.append(f"--margin-neg ({args.margin_neg}) must be >= --margin-pos ({args.margin_pos})")
    if args.checkpoint is not None and not os.path.isfile(args.checkpoint):
        errors.append(f"--checkpoint {args.checkpoint}: no such file")
    if errors:
        raise SystemExit("dgrl_hrac.py: invalid arguments:\n  " + "\n  ".join(errors))


if __name__ == "__main__":
    args = tyro.cli(Args)
    validate(args)
    dgrl = args.groups > 0
    man_reward_scale = args.man_reward_scale or (1.0 if args.env_id in ("AntMazeSparse", "AntGather") else 0.1)
    run_name = f"{args.env_id}__G{args.groups}__{args.exp_name}__{args.seed}__{int(time.time())}"

    random.seed(args.seed)
    rng = np.random.default_rng(args.seed)
    torch.manual_seed(args.seed)
    torch.backends.cudnn.deterministic = args.torch_deterministic
    torch.set_num_threads(args.threads)
    # The critics' weight decay drives the weights of dead ReLU units into subnormal floats, which slow a CPU's matrix
    # multiplies 20x (measured: 27 ms instead of 1.2 ms per batch after 5k steps); flush them to zero.
    torch.set_flush_denormal(True)
    device = torch.device("cuda" if torch.cuda.is_available() and args.cuda else "cpu")

    env = HiroAntEnv(args.env_id)
    eval_env = HiroAntEnv(args.env_id, evaluate=True, render_mode="rgb_array" if args.capture_video else None)
    eval_env.reset(seed=args.seed + 10_000)  # one evaluation stream per run, continued across evaluations
    state_dim, action_dim = env.observation_space.shape[0], env.action_space.shape[0]
    bounds = subgoal_bounds(args.env_id, args.subgoal_scale)
    goal_dim, man_goal_dim = len(bounds), MANAGER_GOAL_DIMS[args.env_id]

    nets, optimizers = make_agent(args, state_dim, action_dim, device)
    modules = {
        "manager_actor": nets["manager"]["actor"], "manager_critic": nets["manager"]["critic"],
        "controller_actor": nets["controller"]["actor"], "controller_critic": nets["controller"]["critic"],
        "adjacency": nets["anet"], "subgoal_encoder": nets["encoder"],
    }  # fmt: skip

    if args.checkpoint is not None:
        saved = torch.load(args.checkpoint, map_location=device)
        architecture = ("env_id", "groups", "embed_dim", "n_embed", "hidden_dim", "encoder_hidden_dim", "subgoal_scale", "k")
        differ = [
            f"--{key.replace('_', '-')} {saved['args'][key]}" for key in architecture if saved["args"][key] != vars(args)[key]
        ]
        if differ:
            raise SystemExit(f"--checkpoint {args.checkpoint} was saved with other settings: pass {' '.join(differ)}")
        for name, module in modules.items():
            if module is not None:
                module.load_state_dict(saved[name])
        result = evaluate(eval_env, nets, args, bounds, rng, args.eval_episodes)
        print(
            f"{args.eval_episodes} evaluation episodes: success {result['success']:.0%}, distance {result['distance']:.2f}, "
            f"return {result['return']:.2f}"
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
    print(
        f"{run_name}: state {state_dim}-d, subgoal {goal_dim}-d (bounds {bounds.tolist()}), manager goal {man_goal_dim}-d, "
        f"{args.total_timesteps} steps, device {device}"
    )

    ctrl_replay = Replay(
        args.buffer_size, states=(state_dim,), goals=(goal_dim,), actions=(action_dim,), rewards=(), next_states=(state_dim,),
        next_goals=(goal_dim,), dones=(),
    )  # fmt: skip
    man_replay = Replay(
        args.buffer_size, states=(state_dim,), goals=(man_goal_dim,), actions=(goal_dim,), rewards=(),
        next_states=(state_dim,), dones=(), state_seq=(args.k + 1, state_dim), action_seq=(args.k, action_dim),
    )  # fmt: skip
    memory = AdjacencyMemory(args.k)
    stop = []  # Ctrl-C or SIGTERM ends the run after the current step, with the checkpoint saved and the logs flushed

    def request_stop(number, frame):
        stop.append(number)
        signal.signal(number, signal.SIG_DFL)  # a second Ctrl-C or SIGTERM stops at once

    for signal_number in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signal_number, request_stop)

    checkpoint_path = f"runs/{run_name}/{args.exp_name}.cleanrl_model"
    start_time, step, episodes, evaluations = time.time(), 0, 0, 0
    next_eval, next_adjacency = args.eval_frequency, args.adj_frequency
    last_print = start_time  # a heartbeat line at least every 60 s, so that a slow run never looks hung
    result = {"success": float("nan"), "distance": float("nan"), "return": float("nan")}
    recent = {"final_distance": [], "subgoal_distance": [], "return": []}
    seg_states, seg_actions = np.zeros((args.k + 1, state_dim)), np.zeros((args.k, action_dim))
    state, _ = env.reset(seed=args.seed)
    while step < args.total_timesteps and not stop:
        # One episode: the manager proposes a relative subgoal every k steps; the controller chases it, re-targeted.
        goal, positions = manager_goal(env), [state[:2]]
        episode_return, episode_steps, seg_reward, remaining, proposals, ctrl_rewards = 0.0, 0, 0.0, [], [], 0.0
        while True:
            t = episode_steps % args.k
            if t == 0:
                subgoal = propose_subgoal(nets, state, goal, bounds, args.man_noise, rng)
                proposed, seg_states[0], seg_reward = subgoal, state, 0.0
            action = controller_action(nets, state, subgoal, args.ctrl_noise, rng)
            next_state, reward, terminated, truncated, info = env.step(action)
            step, episode_steps, episode_return = step + 1, episode_steps + 1, episode_return + reward
            seg_reward += man_reward_scale * reward
            next_subgoal = subgoal_transition(state, subgoal, next_state)
            ctrl_reward = controller_reward(state, subgoal, next_state)
            ctrl_rewards += ctrl_reward
            ctrl_replay.add(
                states=controller_input(state), goals=subgoal, actions=action, rewards=ctrl_reward,
                next_states=controller_input(next_state), next_goals=next_subgoal, dones=0.0,
            )  # fmt: skip
            seg_states[t + 1], seg_actions[t] = next_state, action
            positions.append(next_state[:2])
            state, subgoal = next_state, next_subgoal
            if t == args.k - 1:  # a whole segment: the manager's transition (the envs never terminate, so no done)
                man_replay.add(
                    states=seg_states[0], goals=goal, actions=proposed, rewards=seg_reward, next_states=state, dones=0.0,
                    state_seq=seg_states, action_seq=seg_actions,
                )  # fmt: skip
                remaining.append(np.linalg.norm(subgoal[:2]))
                proposals.append(np.linalg.norm(proposed[:2]))
            if terminated or truncated or stop or step >= args.total_timesteps:
                break
        episodes += 1
        memory.add_trajectory(np.array(positions))
        recent["return"].append(episode_return)
        recent["subgoal_distance"].extend(remaining)
        writer.add_scalar("charts/episodic_return", episode_return, step)
        writer.add_scalar("charts/episodic_length", episode_steps, step)
        writer.add_scalar("charts/controller_reward", ctrl_rewards / episode_steps, step)
        if remaining:
            writer.add_scalar("charts/subgoal_distance", float(np.mean(remaining)), step)
            writer.add_scalar("charts/subgoal_norm", float(np.mean(proposals)), step)
        if "distance" in info:
            recent["final_distance"].append(info["distance"])
            writer.add_scalar("charts/final_distance", info["distance"], step)
            writer.add_scalar("charts/success_rate", float(info["success"]), step)

        # Train at the episode's end: 500 controller updates, 50 manager updates (HRAC), no warm-up.
        for _ in range(args.ctrl_updates or episode_steps):
            ctrl_metrics = controller_update(nets, optimizers["controller"], ctrl_replay, args, rng, device)
        man_metrics = {}
        for _ in range(args.man_updates or -(-episode_steps // args.k)) if man_replay.size else ():
            man_metrics = manager_update(nets, optimizers["manager"], man_replay, args, bounds, rng, device)
        for name in ("critic_loss", "actor_loss", "q"):
            writer.add_scalar(f"losses/controller_{name}", ctrl_metrics[name].item(), step)
            if man_metrics:
                writer.add_scalar(f"losses/manager_{name}", man_metrics[name].item(), step)
        if man_metrics:
            writer.add_scalar("losses/manager_adjacency_loss", man_metrics["adjacency_loss"].item(), step)
        if dgrl:  # DGRL
            writer.add_scalar("losses/reconstruction", ctrl_metrics["reconstruction_loss"].item(), step)  # DGRL
            writer.add_scalar("vq/commit_loss", ctrl_metrics["vq_loss"].item(), step)  # DGRL
            writer.add_scalar("vq/perplexity", perplexity(ctrl_metrics["codes"], args.n_embed).item(), step)  # DGRL
            writer.add_scalar("vq/active_codes", active_codes(ctrl_metrics["codes"], args.n_embed).item(), step)  # DGRL

        # Adjacency network: retrained every adj_frequency steps on the labels gathered so far.
        if step >= next_adjacency:
            next_adjacency += args.adj_frequency
            began = time.time()
            adj_loss, adj_accuracy = train_adjacency(nets["anet"], optimizers["adjacency"], memory, args, rng, device)
            writer.add_scalar("adjacency/loss", adj_loss, step)
            writer.add_scalar("adjacency/accuracy", adj_accuracy, step)
            writer.add_scalar("adjacency/cells", len(memory.index), step)
            writer.add_scalar("adjacency/edges", len(memory.edges), step)
            print(
                f"step {step:>8}: adjacency network trained on {len(memory.index)} cells, {len(memory.edges)} adjacent "
                f"pairs: loss {adj_loss:.3f}, accuracy {adj_accuracy:.1%} ({time.time() - began:.0f} s)"
            )

        if time.time() - last_print > 60:
            last_print = time.time()
            print(f"step {step:>8}/{args.total_timesteps}  {episodes} episodes  SPS {int(step / (last_print - start_time))}")

        # Evaluate (deterministic, the fixed evaluation goal), log, print progress, checkpoint.
        if step >= next_eval or step >= args.total_timesteps or stop:
            last_print = time.time()
            next_eval = step + args.eval_frequency
            video = [] if args.capture_video and evaluations % 10 == 0 else None
            result = evaluate(eval_env, nets, args, bounds, rng, args.eval_episodes, video)
            evaluations += 1
            elapsed = time.time() - start_time
            sps = int(step / elapsed)
            for name, tag in (("success", "success_rate"), ("distance", "final_distance"), ("return", "return")):
                writer.add_scalar(f"eval/{tag}", result[name], step)
            writer.add_scalar("charts/SPS", sps, step)
            summary = {name: float(np.mean(values)) if values else float("nan") for name, values in recent.items()}
            recent = {name: [] for name in recent}
            task = (
                f"return {result['return']:6.2f}" if args.env_id == "AntGather"
                else f"success {result['success']:4.0%} distance {result['distance']:5.2f}"
            )  # fmt: skip
            print(
                f"step {step:>8}/{args.total_timesteps}  eval {task}  train return {summary['return']:8.1f} "
                f"final distance {summary['final_distance']:5.2f}  subgoal distance {summary['subgoal_distance']:5.2f}  "
                f"SPS {sps}  {elapsed:.0f}s elapsed, {(args.total_timesteps - step) / max(sps, 1):.0f}s left"
            )
            if video:
                write_video(f"videos/{run_name}/eval_{step}.mp4", video)
            if args.save_model:
                save_checkpoint(checkpoint_path, modules, args)
        if not (terminated or truncated):
            break  # stopped or out of steps mid-episode
        state, _ = env.reset()

    if args.save_model:
        save_checkpoint(checkpoint_path, modules, args)
        print(f"checkpoint: {checkpoint_path}")
    print(
        f"{'stopped' if stop else 'done'}: {step} steps, {episodes} episodes, last eval success {result['success']:.0%} "
        f"distance {result['distance']:.2f} return {result['return']:.2f}, {time.time() - start_time:.0f} s"
    )
    env.close()
    eval_env.close()
    writer.close()
