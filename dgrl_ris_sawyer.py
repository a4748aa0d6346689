"""DGRL on RIS in the vision-based Sawyer push-and-reach task. STATUS: environment only, agent to come (issue 9).

Paper: Islam et al. 2022, "Discrete Factorial Representations as an Abstraction for Goal Conditioned RL", section "Vision
Based Robotic Manipulation". The agent will be RIS (Chane-Sane et al., ICML 2021) with its image encoder, and DGRL's
discretized goal and subgoal embeddings on top (reference ris.md); neither is written yet. This file holds the task:
multiworld's `SawyerPushAndReachXYEnv` in its "TrainEnvBig" / "TestEnvBig" configurations, rebuilt on the modern `mujoco`
bindings with an MJCF scene generated in code (a table, four low walls around the arena, a puck and an end effector
driven by a mocap body; the original Sawyer arm meshes ship with no installable package, so the arm is left out).

    MUJOCO_GL=egl python dgrl_ris_sawyer.py                 # random actions on the training env: frames/s
    MUJOCO_GL=egl python dgrl_ris_sawyer.py --test --steps 500   # the same on the test configuration

Env speed and a picture of state and goal images: benchmark/sawyer_env.py.
"""

import time
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from typing import ClassVar

import gymnasium as gym
import mujoco
import numpy as np
import tyro


@dataclass
class Args:
    seed: int = 1
    """seed of the env's reset and of the random actions"""
    steps: int = 1000
    """random-action steps to time"""
    test: bool = False
    """step the test configuration (both objects cross the arena) instead of the training one"""


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


if __name__ == "__main__":
    args = tyro.cli(Args)
    print("the RIS agent is not written yet (issue 9): stepping the environment with random actions")
    env = SawyerPushAndReachEnv(test=args.test)
    env.action_space.seed(args.seed)
    env.reset(seed=args.seed)
    episodes = successes = 0
    start = time.perf_counter()
    for _ in range(args.steps):
        _, _, terminated, truncated, info = env.step(env.action_space.sample())
        if terminated or truncated:
            episodes, successes = episodes + 1, successes + info["success"]
            env.reset()
    elapsed = time.perf_counter() - start
    print(f"{args.steps} steps ({episodes} episodes, {successes} successes) at {args.steps / elapsed:,.0f} frames/s")
    env.close()
