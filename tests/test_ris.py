"""dgrl_ris.py: the four Ant mazes (walls, collisions, physics, resets), the 31-d state and goals, HER relabelling in the
episode replay, RIS's losses (advantage weights, subgoal cost, prior KL), one RIS update with and without DGRL, the
gymnasium-robotics wrapper, smoke runs of every env id, checkpoints, Ctrl-C, stopping and resuming exactly, bad flags."""

import ast
import copy
import math
import os
import re
import subprocess
import sys
import warnings
from pathlib import Path

import mujoco
import numpy as np
import pytest
import torch
from conftest import HANG_TIMEOUT, record_outputs_with_grad
from gymnasium.utils.env_checker import check_env

import dgrl_ris as ris
from tests.conftest import check_fast_update

ROOT = Path(__file__).resolve().parents[1]

# RIS's table of its four mazes (the authors' multiworld code; docs/dgrl_ris.md), typed in independently of the script:
# interior ((x0, x1), (y0, y1)), inner walls (cx, cy, hx, hy), test start box and goal box ((x0, x1), (y0, y1)).
RIS_MAZES = {
    "AntU": (
        ((-3.75, 3.75), (-9.0, 9.0)),
        [(0.0, 1.5, 0.75, 7.5)],
        ((-2.5, -2.0), (7.25, 7.75)),
        ((2.0, 2.5), (7.25, 7.75)),
    ),
    "AntFb": (
        ((-6.0, 6.0), (-6.0, 6.0)),
        [(-2.25, 1.5, 0.75, 4.5), (2.25, -1.5, 0.75, 4.5)],
        ((-4.75, -4.25), (4.25, 4.75)),
        ((4.25, 4.75), (-4.75, -4.25)),
    ),
    "AntMaze": (
        ((-8.0, 8.0), (-8.0, 8.0)),
        [
            (-2.375, 3.25, 1.625, 0.75),
            (2.375, 3.25, 1.625, 0.75),
            (0.0, 2.0, 0.75, 6.0),
            (-6, -2.25, 2, 0.75),
            (6, -2.25, 2, 0.75),
        ],
        ((-2.5, -2.0), (6.25, 6.75)),
        ((2.0, 2.5), (6.25, 6.75)),
    ),
    "AntFg": (
        ((-8.0, 8.0), (-8.0, 8.0)),
        [(0.0, -3.25, 3.0, 0.75), (-3.75, 0.0, 0.75, 4.0), (3.75, 0.0, 0.75, 4.0), (0.0, -6.0, 0.75, 2.0)],
        ((-2.5, -2.0), (-6.75, -6.25)),
        ((2.0, 2.5), (-6.75, -6.25)),
    ),
}
MAZES = list(RIS_MAZES)
REST_POSE = np.array((0.0, 1.0, 0.0, -1.0, 0.0, -1.0, 0.0, 1.0))
ALLOWED_YAWS = (0.0, math.pi, math.pi / 2, -math.pi / 2)


def quaternion(axis: str, angle: float) -> np.ndarray:
    """(w, x, y, z) of a rotation by `angle` about one coordinate axis."""
    q = np.zeros(4)
    q[0], q["xyz".index(axis) + 1] = math.cos(angle / 2), math.sin(angle / 2)
    return q


def multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    (w1, x1, y1, z1), (w2, x2, y2, z2) = a, b
    return np.array(
        (
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        )
    )


def yaw_of(state: np.ndarray) -> float:
    return math.atan2(state[8], state[7])


def is_allowed_yaw(yaw: float) -> bool:
    return any(abs(math.remainder(yaw - allowed, 2 * math.pi)) < 1e-5 for allowed in ALLOWED_YAWS)


def inside(xy: np.ndarray, box) -> bool:
    (x0, x1), (y0, y1) = box
    return x0 <= xy[0] <= x1 and y0 <= xy[1] <= y1


# --- walls, collisions, physics ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", MAZES)
def test_maze_boxes_match_ris_table(name):
    interior, inner, test_start, test_goal = RIS_MAZES[name]
    assert ris.ANT_MAZES[name]["interior"] == interior
    assert ris.ANT_MAZES[name]["test_start"] == test_start and ris.ANT_MAZES[name]["test_goal"] == test_goal
    boxes = ris.maze_boxes(name)
    assert boxes.shape == (len(inner) + 4, 4)
    np.testing.assert_allclose(sorted(map(tuple, boxes[:-4])), sorted(inner))
    outer = boxes[-4:]
    assert (outer[:, 2:].min(1) == 1.0).all()  # half-thickness 1
    (x0, x1), (y0, y1) = interior
    # Inside the interior, the distance to the outer walls is exactly the distance to the interior's boundary ...
    grid = np.stack(np.meshgrid(np.linspace(x0, x1, 41), np.linspace(y0, y1, 41)), -1).reshape(-1, 2)
    boundary = np.minimum.reduce([grid[:, 0] - x0, x1 - grid[:, 0], grid[:, 1] - y0, y1 - grid[:, 1]])
    np.testing.assert_allclose(ris.wall_distance(grid, outer), boundary, atol=1e-12)
    # ... and the band of width 2 around the interior (corners included) is solid wall.
    band = np.stack(np.meshgrid(np.linspace(x0 - 1.99, x1 + 1.99, 81), np.linspace(y0 - 1.99, y1 + 1.99, 81)), -1)
    band = band.reshape(-1, 2)
    band = band[(band[:, 0] < x0) | (band[:, 0] > x1) | (band[:, 1] < y0) | (band[:, 1] > y1)]
    assert len(band) > 100 and (ris.wall_distance(band, outer) == 0).all()


@pytest.mark.parametrize("name", MAZES)
def test_wall_distance_is_zero_inside_every_wall_and_the_model_has_those_walls(name):
    boxes = ris.maze_boxes(name)
    rng = np.random.default_rng(0)
    for cx, cy, hx, hy in boxes:
        points = rng.uniform((cx - hx, cy - hy), (cx + hx, cy + hy), size=(50, 2))
        assert (ris.wall_distance(points, boxes) == 0).all()
    model = ris.AntMazeEnv(name).model
    for index, (cx, cy, hx, hy) in enumerate(boxes):
        geom = model.geom(f"wall_{index}")
        np.testing.assert_allclose(geom.pos[:2], (cx, cy))
        np.testing.assert_allclose(geom.size[:2], (hx, hy))
        assert geom.contype[0] and geom.conaffinity[0]


def test_wall_distance_at_hand_computed_points():
    boxes = ris.maze_boxes("AntU")  # inner wall x in [-0.75, 0.75], y in [-6, 9]; interior x in [-3.75, 3.75], |y| <= 9
    points = np.array([(0.0, 0.0), (-2.0, 0.0), (0.0, -7.0), (-1.5, -6.5), (-2.0, -7.5), (-5.0, 10.0), (-6.0, 12.0)])
    expected = [0.0, 1.25, 1.0, math.hypot(0.75, 0.5), 1.5, 0.0, math.hypot(0.25, 1.0)]
    np.testing.assert_allclose(ris.wall_distance(points, boxes), expected, atol=1e-12)


def test_ant_model_gear_timestep_integrator_frame_skip():
    env = ris.AntMazeEnv("AntMaze")
    model = env.model
    assert model.nu == 8 and model.nq == 15 and model.nv == 14
    np.testing.assert_array_equal(model.actuator_gear[:, 0], np.full(8, 10.0))
    np.testing.assert_array_equal(model.actuator_ctrlrange, np.tile((-1.0, 1.0), (8, 1)))
    assert model.opt.timestep == pytest.approx(0.03)
    assert model.opt.integrator == mujoco.mjtIntegrator.mjINT_RK4
    assert env.frame_skip == 5
    assert model.geom("torso_geom").size[0] == pytest.approx(0.25)
    joint_range = model.jnt_range[1:]  # the 8 hinge joints, after the free joint
    assert ((joint_range[:, 0] <= REST_POSE) & (REST_POSE <= joint_range[:, 1])).all()  # the rest pose is reachable
    assert env.action_space.shape == (8,) and (env.action_space.low == -1).all() and (env.action_space.high == 1).all()
    env.reset(seed=0)
    env.step(np.zeros(8))
    assert env.data.time == pytest.approx(0.15)  # 5 physics steps of 0.03 per env step
    env.data.ctrl[:] = 0
    env.step(np.full(8, 5.0))
    np.testing.assert_array_equal(env.data.ctrl, np.ones(8))  # actions clipped to [-1, 1]


def push(name: str, xy, velocity, steps: int = 20) -> np.ndarray:
    """Put the ant at rest at `xy`, give its torso a velocity, step with zero action; the torso's xy path."""
    env = ris.AntMazeEnv(name)
    env.reset(seed=0)
    env.data.qpos[:2] = xy
    env.data.qvel[:] = 0.0
    env.data.qvel[:2] = velocity
    mujoco.mj_forward(env.model, env.data)
    return np.array([env.step(np.zeros(8))[0]["state"][:2] for _ in range(steps)])


@pytest.mark.parametrize(
    ("name", "xy", "velocity"),
    [
        ("AntU", (-1.6, 0.0), (6.0, 0.0)),  # into the inner wall (x >= -0.75) from the left
        ("AntU", (1.6, 0.0), (-6.0, 0.0)),  # into the inner wall from the right
        ("AntFg", (0.0, 7.1), (0.0, 6.0)),  # into the outer top wall (y >= 8)
        ("AntMaze", (-6.0, -0.6), (0.0, -6.0)),  # into the wall (-6, -2.25; 2, 0.75): y <= -1.5
    ],
)
def test_walls_stop_the_ant(name, xy, velocity):
    start_gap = ris.wall_distance(np.array([xy]), ris.maze_boxes(name))[0]
    assert 0.75 <= start_gap < 1.0
    path = push(name, xy, velocity)
    distance = ris.wall_distance(path, ris.maze_boxes(name))
    assert (distance > 0.2).all(), distance.min()  # the torso (radius 0.25) never enters a wall
    assert distance.min() < start_gap - 0.1  # it did move towards the wall


def test_the_same_push_in_open_space_goes_much_further():
    """The control for test_walls_stop_the_ant: without a wall in the way the push carries the ant over 2 m."""
    free = push("AntFb", (-5.0, -5.0), (6.0, 0.0))  # along the S maze's free bottom corridor
    assert free[-1, 0] + 5.0 > 2.0 and abs(free[-1, 1] + 5.0) < 1.0
    assert (ris.wall_distance(free, ris.maze_boxes("AntFb")) > 0.2).all()


# --- observation, goals, resets, termination --------------------------------------------------------------------------


def test_ant_state_layout():
    joints = np.arange(8) / 10 + 0.05
    velocities = np.arange(14) + 100.0
    qpos = np.concatenate(((1.0, 2.0, 3.0), quaternion("z", math.pi / 2), joints))
    state = ris.ant_state(qpos, velocities)
    assert state.shape == (31,) and state.dtype == np.float32
    np.testing.assert_allclose(state[:3], (1, 2, 3))
    np.testing.assert_allclose(state[3:9], (1, 0, 1, 0, 0, 1), atol=1e-6)  # cos, sin of roll, pitch, yaw
    np.testing.assert_allclose(state[9:17], joints, rtol=1e-6)
    np.testing.assert_array_equal(state[17:31], velocities)
    roll = ris.ant_state(np.concatenate(((0, 0, 0), quaternion("x", 0.3), joints)), velocities)
    np.testing.assert_allclose(roll[3:9], (math.cos(0.3), math.sin(0.3), 1, 0, 1, 0), atol=1e-6)
    pitch = ris.ant_state(np.concatenate(((0, 0, 0), quaternion("y", -0.4), joints)), velocities)
    np.testing.assert_allclose(pitch[3:9], (1, 0, math.cos(0.4), -math.sin(0.4), 1, 0), atol=1e-6)


def test_quat_to_euler_known_rotations():
    np.testing.assert_allclose(ris.quat_to_euler(np.array((1.0, 0, 0, 0))), (0, 0, 0), atol=1e-12)
    for axis, index in (("x", 0), ("y", 1), ("z", 2)):
        for angle in (0.3, -1.2):
            expected = np.zeros(3)
            expected[index] = angle
            np.testing.assert_allclose(ris.quat_to_euler(quaternion(axis, angle)), expected, atol=1e-9)
    np.testing.assert_allclose(ris.quat_to_euler(quaternion("z", math.pi)), (0, 0, math.pi), atol=1e-9)
    # Intrinsic z-y-x (yaw, then pitch, then roll): q = qz(yaw) qy(pitch) qx(roll).
    roll, pitch, yaw = 0.2, -0.5, 2.5
    q = multiply(multiply(quaternion("z", yaw), quaternion("y", pitch)), quaternion("x", roll))
    np.testing.assert_allclose(ris.quat_to_euler(q), (roll, pitch, yaw), atol=1e-9)
    # and against MuJoCo's own conversion of the same rotation to a matrix: the yaw is the heading of the body's x axis
    matrix = np.zeros(9)
    mujoco.mju_quat2Mat(matrix, q)
    assert math.atan2(matrix[3], matrix[0]) == pytest.approx(yaw)


@pytest.mark.parametrize("yaw", ALLOWED_YAWS)
def test_goal_state(yaw):
    goal = ris.goal_state(np.array((1.5, -2.0)), yaw)
    assert goal.shape == (31,)
    np.testing.assert_allclose(goal[:3], (1.5, -2.0, 0.565), rtol=1e-6)
    np.testing.assert_allclose(goal[3:7], (1, 0, 1, 0), atol=1e-6)  # roll = pitch = 0
    np.testing.assert_allclose(goal[7:9], (math.cos(yaw), math.sin(yaw)), atol=1e-6)
    np.testing.assert_array_equal(goal[9:17], REST_POSE)
    np.testing.assert_array_equal(goal[17:31], np.zeros(14))


@pytest.mark.parametrize("name", MAZES)
def test_training_resets_are_free_space_with_clearance(name):
    env = ris.AntMazeEnv(name)
    boxes = ris.maze_boxes(name)
    (x0, x1), (y0, y1) = RIS_MAZES[name][0]
    starts, goals, yaws = [], [], set()
    for seed in range(150):
        observation, _ = env.reset(seed=seed)
        state, goal = observation["state"], observation["goal"]
        for point in (state, goal):
            assert is_allowed_yaw(yaw_of(point)), yaw_of(point)
            assert point[2] == pytest.approx(0.565)
            np.testing.assert_allclose(point[3:7], (1, 0, 1, 0), atol=1e-6)
            np.testing.assert_allclose(point[9:17], REST_POSE, atol=1e-6)
            np.testing.assert_array_equal(point[17:31], np.zeros(14))
        yaws.update(
            min(range(4), key=lambda i: abs(math.remainder(yaw_of(p) - ALLOWED_YAWS[i], 2 * math.pi))) for p in (state, goal)
        )
        np.testing.assert_array_equal(env.data.mocap_pos[0, :2], goal[:2])  # the marker shows the goal
        starts.append(state[:2])
        goals.append(goal[:2])
    points = np.array(starts + goals, dtype=np.float64)
    assert (ris.wall_distance(points, boxes) >= 0.75 - 1e-6).all()
    assert (points[:, 0] > x0).all() and (points[:, 0] < x1).all() and (points[:, 1] > y0).all() and (points[:, 1] < y1).all()
    assert len(yaws) == 4  # all four headings occur
    # Spread over the whole maze, not the test boxes: both halves of each axis are visited by starts and by goals.
    for half in (np.array(starts), np.array(goals)):
        assert half[:, 0].min() < (x0 + x1) / 2 - 1 < (x0 + x1) / 2 + 1 < half[:, 0].max()
        assert half[:, 1].min() < (y0 + y1) / 2 - 1 < (y0 + y1) / 2 + 1 < half[:, 1].max()


@pytest.mark.parametrize("name", MAZES)
def test_test_resets_use_ris_test_boxes(name):
    _, _, start_box, goal_box = RIS_MAZES[name]
    env = ris.AntMazeEnv(name, test=True)
    starts = []
    for seed in range(60):
        observation, _ = env.reset(seed=seed)
        assert inside(observation["state"][:2], start_box), observation["state"][:2]
        assert inside(observation["goal"][:2], goal_box), observation["goal"][:2]
        assert is_allowed_yaw(yaw_of(observation["state"])) and is_allowed_yaw(yaw_of(observation["goal"]))
        starts.append(observation["state"][:2])
    assert np.ptp(np.array(starts), axis=0).min() > 0.3  # drawn over the box, not a fixed point


def test_step_reward_and_termination_at_half_a_metre():
    env = ris.AntMazeEnv("AntU")
    observation, _ = env.reset(seed=3)
    xy = observation["state"][:2].copy()
    for offset, expected in ((0.45, True), (0.55, False), (0.3, True), (0.7, False)):
        env.goal[:2] = xy + np.array((0.0, offset))
        observation, reward, terminated, truncated, info = env.step(np.zeros(8))
        distance = np.linalg.norm(observation["state"][:2] - env.goal[:2])
        assert abs(distance - offset) < 0.04  # the ant at rest barely moves in one step
        assert reward == -1.0 and not truncated
        assert terminated is expected and info["success"] is expected
        np.testing.assert_array_equal(observation["goal"], env.goal)
        xy = observation["state"][:2].copy()


# --- HER relabelling in the episode replay ----------------------------------------------------------------------------

STATE_DIM, GOAL_DIM = 6, 5
KIND_STATE, KIND_NEXT, KIND_GOAL = 0.0, 1.0, 2.0


def labelled_episode(episode: int, length: int, far_goals: bool = True):
    """States [t, 100 * ep, ep, t, kind, 99]; s'_t has the xy (t + 1, 100 * ep) and kind 1; the rollout goal of step t
    (kind 2) is 1000 m away, or when far_goals is False 0.45 m from s'_t for odd t and 0.55 m for even t."""
    t = np.arange(length, dtype=np.float32)
    ep = np.full(length, float(episode), dtype=np.float32)
    states = np.stack((t, 100 * ep, ep, t, np.full(length, KIND_STATE), np.full(length, 99.0)), 1)
    next_states = np.stack((t + 1, 100 * ep, ep, t, np.full(length, KIND_NEXT), np.full(length, 99.0)), 1)
    goal_x = 1000.0 if far_goals else t + 1 + np.where(t % 2 == 1, 0.45, 0.55)
    goals = np.stack((np.broadcast_to(goal_x, (length,)), 100 * ep, ep, t, np.full(length, KIND_GOAL)), 1)
    actions = np.stack((ep, t), 1)
    return states.astype(np.float32), actions, next_states.astype(np.float32), goals.astype(np.float32)


def test_her_batch_proportions_rewards_and_done():
    replay = ris.EpisodeReplay(1000, STATE_DIM, 2, GOAL_DIM, torch.device("cpu"))
    lengths = [12, 7, 20, 1, 15]
    for episode, length in enumerate(lengths):
        replay.add_episode(*labelled_episode(episode, length, far_goals=False))
    assert replay.size == sum(lengths)
    states, actions, next_states, goals, rewards, done, subgoals = replay.sample(1000, GOAL_DIM, 0.5, 0.2, 0.4)
    assert goals.shape == (1000, GOAL_DIM) and states.shape == (1000, STATE_DIM) and subgoals.shape == (1000, STATE_DIM)
    ep, t = states[:, 2], states[:, 3]
    # The batch is made of stored transitions: a, s' belong to the same (episode, t) as s.
    assert (states[:, 4] == KIND_STATE).all() and (next_states[:, 4] == KIND_NEXT).all()
    assert torch.equal(next_states[:, 2], ep) and torch.equal(next_states[:, 3], t)
    assert torch.equal(actions, torch.stack((ep, t), 1))
    assert torch.equal(states[:, 0], t) and torch.equal(next_states[:, 0], t + 1)
    # First 200: the rollout goal of that very transition.
    keep = goals[:200]
    assert (keep[:, 4] == KIND_GOAL).all() and torch.equal(keep[:, 2], ep[:200]) and torch.equal(keep[:, 3], t[:200])
    # Next 400: the first GOAL_DIM entries of random stored states (s, not s'), from across the buffer.
    stored = replay.states[: replay.size, :GOAL_DIM]
    random_goals = goals[200:600]
    assert (random_goals[:, 4] == KIND_STATE).all()
    assert ((random_goals[:, None, :] == stored[None]).all(-1)).any(1).all()
    assert len(set(random_goals[:, 2].tolist())) == len(lengths)
    assert (random_goals[:, 2] != ep[200:600]).float().mean() > 0.3  # independent of the transition's episode
    # Last 400: s' of the same episode at a time >= the transition's, uniform over s'_t..s'_end.
    future = goals[600:]
    assert (future[:, 4] == KIND_NEXT).all() and torch.equal(future[:, 2], ep[600:])
    offsets = future[:, 3] - t[600:]
    assert (offsets >= 0).all() and (offsets == 0).any() and (offsets > 3).any()
    last_t = torch.as_tensor(lengths, dtype=torch.float32)[ep[600:].long()] - 1
    assert (future[:, 3] <= last_t).all()
    assert ((future[:, 3] == last_t) & (t[600:] < last_t)).any()  # the episode's last s' is a possible future goal
    # Rewards and done, recomputed.
    assert (rewards == -1).all()
    distance = torch.linalg.vector_norm(next_states[:, :2] - goals[:, :2], dim=-1)
    assert torch.equal(done, (distance < 0.5).float())
    assert torch.equal(done[600:], (offsets == 0).float())  # a future goal equal to s' itself is reached
    assert done[:200].sum() > 0 and torch.equal(done[:200], (t[:200] % 2 == 1).float())  # 0.45 m: done, 0.55 m: not
    assert done[600:].sum() > 0 and (done[600:] == 0).any()
    # High-level candidates: stored states.
    assert (subgoals[:, 4] == KIND_STATE).all()
    assert ((subgoals[:, None, :] == replay.states[None, : replay.size]).all(-1)).any(1).all()


def test_future_goals_are_uniform_over_the_rest_of_the_episode():
    replay = ris.EpisodeReplay(100, STATE_DIM, 2, GOAL_DIM, torch.device("cpu"))
    replay.add_episode(*labelled_episode(0, 4))
    states, _, _, goals, _, done, _ = replay.sample(8000, GOAL_DIM, 0.5, 0.0, 0.0)
    for t in range(4):
        rows = states[:, 3] == t
        offsets = goals[rows, 3] - t
        counts = torch.bincount(offsets.long(), minlength=4 - t)
        assert len(counts) == 4 - t  # s'_t .. s'_3, nothing else
        assert (counts / rows.sum() - 1 / (4 - t)).abs().max() < 0.06, counts
        assert torch.equal(done[rows], (offsets == 0).float())


@pytest.mark.parametrize(("goal_frac", "random_frac"), [(0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (0.25, 0.5)])
def test_her_fractions_are_respected(goal_frac, random_frac):
    replay = ris.EpisodeReplay(200, STATE_DIM, 2, GOAL_DIM, torch.device("cpu"))
    for episode in range(6):
        replay.add_episode(*labelled_episode(episode, 10))
    goals = replay.sample(64, GOAL_DIM, 0.5, goal_frac, random_frac)[3]
    n_keep, n_random = round(64 * goal_frac), round(64 * random_frac)
    kinds = [KIND_GOAL] * n_keep + [KIND_STATE] * n_random + [KIND_NEXT] * (64 - n_keep - n_random)
    assert goals[:, 4].tolist() == kinds


def test_replay_ring_keeps_episode_suffixes():
    capacity = 60
    replay = ris.EpisodeReplay(capacity, STATE_DIM, 2, GOAL_DIM, torch.device("cpu"))
    rng = np.random.default_rng(0)
    lengths = rng.integers(1, 16, size=40)
    for episode, length in enumerate(lengths):
        replay.add_episode(*labelled_episode(episode, int(length)))
        size = replay.size
        assert size <= capacity
        ends = replay.episode_end[:size]
        rows = torch.arange(size)
        assert (ends >= rows).all() and (ends < size).all()
        ep, t = replay.states[:size, 2], replay.states[:size, 3]
        assert torch.equal(ep[ends], ep)  # the stored end belongs to the same episode ...
        assert torch.equal(t[ends], torch.as_tensor(lengths, dtype=torch.float32)[ep.long()] - 1)  # ... and is its last step
        assert torch.equal(t[ends] - t, (ends - rows).float())  # and every step in between survives, in order
    assert sum(lengths) > 5 * capacity  # the ring wrapped several times
    assert replay.states[: replay.size, 2].max() == len(lengths) - 1  # the latest episode is stored
    states, _, _, goals, _, _, _ = replay.sample(2000, GOAL_DIM, 0.5, 0.0, 0.0)  # all future goals
    assert torch.equal(goals[:, 2], states[:, 2]) and (goals[:, 3] >= states[:, 3]).all()
    assert (goals[:, 4] == KIND_NEXT).all()


# --- RIS losses on toy tensors ----------------------------------------------------------------------------------------


def test_advantage_weights():
    proposed = torch.tensor([5.0, 5.0, 5.0, 5.0])
    candidates = torch.tensor([3.0, 7.0, 5.0, 4.9])
    weights = ris.advantage_weights(proposed, candidates, 0.1)
    assert weights.sum() == pytest.approx(1.0)
    assert weights.argmax() == 0 and weights.argmin() == 1  # the cheaper candidate weighs more
    expected = torch.softmax(torch.tensor([20.0, -20.0, 0.0, 1.0]), 0)
    assert torch.allclose(weights, expected)
    batch = ris.advantage_weights(torch.randn(64), torch.randn(64), 1.0)
    assert batch.sum() == pytest.approx(1.0) and (batch > 0).all()


def test_subgoal_cost_clips_and_takes_the_longer_half():
    to_subgoal = torch.tensor([-3.0, -150.0, 4.0, -10.0, -20.0])
    from_subgoal = torch.tensor([-5.0, -1.0, -2.0, 7.0, -300.0])
    assert torch.equal(ris.subgoal_cost(to_subgoal, from_subgoal), torch.tensor([5.0, 100.0, 2.0, 10.0, 100.0]))


def naive_prior_kl(u, mean, std, prior_mean, prior_std, epsilon):
    """log N(u; mu, sigma) - log(mean_k N(u; mu_k, sigma_k) + eps), as products of densities in float64."""
    u, mean, std, prior_mean, prior_std = (x.double() for x in (u, mean, std, prior_mean, prior_std))

    def density(x, mu, sigma):
        return (torch.exp(-0.5 * ((x - mu) / sigma) ** 2) / (sigma * math.sqrt(2 * math.pi))).prod(-1)

    return torch.log(density(u, mean, std)) - torch.log(density(u.unsqueeze(0), prior_mean, prior_std).mean(0) + epsilon)


@pytest.mark.parametrize("epsilon", [1e-16, 1e-4, 0.3])
def test_prior_kl_matches_the_direct_formula(epsilon):
    generator = torch.Generator().manual_seed(1)
    batch, actions, k = 6, 3, 5
    mean, std = torch.randn(batch, actions, generator=generator), 0.5 + torch.rand(batch, actions, generator=generator)
    u = mean + std * torch.randn(batch, actions, generator=generator)
    prior_mean = mean + 0.7 * torch.randn(k, batch, actions, generator=generator)
    prior_std = 0.3 + torch.rand(k, batch, actions, generator=generator)
    kl = ris.prior_kl(u, mean, std, prior_mean, prior_std, epsilon)
    assert kl.shape == (batch,)
    torch.testing.assert_close(kl.double(), naive_prior_kl(u, mean, std, prior_mean, prior_std, epsilon), rtol=1e-4, atol=1e-4)
    # Prior = policy at every subgoal: KL = -log(1 + eps / N(u; mu, sigma)).
    same = ris.prior_kl(u, mean, std, mean.expand(k, -1, -1), std.expand(k, -1, -1), epsilon)
    torch.testing.assert_close(
        same.double(),
        naive_prior_kl(u, mean, std, mean.expand(k, -1, -1), std.expand(k, -1, -1), epsilon),
        rtol=1e-4,
        atol=1e-5,
    )
    if epsilon == 1e-16:
        assert same.abs().max() < 1e-5


def test_prior_kl_is_finite_where_the_density_underflows():
    mean, std, u = torch.zeros(4, 8), torch.ones(4, 8), torch.full((4, 8), 0.1)
    log_policy = torch.distributions.Normal(mean, std).log_prob(u).sum(-1)
    # Prior means 100 sigmas away in 8 dimensions: the mixture density is exactly 0 even in float64; the KL is the
    # policy's log density minus log(eps).
    prior_mean, prior_std = torch.full((3, 4, 8), 50.0), torch.full((3, 4, 8), 0.5)
    for epsilon in (1e-16, 1e-300):
        kl = ris.prior_kl(u, mean, std, prior_mean, prior_std, epsilon)
        assert torch.isfinite(kl).all()
        torch.testing.assert_close(kl, log_policy - math.log(epsilon))
        torch.testing.assert_close(kl.double(), naive_prior_kl(u, mean, std, prior_mean, prior_std, epsilon))
    # A mixture density of about 1e-60 (8 sigmas away in 4 dimensions), far above eps = 1e-300: the naive float32 formula
    # underflows to log(0), prior_kl on the same float32 inputs matches the float64 formula, gradients included.
    mean, std = torch.zeros(2, 4), torch.ones(2, 4)
    u = torch.zeros(2, 4, requires_grad=True)
    prior_mean, prior_std = torch.full((5, 2, 4), 8.2), torch.ones(5, 2, 4)
    naive32 = torch.log(torch.distributions.Normal(prior_mean, prior_std).log_prob(u.detach()).sum(-1).exp().mean(0) + 1e-300)
    assert torch.isinf(naive32).all()
    kl = ris.prior_kl(u, mean, std, prior_mean, prior_std, 1e-300)
    expected = naive_prior_kl(u.detach(), mean, std, prior_mean, prior_std, 1e-300)
    assert 100 < expected.min() < 200
    torch.testing.assert_close(kl.double(), expected, rtol=1e-5, atol=1e-3)
    kl.sum().backward()
    assert torch.isfinite(u.grad).all() and u.grad.abs().sum() > 0


# --- one RIS update ---------------------------------------------------------------------------------------------------

RIS_SETTINGS = dict(gamma=0.99, tau=0.25, alpha=0.1, h_lambda=0.1, n_subgoals=3, prior_epsilon=1e-16)  # tau: visible steps
RIS_SETTINGS |= dict(vq_loss_reduction="mean")
STATE_DIM_UPDATE, GOAL_DIM_UPDATE, ACTION_DIM_UPDATE, BATCH = 6, 2, 2, 32


def tiny_agent(groups: int) -> tuple[ris.Agent, ris.EpisodeReplay]:
    """The script's own make_agent at a tiny size, and a replay of 8 random walks (each with its last point as goal)."""
    flags = dict(hidden_dim=16, q_lr=1e-3, actor_lr=1e-3, h_lr=1e-4, groups=groups, embed_dim=8, n_embed=8, vq_beta=0.25)
    flags |= dict(vq_decay=0.99, vq_dead_code_steps=0, encoder_lr=1e-4)
    agent = ris.make_agent(STATE_DIM_UPDATE, GOAL_DIM_UPDATE, ACTION_DIM_UPDATE, ris.Args(**flags), torch.device("cpu"))
    replay = ris.EpisodeReplay(500, STATE_DIM_UPDATE, ACTION_DIM_UPDATE, GOAL_DIM_UPDATE, torch.device("cpu"))
    rng = np.random.default_rng(0)
    for _ in range(8):
        states = np.cumsum(rng.normal(size=(21, STATE_DIM_UPDATE)), 0).astype(np.float32)
        actions = rng.uniform(-1, 1, (20, ACTION_DIM_UPDATE)).astype(np.float32)
        replay.add_episode(states[:-1], actions, states[1:], np.tile(states[-1, :GOAL_DIM_UPDATE], (20, 1)))
    return agent, replay


def update(agent: ris.Agent, replay: ris.EpisodeReplay, **settings) -> dict[str, torch.Tensor]:
    batch = replay.sample(BATCH, GOAL_DIM_UPDATE, 0.45, 0.2, 0.4)
    return ris.ris_update(agent, batch, ris.Args(**(RIS_SETTINGS | settings)))


def test_make_agent_wiring():
    for groups in (0, 4):
        agent, _ = tiny_agent(groups)
        assert (agent.goal_encoder is None) == (groups == 0)
        goal_input_dim = 8 if groups else GOAL_DIM_UPDATE  # DGRL: the networks take z_q(g) (embed_dim 8)
        assert agent.actor.net[0].in_features == STATE_DIM_UPDATE + goal_input_dim
        assert agent.critic.q1[0].in_features == STATE_DIM_UPDATE + ACTION_DIM_UPDATE + goal_input_dim
        assert agent.high.net[0].in_features == STATE_DIM_UPDATE + GOAL_DIM_UPDATE  # the high level sees raw goals
        for target, online in ((agent.actor_target, agent.actor), (agent.critic_target, agent.critic)):
            assert target is not online and all(
                torch.equal(a, b) for a, b in zip(target.parameters(), online.parameters(), strict=True)
            )
        critic_groups = agent.critic_optimizer.param_groups
        assert [group["lr"] for group in critic_groups] == ([1e-3, 1e-4] if groups else [1e-3])  # the encoder's own lr
        if groups:
            assert {id(p) for p in critic_groups[1]["params"]} == {id(p) for p in agent.goal_encoder.parameters()}
            assert agent.goal_encoder.vq.groups == 4 and agent.goal_encoder.vq.n_embed == 8
        assert agent.actor_optimizer.param_groups[0]["lr"] == 1e-3 and agent.high_optimizer.param_groups[0]["lr"] == 1e-4


@pytest.mark.parametrize("groups", [0, 4])
def test_ris_update_runs_and_moves_targets_by_polyak(groups):
    agent, replay = tiny_agent(groups)
    # Targets that differ from the online nets, so that the Polyak step is visible.
    for target in (agent.actor_target, agent.critic_target):
        with torch.no_grad():
            for parameter in target.parameters():
                parameter.add_(torch.randn_like(parameter))
    pairs = {"actor": (agent.actor_target, agent.actor), "critic": (agent.critic_target, agent.critic)}
    before = {name: [p.clone() for p in target.parameters()] for name, (target, _) in pairs.items()}
    online = {"actor": agent.actor, "critic": agent.critic, "high": agent.high}
    online_before = {name: [p.clone() for p in net.parameters()] for name, net in online.items()}
    metrics = update(agent, replay)
    for name in ("critic_loss", "actor_loss", "high_loss", "kl", "q_values", "high_weight_max", "subgoal_distance"):
        assert metrics[name].shape == () and torch.isfinite(metrics[name]), name
        assert not metrics[name].requires_grad
    assert 0 < metrics["high_weight_max"] <= 1
    assert ("codes" in metrics) == (groups > 0) and ("reconstruction_loss" in metrics) == (groups > 0)
    if groups:
        assert metrics["codes"].shape == (4 * BATCH, groups)
        assert torch.isfinite(metrics["vq_loss"]) and torch.isfinite(metrics["reconstruction_loss"])
    for name, net in online.items():  # every online net took a step
        assert any(not torch.equal(p, q) for p, q in zip(net.parameters(), online_before[name], strict=True)), name
    for name, (target, source_net) in pairs.items():
        for old, new, source in zip(before[name], target.parameters(), source_net.parameters(), strict=True):
            torch.testing.assert_close(new, old + RIS_SETTINGS["tau"] * (source - old))
            assert not torch.equal(new, source)


def test_dgrl_update_moves_the_codebook_and_acting_does_not():
    agent, replay = tiny_agent(4)
    encoder = agent.goal_encoder
    encoder_weights = [p.clone() for p in encoder.encoder.parameters()]
    goals = torch.randn(16, 2)
    buffers = {name: b.clone() for name, b in encoder.vq.named_buffers()}
    z_q = ris.goal_input(encoder, goals)
    assert z_q.shape == (16, 8)
    with torch.no_grad():
        assert torch.equal(z_q, ris.goal_input(encoder, goals))
    actions = ris.act(agent.actor, encoder, {"state": torch.randn(16, 6).numpy(), "goal": goals.numpy()}, "cpu", True)
    assert actions.shape == (16, 2) and np.abs(actions).max() <= 1
    for name, buffer in encoder.vq.named_buffers():
        assert torch.equal(buffer, buffers[name]), name  # acting never moves the codebook
    # The quantized goal is made of codebook rows.
    codes = encoder.vq.codebook
    segments = z_q.detach().reshape(-1, codes.shape[1])
    assert ((segments[:, None, :] == codes[None]).all(-1)).any(1).all()
    update(agent, replay)
    assert not torch.equal(encoder.vq.codebook, buffers["codebook"])
    assert not torch.equal(encoder.vq.ema_count, buffers["ema_count"])
    assert any(not torch.equal(p, q) for p, q in zip(encoder.encoder.parameters(), encoder_weights, strict=True))


@pytest.mark.parametrize("script", ["dgrl_ris", "dgrl_ris_sawyer"])
def test_commitment_losses_combine_as_their_mean_or_their_sum(script):
    """Four embeddings with known distances to their codes, in one call of the bottleneck: its loss is the mean of their
    four commitment losses beta/G sum_i ||c_i - e_oi||^2 (the paper's text), 4 x that mean is their sum (the snippet).
    Both RIS scripts hold the same rule (combined_commitment_loss)."""
    combined = __import__(script).combined_commitment_loss
    vq = ris.VectorQuantizerEMA(2, 2, 2, beta=0.5).eval()  # G = 2 one-entry segments; codes 0 and 10
    vq.codebook.copy_(torch.tensor([[0.0], [10.0]]))
    embeddings = [torch.tensor([[k, 0.0]]) for k in (1.0, 2.0, 3.0, 4.0)]  # segment k is k from code 0, segment 2 is on it
    separate = [vq(z)[1] for z in embeddings]
    torch.testing.assert_close(torch.stack(separate), torch.tensor([1.0, 4.0, 9.0, 16.0]) * 0.5 / 2)  # beta/G k^2
    pooled = vq(torch.cat(embeddings))[1]
    torch.testing.assert_close(combined(pooled, 4, "mean"), torch.tensor(30.0 / 16))
    torch.testing.assert_close(combined(pooled, 4, "sum"), torch.tensor(30.0 / 4))


@pytest.mark.parametrize(("reduction", "factor"), [("mean", 1), ("sum", 4)])
def test_the_encoder_feels_the_commitment_losses_as_combined(reduction, factor):
    """In ris_update the encoder's outputs for s' and s_g take part in nothing but the commitment loss, so the gradient
    they receive is that loss's: factor x 2 beta (z - e) / (4 B G), with e the code each segment snapped to (the codebook
    before the update) and factor 1 for the mean of the four losses, 4 for their sum."""
    agent, replay = tiny_agent(4)
    vq_before = copy.deepcopy(agent.goal_encoder.vq).eval()
    outputs, grads = record_outputs_with_grad(agent.goal_encoder.encoder)
    update(agent, replay, vq_loss_reduction=reduction)
    assert len(outputs) == len(grads) == 1  # one encoder pass with gradient: s, s', g and s_g together
    embeddings = outputs[0]
    assert embeddings.shape == (4 * BATCH, 8)
    codes = vq_before(embeddings)[0]
    expected = factor * 2 * 0.25 * (embeddings - codes) / (4 * BATCH * 4)
    for block in (1, 3):  # s' and s_g
        rows = slice(block * BATCH, (block + 1) * BATCH)
        assert expected[rows].abs().min() > 0
        torch.testing.assert_close(grads[0][rows], expected[rows])


def test_act_mean_action_is_tanh_of_the_mean():
    agent, _ = tiny_agent(0)
    observations = {
        "state": np.random.default_rng(0).normal(size=(5, 6)).astype(np.float32),
        "goal": np.zeros((5, 2), np.float32),
    }
    actions = ris.act(agent.actor, None, observations, "cpu", deterministic=True)
    with torch.no_grad():
        mean = agent.actor(torch.as_tensor(observations["state"]), torch.as_tensor(observations["goal"]))[0]
    np.testing.assert_allclose(actions, torch.tanh(mean).numpy(), rtol=1e-6)
    sampled = ris.act(agent.actor, None, observations, "cpu", deterministic=False)
    assert sampled.shape == (5, 2) and np.abs(sampled).max() <= 1 and not np.allclose(sampled, actions)


# --- gymnasium-robotics wrapper ---------------------------------------------------------------------------------------


def test_robotics_maze_state_is_achieved_goal_then_observation():
    observation = {
        "achieved_goal": np.array([1.0, 2.0]),
        "observation": np.array([3.0, 4.0, 5.0, 6.0]),
        "desired_goal": np.array([7.0, 8.0]),
    }
    converted = ris.RoboticsMaze.observation(observation)
    np.testing.assert_array_equal(converted["state"], [1, 2, 3, 4, 5, 6])
    np.testing.assert_array_equal(converted["goal"], [7, 8])
    assert converted["state"].dtype == np.float32 and converted["goal"].dtype == np.float32


@pytest.mark.parametrize("test", [False, True])
def test_robotics_maze_passes_gymnasium_env_checker(test):
    env = ris.make_env("PointMaze_UMaze-v3", 0, test, 0, ris.ROBOTICS_THRESHOLD)()
    wrapper = env.env
    assert isinstance(wrapper, ris.RoboticsMaze)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the checker's advice on unbounded Boxes and on checking a wrapped env
        check_env(wrapper, skip_render_check=True)
        check_env(env, skip_render_check=True)  # with RecordEpisodeStatistics on top, as the script steps it
    recorded = [spec for spec in wrapper.spec.additional_wrappers if spec.name == "RoboticsMaze"]
    assert len(recorded) == 1 and recorded[0].kwargs == {"test": test}  # gymnasium can re-create the wrapper


@pytest.mark.parametrize("test", [False, True])
def test_ant_maze_env_passes_gymnasium_env_checker(test):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the checker's advice on unbounded Boxes
        check_env(ris.AntMazeEnv("AntFb", test=test), skip_render_check=True)


def test_point_umaze_test_resets_use_the_two_ends_of_the_u():
    env = ris.make_env("PointMaze_UMaze-v3", 0, True, 0, ris.ROBOTICS_THRESHOLD)()
    assert env.observation_space["state"].shape == (6,) and env.observation_space["goal"].shape == (2,)
    maze = env.unwrapped.maze
    assert maze.maze_map[1][1] == 0 and maze.maze_map[3][1] == 0 and maze.maze_map[2][1] == 1  # two ends of the U
    start_cell, goal_cell = maze.cell_rowcol_to_xy(np.array((1, 1))), maze.cell_rowcol_to_xy(np.array((3, 1)))
    np.testing.assert_allclose(start_cell, (-1.0, 1.0))
    np.testing.assert_allclose(goal_cell, (-1.0, -1.0))
    for seed in range(10):
        observation, _ = env.reset(seed=seed)
        state, goal = observation["state"], observation["goal"]
        assert state.shape == (6,) and goal.shape == (2,)
        np.testing.assert_allclose(state[:2], state[2:4])  # achieved goal = the point's xy, the head of the observation
        assert np.abs(state[:2] - start_cell).max() <= 0.25 + 1e-6, state
        assert np.abs(goal - goal_cell).max() <= 0.25 + 1e-6, goal
    observation, *_ = env.step(np.zeros(2))
    assert observation["state"].shape == (6,)
    training = ris.make_env("PointMaze_UMaze-v3", 0, False, 0, ris.ROBOTICS_THRESHOLD)()
    far = [np.abs(training.reset(seed=seed)[0]["state"][:2] - start_cell).max() > 0.5 for seed in range(20)]
    assert any(far)  # training resets are not confined to the test cells


# --- smoke runs, checkpoints, videos, Ctrl-C ---------------------------------------------------------------------------

TINY = [
    "--total-timesteps", "150", "--start-timesteps", "100", "--batch-size", "32", "--eval-frequency", "150",
    "--eval-episodes", "2", "--max-episode-steps", "50", "--buffer-size", "10000", "--hidden-dim", "32",
]  # fmt: skip
ENV_IDS = ["AntU", "AntFb", "AntMaze", "AntFg", "PointMaze_UMaze-v3", "AntMaze_UMaze-v5"]


def script_env(**extra: str) -> dict[str, str]:
    """The environment of a script run by hand: no MUJOCO_GL and no DISPLAY (a headless machine), one thread."""
    base = {key: value for key, value in os.environ.items() if key not in ("MUJOCO_GL", "DISPLAY", "PYOPENGL_PLATFORM")}
    return base | {"PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"} | extra


@pytest.mark.parametrize("groups", ["0", "16"])
@pytest.mark.parametrize("env_id", ENV_IDS)
def test_smoke_run(run_script, tmp_path, env_id, groups):
    save = env_id == "AntU"
    flags = ["--env-id", env_id, "--groups", groups]
    result = run_script("dgrl_ris.py", *TINY, *flags, *(["--save-model"] if save else []))
    assert result.returncode == 0, result.stderr[-3000:]
    assert re.search(r"eval success +\d+% distance +[\d.]+", result.stdout), result.stdout
    assert re.search(r"done: 150 steps, 51 updates, last eval success \d+%", result.stdout), result.stdout
    events = next(tmp_path.glob("runs/*/events.out.tfevents.*")).read_bytes()
    assert b"eval/success_rate" in events and b"charts/episodic_length" in events
    if save:
        checkpoint = next(tmp_path.glob("runs/*/dgrl_ris.cleanrl_model"))
        saved = torch.load(checkpoint, weights_only=True)
        assert saved["script"] == "dgrl_ris.py" and saved["format"] == ris.CHECKPOINT_FORMAT
        assert saved["args"]["groups"] == int(groups) and saved["args"]["goal_threshold"] == 0.5  # the resolved radius
        assert set(saved) == {"script", "format", "args", "actor", "critic", "high", "goal_encoder"}
        assert (saved["goal_encoder"] is None) == (groups == "0")
        if groups != "0":
            assert "vq.codebook" in saved["goal_encoder"] and "vq.ema_count" in saved["goal_encoder"]
        reloaded = run_script(
            "dgrl_ris.py", *flags, "--hidden-dim", "32", "--eval-episodes", "2", "--max-episode-steps", "50",
            "--checkpoint", str(checkpoint),
        )  # fmt: skip
        assert reloaded.returncode == 0, reloaded.stderr[-3000:]
        assert re.search(r"2 test episodes: success \d+%, final distance [\d.]+", reloaded.stdout), reloaded.stdout
        other = ["--env-id", "AntU", "--groups", "8" if groups == "16" else "0", "--hidden-dim", "16", "--vq-beta", "0.5"]
        refused = run_script("dgrl_ris.py", *other, "--max-episode-steps", "60", "--checkpoint", str(checkpoint))
        named = (
            "--max-episode-steps 50 --groups 16 --hidden-dim 32"
            if groups == "16"
            else "--max-episode-steps 50 --hidden-dim 32"
        )
        assert_clean_refusal(refused, f"was saved with other settings: pass {named}")


def test_capture_video_writes_an_mp4_without_mujoco_gl_or_display(tmp_path):
    """Headless rendering needs MUJOCO_GL=egl (or osmesa); the script sets egl when no display is set, so a plain run on
    a server records its video instead of crashing at the first evaluation."""
    flags = ["--env-id", "AntFb", "--groups", "0", "--total-timesteps", "48", "--start-timesteps", "40"]
    flags += ["--batch-size", "8", "--buffer-size", "1000", "--eval-frequency", "48", "--eval-episodes", "1"]
    flags += ["--max-episode-steps", "8", "--hidden-dim", "32", "--capture-video"]
    env = script_env()
    assert "MUJOCO_GL" not in env and "DISPLAY" not in env
    result = subprocess.run(
        [sys.executable, str(ROOT / "dgrl_ris.py"), *flags],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=HANG_TIMEOUT,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    videos = list(tmp_path.glob("videos/*/eval_*.mp4"))
    assert len(videos) == 1 and os.path.getsize(videos[0]) > 1000


# --- stopping and resuming (--resume) --------------------------------------------------------------------------------

SMALL_DGRL = ["--env-id", "AntU", "--groups", "4", "--embed-dim", "8", "--n-embed", "8", "--hidden-dim", "16"]
SMALL_DGRL += ["--batch-size", "16", "--n-subgoals", "2", "--eval-episodes", "2", "--buffer-size", "5000", "--seed", "2"]


def stopped_at(output: str) -> tuple[int, int]:
    """(steps, updates) of the `stopped:` line of a run's output."""
    steps, updates = re.search(r"stopped: (\d+) steps, (\d+) updates", output).groups()
    return int(steps), int(updates)


def test_resume_from_the_random_warm_up_equals_a_straight_run(resume_check):
    """SIGTERM right after the first evaluation (step 150 of a 1000-step random warm-up, two envs), then --resume: every
    scalar and the final checkpoint equal those of a run straight through (the random actions, the envs mid-episode and
    the evaluation stream continue)."""
    flags = [*SMALL_DGRL, "--total-timesteps", "1150", "--start-timesteps", "1000", "--eval-frequency", "150"]
    flags += ["--num-envs", "2"]
    output = resume_check("dgrl_ris.py", [*flags, "--max-episode-steps", "70", "--save-model"], r"^step +150/1150 ")
    steps, updates = stopped_at(output)
    assert 150 <= steps < 1000 and updates == 0, output


def test_resume_mid_episode_after_updates_started_equals_a_straight_run(resume_check):
    """SIGTERM at step 650 (100-step episodes: halfway through one; 250 updates done), then --resume: every scalar,
    the losses logged at update 1000 included, and the final checkpoint (networks, codebook) equal a straight run's.
    --checkpoint-every-steps 200 also writes resume files during both runs: writing one changes nothing."""
    flags = [*SMALL_DGRL, "--total-timesteps", "1500", "--start-timesteps", "400", "--eval-frequency", "325"]
    flags += ["--max-episode-steps", "100", "--checkpoint-every-steps", "200", "--save-model"]
    output = resume_check("dgrl_ris.py", flags, r"^step +650/1500 ")
    steps, updates = stopped_at(output)
    assert 650 <= steps < 1400 and updates > 0, output  # stopped before the loss log, which the resumed run writes


def test_resume_of_a_gymnasium_robotics_maze_equals_a_straight_run(resume_check):
    """PointMaze (RIS, --groups 0): the robotics env's own state (MuJoCo data, goal, generators, time limit) continues."""
    flags = ["--env-id", "PointMaze_UMaze-v3", "--groups", "0", "--hidden-dim", "16", "--batch-size", "16"]
    flags += ["--total-timesteps", "500", "--start-timesteps", "200", "--eval-frequency", "150", "--eval-episodes", "2"]
    output = resume_check("dgrl_ris.py", [*flags, "--max-episode-steps", "70", "--save-model"], r"^step +300/500 ")
    steps, updates = stopped_at(output)
    assert 300 <= steps < 500 and updates > 0, output


@pytest.mark.parametrize("env_id", ["AntU", "PointMaze_UMaze-v3", "AntMaze_UMaze-v5"])
def test_env_state_restores_an_env_mid_episode_exactly(env_id, tmp_path):
    """A vector env restored from env_state (through torch.save, as in resume.pt) into a fresh one that has stepped
    elsewhere then steps exactly as the original: observations, goals, ends of episodes, episode statistics, resets."""
    original, restored = (ris.make_vector_env(env_id, 2, 3, False, 30, 0.5) for _ in range(2))
    original.reset(seed=3)
    restored.reset(seed=4)
    for _ in range(45):
        original.step(original.action_space.sample())
        restored.step(restored.action_space.sample())
    torch.save(
        {"envs": [ris.env_state(env) for env in original.envs], "actions": original.action_space.np_random},
        tmp_path / "state.pt",
    )
    saved = torch.load(tmp_path / "state.pt", weights_only=False)
    for env, state in zip(restored.envs, saved["envs"], strict=True):
        ris.restore_env(env, state)
    restored.action_space._np_random = saved["actions"]
    ends = 0
    for _ in range(40):
        expected, got = original.step(original.action_space.sample()), restored.step(restored.action_space.sample())
        for key in ("state", "goal"):
            assert np.array_equal(expected[0][key], got[0][key])
        assert np.array_equal(expected[2], got[2]) and np.array_equal(expected[3], got[3])
        if "final_info" in expected[4]:
            ends += 1
            for key in ("r", "l"):
                assert np.array_equal(expected[4]["final_info"]["episode"][key], got[4]["final_info"]["episode"][key])
    assert ends > 0  # the 30-step time limit (15 steps left) and a reset were crossed


def test_a_finished_run_resumes_to_its_end_and_its_resume_file_holds_the_filled_replay(run_script, tmp_path):
    """Under the same flags (--checkpoint-every may change) a finished run says so and adds nothing. resume.pt holds only
    the replay's filled rows. (Changed flags that must match are refused for every script: tests/test_skeleton.py.)"""
    flags = ["--env-id", "AntU", "--groups", "0", "--hidden-dim", "16", "--total-timesteps", "150"]
    flags += ["--start-timesteps", "100", "--batch-size", "16", "--eval-frequency", "150", "--eval-episodes", "1"]
    flags += ["--max-episode-steps", "50", "--buffer-size", "1000"]
    first = run_script("dgrl_ris.py", *flags)
    assert first.returncode == 0, first.stderr[-3000:]
    (run_dir,) = (tmp_path / "runs").iterdir()
    saved = torch.load(run_dir / "resume.pt", weights_only=False)
    assert saved["replay"]["size"] == 150 and saved["replay"]["states"].shape == (150, 31)
    assert saved["loop"]["step"] == 150 and saved["agent"]["critic_optimizer"]["state"]
    resume = ["--resume", f"runs/{run_dir.name}"]
    again = run_script("dgrl_ris.py", *flags, *resume, "--checkpoint-every", "0")
    assert again.returncode == 0, again.stderr[-3000:]
    assert f"resumed at step 150 (51 updates) from runs/{run_dir.name}/resume.pt" in again.stdout
    assert re.search(r"done: 150 steps, 51 updates", again.stdout), again.stdout


# --- flags ------------------------------------------------------------------------------------------------------------


def assert_clean_refusal(result: subprocess.CompletedProcess, *messages: str) -> None:
    """Exit status 2, every message in stderr, no traceback."""
    assert result.returncode == 2, result.stdout[-2000:] + result.stderr[-2000:]
    assert "Traceback" not in result.stderr, result.stderr[-3000:]
    for message in messages:
        assert message in result.stderr, (message, result.stderr[-3000:])


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"env_id": "AntX"}, r"--env-id 'AntX' is unknown: use one of AntU, AntFb, AntMaze, AntFg"),
        ({"env_id": "PointMaze_Nope-v3"}, r"--env-id 'PointMaze_Nope-v3' is not a registered .*PointMaze_UMaze-v3"),
        ({"groups": 5}, r"--groups must be 0 \(RIS\) or divide --embed-dim 64: one of \[1, 2, 4, 8, 16, 32, 64\]; got 5"),
        ({"her_goal_frac": 0.8, "her_random_frac": 0.4}, r"--her-goal-frac \(0.8\) and --her-random-frac \(0.4\)"),
        ({"batch_size": 64, "buffer_size": 32}, r"--buffer-size \(32\) must be >= --batch-size \(64\)"),
        ({"gamma": 0.0}, r"--gamma must be in \(0, 1\]; got 0.0"),
        ({"gamma": 1.5}, r"--gamma must be in \(0, 1\]; got 1.5"),
        ({"tau": 2.0}, r"--tau must be in \(0, 1\]; got 2.0"),
        ({"tau": 0.0}, r"--tau must be in \(0, 1\]; got 0.0"),
        ({"goal_threshold": -0.5}, r"--goal-threshold must be >= 0; got -0.5"),
        ({"vq_decay": 1.5}, r"--vq-decay must be in \[0, 1\); got 1.5"),
        ({"vq_decay": 1.0}, r"--vq-decay must be in \[0, 1\); got 1.0"),
        ({"vq_beta": -1.0}, r"--vq-beta must be >= 0; got -1.0"),
        ({"q_lr": -1.0}, r"--q-lr must be > 0; got -1.0"),
        ({"seed": -1}, r"--seed must be in \[0, 2\*\*64\)"),
        ({"alpha": math.nan}, r"--alpha must be a finite number; got nan"),
        ({"tau": math.inf}, r"--tau must be a finite number; got inf"),
        ({"total_timesteps": 10_000}, r"--total-timesteps \(10000\) must exceed --start-timesteps \(10000\)"),
        ({"total_timesteps": 1000, "start_timesteps": 0, "batch_size": 2048}, r"must exceed --start-timesteps \(0\) and "),
        ({"vq_loss_reduction": "max"}, r"--vq-loss-reduction must be mean \(the paper's text\) or sum .*; got 'max'"),
    ],
)
def test_validate_names_the_bad_flag(overrides, message, capsys):
    with pytest.raises(SystemExit) as error:
        ris.validate(ris.Args(**overrides))
    assert error.value.code == 2
    assert re.search(message, capsys.readouterr().err)
    ris.validate(ris.Args(env_id="AntU", groups=16))  # the defaults pass
    ris.validate(ris.Args(env_id="AntU", groups=16, vq_loss_reduction="sum"))


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        # EpisodeReplay writes whole episodes into one contiguous slice: an episode longer than the buffer crashed with a
        # torch shape error in add_episode at the end of the first episode, after the envs and networks were built.
        ({"buffer_size": 64, "batch_size": 32}, r"--buffer-size \(64\) must hold one whole episode: >= 100"),
        # 100 transitions hold one whole 60-step episode: the replay never reached a batch of 100 (zero updates, silently).
        ({"buffer_size": 100, "batch_size": 100, "max_episode_steps": 60}, r"holds 1 whole 60-step episodes, fewer "),
        # No episode ends before step 100 unless by luck, so the replay stays empty: zero updates, silently.
        ({"total_timesteps": 99, "start_timesteps": 10, "batch_size": 16}, r"--total-timesteps \(99\) must exceed 115"),
        ({"total_timesteps": 400, "start_timesteps": 10, "batch_size": 16, "num_envs": 4}, r"exceed 412: .*--num-envs 4"),
    ],
)
def test_validate_refuses_runs_whose_replay_never_holds_a_batch(overrides, message, capsys):
    with pytest.raises(SystemExit) as error:
        ris.validate(ris.Args(**{"env_id": "AntU", "max_episode_steps": 100, **overrides}))
    assert error.value.code == 2
    assert re.search(message, capsys.readouterr().err)
    ris.validate(ris.Args(env_id="AntU", max_episode_steps=100, buffer_size=100, batch_size=32))  # one episode fits
    ris.validate(ris.Args(env_id="AntU", total_timesteps=116, start_timesteps=10, batch_size=16, max_episode_steps=100))


def test_bad_flags_fail_before_any_work(run_script, tmp_path):
    """Every bad flag is reported at once, by name, before any env, network or log directory is made: exit status 2."""
    flags = ["--env-id", "AntX", "--groups", "5", "--her-goal-frac", "0.8", "--her-random-frac", "0.4", "--gamma", "1.5"]
    flags += ["--tau", "0", "--vq-decay", "1.5", "--vq-beta", "-1", "--goal-threshold", "-1", "--seed", "-1"]
    flags += ["--q-lr", "-1", "--alpha", "nan", "--total-timesteps", "100", "--start-timesteps", "100"]
    result = run_script("dgrl_ris.py", *flags)
    assert_clean_refusal(
        result, "--env-id 'AntX' is unknown: use one of AntU, AntFb, AntMaze, AntFg", "--groups must be 0 (RIS)",
        "--her-goal-frac (0.8) and --her-random-frac (0.4)", "--gamma must be in (0, 1]; got 1.5",
        "--tau must be in (0, 1]; got 0.0", "--vq-decay must be in [0, 1); got 1.5", "--vq-beta must be >= 0; got -1.0",
        "--goal-threshold must be >= 0; got -1.0", "--seed must be in [0, 2**64)", "--q-lr must be > 0; got -1.0",
        "--alpha must be a finite number; got nan", "--total-timesteps (100) must exceed --start-timesteps (100)",
    )  # fmt: skip
    assert "state 31-d" not in result.stdout and not (tmp_path / "runs").exists()


def test_a_replay_too_large_for_memory_is_refused_before_the_logs(run_script, tmp_path):
    flags = ["--env-id", "AntU", "--total-timesteps", "200", "--start-timesteps", "100", "--batch-size", "16"]
    result = run_script("dgrl_ris.py", *flags, "--max-episode-steps", "50", "--buffer-size", str(10**11))
    assert_clean_refusal(result, f"--buffer-size {10**11}: the replay does not fit in cpu memory")
    assert not (tmp_path / "runs").exists()


def test_args_docstrings_are_one_line():
    """tyro wraps --help text itself; a line break inside a field's docstring breaks its wrapping."""
    tree = ast.parse((ROOT / "dgrl_ris.py").read_text())
    args_class = next(node for node in tree.body if isinstance(node, ast.ClassDef) and node.name == "Args")
    docstrings = [
        node.value.value
        for node in args_class.body
        if isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant) and isinstance(node.value.value, str)
    ]
    assert len(docstrings) == len([node for node in args_class.body if isinstance(node, ast.AnnAssign)])
    assert [text for text in docstrings if "\n" in text] == []


@pytest.mark.parametrize("groups", [0, 4])
def test_fast_update_equals_eager_and_is_free_of_host_syncs(groups):
    """--fast compile: ris_update compiled (backward passes, Adam steps, Polyak, codebook EMA with dead-code
    restarts) and equal to eager."""
    agent, replay = tiny_agent(groups)
    if groups:
        agent.goal_encoder.vq.dead_code_steps = 3
    batches = [replay.sample(BATCH, GOAL_DIM_UPDATE, 0.45, 0.2, 0.4) for _ in range(31)]

    settings = ris.Args(**RIS_SETTINGS)

    def call(function, state, i):
        return function(state, batches[i], settings)

    optimizers = lambda state: [state.critic_optimizer, state.high_optimizer, state.actor_optimizer]  # noqa: E731
    check_fast_update(ris, ris.ris_update, agent, call, optimizers)
