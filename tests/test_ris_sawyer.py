"""dgrl_ris_sawyer.py: the Sawyer push-and-reach environment (scene layout, training and test reset distributions, the
success test and its termination, goal images and exact state restoration after rendering one, images that show the
hand and the puck, mocap xy control, pushing, walls); the agent (random-translate augmentation, the image encoder, the
DRIML loss, the image replay's relabelling and rewards, make_agent, one RIS update with and without DGRL, acting,
evaluation); flag validation (a clean exit 2 naming the flag); smoke runs of the script in both modes, headless without
MUJOCO_GL, with a checkpoint evaluated, refused with other network flags, a video written, and a Ctrl-C mid-run;
stopping and resuming (env state and cut-short evaluation round trips, runs stopped by SIGTERM in the warm-up and
mid-episode that resume to the scalars and checkpoint of a run straight through, changed flags refused)."""

import copy
import math
import re
import signal
import subprocess
from pathlib import Path

import mujoco
import numpy as np
import pytest
import torch
from conftest import record_outputs_with_grad
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

import dgrl_ris_sawyer as sawyer
from tests.conftest import check_fast_update
from vq import VectorQuantizerEMA

ROOT = Path(__file__).resolve().parents[1]
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


def test_reached_is_the_envs_success_test(env):
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    states = rng.uniform((-0.2, 0.5, -0.2, 0.5), (0.2, 0.7, 0.2, 0.7), (200, 4)).astype(np.float32)
    goals = (states + rng.normal(0, 0.04, (200, 4))).astype(np.float32)
    expected = []
    for state, goal in zip(states, goals, strict=True):
        env.goal = goal
        expected.append(env._info(state)["success"])
    assert 20 < sum(expected) < 180
    np.testing.assert_array_equal(sawyer.reached(states, goals), expected)


# --- augmentation -----------------------------------------------------------------------------------------------------


def test_translate_shapes_and_uint8_to_float():
    images = torch.randint(0, 256, (5, 84, 84, 3), dtype=torch.uint8)
    images[0, 0, 0] = 255
    out = sawyer.translate(images, torch.zeros(5, 2, dtype=torch.long))
    assert out.shape == (5, 3, 84, 84) and out.dtype == torch.float32
    torch.testing.assert_close(out, images.permute(0, 3, 1, 2).float() / 255, rtol=0, atol=1e-7)  # no shift: identity
    assert out[0, :, 0, 0].tolist() == [1.0, 1.0, 1.0]
    augmented = sawyer.random_translate(images, 8)
    assert augmented.shape == (5, 3, 84, 84) and augmented.min() >= 0 and augmented.max() <= 1
    assert not torch.equal(augmented, out)


def test_a_shift_moves_the_content_by_its_offset_and_fills_the_border_with_zeros_as_ris():
    image = np.zeros((84, 84, 3), np.uint8)
    image[..., 0] = np.arange(84)[:, None]  # rows numbered in red, columns in green
    image[..., 1] = np.arange(84)[None, :]
    image[40:43, 30:33, 2] = 200  # a blue square
    shifts = torch.tensor([[3, -5], [-8, 8], [0, 0]])
    out = (sawyer.translate(torch.as_tensor(image).expand(3, -1, -1, -1), shifts) * 255).round().to(torch.uint8).numpy()
    for sample, (dy, dx) in enumerate(shifts.tolist()):
        blue = np.argwhere(out[sample, 2] == 200)
        assert blue.min(0).tolist() == [40 + dy, 30 + dx] and blue.max(0).tolist() == [42 + dy, 32 + dx]
        # RIS's augmentation: pad 8 with zeros (F.pad's default), crop at (8 - dy, 8 - dx): the same picture
        padded = np.pad(image, ((8, 8), (8, 8), (0, 0)), mode="constant")
        crop = padded[8 - dy : 8 - dy + 84, 8 - dx : 8 - dx + 84].transpose(2, 0, 1)
        np.testing.assert_array_equal(out[sample], crop)
    assert (out[0, :, :3] == 0).all() and (out[0, :, :, -5:] == 0).all()  # the uncovered border is black
    assert (out[0, 1, 3:, :-5] == np.arange(5, 84)).all()  # column j shows column j + 5 of the image


def test_random_translate_gives_each_sample_its_own_shift():
    image = torch.zeros(400, 84, 84, 3, dtype=torch.uint8)
    image[:, 42, 42] = 255  # one white pixel: its new place reads off the shift
    out = sawyer.random_translate(image, 8)
    where = (out[:, 0] == 1).flatten(1).float().argmax(1)
    shifts = torch.stack((where // 84 - 42, where % 84 - 42), 1)
    assert (out[:, 0] == 1).flatten(1).sum(1).eq(1).all()
    assert shifts.min() == -8 and shifts.max() == 8  # pad 8: offsets from -8 to 8, both ends reached
    assert (shifts[:, 0] == -8).any() and (shifts[:, 1] == 8).any()
    assert len({tuple(shift) for shift in shifts.tolist()}) > 150  # 17 x 17 offsets, drawn per sample
    assert (shifts[:, 0] != shifts[:, 1]).float().mean() > 0.8  # rows and columns drawn independently


# --- networks and the DRIML loss --------------------------------------------------------------------------------------


def test_encoder_shapes_and_initialisation():
    encoder = sawyer.ImageEncoder(16)
    images = torch.rand(5, 3, 84, 84)
    assert encoder.conv_map(images).shape == (5, 32, 7, 7) and encoder(images).shape == (5, 16)
    torch.testing.assert_close(encoder(images), encoder.head(encoder.conv_map(images)))
    convs = [m for m in encoder.modules() if isinstance(m, torch.nn.Conv2d)]
    assert [(c.in_channels, c.out_channels, c.kernel_size, c.stride) for c in convs] == [
        (3, 32, (3, 3), (2, 2)), (32, 32, (3, 3), (2, 2)), (32, 32, (3, 3), (2, 2)), (32, 32, (3, 3), (1, 1)),
    ]  # fmt: skip
    gain = math.sqrt(2)
    for conv in convs:  # delta-orthogonal: an orthogonal matrix at the kernel's centre, zeros elsewhere
        centre = conv.weight[:, :, 1, 1].detach()
        assert conv.weight.detach().abs().sum().item() == pytest.approx(centre.abs().sum().item())
        torch.testing.assert_close(centre.T @ centre, gain**2 * torch.eye(conv.in_channels), atol=1e-4, rtol=0)
        assert (conv.bias == 0).all()
    weight = encoder.linear.weight.detach()
    assert weight.shape == (16, 1568) and (encoder.linear.bias == 0).all()
    torch.testing.assert_close(weight @ weight.T, torch.eye(16), atol=1e-4, rtol=0)


def test_infonce_is_log_batch_for_constant_features_and_lower_when_pairs_align():
    batch = 6
    constant = sawyer.local_global_infonce(torch.full((batch, 49, 8), 0.3), torch.full((batch, 8), -1.2))
    assert constant.item() == pytest.approx(math.log(batch), rel=1e-6)
    aligned_global = torch.eye(batch)
    aligned_local = 3 * torch.eye(batch).unsqueeze(1).expand(-1, 49, -1)  # every position points at its own sample
    aligned = sawyer.local_global_infonce(aligned_local, aligned_global)
    assert aligned.item() == pytest.approx(math.log(1 + (batch - 1) * math.exp(-3)), rel=1e-5)
    assert aligned < 0.15 * math.log(batch)
    shuffled = sawyer.local_global_infonce(aligned_local, aligned_global.roll(1, 0))  # matched with the wrong samples
    assert shuffled > math.log(batch)


def test_infonce_matches_a_hand_computation():
    local = torch.tensor([[[1.0, 0.0], [0.0, 1.0]], [[2.0, 1.0], [0.0, 0.0]]])  # (B=2, P=2, D=2)
    global_ = torch.tensor([[1.0, 2.0], [0.0, 1.0]])
    # scores (b, p) -> (own, other): (1, 0), (2, 1), (4, 1), (0, 0); loss = -own + log(exp(own) + exp(other))
    expected = (2 * math.log(1 + math.exp(-1)) + math.log(1 + math.exp(3)) + math.log(2)) / 4
    assert sawyer.local_global_infonce(local, global_).item() == pytest.approx(expected, rel=1e-6)


def test_driml_loss_pairs_each_conv_position_and_action_with_the_next_features():
    heads = sawyer.DrimlHeads(32, 2, 16, 8)
    conv_map, actions, next_features = torch.randn(4, 32, 7, 7, requires_grad=True), torch.randn(4, 2), torch.randn(4, 16)
    loss = sawyer.driml_loss(heads, conv_map, actions, next_features)
    # the same loss, one conv position at a time
    globals_ = heads.globl(next_features)
    per_position = []
    for i in range(7):
        for j in range(7):
            local = heads.local(torch.cat((conv_map[:, :, i, j], actions), 1))
            per_position.append(torch.nn.functional.cross_entropy(local @ globals_.T, torch.arange(4)))
    torch.testing.assert_close(loss, torch.stack(per_position).mean())
    loss.backward()
    assert conv_map.grad.abs().sum() > 0
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in heads.parameters())
    assert not torch.isclose(loss, sawyer.driml_loss(heads, conv_map, -actions, next_features))  # the action matters


def test_ris_losses_prior_kl_advantage_weights_subgoal_cost():
    u, mean, std = torch.randn(3, 2), torch.randn(3, 2), torch.rand(3, 2) + 0.5
    prior_mean, prior_std = torch.randn(4, 3, 2), torch.rand(4, 3, 2) + 0.5
    normal = torch.distributions.Normal
    prior = normal(prior_mean, prior_std).log_prob(u).sum(-1).exp().mean(0)
    expected = normal(mean, std).log_prob(u).sum(-1) - torch.log(prior + 1e-4)
    torch.testing.assert_close(sawyer.prior_kl(u, mean, std, prior_mean, prior_std, 1e-4), expected)
    weights = sawyer.advantage_weights(torch.full((3,), 5.0), torch.tensor([3.0, 7.0, 5.0]), 0.1)
    assert weights.sum().item() == pytest.approx(1.0) and weights.argmax() == 0 and weights[1] < weights[2]
    cost = sawyer.subgoal_cost(torch.tensor([-3.0, -150.0, 2.0]), torch.tensor([-5.0, -1.0, -0.5]))
    assert cost.tolist() == [5.0, 100.0, 0.5]  # the longer half, values clipped to [-100, 0]


# --- replay: relabelling and rewards ----------------------------------------------------------------------------------

STEP_X = 0.02  # the hand moves 0.02 along x per step in the labelled episodes: goals 2 steps away are reached, 3 are not


def labelled_episode(episode: int, length: int):
    """Images that name themselves: red = the episode, green = t for o_t and 255 for the goal. States: the hand moves
    STEP_X per step along x at a height set by the episode (episodes 0.1 apart), the puck stays; the goal is the hand 2
    steps past o_L. Actions are (episode, t)."""
    t = np.arange(length + 1)
    images = np.zeros((length + 1, 84, 84, 3), np.uint8)
    images[..., 0], images[..., 1] = episode, t[:, None, None]
    states = np.stack((-0.2 + STEP_X * t, np.full(length + 1, 0.1 * episode), np.zeros(length + 1), np.full(length + 1, 0.6)))
    goal_image = np.zeros((84, 84, 3), np.uint8)
    goal_image[..., 0], goal_image[..., 1] = episode, 255
    goal_state = np.array((-0.2 + STEP_X * (length + 2), 0.1 * episode, 0.0, 0.6), np.float32)
    actions = np.stack((np.full(length, episode), t[:-1]), 1).astype(np.float32)
    return images, states.T.astype(np.float32), actions, goal_image, goal_state


def decode(images: np.ndarray | torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """(episode, t or 255) of each image."""
    images = np.asarray(images)
    return images[:, 0, 0, 0].astype(int), images[:, 0, 0, 1].astype(int)


def test_relabelled_batches_hold_stored_rows_and_rewards_follow_the_success_test():
    replay = sawyer.ImageEpisodeReplay(1000, (84, 84, 3), 2)
    lengths = [12, 7, 20, 1, 15]
    for episode, length in enumerate(lengths):
        replay.add_episode(*labelled_episode(episode, length))
    assert replay.size == sum(lengths) + 2 * len(lengths)
    n = 1000
    batch = replay.sample(n, 0.2, 0.4, np.random.default_rng(0))
    assert all(isinstance(value, torch.Tensor) and value.device == replay.device for value in batch.values())
    assert batch["images"].shape == (4 * n, 84, 84, 3) and batch["images"].dtype == torch.uint8  # converted in the update
    batch = {key: value.numpy() for key, value in batch.items()}
    ep, t = decode(batch["images"][:n])
    next_ep, next_t = decode(batch["images"][n : 2 * n])
    goal_ep, goal_t = decode(batch["images"][2 * n : 3 * n])
    subgoal_ep, subgoal_t = decode(batch["images"][3 * n :])
    length_of = np.array(lengths)
    # s is a stored transition (never o_L or a goal), s' its successor; actions and states belong to the same rows.
    assert (t < length_of[ep]).all() and (next_ep == ep).all() and (next_t == t + 1).all()
    np.testing.assert_array_equal(batch["actions"], np.stack((ep, t), 1))
    np.testing.assert_allclose(batch["states"][:, 0], -0.2 + STEP_X * t, atol=1e-6)
    np.testing.assert_allclose(batch["next_states"][:, 0], -0.2 + STEP_X * (t + 1), atol=1e-6)
    # Every goal's state is the state stored with its image.
    is_goal_row = goal_t == 255
    x = np.where(is_goal_row, -0.2 + STEP_X * (length_of[goal_ep] + 2), -0.2 + STEP_X * goal_t)
    np.testing.assert_allclose(batch["goal_states"][:, 0], x, atol=1e-6)
    np.testing.assert_allclose(batch["goal_states"][:, 1], 0.1 * goal_ep, atol=1e-6)
    # First 200: the rollout goal; next 400: random stored transitions' s; last 400: s'_t..s'_end of the same episode.
    assert is_goal_row[:200].all() and (goal_ep[:200] == ep[:200]).all()
    assert not is_goal_row[200:].any() and (goal_t[200:600] < length_of[goal_ep[200:600]]).all()
    assert len(set(goal_ep[200:600])) == len(lengths) and (goal_ep[200:600] != ep[200:600]).mean() > 0.3
    future_offset = goal_t[600:] - t[600:]
    assert (goal_ep[600:] == ep[600:]).all() and (future_offset >= 1).all() and (goal_t[600:] <= length_of[ep[600:]]).all()
    assert (future_offset == 1).any() and ((goal_t[600:] == length_of[ep[600:]]) & (future_offset > 1)).any()  # o_L too
    # Rewards -1; done exactly when max(hand, puck distance) between s' and the relabelled goal is below 0.05.
    assert (batch["rewards"] == -1).all()
    hand = np.linalg.norm(batch["next_states"][:, :2] - batch["goal_states"][:, :2], axis=1)
    puck = np.linalg.norm(batch["next_states"][:, 2:] - batch["goal_states"][:, 2:], axis=1)
    np.testing.assert_array_equal(batch["done"], (np.maximum(hand, puck) < 0.05).astype(np.float32))
    np.testing.assert_array_equal(batch["done"][600:], future_offset <= 3)  # 1..2 steps of 0.02 apart: within 0.05
    np.testing.assert_array_equal(batch["done"][:200], t[:200] + 1 >= length_of[ep[:200]])  # 2 steps past o_L
    for part in (slice(0, 200), slice(600, None)):
        assert batch["done"][part].any() and not batch["done"][part].all()
    # The high level's candidates: stored transitions' s.
    assert (subgoal_t < length_of[subgoal_ep]).all() and len(set(subgoal_ep)) == len(lengths)


def test_replay_ring_keeps_episode_suffixes_with_their_goals():
    replay = sawyer.ImageEpisodeReplay(60, (84, 84, 3), 2)
    rng = np.random.default_rng(0)
    lengths = rng.integers(1, 16, size=40)
    for episode, length in enumerate(lengths):
        replay.add_episode(*labelled_episode(episode, int(length)))
        rows = np.flatnonzero(replay.is_transition[: replay.size])
        ep, t = decode(replay.images[rows])
        assert (t < lengths[ep]).all()
        next_ep, next_t = decode(replay.images[rows + 1])
        assert (next_ep == ep).all() and (next_t == t + 1).all()  # s' is the next row, of the same episode
        end_ep, end_t = decode(replay.images[replay.episode_end[rows]])
        assert (end_ep == ep).all() and (end_t == lengths[ep] - 1).all()  # the stored last transition is the episode's
        goal_ep, goal_t = decode(replay.images[replay.goal_row[rows]])
        assert (goal_ep == ep).all() and (goal_t == 255).all()  # the goal survives with the suffix
    assert sum(lengths) > 5 * 60  # the ring wrapped several times
    batch = replay.sample(2000, 0.0, 0.0, rng)  # all future goals
    ep, t = decode(batch["images"][:2000])
    goal_ep, goal_t = decode(batch["images"][4000:6000])
    assert (goal_ep == ep).all() and (goal_t > t).all() and (goal_t <= lengths[ep]).all()
    assert ep.max() == len(lengths) - 1  # the latest episode is stored


def test_the_replay_fills_to_a_batch_exactly_when_validate_accepts_its_size():
    """Whole episodes and a restart at row 0: 256 rows hold only two 100-step episodes (204 rows), never a batch of 256
    (validate refuses that); --batch-size + 101 rows reach a batch whatever the episode lengths."""

    def fill(capacity: int, lengths) -> int:
        replay = sawyer.ImageEpisodeReplay(capacity, (1, 1, 3), 2)
        for length in lengths:
            images, states = np.zeros((length + 1, 1, 1, 3), np.uint8), np.zeros((length + 1, 4), np.float32)
            replay.add_episode(images, states, np.zeros((length, 2), np.float32), images[0], states[0])
        return replay.size

    assert fill(256, [100] * 20) == 204
    rng = np.random.default_rng(0)
    for batch in (1, 16, 100, 256):
        for lengths in ([100] * 30, rng.integers(1, 101, 60), [50, 100] * 15, [99] * 30):
            assert fill(batch + sawyer.EPISODE_STEPS + 1, lengths) >= batch, (batch, lengths)


# --- one RIS update ---------------------------------------------------------------------------------------------------


def tiny_agent(groups: int):
    args = sawyer.Args(groups=groups, n_embed=8, hidden_dim=32, n_subgoals=3, batch_size=8, tau=0.25, driml_dim=16)
    agent = sawyer.make_agent(84, 2, args, torch.device("cpu"))
    replay = sawyer.ImageEpisodeReplay(200, (84, 84, 3), 2)
    rng = np.random.default_rng(0)
    for _ in range(4):
        replay.add_episode(
            rng.integers(0, 256, (11, 84, 84, 3), dtype=np.uint8), rng.uniform(-0.2, 0.7, (11, 4)).astype(np.float32),
            rng.uniform(-1, 1, (10, 2)).astype(np.float32), rng.integers(0, 256, (84, 84, 3), dtype=np.uint8),
            rng.uniform(-0.2, 0.7, 4).astype(np.float32),
        )  # fmt: skip
    return args, agent, replay, rng


def update(agent: sawyer.Agent, batch: dict, args: sawyer.Args, function=sawyer.ris_update) -> dict:
    """ris_update (or its --fast version `function`) with the hyper-parameters of `args`, as the training loop calls it."""
    return function(agent, batch, args)


def random_observations(n: int) -> dict:
    rng = np.random.default_rng(1)
    return {key: rng.integers(0, 256, (n, 84, 84, 3), dtype=np.uint8) for key in ("image", "goal_image")}


def test_make_agent_builds_the_baseline_and_the_dgrl_agent():
    _, ris, _, _ = tiny_agent(0)
    _, dgrl, _, _ = tiny_agent(4)
    assert ris.vq is None and isinstance(dgrl.vq, VectorQuantizerEMA)
    assert (dgrl.vq.dim, dgrl.vq.n_embed, dgrl.vq.groups, dgrl.vq.beta, dgrl.vq.decay) == (16, 8, 4, 0.25, 0.99)
    for agent in (ris, dgrl):
        # the critic's optimizer trains the critic and the DRIML heads at --q-lr and the encoder at --encoder-lr
        groups = agent.critic_optimizer.param_groups
        assert [group["lr"] for group in groups] == [1e-3, 1e-4]
        q_lr_parameters = (*agent.critic.parameters(), *agent.driml_heads.parameters())
        assert {id(p) for p in groups[0]["params"]} == {id(p) for p in q_lr_parameters}
        assert {id(p) for p in groups[1]["params"]} == {id(p) for p in agent.encoder.parameters()}
        assert agent.actor_optimizer.param_groups[0]["lr"] == 1e-4 and agent.high_optimizer.param_groups[0]["lr"] == 1e-4
        for target, online in ((agent.actor_target, agent.actor), (agent.critic_target, agent.critic)):
            assert target is not online
            for new, old in zip(target.parameters(), online.parameters(), strict=True):
                assert torch.equal(new, old) and not new.requires_grad
    assert dgrl.state_dicts()["vq"].keys() >= {"codebook", "ema_count", "ema_sum"}
    assert ris.state_dicts()["vq"] is None


@pytest.mark.parametrize("groups", [0, 4])
def test_one_update_moves_every_network_the_codebook_and_the_targets_by_polyak(groups):
    args, agent, replay, rng = tiny_agent(groups)
    for target in (agent.actor_target, agent.critic_target):
        with torch.no_grad():
            for parameter in target.parameters():
                parameter.add_(torch.randn_like(parameter))
    networks = {
        "encoder": agent.encoder, "driml": agent.driml_heads, "critic": agent.critic, "actor": agent.actor,
        "high": agent.high, "actor_target": agent.actor_target, "critic_target": agent.critic_target,
    }  # fmt: skip
    before = {name: [p.clone() for p in network.parameters()] for name, network in networks.items()}
    codebook = None if groups == 0 else {name: b.clone() for name, b in agent.vq.named_buffers()}
    goal_inputs = {"critic": [], "actor_target": []}  # what the critic and the prior see of goals and subgoals
    for name, seen in goal_inputs.items():
        networks[name].register_forward_pre_hook(lambda module, inputs, seen=seen: seen.append(inputs[-1].detach()))
    metrics = update(agent, replay.sample(args.batch_size, 0.2, 0.4, rng), args)
    for name in ("critic_loss", "actor_loss", "high_loss", "driml_loss", "kl", "q_values", "high_weight_max"):
        assert metrics[name].shape == () and torch.isfinite(metrics[name]) and not metrics[name].requires_grad, name
    assert 0 < metrics["driml_loss"] < 2 * math.log(args.batch_size)
    for name in ("encoder", "driml", "critic", "actor", "high"):  # every parameter tensor of every online net moved
        for (parameter_name, new), old in zip(networks[name].named_parameters(), before[name], strict=True):
            assert not torch.equal(new, old), f"{name}.{parameter_name}"
    for target, online in (("actor_target", "actor"), ("critic_target", "critic")):
        for old, new, source in zip(before[target], networks[target].parameters(), networks[online].parameters(), strict=True):
            torch.testing.assert_close(new, old + args.tau * (source - old))
    if groups:
        vq = agent.vq
        assert metrics["codes"].shape == (4 * args.batch_size, groups) and torch.isfinite(metrics["vq_loss"])
        assert not torch.equal(vq.codebook, codebook["codebook"]) and not torch.equal(vq.ema_count, codebook["ema_count"])
        assert not any(p is vq.codebook for group in agent.critic_optimizer.param_groups for p in group["params"])
        for name, inputs in goal_inputs.items():  # DGRL: goals and imagined subgoals reach the nets as codebook rows
            for goal in inputs:
                segments = goal.reshape(-1, 16 // groups)
                rows = torch.cat((codebook["codebook"], vq.codebook))
                assert ((segments[:, None, :] == rows[None]).all(-1)).any(1).all(), name
    else:
        assert "codes" not in metrics and "vq_loss" not in metrics


@pytest.mark.parametrize(
    ("reduction", "grad", "factor"), [("mean", "all", 1), ("sum", "all", 4), ("mean", "state", 1), ("sum", "state", 4)]
)
def test_the_encoder_feels_the_commitment_loss_of_each_embedding(reduction, grad, factor):
    """By default (--vq-commitment-grad all) the encoder's features of s', g and s_g carry a gradient, and it is their
    commitment loss's alone: factor x 2 beta (z - e) / (4 B G), with e the code each segment snapped to (the codebook before
    the update), factor 1 for the mean of the four losses and 4 for their sum; s's features get that and the critic's
    gradient. With --vq-commitment-grad state only s's features carry a gradient (RIS's stop-gradient)."""
    args, agent, replay, rng = tiny_agent(4)
    args.vq_loss_reduction, args.vq_commitment_grad = reduction, grad
    assert sawyer.Args().vq_loss_reduction == "mean" and sawyer.Args().vq_commitment_grad == "all"  # the defaults
    vq_before = copy.deepcopy(agent.vq).eval()
    outputs, grads = record_outputs_with_grad(agent.encoder.linear)
    update(agent, replay.sample(args.batch_size, 0.2, 0.4, rng), args)
    batch = args.batch_size
    assert len(outputs) == len(grads) == 1
    features, grad_features = outputs[0], grads[0]
    commitment = factor * 2 * args.vq_beta * (features - vq_before(features)[0]) / (4 * batch * 4)
    if grad == "state":
        assert features.shape == (batch, 16)  # s alone: its critic and commitment gradients
        assert not torch.allclose(grad_features, commitment)
        return
    assert features.shape == (4 * batch, 16)  # s, s', g, s_g in one pass with gradient
    for block in (1, 2, 3):  # s', g, s_g: the commitment loss and nothing else (no critic gradient through the goal)
        rows = slice(block * batch, (block + 1) * batch)
        assert commitment[rows].abs().min() > 0
        torch.testing.assert_close(grad_features[rows], commitment[rows])
    assert not torch.allclose(grad_features[:batch], commitment[:batch])  # s: the critic's gradient as well


@pytest.mark.parametrize("groups", [0, 4])
def test_fast_update_equals_eager_and_is_free_of_host_syncs(groups):
    """--fast compile: ris_update compiled (random translate, encoder, DRIML loss, backward passes, Adam steps,
    Polyak, codebook EMA with dead-code restarts) and equal to eager, on batches the replay gathered on its device.

    The DRIML loss is blind to a shift common to the global vectors of the batch, so the gradient of the global head's
    last bias, and of its first bias at units on for the whole batch, is zero but for rounding; Adam scales any such noise
    (1e-10 to 1e-8) up to steps of a learning rate, either way. Adam's eps at 1e-4 on that parameter group (the critic and
    the DRIML heads) keeps rounding noise from moving parameters, so the comparison sees the update's arithmetic."""
    args, agent, replay, rng = tiny_agent(groups)
    agent.critic_optimizer.param_groups[0]["eps"] = 1e-4
    if groups:
        agent.vq.dead_code_steps = 3
    batches = [replay.sample(args.batch_size, 0.2, 0.4, rng) for _ in range(31)]
    optimizers = lambda state: [state.critic_optimizer, state.high_optimizer, state.actor_optimizer]  # noqa: E731
    check_fast_update(sawyer, sawyer.ris_update, agent, lambda function, state, i: update(state, batches[i], args, function),
                      optimizers)  # fmt: skip


def test_replay_state_round_trips_and_saves_only_the_filled_rows(tmp_path):
    replay = sawyer.ImageEpisodeReplay(1000, (84, 84, 3), 2)
    for episode, length in enumerate((12, 7)):
        replay.add_episode(*labelled_episode(episode, length))
    state = replay.state()
    assert {name: state[name].shape[0] for name in replay.ARRAYS} == dict.fromkeys(replay.ARRAYS, 23)
    torch.save(state, tmp_path / "replay.pt")
    assert (tmp_path / "replay.pt").stat().st_size < 24 * 84 * 84 * 3  # the filled rows, not the 1000 of the ring
    other = sawyer.ImageEpisodeReplay(1000, (84, 84, 3), 2)
    other.load_state(torch.load(tmp_path / "replay.pt", weights_only=True))
    assert (other.position, other.size) == (replay.position, replay.size)
    for name in replay.ARRAYS:
        assert np.array_equal(np.asarray(getattr(other, name)), np.asarray(getattr(replay, name))), name
    rng, other_rng = np.random.default_rng(3), np.random.default_rng(3)
    expected, got = replay.sample(16, 0.2, 0.4, rng), other.sample(16, 0.2, 0.4, other_rng)
    for key, value in expected.items():
        assert torch.equal(got[key], value), key


def test_acting_quantizes_the_goal_without_moving_the_codebook():
    _, agent, _, _ = tiny_agent(4)
    vq, observations = agent.vq, random_observations(6)
    buffers = {name: b.clone() for name, b in vq.named_buffers()}
    seen = []
    agent.actor.register_forward_pre_hook(lambda module, inputs: seen.append(inputs[1].detach()))
    actions = sawyer.act(agent, observations, "cpu", deterministic=False)
    mean_actions = sawyer.act(agent, observations, "cpu", deterministic=True)
    assert actions.shape == (6, 2) and np.abs(actions).max() <= 1 and not np.allclose(actions, mean_actions)
    for name, buffer in vq.named_buffers():
        assert torch.equal(buffer, buffers[name]), name  # acting never moves the codebook
    segments = seen[0].reshape(-1, 4)
    assert ((segments[:, None, :] == vq.codebook[None]).all(-1)).any(1).all()  # the actor saw a discrete goal
    with torch.no_grad():
        images = sawyer.image_batch(np.concatenate((observations["image"], observations["goal_image"])), "cpu")
        features = agent.encoder(images)
        mean = agent.actor(features[:6], vq(features[6:], update=False)[0])[0]
    np.testing.assert_allclose(mean_actions, torch.tanh(mean).numpy(), rtol=1e-5, atol=1e-6)


def test_evaluation_runs_one_test_episode_per_env_and_gives_up_when_asked_to_stop():
    _, agent, _, _ = tiny_agent(4)
    envs = sawyer.make_vector_env(2, 0, test=True)
    envs.reset(seed=0)
    frames = []
    result = sawyer.evaluate(envs, agent, "cpu", deterministic=True, frames=frames)
    assert set(result) == {"success_rate", "hand_success_rate", "final_hand_distance", "final_puck_distance"}
    assert 0 < result["final_hand_distance"] < 0.6 and 0 < result["final_puck_distance"] < 0.6
    assert len(frames) == 100 and frames[0].shape == (252, 504, 3)  # an untrained agent: the episode runs to truncation
    assert sawyer.evaluate(envs, agent, "cpu", deterministic=True, stop=[signal.SIGINT]) is None  # Ctrl-C: no result
    envs.close()


# --- flags, checkpoints and smoke runs --------------------------------------------------------------------------------


def assert_clean_refusal(result: subprocess.CompletedProcess, *messages: str) -> None:
    assert result.returncode == 2, result.stdout + result.stderr
    assert "Traceback" not in result.stderr, result.stderr
    for message in messages:
        assert message in result.stderr, (message, result.stderr)


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"groups": 5}, "--groups must be 0 (RIS) or divide --feature-dim 16: one of [1, 2, 4, 8, 16]; got 5"),
        ({"groups": 32}, "--groups must be 0 (RIS) or divide --feature-dim 16: one of [1, 2, 4, 8, 16]; got 32"),
        ({"gamma": 0.0}, "--gamma must be in (0, 1]; got 0.0"),
        ({"gamma": 1.5}, "--gamma must be in (0, 1]; got 1.5"),
        ({"tau": 0.0}, "--tau must be in (0, 1]; got 0.0"),
        ({"tau": 2.0}, "--tau must be in (0, 1]; got 2.0"),
        ({"q_lr": -1.0}, "--q-lr must be > 0; got -1.0"),
        ({"alpha": math.nan}, "--alpha must be a finite number; got nan"),
        ({"h_lambda": math.inf}, "--h-lambda must be a finite number; got inf"),
        ({"vq_decay": 1.0}, "--vq-decay must be in [0, 1); got 1.0"),
        ({"vq_decay": 1.5}, "--vq-decay must be in [0, 1); got 1.5"),
        ({"vq_beta": -0.1}, "--vq-beta must be >= 0; got -0.1"),
        ({"driml_coef": -1.0}, "--driml-coef must be >= 0; got -1.0"),
        ({"seed": -1}, "--seed must be in [0, 2**64) (what numpy, gymnasium and torch accept); got -1"),
        ({"image_pad": 84}, "--image-pad must be in [0, 83]; got 84"),
        ({"vq_loss_reduction": "max"}, "--vq-loss-reduction must be mean (the paper's text) or sum (the paper's snippet)"),
        ({"vq_commitment_grad": "none"}, "--vq-commitment-grad must be all (s, s', g and s_g, the paper's snippet) or state"),
        ({"eval_episodes": 0}, "--eval-episodes must be >= 1; got 0"),
        ({"her_goal_frac": 0.8, "her_random_frac": 0.4}, "--her-goal-frac (0.8) and --her-random-frac (0.4)"),
        # a replay that restarts at row 0 before it holds a batch would never start training
        ({"buffer_size": 356}, "--buffer-size must be >= --batch-size + 101 = 357 (whole episodes of up to 102 rows"),
        ({"buffer_size": 10**9}, "--buffer-size 1000000000 needs 21209 GB of host memory (21 KB a row)"),
        # budgets that end before the first update
        ({"total_timesteps": 10_000}, "--total-timesteps must be >= 10001 for any update to run"),
        ({"total_timesteps": 300, "start_timesteps": 0, "batch_size": 256}, "--total-timesteps must be >= 355 for any"),
        ({"total_timesteps": 600, "start_timesteps": 0, "batch_size": 16, "num_envs": 8}, "must be >= 808 for any update"),
    ],
)
def test_validate_names_the_bad_flag(overrides, message, capsys):
    with pytest.raises(SystemExit) as error:
        sawyer.validate(sawyer.Args(**overrides))
    assert error.value.code == 2
    assert message in capsys.readouterr().err
    for groups in (0, 1, 2, 4, 8, 16):
        sawyer.validate(sawyer.Args(groups=groups))  # the defaults pass
    sawyer.validate(sawyer.Args(vq_loss_reduction="sum", vq_commitment_grad="state"))
    sawyer.validate(sawyer.Args(total_timesteps=115, start_timesteps=0, batch_size=16, buffer_size=117))  # the least


def test_bad_flags_fail_before_any_work(run_script, tmp_path):
    flags = ["--vq-decay", "1.5", "--q-lr", "-1", "--gamma", "0", "--buffer-size", "50", "--total-timesteps", "5000"]
    result = run_script("dgrl_ris_sawyer.py", *flags)
    assert_clean_refusal(
        result, "--vq-decay must be in [0, 1); got 1.5", "--q-lr must be > 0; got -1.0", "--gamma must be in (0, 1]; got 0.0",
        "--buffer-size must be >= --batch-size + 101 = 357", "--total-timesteps must be >= 10001",
    )  # fmt: skip
    assert result.stdout == "" and not (tmp_path / "runs").exists()


def test_a_renderer_that_cannot_start_is_refused_before_any_work(run_script, tmp_path):
    """Pixels need MuJoCo's off-screen renderer: glfw without a display cannot give one. One line naming the backend and
    what to use, exit status 2, no traceback, nothing written."""
    result = run_script("dgrl_ris_sawyer.py", *TINY, env={"MUJOCO_GL": "glfw"})  # the run_script env has no DISPLAY
    assert_clean_refusal(result, "off-screen rendering failed (MUJOCO_GL=glfw): try MUJOCO_GL=egl or osmesa")
    assert not (tmp_path / "runs").exists()


TINY = ["--total-timesteps", "300", "--start-timesteps", "100", "--batch-size", "16", "--eval-frequency", "300"]
TINY += ["--eval-episodes", "2", "--buffer-size", "1000"]
TAGS = [
    "charts/episodic_return", "charts/success_rate", "charts/hand_distance", "charts/puck_distance", "charts/SPS",
    "eval/success_rate", "eval/hand_success_rate", "eval/final_hand_distance", "eval/final_puck_distance",
    "losses/critic_loss", "losses/actor_loss", "losses/high_loss", "losses/driml_loss", "losses/kl",
]  # fmt: skip
PROGRESS = r"step +{step}/{total} +eval success +\d+% hand +\d+% +distance hand [\d.]+ puck [\d.]+ +train success +(\d+%|-)"
PROGRESS += r" +SPS \d+ +\d+s elapsed, \d+s left"


@pytest.mark.parametrize("groups", ["0", "16"])
def test_smoke_run(run_script, tmp_path, groups):
    """RIS with a video, rendered headless with no MUJOCO_GL and no DISPLAY set (the script's default), and a checkpoint
    that evaluates whatever the DGRL-only flags say; DGRL with a checkpoint, then evaluated from it (with a video) and
    refused with other network flags."""
    extra = ["--save-model"] if groups == "16" else ["--capture-video", "--save-model"]
    result = run_script("dgrl_ris_sawyer.py", *TINY, "--groups", groups, *extra)
    assert result.returncode == 0, result.stderr[-3000:]
    assert re.search(PROGRESS.format(step=300, total=300), result.stdout), result.stdout
    done = r"done: 300 steps, 201 updates, last eval success \d+% \(hand \d+%\); \d+s; logs in runs/SawyerPushAndReach__G"
    assert re.search(done + groups + "__", result.stdout), result.stdout
    events = next(tmp_path.glob("runs/*/events.out.tfevents.*")).read_bytes()
    for tag in TAGS:
        assert tag.encode() in events, tag
    for tag in ("vq/commit_loss", "vq/perplexity", "vq/active_codes"):
        assert (tag.encode() in events) == (groups == "16"), tag
    if groups == "0":
        videos = list(tmp_path.glob("videos/*/eval_300.mp4"))
        assert len(videos) == 1 and videos[0].stat().st_size > 1000
    checkpoint = next(tmp_path.glob("runs/*/dgrl_ris_sawyer.cleanrl_model"))
    if groups == "0":
        flags = ["--groups", "0", "--n-embed", "7", "--eval-episodes", "1", "--checkpoint", str(checkpoint)]
        reloaded = run_script("dgrl_ris_sawyer.py", *flags)  # the codebook's size means nothing to RIS
        assert reloaded.returncode == 0 and "1 test episodes: success" in reloaded.stdout, reloaded.stderr[-3000:]
        assert torch.load(checkpoint, weights_only=True)["vq"] is None
        return
    saved = torch.load(checkpoint, weights_only=True)
    assert saved["script"] == "dgrl_ris_sawyer.py" and saved["format"] == sawyer.CHECKPOINT_FORMAT
    assert saved["args"]["groups"] == 16 and saved["args"]["batch_size"] == 16
    assert set(saved) == {"script", "format", "args", "actor", "critic", "high", "encoder", "driml", "vq"}
    assert "codebook" in saved["vq"] and "ema_count" in saved["vq"] and "linear.weight" in saved["encoder"]
    common = ["--eval-episodes", "2", "--checkpoint", str(checkpoint)]
    reloaded = run_script("dgrl_ris_sawyer.py", "--groups", "16", "--capture-video", *common)
    assert reloaded.returncode == 0, reloaded.stderr[-3000:]
    assert re.search(r"2 test episodes: success \d+%, hand success \d+%, final hand distance [\d.]+", reloaded.stdout)
    assert next(tmp_path.glob("videos/*/checkpoint_eval.mp4")).stat().st_size > 1000
    mismatch = run_script("dgrl_ris_sawyer.py", "--groups", "8", "--feature-dim", "32", *common)
    assert_clean_refusal(mismatch, "was saved with other settings: pass --feature-dim 16 --groups 16")


# --- stopping and resuming --------------------------------------------------------------------------------------------


def run_steps(envs, actions: np.ndarray) -> list:
    """Step a vector env through `actions`; everything it returns, flattened to arrays for comparison."""
    trace = []
    for action in actions:
        observations, rewards, terminations, truncations, infos = envs.step(action)
        ended = infos.get("final_info", {}).get("episode", {})
        trace += [*observations.values(), rewards, terminations, truncations, *(ended.get(key, []) for key in "rl")]
    return trace


def test_a_restored_vector_env_continues_exactly():
    """After 60 steps, the state of two training envs restored into envs built with another seed gives the same steps,
    across an episode's end and its autoreset (the reset draws, the episode statistics), and the same random actions."""
    envs = sawyer.make_vector_env(2, 0, test=False)
    envs.reset(seed=0)
    actions = np.random.default_rng(0).uniform(-1, 1, (110, 2, 2)).astype(np.float32)
    run_steps(envs, actions[:60])
    state = sawyer.vector_env_state(envs)
    other = sawyer.make_vector_env(2, 7, test=False)
    other.reset(seed=7)
    sawyer.set_vector_env_state(other, state)
    assert np.array_equal(other.action_space.sample(), envs.action_space.sample())
    expected, got = run_steps(envs, actions[60:]), run_steps(other, actions[60:])
    assert len(got) == len(expected) > 50 * 7  # 50 steps, one of them an episode's end (with its return and length)
    for want, have in zip(expected, got, strict=True):
        assert np.array_equal(want, have)
    envs.close()
    other.close()


def test_an_evaluation_cut_short_is_undone_by_restoring_the_eval_envs_and_the_rngs():
    """What the training loop does when a stop arrives mid-evaluation: the eval envs' state and the global random states
    taken before it, put back after it, make the next evaluation the one an uninterrupted run would have made."""
    _, agent, _, _ = tiny_agent(4)
    envs = sawyer.make_vector_env(2, 10_000, test=True)
    envs.reset(seed=10_000)
    before = sawyer.vector_env_state(envs), sawyer.rng_states()
    expected = sawyer.evaluate(envs, agent, "cpu", deterministic=False)

    class StopAfter:  # a stop list that fills at its 30th check
        checks = 0

        def __bool__(self):
            self.checks += 1
            return self.checks > 30

    sawyer.set_vector_env_state(envs, before[0])
    sawyer.rng_states(restore=before[1])
    assert sawyer.evaluate(envs, agent, "cpu", deterministic=False, stop=StopAfter()) is None
    sawyer.set_vector_env_state(envs, before[0])
    sawyer.rng_states(restore=before[1])
    assert sawyer.evaluate(envs, agent, "cpu", deterministic=False) == expected
    envs.close()


RESUME = ["--batch-size", "16", "--start-timesteps", "100", "--eval-episodes", "1", "--buffer-size", "400", "--save-model"]
STOPPED = r"stopped: (\d+) steps, (\d+) updates"


def test_a_run_stopped_in_the_random_warm_up_resumes_exactly(resume_check):
    """SIGTERM after the evaluation at step 50: the run stops within the random warm-up (100 steps), inside the first
    episode, and resumed it logs the same scalars and ends with the same networks, codebook and targets as a run straight
    through."""
    flags = [*RESUME, "--groups", "4", "--total-timesteps", "130", "--eval-frequency", "50"]
    output = resume_check("dgrl_ris_sawyer.py", flags, r"^step +50/130 +eval success")
    steps, updates = map(int, re.search(STOPPED, output).groups())
    assert 50 < steps < 100 and updates == 0, output


def test_a_run_stopped_inside_an_episode_after_updates_started_resumes_exactly(resume_check, tmp_path):
    """SIGTERM after the evaluation at step 120 (20 steps into the second episode, updates running): the resumed run
    continues that episode to its end at step 200 (its rows then sampled by the last 11 updates), and logs and ends as a
    run straight through."""
    flags = [*RESUME, "--groups", "16", "--total-timesteps", "210", "--eval-frequency", "120"]
    output = resume_check("dgrl_ris_sawyer.py", flags, r"^step +120/210 +eval success")
    steps, updates = map(int, re.search(STOPPED, output).groups())
    assert 120 < steps < 200 and updates == steps - 99, output
    events = EventAccumulator(str(next((tmp_path / "straight" / "runs").iterdir())))
    events.Reload()
    ends = [event.step for event in events.Scalars("charts/episodic_length")]
    assert ends[:2] == [100, 200], ends  # the stop fell inside the second episode


def test_a_finished_run_resumes_to_its_end_and_its_resume_file_holds_uint8_images(run_script, tmp_path):
    """With only free flags changed, a finished run stays as it was (no new point). The replay's images are stored in
    resume.pt as uint8, only the filled rows. (Changed flags that must match are refused for every script:
    tests/test_skeleton.py.)"""
    flags = [*RESUME, "--groups", "4", "--total-timesteps", "115", "--eval-frequency", "1000"]
    first = run_script("dgrl_ris_sawyer.py", *flags)
    assert first.returncode == 0, first.stderr[-3000:]
    (run,) = (tmp_path / "runs").iterdir()
    saved = torch.load(run / "resume.pt", weights_only=False)
    assert saved["replay"]["images"].dtype == torch.uint8 and saved["replay"]["images"].shape == (102, 84, 84, 3)
    assert saved["loop"]["finished"] and saved["loop"]["step"] == 115
    resume = ["--resume", f"runs/{run.name}"]
    again = run_script("dgrl_ris_sawyer.py", *flags, "--checkpoint-every", "0", "--threads", "2", *resume)
    assert again.returncode == 0, again.stderr[-3000:]
    assert f"{run.name}: (84, 84, 3) images" in again.stdout and "resumed at step 115" in again.stdout
    assert re.search(r"done: 115 steps, 16 updates", again.stdout), again.stdout
    events = EventAccumulator(str(run))
    events.Reload()
    assert [event.step for event in events.Scalars("eval/success_rate")] == [115]
