"""dgrl_ris_sawyer.py: the Sawyer push-and-reach environment (scene layout, training and test reset distributions, the
success test and its termination, goal images and exact state restoration after rendering one, images that show the
hand and the puck, mocap xy control, pushing, walls) and a smoke run of the script."""

import os

os.environ.setdefault("MUJOCO_GL", "egl")  # in-process rendering on a headless machine; read when mujoco is imported

import re

import mujoco
import numpy as np
import pytest

import dgrl_ris_sawyer as sawyer

LOW, HIGH = sawyer.ARENA_LOW, sawyer.ARENA_HIGH
CENTRE = np.array((0.0, 0.6, 0.1, 0.6))  # hand in the middle, puck 0.1 to its right


@pytest.fixture
def env():
    env = sawyer.SawyerPushAndReachEnv()
    yield env
    env.close()


def in_arena(xy: np.ndarray, tolerance: float = 1e-6) -> bool:
    return bool(np.all(xy >= LOW - tolerance) and np.all(xy <= HIGH + tolerance))


def red_and_blue(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel masks of the hand (red) and of the puck (blue)."""
    r, g, b = (image[..., i].astype(int) for i in range(3))
    return (r > 100) & (g < 60) & (b < 60), (b > 150) & (r < 100)


def centroid(mask: np.ndarray) -> np.ndarray:
    rows, columns = np.nonzero(mask)
    return np.array((rows.mean(), columns.mean()))


def test_scene_layout():
    model = mujoco.MjModel.from_xml_string(sawyer.sawyer_xml())
    assert [model.joint(j).name for j in range(model.njnt)] == ["hand_x", "hand_y", "puck_x", "puck_y"]
    assert all(model.jnt_type[j] == mujoco.mjtJoint.mjJNT_SLIDE for j in range(model.njnt))
    assert model.opt.timestep == pytest.approx(0.002) and sawyer.FRAME_SKIP == 50
    assert model.nmocap == 1 and model.body("hand").pos.tolist() == pytest.approx([0, 0, 0.06])
    np.testing.assert_allclose(model.geom("puck").size[:2], (0.04, 0.015))
    assert model.geom("hand").size[0] == pytest.approx(0.015)
    # MuJoCo 3's weld eq_data: anchor (3), relative position (3), relative quaternion (4), torque scale (1)
    np.testing.assert_allclose(model.eq_data[0], (0, 0, 0, 0, 0, 0, 1, 0, 0, 0, 1))
    # the walls' inner faces stop the puck's centre exactly at the arena's bounds
    faces = {
        "left": model.geom("wall_left").pos[0] + model.geom("wall_left").size[0],
        "right": model.geom("wall_right").pos[0] - model.geom("wall_right").size[0],
        "near": model.geom("wall_near").pos[1] + model.geom("wall_near").size[1],
        "far": model.geom("wall_far").pos[1] - model.geom("wall_far").size[1],
    }
    assert faces == pytest.approx({"left": -0.24, "right": 0.24, "near": 0.46, "far": 0.74})


def test_training_resets_follow_the_distribution(env):
    starts, goals = [], []
    for seed in range(150):
        observation, info = env.reset(seed=seed)
        starts.append(observation["state"])
        goals.append(observation["goal"])
        assert set(info) == {"success", "hand_distance", "puck_distance"}
    starts, goals = np.array(starts), np.array(goals)
    for xy in (starts[:, :2], starts[:, 2:], goals[:, :2], goals[:, 2:]):
        assert in_arena(xy)
    ring = np.linalg.norm(starts[:, 2:] - starts[:, :2], axis=1)
    assert ring.min() >= 0.055 - 1e-6 and ring.max() <= 0.075 + 1e-6
    assert np.linalg.norm(goals[:, 2:] - goals[:, :2], axis=1).min() > sawyer.GOAL_CLEARANCE - 1e-6
    # spread over the arena, not a few fixed points
    assert starts[:, 0].min() < -0.15 and starts[:, 0].max() > 0.15 and goals[:, 3].min() < 0.53 and goals[:, 3].max() > 0.67
    offsets = starts[:, 2:] - starts[:, :2]
    directions = np.arctan2(offsets[:, 1], offsets[:, 0])
    assert np.histogram(directions, bins=4, range=(-np.pi, np.pi))[0].min() > 10  # the puck on every side of the hand
    again, _ = env.reset(seed=7)
    np.testing.assert_array_equal(again["state"], starts[7])


def test_test_resets_cross_the_arena():
    env = sawyer.SawyerPushAndReachEnv(test=True)
    for seed in range(40):
        observation, _ = env.reset(seed=seed)
        state, goal = observation["state"], observation["goal"]
        for xy, key in (
            (state[:2], "hand_start"),
            (state[2:], "puck_start"),
            (goal[:2], "hand_goal"),
            (goal[2:], "puck_goal"),
        ):
            low, high = sawyer.TEST_BOXES[key]
            assert np.all(xy >= np.array(low) - 1e-6) and np.all(xy <= np.array(high) + 1e-6), (seed, key, xy)
    assert sawyer.TEST_BOXES["hand_start"] == ((0.15, 0.65), (0.20, 0.70))
    assert sawyer.TEST_BOXES["puck_start"] == ((-0.15, 0.55), (-0.10, 0.60))
    assert sawyer.TEST_BOXES["hand_goal"] == ((-0.20, 0.50), (-0.15, 0.55))
    assert sawyer.TEST_BOXES["puck_goal"] == ((0.15, 0.65), (0.20, 0.70))
    env.close()


def test_reaching_the_goal_state_is_a_success(env):
    observation, _ = env.reset(seed=0)
    env.set_state4(observation["goal"])
    _, reward, terminated, truncated, info = env.step(np.zeros(2))
    assert info["success"] and terminated and not truncated and reward == -1.0


@pytest.mark.parametrize("offset, success", [((0, 0, 0, 0), True), ((0.04, 0, 0, 0), True), ((0.06, 0, 0, 0), False),
                                             ((0, 0, 0, -0.06), False), ((0, 0.035, 0.035, 0), True)])  # fmt: skip
def test_success_is_both_objects_within_five_centimetres(env, offset, success):
    env.reset(seed=0)
    env.goal = np.array((-0.1, 0.55, 0.1, 0.65), dtype=np.float32)
    env.set_state4(env.goal + np.array(offset))
    _, reward, terminated, truncated, info = env.step(np.zeros(2))
    assert reward == -1.0 and not truncated
    assert info["success"] is success and terminated is success
    assert info["hand_distance"] == pytest.approx(np.linalg.norm(offset[:2]), abs=1e-3)
    assert info["puck_distance"] == pytest.approx(np.linalg.norm(offset[2:]), abs=1e-3)


def test_episodes_truncate_after_100_steps(env):
    env.reset(seed=1)
    far = np.array((-0.2, 0.5, 0.2, 0.7), dtype=np.float32)
    env.goal = far  # unreachable with zero actions from the reset state
    for step in range(1, 101):
        _, reward, terminated, truncated, _ = env.step(np.zeros(2))
        assert reward == -1.0 and not terminated
        assert truncated == (step == 100)


def test_goal_image_is_the_goal_configuration_rendered(env):
    observation, _ = env.reset(seed=3)
    assert observation["goal_image"].shape == (84, 84, 3) and observation["goal_image"].dtype == np.uint8
    assert not np.array_equal(observation["goal_image"], observation["image"])
    np.testing.assert_array_equal(env.render_state(observation["goal"]), observation["goal_image"])
    env.set_state4(observation["goal"])
    np.testing.assert_array_equal(env.render(), observation["goal_image"])


def test_rendering_a_state_leaves_the_simulation_untouched(env):
    def rollout(render_midway: bool):
        env.reset(seed=5)
        for _ in range(4):
            env.step(np.array((0.7, -0.4)))
        before = {key: np.copy(getattr(env.data, key)) for key in ("qpos", "qvel", "act", "mocap_pos", "time")}
        if render_midway:
            env.render_state(np.array((0.1, 0.6, -0.1, 0.55)))
            for key, value in before.items():
                np.testing.assert_array_equal(getattr(env.data, key), value, err_msg=key)
        return [env.step(np.array((0.3, 0.9)))[0]["state"] for _ in range(5)]

    np.testing.assert_array_equal(rollout(True), rollout(False))  # bit-identical continuation


def test_images_show_hand_and_puck_everywhere_in_the_arena(env):
    env.reset(seed=0)
    blue_counts = []
    for hand, puck in (
        ((0.0, 0.6), (-0.2, 0.5)),
        ((0.0, 0.6), (0.2, 0.7)),
        ((-0.2, 0.7), (0.2, 0.5)),
        ((0.2, 0.5), (-0.2, 0.7)),
    ):
        red, blue = red_and_blue(env.render_state(np.array(hand + puck)))
        assert red.sum() >= 6 and blue.sum() > 0
        blue_counts.append(blue.sum())
        # image columns grow with x, rows with -y
        assert (centroid(red)[1] < centroid(blue)[1]) == (hand[0] < puck[0])
        assert (centroid(red)[0] > centroid(blue)[0]) == (hand[1] < puck[1])
    assert min(blue_counts) > 0.8 * max(blue_counts)  # the puck is never cut off in a corner


def test_hand_follows_actions_and_stays_at_its_height_and_in_bounds(env):
    env.reset(seed=0)
    env.set_state4(np.array((-0.1, 0.6, 0.15, 0.52)))
    previous = env.data.qpos[:2].copy()
    for step in range(6):
        state = env.step(np.array((1.0, -0.5)))[0]["state"]
        if step > 0:  # after the first step's lag the hand moves by action * action_scale per step
            np.testing.assert_allclose(state[:2] - previous, (0.02, -0.01), atol=2e-3)
        previous = state[:2].astype(np.float64)
    for _ in range(30):  # push into the near-left corner: the hand stops at the bounds
        state = env.step(np.array((-1.0, -1.0)))[0]["state"]
        assert in_arena(state[:2], tolerance=1e-3)
        assert env.data.body("hand").xpos[2] == pytest.approx(0.06, abs=1e-6)
    np.testing.assert_allclose(state[:2], LOW, atol=2e-3)
    # the target was clipped at the bounds too: the hand comes straight back
    np.testing.assert_allclose(env.step(np.array((1.0, 1.0)))[0]["state"][:2] - state[:2], 0.02, atol=3e-3)
    slow = sawyer.SawyerPushAndReachEnv(action_scale=0.01)
    slow.reset(seed=0)
    slow.set_state4(CENTRE)
    for _ in range(5):
        state = slow.step(np.array((-1.0, 0.0)))[0]["state"]
    assert state[0] == pytest.approx(-0.05, abs=2e-3)
    slow.close()


def test_pushing_moves_the_puck_and_the_walls_hold_it(env):
    env.reset(seed=0)
    env.set_state4(CENTRE)
    state = env.step(np.zeros(2))[0]["state"]
    np.testing.assert_allclose(state[2:], CENTRE[2:], atol=1e-6)  # the puck rests untouched
    for _ in range(5):
        state = env.step(np.array((1.0, 0.0)))[0]["state"]
    assert state[2] > 0.13 and abs(state[3] - 0.6) < 0.01  # pushed right, in line
    resting = env.step(np.array((-1.0, 0.0)))[0]["state"]
    for _ in range(3):  # the puck stops once the hand moves away
        state = env.step(np.array((-1.0, 0.0)))[0]["state"]
    assert abs(state[2] - resting[2]) < 2e-3
    rng = np.random.default_rng(0)
    for _ in range(60):  # drive the hand at the puck and on into the walls and corners
        aim = state[2:] - state[:2] + rng.normal(0.0, 0.05, 2)
        state = env.step(np.clip(aim * 20, -1, 1))[0]["state"]
        assert in_arena(state[2:], tolerance=2e-3) and in_arena(state[:2], tolerance=1e-3)  # 2 mm: contact softness
        assert np.linalg.norm(state[:2] - state[2:]) > 0.05  # the hand does not sink into the puck


def test_observation_layout(env):
    observation, _ = env.reset(seed=2)
    assert env.observation_space.contains(observation)
    assert observation["state"].dtype == np.float32 and observation["goal"].dtype == np.float32
    np.testing.assert_array_equal(observation["image"], env.render())
    big = sawyer.SawyerPushAndReachEnv(image_size=64)
    assert big.reset(seed=2)[0]["image"].shape == (64, 64, 3)
    big.close()


def test_smoke_run_of_the_script(run_script):
    result = run_script("dgrl_ris_sawyer.py", "--steps", "120", "--seed", "3", env={"MUJOCO_GL": "egl"})
    assert result.returncode == 0, result.stderr
    assert "agent is not written yet" in result.stdout
    assert re.search(r"120 steps \(1 episodes, 0 successes\) at [\d,]+ frames/s", result.stdout), result.stdout  # reset at 100
    test = run_script("dgrl_ris_sawyer.py", "--steps", "20", "--test", env={"MUJOCO_GL": "egl"})
    assert test.returncode == 0 and "20 steps (0 episodes" in test.stdout, test.stderr
