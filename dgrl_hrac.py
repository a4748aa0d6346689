"""DGRL on HRAC in the HIRO Ant suite (AntMaze, AntMazeSparse, AntPush, AntFall, AntGather).

STATUS (issue 8, in progress): the environments and HRAC's building blocks (networks, subgoal transition, controller
reward, HIRO's off-policy correction, adjacency labels and losses) are written and tested; the training loop, the
replay buffers, evaluation and the DGRL integration are not, so running this file only checks its flags and builds,
resets and steps the chosen environment.

Paper: Islam et al. 2022, "Discrete Factorial Representations as an Abstraction for Goal Conditioned RL", section "Ant
Manipulation Control Domains" and appendix "Ant Manipulation tasks". The environments are the HIRO Ant suite as HRAC
uses it (reference hrac-keychest.md): gymnasium's Ant model edited in code (ctrl +-30, gear 1, timestep 0.02 with RK4,
frame_skip 5) inside structures of fixed, sliding and elevated blocks generated into MJCF at run time.

    python dgrl_hrac.py --env-id AntPush      # builds, resets and steps AntPush (the agent is not written yet)

Docs: docs/dgrl_hrac.md (to come with the agent).
"""

import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from typing import ClassVar, Literal

import gymnasium as gym
import mujoco
import numpy as np
import torch
import torch.nn as nn
import tyro

from vq import update_target


@dataclass
class Args:
    seed: int = 1
    """seed of the experiment"""
    env_id: Literal["AntMaze", "AntMazeSparse", "AntPush", "AntFall", "AntGather"] = "AntMaze"
    """the HIRO Ant environment"""
    steps: int = 1000
    """random-action steps to take (a check of the environment while the agent is not written)"""


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
    are truncated after 500 steps; `info["success"]` applies the env's success test.
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
        return self._observe(), reward, False, truncated, {"success": success}

    def render(self):
        if self._renderer is None:
            self._renderer = mujoco.Renderer(self.model, 240, 240)
        self._renderer.update_scene(self.data, camera="top")
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

    def __init__(self, state_dim: int, goal_dim: int, action_dim: int, max_action: float, hidden_dim: int = 300):
        super().__init__()
        self.net, self.max_action = mlp(state_dim + goal_dim, hidden_dim, action_dim), max_action

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
                          scale: np.ndarray, rng: np.random.Generator, n_samples: int = 10) -> np.ndarray:  # fmt: skip
    """HIRO's relabelling of stored manager transitions. `states` (B, k + 1, S), `actions` (B, k, A), `subgoals` (B, d):
    the candidates are the stored subgoal, the achieved offset s_k - s_0 and `n_samples` draws from
    N(s_k - s_0, (0.5 scale)^2) clipped to +-scale; each is rolled through the k stored states with the subgoal
    transition, and the one under which the current controller is most likely to have taken the stored actions,
    argmax of -0.5 sum_t ||pi(s_t, g_t) - a_t||^2, replaces the stored subgoal. Returns (B, d)."""
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
    predicted = controller(
        torch.as_tensor(controller_input(observed), dtype=torch.float32, device=device),
        torch.as_tensor(goals, dtype=torch.float32, device=device),
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
               actor_extra=None) -> dict[str, torch.Tensor]:  # fmt: skip
    """One TD3 step as HRAC runs it at both levels: target actions with clipped Gaussian noise, the min of the target
    critics, a Huber critic loss (the critic optimizer carries the weight decay), the actor updated at every step (no
    policy delay) to maximise Q1, plus `actor_extra(actions)` if given (the manager's adjacency term), then Polyak
    targets. `batch`: states, goals, actions, rewards, next_states, next_goals, dones."""
    with torch.no_grad():
        noise = (torch.randn_like(batch["actions"]) * policy_noise).clamp(-noise_clip, noise_clip)
        next_actions = (nets["actor_target"](batch["next_states"], batch["next_goals"]) + noise).clamp(-max_action, max_action)
        target_q = torch.min(*nets["critic_target"](batch["next_states"], batch["next_goals"], next_actions))
        target = batch["rewards"] + gamma * (1.0 - batch["dones"]) * target_q
    q1, q2 = nets["critic"](batch["states"], batch["goals"], batch["actions"])
    critic_loss = nn.functional.smooth_l1_loss(q1, target) + nn.functional.smooth_l1_loss(q2, target)
    optimizers["critic"].zero_grad(set_to_none=True)
    critic_loss.backward()
    optimizers["critic"].step()
    actions = nets["actor"](batch["states"], batch["goals"])
    actor_loss = -nets["critic"](batch["states"], batch["goals"], actions)[0].mean()
    if actor_extra is not None:
        actor_loss = actor_loss + actor_extra(actions)
    optimizers["actor"].zero_grad(set_to_none=True)
    actor_loss.backward()
    optimizers["actor"].step()
    update_target(nets["actor_target"], nets["actor"], tau)
    update_target(nets["critic_target"], nets["critic"], tau)
    metrics = {"critic_loss": critic_loss.detach(), "actor_loss": actor_loss.detach(), "q": q1.detach().mean()}
    return metrics | {"target_q": target_q.mean()}


if __name__ == "__main__":
    import time

    args = tyro.cli(Args)
    env = HiroAntEnv(args.env_id)
    obs, _ = env.reset(seed=args.seed)
    start = time.time()
    total = 0.0
    for _ in range(args.steps):
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        total += reward
        if terminated or truncated:
            obs, _ = env.reset()
    print(
        f"{args.env_id}: {env.model.nq} qpos, observation {obs.shape[0]}-d, {args.steps} random steps at "
        f"{args.steps / (time.time() - start):.0f} steps/s, reward sum {total:.1f}. The HRAC agent is not written yet "
        "(issue 8)."
    )
