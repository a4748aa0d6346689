"""dgrl_amigo.py: the fully observed MiniGrid encoding, the vectorized env (gymnasium's VectorEnv API, same-step
autoreset, seeding, truncation, the partial-view bypass), AMIGo's goal-reach test on real envs, the student and teacher
rewards, the t* schedule, the outcome buffer, V-trace and the actor-critic losses, the agent make_agent builds, one
teacher and one student update with and without DGRL, evaluation with scripted networks, flag validation, smoke runs
(train, checkpoint, evaluate, video, Ctrl-C); stopping and resuming (the env state, runs stopped by SIGTERM at two
points or killed after periodic saves equal straight runs, changed flags refused)."""

import dataclasses
import math
import re
import signal
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
import torch.nn as nn
import torch.nn.functional as F
from minigrid.core.constants import COLOR_TO_IDX, OBJECT_TO_IDX
from minigrid.core.world_object import Door
from minigrid.wrappers import FullyObsWrapper

import dgrl_amigo as amigo
from tests.conftest import NoHostSync, check_fast_update, training_tensors

LEFT, RIGHT, FORWARD, PICKUP, DROP, TOGGLE, DONE = range(7)
DOORKEY, EMPTY, CORRIDOR = "MiniGrid-DoorKey-5x5-v0", "MiniGrid-Empty-5x5-v0", "MiniGrid-KeyCorridorS3R1-v0"
ROOT = Path(__file__).resolve().parents[1]
TINY_AGENT = dict(goal_channel="on", embed_dim=16, n_embed=8, vq_beta=0.25, vq_decay=0.99, vq_dead_code_steps=50)
TINY_AGENT |= dict(learning_rate=1e-3, teacher_learning_rate=2e-3, rmsprop_alpha=0.99, rmsprop_eps=0.01)
STUDENT_ARGS = amigo.Args(gamma=0.99, baseline_coef=0.5, entropy_coef=0.0005, max_grad_norm=40.0)


def tiny_agent(groups: int, width: int = 5, height: int = 5, **overrides) -> amigo.Agent:
    """The script's make_agent with small goal embeddings (16-d, 8 codes)."""
    return amigo.make_agent(width, height, 7, amigo.Args(groups=groups, **(TINY_AGENT | overrides)), "cpu")


def cell(x: int, y: int, height: int) -> int:
    """The script's flat goal index, typed in independently: x * H + y."""
    return x * height + y


# --- the fully observed grid ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("env_id", [DOORKEY, CORRIDOR, EMPTY, "MiniGrid-MultiRoom-N2-S4-v0"])
def test_full_grid_is_the_fully_observed_wrapper_image(env_id):
    wrapped = FullyObsWrapper(gym.make(env_id))
    rng = np.random.default_rng(0)
    for seed in (0, 1):
        obs, _ = wrapped.reset(seed=seed)
        np.testing.assert_array_equal(amigo.full_grid(wrapped.unwrapped), obs["image"])
        for _ in range(40):
            obs, _, terminated, truncated, _ = wrapped.step(int(rng.integers(7)))
            grid = amigo.full_grid(wrapped.unwrapped)
            assert grid.dtype == np.uint8 and grid.shape == (wrapped.unwrapped.width, wrapped.unwrapped.height, 3)
            np.testing.assert_array_equal(grid, obs["image"])
            if terminated or truncated:
                obs, _ = wrapped.reset()
    wrapped.close()


def test_carried_is_empty_then_the_picked_up_key():
    env = gym.make(DOORKEY).unwrapped
    env.reset(seed=0)  # agent at (1, 3) facing left; the yellow key at (1, 2), above it
    assert amigo.carried(env) == (OBJECT_TO_IDX["empty"], 0) == (1, 0)
    env.step(RIGHT)
    env.step(PICKUP)
    assert env.carrying is not None and env.carrying.type == "key"
    assert amigo.carried(env) == (OBJECT_TO_IDX["key"], COLOR_TO_IDX["yellow"])


# --- the vectorized env -----------------------------------------------------------------------------------------------


def test_vec_env_follows_gymnasiums_vector_env_api():
    envs = amigo.MiniGridVecEnv(CORRIDOR, 3)
    assert isinstance(envs, gym.vector.VectorEnv) and envs.num_envs == 3
    assert envs.metadata["autoreset_mode"] == gym.vector.AutoresetMode.SAME_STEP
    assert envs.single_action_space == gym.spaces.Discrete(7)
    assert envs.action_space == gym.spaces.MultiDiscrete([7, 7, 7])
    assert set(envs.single_observation_space.spaces) == {"grid", "carried"}
    assert envs.single_observation_space["grid"].shape == (7, 3, 3)
    assert envs.observation_space["grid"].shape == (3, 7, 3, 3)
    obs, info = envs.reset(seed=4, options=None)
    assert info == {} and envs.observation_space.contains(obs)
    envs.action_space.seed(0)
    for _ in range(300):  # through the 270-step limit: reset frames are in the space too
        obs, rewards, terminated, truncated, info = envs.step(envs.action_space.sample())
        assert envs.observation_space.contains(obs)
        assert rewards.shape == terminated.shape == truncated.shape == info["_episode"].shape == (3,)
        np.testing.assert_array_equal(info["_episode"], terminated | truncated)
    seeded, _ = envs.reset(seed=[9, None, 11])  # one seed per env, as gymnasium's vector envs take them
    np.testing.assert_array_equal(seeded["grid"][[0, 2]], envs.reset(seed=9)[0]["grid"][[0, 2]])
    assert envs.render_mode is None and not envs.closed
    envs.close()
    assert envs.closed


def test_vec_env_renders_env_0_only():
    envs = amigo.MiniGridVecEnv(EMPTY, 2, render_env0=True)
    envs.reset(seed=0)
    (frame,) = envs.render()
    assert envs.render_mode == "rgb_array" and frame.shape == (5 * 32, 5 * 32, 3) and frame.dtype == np.uint8
    envs.record = True
    envs.step(np.array([FORWARD, FORWARD]))
    assert envs.frame0.shape == frame.shape and not np.array_equal(envs.frame0, frame)  # the agent moved


def test_vec_env_shapes_and_reset_frames():
    envs = amigo.MiniGridVecEnv(CORRIDOR, 3)
    assert (envs.width, envs.height, envs.max_steps, envs.n_actions) == (7, 3, 270, 7)
    obs, _ = envs.reset(seed=4)
    grids, carry = obs["grid"], obs["carried"]
    assert grids.shape == (3, 7, 3, 3) and grids.dtype == np.uint8 and carry.shape == (3, 2)
    obs2, rewards, terminated, truncated, info = envs.step(np.array([LEFT, RIGHT, DONE]))
    after = info["final_grid"]
    assert obs2["grid"].shape == after.shape == (3, 7, 3, 3) and obs2["carried"].shape == (3, 2)
    assert rewards.shape == terminated.shape == truncated.shape == (3,)
    assert not info["_episode"].any()
    for i, env in enumerate(envs.envs):
        np.testing.assert_array_equal(after[i], amigo.full_grid(env))
    assert (obs2["grid"][:, 3, 1, 2] == (grids[:, 3, 1, 2] + np.array([-1, 1, 0])) % 4).all()  # the agent turned in place


def test_vec_env_autoreset_returns_the_reset_frame_and_the_final_frame():
    envs = amigo.MiniGridVecEnv(EMPTY, 2)
    envs.reset(seed=0)
    env = envs.envs[0]
    env.agent_pos, env.agent_dir = (3, 2), 1  # right above the green goal at (3, 3), facing down
    envs.step(np.array([DONE, DONE]))  # one step spent before reaching the goal
    other_before = amigo.full_grid(envs.envs[1])
    obs, rewards, terminated, truncated, info = envs.step(np.array([FORWARD, DONE]))
    grids, carry, after = obs["grid"], obs["carried"], info["final_grid"]
    returns, lengths = info["episode"]["r"][info["_episode"]], info["episode"]["l"][info["_episode"]]
    assert terminated.tolist() == [True, False] and not truncated.any() and info["_episode"].tolist() == [True, False]
    assert rewards[0] == pytest.approx(1 - 0.9 * 2 / 100) and rewards[1] == 0
    np.testing.assert_allclose(returns, [1 - 0.9 * 2 / 100])
    assert lengths.tolist() == [2]
    assert tuple(after[0, 3, 3]) == (OBJECT_TO_IDX["agent"], COLOR_TO_IDX["red"], 1)  # the pre-reset frame
    np.testing.assert_array_equal(grids[0], amigo.full_grid(env))  # the reset frame
    assert tuple(grids[0, 1, 1]) == (OBJECT_TO_IDX["agent"], COLOR_TO_IDX["red"], 0)
    assert tuple(grids[0, 3, 3]) == (OBJECT_TO_IDX["goal"], COLOR_TO_IDX["green"], 0)
    np.testing.assert_array_equal(grids[1], after[1])
    np.testing.assert_array_equal(after[1], other_before)
    assert envs.episode_return.tolist() == [0, 0] and envs.episode_length.tolist() == [0, 2]
    assert env.step_count == 0 and carry.tolist() == [[1, 0], [1, 0]]


def test_vec_env_truncates_at_max_steps():
    envs = amigo.MiniGridVecEnv(EMPTY, 1)
    envs.reset(seed=0)
    for t in range(1, envs.max_steps + 1):
        _, rewards, terminated, truncated, info = envs.step(np.array([DONE]))
        returns, lengths = info["episode"]["r"][info["_episode"]], info["episode"]["l"][info["_episode"]]
        assert not terminated[0] and rewards[0] == 0
        assert truncated[0] == (t == envs.max_steps) and len(lengths) == (t == envs.max_steps)
    assert envs.max_steps == 100 and lengths.tolist() == [100] and returns.tolist() == [0.0]
    assert envs.episode_length.tolist() == [0]


def test_vec_env_seeding_reproduces_and_seeds_env_i_with_seed_plus_i():
    a, b = amigo.MiniGridVecEnv(DOORKEY, 4), amigo.MiniGridVecEnv(DOORKEY, 4)
    grids_a = a.reset(seed=7)[0]["grid"]
    grids_b = b.reset(seed=7)[0]["grid"]
    np.testing.assert_array_equal(grids_a, grids_b)
    for i in range(4):
        single = gym.make(DOORKEY).unwrapped
        single.reset(seed=7 + i)
        np.testing.assert_array_equal(grids_a[i], amigo.full_grid(single))
    assert len({grid.tobytes() for grid in grids_a}) > 1  # a new layout per seed
    rng = np.random.default_rng(0)
    for _ in range(260):  # past one episode's 250 steps: the unseeded autoresets reproduce too
        actions = rng.integers(7, size=4)
        obs_a, *_, info_a = a.step(actions)
        obs_b, *_, info_b = b.step(actions)
        np.testing.assert_array_equal(obs_a["grid"], obs_b["grid"])
        np.testing.assert_array_equal(info_a["final_grid"], info_b["final_grid"])
    other = amigo.MiniGridVecEnv(DOORKEY, 4).reset(seed=8)[0]["grid"]
    np.testing.assert_array_equal(other[:3], a.reset(seed=7)[0]["grid"][1:])


def test_partial_view_bypass_does_not_change_the_dynamics():
    wrapped = FullyObsWrapper(gym.make(DOORKEY))
    envs = amigo.MiniGridVecEnv(DOORKEY, 1)
    obs, _ = wrapped.reset(seed=3)
    np.testing.assert_array_equal(envs.reset(seed=3)[0]["grid"][0], obs["image"])
    rng, episodes, total_reward = np.random.default_rng(1), 0, 0.0
    for _ in range(300):
        action = int(rng.integers(7))
        obs, reward, terminated, truncated, _ = wrapped.step(action)
        vec_obs, rewards, terms, truncs, info = envs.step(np.array([action]))
        np.testing.assert_array_equal(info["final_grid"][0], obs["image"])
        assert (rewards[0], terms[0], truncs[0]) == (reward, terminated, truncated)
        assert tuple(vec_obs["carried"][0]) == amigo.carried(wrapped.unwrapped)
        total_reward += reward
        if terminated or truncated:
            obs, _ = wrapped.reset()
            episodes += 1
        assert tuple(envs.envs[0].agent_pos) == tuple(wrapped.unwrapped.agent_pos)
        assert envs.envs[0].agent_dir == wrapped.unwrapped.agent_dir
        np.testing.assert_array_equal(vec_obs["grid"][0], obs["image"])
    assert episodes >= 1  # the comparison went through an autoreset


@pytest.mark.parametrize("env_id", [DOORKEY, CORRIDOR, "MiniGrid-ObstructedMaze-1Dlhb-v0", "MiniGrid-MemoryS7-v0"])
def test_vec_env_state_continues_the_episodes_in_progress(env_id, tmp_path):
    """get_state, through a file, into envs built with another seed and a renderer: the same steps and autoresets follow."""
    rng = np.random.default_rng(0)
    envs = amigo.MiniGridVecEnv(env_id, 3)
    envs.reset(seed=1)
    for _ in range(40):
        envs.step(rng.integers(envs.n_actions, size=3))
    state = envs.get_state()
    torch.save(state, tmp_path / "state.pt")
    before = [amigo.full_grid(env) for env in envs.envs]
    envs.step(np.full(3, FORWARD))  # the state is a copy: stepping on does not change it
    copy = amigo.MiniGridVecEnv(env_id, 3, render_env0=True)
    copy.reset(seed=99)
    copy.set_state(torch.load(tmp_path / "state.pt", weights_only=False))
    assert copy.envs[0].render_mode == "rgb_array" and copy.envs[1].render_mode is None
    for i, env in enumerate(copy.envs):
        np.testing.assert_array_equal(amigo.full_grid(env), before[i])
    envs.set_state(state)
    assert envs.envs[0].step_count == copy.envs[0].step_count == 40 % envs.max_steps
    ends = 0
    for _ in range(envs.max_steps + 20):  # past an autoreset in every env: the envs' generators were restored too
        actions = rng.integers(envs.n_actions, size=3)
        obs, *outcome, info = envs.step(actions)  # rewards, terminated, truncated
        obs_copy, *outcome_copy, info_copy = copy.step(actions)
        for array, array_copy in zip([*obs.values(), *outcome], [*obs_copy.values(), *outcome_copy], strict=True):
            np.testing.assert_array_equal(array, array_copy)
        np.testing.assert_array_equal(info["final_grid"], info_copy["final_grid"])
        np.testing.assert_array_equal(info["episode"]["r"], info_copy["episode"]["r"])
        ends += int(info["_episode"].sum())
    assert ends >= 3


def test_vec_env_state_keeps_the_carried_object_the_target_object():
    """KeyCorridor succeeds when `carrying is obj`: the state must keep the two one object, not two equal copies."""
    envs = amigo.MiniGridVecEnv(CORRIDOR, 1)
    envs.reset(seed=0)
    env = envs.envs[0]
    env.grid.set(*env.obj.cur_pos, None)
    env.carrying = env.obj
    copy = amigo.MiniGridVecEnv(CORRIDOR, 1)
    copy.set_state(envs.get_state())
    assert copy.envs[0].carrying is copy.envs[0].obj and copy.envs[0].obj is not env.obj


# --- the goal-reach test ----------------------------------------------------------------------------------------------


def reach(env_id: str, seed: int, setup, action: int, goals: list[tuple[int, int]]) -> list[bool]:
    """Arrange a real env with `setup(env)`, issue every goal on the frame right after it, take `action` and run the
    script's reach test on the frame after the step, one GoalBook row per goal."""
    envs = amigo.MiniGridVecEnv(env_id, 1)
    envs.reset(seed=seed)
    env = envs.envs[0]
    setup(env)
    frame = amigo.full_grid(env)
    book = amigo.GoalBook(len(goals), envs.width, envs.height)
    flat = np.array([cell(x, y, envs.height) for x, y in goals])
    book.issue(np.ones(len(goals), dtype=bool), np.repeat(frame[None], len(goals), 0), flat, np.zeros(len(goals)))
    _, _, terminated, truncated, info = envs.step(np.array([action]))
    assert not terminated[0] and not truncated[0]
    return book.reached(np.repeat(info["final_grid"], len(goals), 0)).tolist()


def place(pos, direction):
    def setup(env):
        env.agent_pos, env.agent_dir = pos, direction

    return setup


def test_stepping_onto_a_goal_reaches_it_and_leaves_unrelated_goals_pending():
    # Empty-5x5: the agent at (1, 1) facing right steps to (2, 1); its old cell changes too.
    reached = reach(EMPTY, 0, place((1, 1), 0), FORWARD, [(2, 1), (1, 1), (3, 1), (1, 2), (3, 3)])
    assert reached == [True, True, False, False, False]


def test_turning_in_place_on_the_goal_cell_reaches_it():
    assert reach(EMPTY, 0, place((2, 2), 0), LEFT, [(2, 2), (3, 2), (2, 1)]) == [True, False, False]


def test_nothing_changes_when_walking_into_a_wall():
    assert reach(EMPTY, 0, place((3, 1), 0), FORWARD, [(3, 1), (4, 1), (2, 1)]) == [False, False, False]


def test_reach_on_a_non_square_grid_uses_x_times_height_plus_y():
    # KeyCorridorS3R1 is 7 x 3: the corridor is row y = 1, the agent starts at (3, 1).
    reached = reach(CORRIDOR, 0, place((3, 1), 1), RIGHT, [(3, 1), (2, 1), (4, 1), (1, 1), (5, 1)])
    assert reached == [True, False, False, False, False]
    # Seed 0: an unlocked blue door at (2, 1), a locked yellow one at (4, 1); facing left, the agent opens the first.
    reached = reach(CORRIDOR, 0, place((3, 1), 2), TOGGLE, [(2, 1), (3, 1), (4, 1), (1, 1)])
    assert reached == [True, False, False, False]


def test_picking_up_an_object_at_the_goal_cell_reaches_it():
    def facing_the_key(env):  # DoorKey-5x5 seed 0: the key at (1, 2), the agent below it at (1, 3)
        assert env.grid.get(1, 2).type == "key"
        env.agent_pos, env.agent_dir = (1, 3), 3

    assert reach(DOORKEY, 0, facing_the_key, PICKUP, [(1, 2), (1, 3), (2, 1)]) == [True, False, False]


def test_dropping_an_object_on_the_goal_cell_reaches_it():
    def carrying_the_key(env):
        env.carrying = env.grid.get(1, 2)
        env.grid.set(1, 2, None)
        env.agent_pos, env.agent_dir = (1, 3), 3

    assert reach(DOORKEY, 0, carrying_the_key, DROP, [(1, 2), (1, 3), (1, 1)]) == [True, False, False]


def test_opening_the_locked_door_at_the_goal_cell_with_the_key_reaches_it():
    def at_the_door(with_key):
        def setup(env):  # DoorKey-5x5 seed 0: the locked yellow door at (2, 1)
            assert env.grid.get(2, 1).type == "door" and env.grid.get(2, 1).is_locked
            if with_key:
                env.carrying = env.grid.get(1, 2)
                env.grid.set(1, 2, None)
            env.agent_pos, env.agent_dir = (1, 1), 0

        return setup

    assert reach(DOORKEY, 0, at_the_door(True), TOGGLE, [(2, 1), (1, 1), (3, 1)]) == [True, False, False]
    assert reach(DOORKEY, 0, at_the_door(False), TOGGLE, [(2, 1), (1, 1)]) == [False, False]  # still locked


def test_opening_an_unlocked_door_at_the_goal_cell_reaches_it():
    def at_a_closed_door(env):
        env.grid.set(2, 1, Door("blue", is_open=False, is_locked=False))
        env.agent_pos, env.agent_dir = (1, 1), 0

    assert reach(EMPTY, 0, at_a_closed_door, TOGGLE, [(2, 1), (1, 1), (2, 2)]) == [True, False, False]


def test_goal_book_issue_resets_steps_and_stores_goal_frame_and_logp_for_the_masked_envs_only():
    book = amigo.GoalBook(3, 5, 5)
    book.goal[:], book.steps[:], book.logp[:] = [1, 2, 3], [10, 20, 30], [-1, -2, -3]
    frames = np.arange(2 * 75, dtype=np.uint8).reshape(2, 5, 5, 3)
    book.issue(np.array([True, False, True]), frames, np.array([7, 8]), np.array([-0.5, -0.25]))
    assert book.goal.tolist() == [7, 2, 8] and book.steps.tolist() == [0, 20, 0]
    assert book.logp.tolist() == [-0.5, -2, -0.25]
    np.testing.assert_array_equal(book.frame[[0, 2]], frames)
    assert not book.frame[1].any()


def test_renew_goals_issues_teacher_goals_on_the_current_frames():
    envs = amigo.MiniGridVecEnv(DOORKEY, 3)
    grids = envs.reset(seed=0)[0]["grid"]
    agent = tiny_agent(groups=4)
    teacher, encoder = agent.teacher, agent.goal_encoder
    book = amigo.GoalBook(3, 5, 5)
    book.steps[:] = 9
    embedding = torch.zeros(3, 16)
    mask = np.array([True, False, True])
    codebook = encoder.vq.codebook.clone()
    amigo.renew_goals(agent, book, mask, grids, embedding, "cpu")
    assert book.steps.tolist() == [0, 9, 0]
    np.testing.assert_array_equal(book.frame[mask], grids[mask])
    assert not book.frame[1].any() and ((book.goal >= 0) & (book.goal < 25)).all()
    with torch.no_grad():
        log_probs = F.log_softmax(teacher(torch.as_tensor(grids[mask]))[0], -1)
    np.testing.assert_allclose(book.logp[mask], log_probs[[0, 1], book.goal[mask]].numpy(), rtol=1e-5)
    expected = amigo.embed_goals(encoder, book.frame[mask], book.goal[mask], "cpu")
    torch.testing.assert_close(embedding[torch.as_tensor(mask)], expected)
    assert not embedding[1].any() and embedding[0].abs().sum() > 0
    torch.testing.assert_close(encoder.vq.codebook, codebook)  # acting never moves the codebook


# --- rewards, t*, outcomes --------------------------------------------------------------------------------------------


def test_intrinsic_reward_formula():
    reward = amigo.intrinsic_reward(np.array([True, False, True, True]), np.array([10, 5, 250, 1]), 250, 0.5)
    np.testing.assert_allclose(reward, [0.5 * (1 - 0.9 * 10 / 250), 0.0, 0.5 * 0.1, 0.5 * (1 - 0.9 / 250)])
    np.testing.assert_allclose(amigo.intrinsic_reward(np.array([True]), np.array([50]), 100, 1.0), [0.55])


def test_student_reward_clips_and_adds_one_on_success():
    extrinsic = np.array([0.0, 0.8, 0.955, 0.0, -0.5])
    intrinsic = np.array([0.482, 0.5, 0.0, 0.0, -0.7])
    np.testing.assert_allclose(amigo.student_reward(extrinsic, intrinsic), [0.482, 2.0, 1.955, 0.0, -1.0])


def test_teacher_reward_against_t_star():
    reached = np.array([True, True, True, False, False, True])
    steps = np.array([7, 6, 20, 50, 3, 2])
    success = np.array([False, False, False, False, True, True])
    np.testing.assert_allclose(amigo.teacher_reward(reached, steps, success, 7), [0.7, -0.3, 0.7, -0.3, 1.0, 1.0])
    np.testing.assert_allclose(amigo.teacher_reward(reached, steps, success, 21), [-0.3, -0.3, -0.3, -0.3, 1.0, 1.0])
    np.testing.assert_allclose(amigo.teacher_reward(reached, steps, success, 0, -0.5, 2.0), [1.0, 1, 1, -0.5, 1, 1])


def test_t_star_rises_on_a_fixed_schedule_with_the_published_threshold():
    t_star = amigo.TStar(start=7, threshold=-0.5, patience=10, maximum=11)
    rewards = np.random.default_rng(0).uniform(-0.3, 1.0, 60)  # teacher rewards are never below -0.3
    values = [t_star.update(float(r)) for r in rewards]
    assert values == [min(7 + k // 10, 11) for k in range(1, 61)]
    assert t_star.value == 11


def test_t_star_adaptive_threshold_restarts_the_streak_on_a_low_reward():
    t_star = amigo.TStar(start=7, threshold=-0.1, patience=10, maximum=100)
    rewards = [0.2] * 9 + [-0.3] + [-0.1] * 10 + [0.5] * 9 + [-0.2] + [0.5] * 10
    values = [t_star.update(r) for r in rewards]
    assert values == [7] * 19 + [8] * 20 + [9]


def test_outcome_buffer_is_fifo_with_leftovers():
    buffer = amigo.OutcomeBuffer()
    start = 0
    for n in (100, 80, 0, 120):
        ids = np.arange(start, start + n)
        buffer.add(goal=ids, steps=ids * 2, reached=ids % 3 == 0)
        start += n
    assert buffer.size == 300 and len(buffer.parts) == 3  # the empty batch is not stored
    first = buffer.pop(150)
    assert first["goal"].tolist() == list(range(150)) and buffer.size == 150
    np.testing.assert_array_equal(first["steps"], first["goal"] * 2)
    buffer.add(goal=np.arange(300, 340), steps=np.arange(300, 340) * 2, reached=np.zeros(40, dtype=bool))
    assert buffer.size == 190
    second = buffer.pop(150)
    assert second["goal"].tolist() == list(range(150, 300)) and buffer.size == 40
    np.testing.assert_array_equal(second["reached"], second["goal"] % 3 == 0)
    assert buffer.pop(40)["goal"].tolist() == list(range(300, 340)) and buffer.size == 0 and not buffer.parts


# --- V-trace and the losses -------------------------------------------------------------------------------------------


def naive_vtrace(behaviour, target, rewards, values, bootstrap, discounts):
    """Espeholt et al.'s definition term by term, in float64 Python loops, rho_bar = c_bar = 1."""
    behaviour, target, rewards, values, discounts = (
        np.asarray(a, dtype=np.float64) for a in (behaviour, target, rewards, values, discounts)
    )
    bootstrap = np.asarray(bootstrap, dtype=np.float64)
    T, B = rewards.shape
    ratio = np.exp(target - behaviour)
    rho, c = np.minimum(1.0, ratio), np.minimum(1.0, ratio)
    vs, advantages = np.zeros((T, B)), np.zeros((T, B))
    for b in range(B):
        next_value = [*values[1:, b], bootstrap[b]]
        for s in range(T):
            total, trace = 0.0, 1.0
            for t in range(s, T):
                total += trace * rho[t, b] * (rewards[t, b] + discounts[t, b] * next_value[t] - values[t, b])
                trace *= discounts[t, b] * c[t, b]
            vs[s, b] = values[s, b] + total
        for s in range(T):
            next_vs = vs[s + 1, b] if s + 1 < T else bootstrap[b]
            advantages[s, b] = rho[s, b] * (rewards[s, b] + discounts[s, b] * next_vs - values[s, b])
    return vs, advantages


def vtrace_inputs(seed: int, off_policy: bool):
    rng = np.random.default_rng(seed)
    T, B = 6, 3
    behaviour = np.log(rng.uniform(0.05, 1.0, (T, B)))
    target = behaviour + (rng.normal(0.0, 0.8, (T, B)) if off_policy else 0.0)
    rewards, values, bootstrap = rng.normal(size=(T, B)), rng.normal(size=(T, B)), rng.normal(size=B)
    dones = np.zeros((T, B))
    dones[2, 0] = dones[4, 2] = 1.0
    discounts = 0.9 * (1.0 - dones)
    return behaviour, target, rewards, values, bootstrap, discounts


def run_vtrace(*arrays):
    return [out.double().numpy() for out in amigo.vtrace(*(torch.tensor(a, dtype=torch.float32) for a in arrays))]


def test_vtrace_on_policy_is_the_n_step_return_cut_at_dones():
    behaviour, target, rewards, values, bootstrap, discounts = vtrace_inputs(0, off_policy=False)
    vs, advantages = run_vtrace(behaviour, target, rewards, values, bootstrap, discounts)
    T, B = rewards.shape
    returns = np.zeros((T, B))
    for b in range(B):
        for s in range(T):
            total, scale = 0.0, 1.0
            for t in range(s, T):
                total += scale * rewards[t, b]
                scale *= discounts[t, b]
            returns[s, b] = total + scale * bootstrap[b]
    np.testing.assert_allclose(vs, returns, rtol=1e-5, atol=1e-5)
    assert returns[2, 0] == pytest.approx(rewards[2, 0])  # the done at t = 2 cuts the bootstrap of env 0
    next_returns = np.concatenate([returns[1:], bootstrap[None]])
    np.testing.assert_allclose(advantages, rewards + discounts * next_returns - values, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("seed", [1, 2])
def test_vtrace_off_policy_matches_the_truncated_recursion(seed):
    inputs = vtrace_inputs(seed, off_policy=True)
    ratio = np.exp(inputs[1] - inputs[0])
    assert (ratio > 1.2).any() and (ratio < 0.8).any()  # both truncation and down-weighting happen
    vs, advantages = run_vtrace(*inputs)
    expected_vs, expected_advantages = naive_vtrace(*inputs)
    np.testing.assert_allclose(vs, expected_vs, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(advantages, expected_advantages, rtol=1e-5, atol=1e-5)


def float64_vtrace_recursion(behaviour, target, rewards, values, bootstrap, discounts):
    """V-trace as the backward recursion acc_s = delta_s + gamma_s c_s acc_{s+1}, in float64 (rho_bar = c_bar = 1)."""
    ratio = np.exp(target - behaviour)
    rho = c = np.minimum(1.0, ratio)
    deltas = rho * (rewards + discounts * np.concatenate([values[1:], bootstrap[None]]) - values)
    acc, corrections = np.zeros_like(bootstrap), np.zeros_like(values)
    for t in reversed(range(len(values))):
        acc = deltas[t] + discounts[t] * c[t] * acc
        corrections[t] = acc
    vs = values + corrections
    return vs, rho * (rewards + discounts * np.concatenate([vs[1:], bootstrap[None]]) - values)


def test_vtrace_at_the_learners_size_matches_the_recursion_without_a_time_loop():
    """T = 100 steps x 8 rollouts, sparse rewards, episode ends, off-policy ratios: the matrix form agrees with the
    float64 recursion to 1e-5, and runs without a host sync (it is one fixed-shape computation)."""
    rng = np.random.default_rng(0)
    T, B = 100, 8
    behaviour = np.log(rng.uniform(0.05, 1.0, (T, B)))
    target = behaviour + rng.normal(0.0, 0.3, (T, B))
    rewards = (rng.random((T, B)) < 0.05) * rng.uniform(0.0, 1.0, (T, B))
    values, bootstrap = rng.normal(size=(T, B)), rng.normal(size=B)
    discounts = 0.99 * (rng.random((T, B)) >= 0.01)
    inputs = [torch.tensor(a, dtype=torch.float32) for a in (behaviour, target, rewards, values, bootstrap, discounts)]
    with NoHostSync() as guard:
        vs, advantages = amigo.vtrace(*inputs)
    assert guard.ops < 60, f"{guard.ops} ops: a loop over the {T} time steps takes 4 or more each"
    expected_vs, expected_advantages = float64_vtrace_recursion(behaviour, target, rewards, values, bootstrap, discounts)
    np.testing.assert_allclose(vs.double().numpy(), expected_vs, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(advantages.double().numpy(), expected_advantages, rtol=1e-5, atol=1e-5)
    assert (discounts == 0).any() and (np.exp(target - behaviour) > 1).any()


def test_actor_critic_loss_by_hand_averages_over_the_batch_and_sums_over_time():
    """AMIGo's reduction ("Take the mean over batch, sum over time"), on T = 2 steps of B = 2 rollouts, typed in."""
    logits = torch.zeros(2, 2, 2, requires_grad=True)  # two actions: log-probabilities -ln 2, entropy ln 2 a step
    values = torch.tensor([[0.5, 1.0], [0.0, 2.0]], requires_grad=True)
    actions, vs = torch.tensor([[0, 1], [1, 1]]), torch.tensor([[1.0, 0.0], [1.0, 2.0]])
    advantages = torch.tensor([[1.0, -2.0], [3.0, 0.0]])
    total, policy, baseline, entropy = amigo.actor_critic_loss(logits, values, actions, vs, advantages, 0.5, 0.01)
    ln2 = math.log(2)
    assert policy.item() == pytest.approx(ln2 * ((1.0 - 2.0) / 2 + (3.0 + 0.0) / 2))  # -log pi * A, per step
    assert baseline.item() == pytest.approx(0.5 * ((0.5**2 + 1.0**2) / 2 + (1.0**2 + 0.0) / 2))
    assert entropy.item() == pytest.approx(2 * ln2)  # ln 2 a step, averaged over 2 rollouts, summed over 2 steps
    assert total.item() == pytest.approx(policy.item() + 0.5 * baseline.item() - 0.01 * 2 * ln2)
    total.backward()
    torch.testing.assert_close(values.grad, 0.5 * (values - vs).detach() / 2)  # d/dV of 0.5 * 0.5 * (vs - V)^2 / B


def test_actor_critic_loss_on_random_numbers():
    rng = np.random.default_rng(3)
    logits, values = rng.normal(size=(3, 2, 5)), rng.normal(size=(3, 2))
    actions, vs, advantages = rng.integers(5, size=(3, 2)), rng.normal(size=(3, 2)), rng.normal(size=(3, 2))
    log_probs = logits - np.log(np.exp(logits).sum(-1, keepdims=True))
    chosen = np.take_along_axis(log_probs, actions[..., None], -1)[..., 0]
    policy = -(chosen * advantages).mean(1).sum()
    baseline = 0.5 * ((vs - values) ** 2).mean(1).sum()
    entropy = -(np.exp(log_probs) * log_probs).sum(-1).mean(1).sum()
    out = amigo.actor_critic_loss(*(torch.tensor(a) for a in (logits, values, actions, vs, advantages)), 0.3, 0.2)
    np.testing.assert_allclose([o.item() for o in out], [policy + 0.3 * baseline - 0.2 * entropy, policy, baseline, entropy])


# --- the teacher ------------------------------------------------------------------------------------------------------


def teacher_batch(teacher, goal: int, n: int, behaviour_shift: float = 0.0):
    envs = amigo.MiniGridVecEnv(DOORKEY, n)
    frames = envs.reset(seed=0)[0]["grid"]
    with torch.no_grad():
        logp = F.log_softmax(teacher(torch.as_tensor(frames))[0], -1)[:, goal].numpy()
    goals = np.full(n, goal)
    return {"frame": frames, "goal": goals, "logp": (logp + behaviour_shift).astype(np.float32)}


def test_teacher_loss_on_policy_values():
    teacher = amigo.Teacher(5, 5)
    batch = teacher_batch(teacher, cell(3, 2, 5), 3)
    rewards = np.array([0.7, -0.3, 1.0])
    losses = amigo.teacher_loss(teacher, amigo.teacher_tensors(batch, rewards, "cpu"), baseline_coef=0.5, entropy_coef=0.05)
    with torch.no_grad():
        logits, baseline = teacher(torch.as_tensor(batch["frame"]))
        log_probs = F.log_softmax(logits, -1)
    logp, r = log_probs[:, cell(3, 2, 5)].double(), torch.tensor(rewards)
    # one step of a batch of 3 outcomes: each term is the batch's mean (AMIGo's teacher loss)
    assert losses["policy_loss"].item() == pytest.approx(-(logp * (r - baseline.double())).mean().item(), rel=1e-5)
    assert losses["baseline_loss"].item() == pytest.approx(0.5 * ((r - baseline.double()) ** 2).mean().item(), rel=1e-5)
    entropy = -(log_probs.exp() * log_probs).sum(-1).mean().item()
    assert losses["entropy"].item() == pytest.approx(entropy, rel=1e-5)
    total = losses["policy_loss"] + 0.5 * losses["baseline_loss"] - 0.05 * losses["entropy"]
    assert losses["loss"].item() == pytest.approx(total.item(), rel=1e-5)


def test_teacher_loss_off_policy_truncates_the_importance_weight():
    teacher = amigo.Teacher(5, 5)
    rewards = np.array([1.0, 1.0])
    with torch.no_grad():
        frames = teacher_batch(teacher, 12, 2)["frame"]
        logits, baseline = teacher(torch.as_tensor(frames))
        logp = F.log_softmax(logits, -1)[:, 12].double()
    advantage = torch.tensor(rewards) - baseline.double()
    for shift, rho in ((-1.0, 1.0), (1.0, math.exp(-1.0))):  # pi/mu = e (truncated to 1) or 1/e
        batch = teacher_batch(teacher, 12, 2, behaviour_shift=shift)
        batch = amigo.teacher_tensors(batch, rewards, "cpu")
        losses = amigo.teacher_loss(teacher, batch, baseline_coef=0.5, entropy_coef=0.0)
        assert losses["policy_loss"].item() == pytest.approx(-(logp * rho * advantage).mean().item(), rel=1e-4)
        vs = baseline.double() + rho * advantage
        assert losses["baseline_loss"].item() == pytest.approx(0.5 * ((vs - baseline) ** 2).mean().item(), rel=1e-4)


@pytest.mark.parametrize("direction", [1.0, -1.0])
def test_teacher_update_pushes_a_goal_up_or_down_with_its_reward(direction):
    teacher = amigo.Teacher(5, 5)
    goal = cell(3, 3, 5)
    batch = teacher_batch(teacher, goal, 4)
    with torch.no_grad():
        _, baseline = teacher(torch.as_tensor(batch["frame"]))
    rewards = baseline.numpy() + direction  # above or below the baseline by 1
    optimizer = torch.optim.SGD(teacher.parameters(), lr=1e-2)
    losses = amigo.teacher_loss(teacher, amigo.teacher_tensors(batch, rewards, "cpu"), baseline_coef=0.0, entropy_coef=0.0)
    optimizer.zero_grad()
    losses["loss"].backward()
    optimizer.step()
    after = teacher_batch(teacher, goal, 4)["logp"]
    assert (np.sign(after - batch["logp"]) == direction).all()


def test_teacher_update_steps_the_teacher_only_with_clipped_gradients():
    agent = tiny_agent(groups=4)
    batch = teacher_batch(agent.teacher, cell(3, 3, 5), 4)
    student = {name: p.detach().clone() for name, p in agent.student.named_parameters()}
    teacher = {name: p.detach().clone() for name, p in agent.teacher.named_parameters()}
    batch = amigo.teacher_tensors(batch, np.array([1.0, -0.3, 0.7, 1.0]), "cpu")
    args = amigo.Args(teacher_baseline_coef=0.5, teacher_entropy_coef=0.05, max_grad_norm=1e-3)
    losses = amigo.teacher_update(agent, batch, args)
    assert set(losses) == {"loss", "policy_loss", "baseline_loss", "entropy"}
    for name, p in agent.student.named_parameters():
        torch.testing.assert_close(p, student[name])
    assert all(not torch.equal(p, teacher[name]) for name, p in agent.teacher.named_parameters() if p.grad is not None)
    grads = [p.grad for p in agent.teacher.parameters() if p.grad is not None]
    assert torch.linalg.vector_norm(torch.stack([g.norm() for g in grads])) == pytest.approx(1e-3, rel=1e-3)  # clipped


# --- the agent and the student update ---------------------------------------------------------------------------------


@pytest.mark.parametrize("groups", [0, 4])
def test_make_agent_wires_the_optimizers(groups):
    agent = tiny_agent(groups=groups)
    student_params = {id(p) for group in agent.student_optimizer.param_groups for p in group["params"]}
    teacher_params = {id(p) for group in agent.teacher_optimizer.param_groups for p in group["params"]}
    assert student_params == {id(p) for p in [*agent.student.parameters(), *agent.goal_encoder.parameters()]}
    assert teacher_params == {id(p) for p in agent.teacher.parameters()}
    for optimizer, lr in ((agent.student_optimizer, 1e-3), (agent.teacher_optimizer, 2e-3)):
        assert isinstance(optimizer, torch.optim.RMSprop)
        assert optimizer.defaults["lr"] == lr and optimizer.defaults["alpha"] == 0.99 and optimizer.defaults["eps"] == 0.01
    assert (agent.goal_encoder.vq is None) == (groups == 0)
    if groups:  # the codebook is a buffer, moved by EMA, in no optimizer; a checkpoint holds it
        assert agent.goal_encoder.vq.groups == groups and agent.goal_encoder.vq.n_embed == 8
        assert "vq.codebook" in agent.state_dicts()["goal_encoder"]
    assert set(agent.state_dicts()) == {"student", "goal_encoder", "teacher"}


@pytest.mark.parametrize(
    ("goal_channel", "groups", "resolved"),
    [("auto", 0, "on"), ("auto", 4, "off"), ("auto", 16, "off"), ("on", 16, "on"), ("off", 0, "off"), ("on", 0, "on")],
)
def test_goal_channel_auto_is_on_for_amigo_and_off_under_dgrl(goal_channel, groups, resolved):
    assert amigo.resolve_goal_channel(goal_channel, groups) == resolved
    assert amigo.Args().goal_channel == "auto"


@pytest.mark.parametrize("goal_channel", [True, "yes", None])
def test_make_agent_refuses_a_goal_channel_that_is_not_auto_on_or_off(goal_channel):
    with pytest.raises(ValueError, match="goal_channel must be one of auto, on, off"):
        tiny_agent(groups=4, goal_channel=goal_channel)


def trunk_inputs_and_logits(agent: amigo.Agent, goals: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """What the student's conv trunk receives and the student's logits, for 4 DoorKey frames with `goals` and one fixed
    goal embedding (so that the goal can reach the student only through the map)."""
    grids = torch.as_tensor(amigo.MiniGridVecEnv(DOORKEY, 4).reset(seed=0)[0]["grid"])
    carried = torch.zeros(4, 2, dtype=torch.long)
    embedding = torch.randn(1, agent.student.embed_dim, generator=torch.Generator().manual_seed(0)).expand(4, -1)
    seen = []
    hook = agent.student.trunk[0].register_forward_hook(lambda module, inputs, output: seen.append(inputs[0]))
    with torch.no_grad():
        logits, _ = agent.student(grids, carried, goals, embedding)
    hook.remove()
    return seen[0], logits


@pytest.mark.parametrize("groups", [0, 16])
def test_the_default_student_sees_the_goal_map_for_amigo_and_only_the_codes_under_dgrl(groups):
    """The agent main builds from the default flags: AMIGo's student gets the 10 embedded channels plus the one-hot goal
    cell (11), as the original; DGRL's gets the 10 alone, so a goal reaches it only through the goal embedding."""
    args = amigo.Args(env_id=DOORKEY, groups=groups)
    agent = amigo.make_agent(5, 5, 7, args, "cpu")
    goals, other_goals = torch.tensor([6, 7, 12, 18]), torch.tensor([8, 11, 13, 16])
    inputs, logits = trunk_inputs_and_logits(agent, goals)
    _, other_logits = trunk_inputs_and_logits(agent, other_goals)
    assert agent.student.trunk[0].in_channels == inputs.shape[1] == (11 if groups == 0 else 10)
    if groups == 0:
        one_hot = F.one_hot(goals, 25).float().view(4, 5, 5)  # cell x * H + y of a (W, H) map
        torch.testing.assert_close(inputs[:, 10], one_hot, rtol=0, atol=0)
        assert not torch.allclose(logits, other_logits)  # the goal map changes what the student does
    else:
        torch.testing.assert_close(logits, other_logits, rtol=0, atol=0)  # no goal map: the goals change nothing


def test_goal_channel_on_and_off_override_the_mode():
    goals = torch.tensor([6, 7, 12, 18])
    with_map, _ = trunk_inputs_and_logits(tiny_agent(groups=4, goal_channel="on"), goals)
    without_map, _ = trunk_inputs_and_logits(tiny_agent(groups=0, goal_channel="off"), goals)
    assert with_map.shape[1] == 11 and without_map.shape[1] == 10
    torch.testing.assert_close(with_map[:, 10], F.one_hot(goals, 25).float().view(4, 5, 5), rtol=0, atol=0)


def collect(envs, agent, steps: int):
    """A rollout of `steps` steps, collected with the script's acting functions."""
    n = envs.num_envs
    obs, _ = envs.reset(seed=0)
    book = amigo.GoalBook(n, envs.width, envs.height)
    embedding = torch.zeros(n, agent.student.embed_dim)
    amigo.renew_goals(agent, book, np.ones(n, dtype=bool), obs["grid"], embedding, "cpu")
    keys = ("grids", "carried", "goal_frames", "goals", "actions", "logps")
    rollout = {key: [] for key in keys}
    for _ in range(steps):
        actions, logps = amigo.act(agent.student, obs, book.goal, embedding, "cpu")
        for key, value in zip(keys, (obs["grid"], obs["carried"], book.frame, book.goal, actions, logps), strict=True):
            rollout[key].append(np.copy(value))
        obs, *_ = envs.step(actions)
    rollout = {key: np.stack(value) for key, value in rollout.items()}
    rng = np.random.default_rng(0)
    rollout["rewards"] = rng.uniform(0, 1, (steps, n)).astype(np.float32)
    rollout["dones"] = np.zeros((steps, n), dtype=np.float32)
    rollout["dones"][1, 0] = 1.0
    last = {"grids": obs["grid"], "carried": obs["carried"], "goal_frames": book.frame.copy(), "goals": book.goal.copy()}
    return rollout, last


def test_student_update_under_dgrl_moves_the_codebook_and_every_parameter():
    agent = tiny_agent(groups=4)
    encoder = agent.goal_encoder
    rollout, last = collect(amigo.MiniGridVecEnv(DOORKEY, 2), agent, steps=4)
    buffers = {name: value.clone() for name, value in encoder.vq.named_buffers()}
    amigo.embed_goals(encoder, rollout["goal_frames"][0], rollout["goals"][0], "cpu")  # acting: no codebook update
    for name, value in encoder.vq.named_buffers():
        torch.testing.assert_close(value, buffers[name])
    teacher = {name: p.detach().clone() for name, p in agent.teacher.named_parameters()}
    params = {name: p.detach().clone() for name, p in [*agent.student.named_parameters(), *encoder.named_parameters()]}
    metrics = amigo.student_update(agent, amigo.student_batch(rollout, last, "cpu"), STUDENT_ARGS)
    assert not torch.equal(encoder.vq.codebook, buffers["codebook"])
    assert not torch.equal(encoder.vq.ema_count, buffers["ema_count"])
    for name, p in [*agent.student.named_parameters(), *encoder.named_parameters()]:
        assert not torch.equal(p, params[name]), name
    for name, p in agent.teacher.named_parameters():
        torch.testing.assert_close(p, teacher[name])  # the teacher learns only from its own outcomes
    assert metrics["codes"].shape == ((4 + 1) * 2, 4)
    assert ((metrics["codes"] >= 0) & (metrics["codes"] < 8)).all()
    assert metrics["vq_loss"].item() > 0
    for name in ("policy_loss", "baseline_loss", "entropy"):
        assert torch.isfinite(metrics[name])
    assert 0 < metrics["entropy"].item() <= math.log(7)


@pytest.mark.parametrize("dead_code_steps", [0, 50])
def test_default_encoder_uses_many_codes_only_with_dead_code_restarts(dead_code_steps):
    """The failure the default guards against: at initialisation the goal encoder's segments are short and nearly equal
    across goals, far inside the codebook's scale, so every segment picks one of the few codes nearest the origin and the
    EMA keeps it so (the study's runs used 1 code of 64 throughout before the default changed). Restarting
    codes unused for 50 updates (the script's default) spreads the codebook over the segments."""
    args = amigo.Args(env_id=DOORKEY, vq_dead_code_steps=dead_code_steps)
    encoder = amigo.GoalEncoder(5, 5, args)
    envs = amigo.MiniGridVecEnv(DOORKEY, 64)
    frames = envs.reset(seed=0)[0]["grid"]
    goals = torch.as_tensor(np.random.default_rng(0).integers(25, size=64))
    for _ in range(60):
        _, _, codes = encoder(torch.as_tensor(frames), goals, update=True)
    active = int(amigo.active_codes(codes, args.n_embed))
    if dead_code_steps == 0:
        assert active <= 2
    else:
        assert active >= 16


def test_student_update_without_dgrl_matches_the_n_step_targets():
    agent = tiny_agent(groups=0)
    student, encoder = agent.student, agent.goal_encoder
    assert encoder.vq is None
    rollout, last = collect(amigo.MiniGridVecEnv(DOORKEY, 2), agent, steps=4)
    T, B = rollout["actions"].shape
    with torch.no_grad():  # the values before the update: on-policy V-trace targets are n-step returns
        stacked = [np.concatenate([rollout[key].reshape(T * B, *rollout[key].shape[2:]), last[key]]) for key in last]
        grids, carry, frames, goals = (torch.as_tensor(a) for a in stacked)
        embedding, _, codes = encoder(frames, goals)
        assert codes is None
        values = student(grids, carry, goals, embedding)[1].double().numpy().reshape(T + 1, B)
    discounts = 0.99 * (1.0 - rollout["dones"])
    vs, _ = naive_vtrace(rollout["logps"], rollout["logps"], rollout["rewards"], values[:T], values[T], discounts)
    params = {name: p.detach().clone() for name, p in [*student.named_parameters(), *encoder.named_parameters()]}
    metrics = amigo.student_update(agent, amigo.student_batch(rollout, last, "cpu"), STUDENT_ARGS)
    assert metrics["baseline_loss"].item() == pytest.approx(0.5 * ((vs - values[:T]) ** 2).mean(1).sum(), rel=1e-4)
    assert metrics["codes"] is None and metrics["vq_loss"].item() == 0
    for name, p in [*student.named_parameters(), *encoder.named_parameters()]:
        assert not torch.equal(p, params[name]), name  # the continuous goal encoder learns from the student's loss


def test_linear_decay_reaches_zero_at_the_budget():
    assert [amigo.linear_decay(frames, 1000) for frames in (0, 250, 1000, 1200)] == [1.0, 0.75, 0.0, 0.0]


@pytest.mark.parametrize("groups", [0, 4])
def test_the_student_step_is_on_the_rl_loss_plus_the_commitment_reduced_the_same_way(groups, monkeypatch):
    """The loss student_update steps on, caught at `learn`: the three terms as actor_critic_loss reduces them, plus
    (DGRL) the commitment loss summed over time and averaged over the batch: its mean over the (T + 1) * B goals times
    T + 1. A batch of each rollout twice steps on the same loss as the batch once (no term grows with B)."""
    seen = []
    monkeypatch.setattr(amigo, "learn", lambda optimizer, loss, max_grad_norm: seen.append(loss.detach()))
    agent = tiny_agent(groups=groups)
    rollout, last = collect(amigo.MiniGridVecEnv(DOORKEY, 2), agent, steps=4)
    T = rollout["actions"].shape[0]
    twice = {key: np.concatenate([value, value], 1) for key, value in rollout.items()}
    last_twice = {key: np.concatenate([value, value]) for key, value in last.items()}
    metrics = amigo.student_update(agent, amigo.student_batch(rollout, last, "cpu"), STUDENT_ARGS)
    rl = metrics["policy_loss"] + 0.5 * metrics["baseline_loss"] - 0.0005 * metrics["entropy"] * T
    assert seen[0].item() == pytest.approx((rl + metrics["vq_loss"] * (T + 1)).item(), rel=1e-5)
    assert (metrics["vq_loss"].item() > 0) == (groups > 0)
    if groups == 0:  # (under DGRL the codebook's EMA moved in the first call)
        amigo.student_update(agent, amigo.student_batch(twice, last_twice, "cpu"), STUDENT_ARGS)
        assert seen[1].item() == pytest.approx(seen[0].item(), rel=1e-5)


def test_the_teachers_logits_are_never_below_minus_one():
    """An ELU after the teacher's last conv, as in the original: however large its weights, no cell's logit is below
    -1, so no cell's probability goes to zero (without it, these weights put logits far below -1)."""
    teacher = amigo.Teacher(5, 5)
    with torch.no_grad():
        for conv in teacher.net:
            if isinstance(conv, torch.nn.Conv2d):
                conv.weight.mul_(20.0)
        frames = amigo.MiniGridVecEnv(DOORKEY, 4).reset(seed=0)[0]["grid"]
        logits = teacher(torch.as_tensor(frames))[0]
        before_elu = teacher.net[:-2](teacher.embedding(torch.as_tensor(frames))).flatten(1)
    assert logits.min().item() >= -1.0 and before_elu.min().item() < -5.0
    torch.testing.assert_close(logits, F.elu(before_elu))


def test_the_learning_rates_step_per_update_as_amigos_schedulers_do(run_script, tmp_path):
    """Both optimizers follow AMIGo's LambdaLR, stepped once per update of each: the k-th update at 1 - k * T * B / total,
    T * B one student batch of frames. After a tiny run, each optimizer's rate is its flag's times that factor, k its
    own update count: the student's follows the frames (0 at the end), the teacher's only its few updates."""
    result = run_script("dgrl_amigo.py", *TINY, "--checkpoint-every", "0")
    assert result.returncode == 0, result.stderr[-3000:]
    (run_dir,) = (tmp_path / "runs").iterdir()
    saved = torch.load(run_dir / "resume.pt", weights_only=False)
    loop, args, batch_frames = saved["loop"], saved["args"], 8 * 1  # --num-steps 8, --batch-envs 1
    for name, updates, lr in (
        ("student", "student_updates", "learning_rate"),
        ("teacher", "teacher_updates", "teacher_learning_rate"),
    ):
        (group,) = saved[f"{name}_optimizer"]["param_groups"]
        factor = max(1 - loop[updates] * batch_frames / args["total_timesteps"], 0.0)
        assert float(group["lr"]) == pytest.approx(args[lr] * factor), (name, loop[updates])
    assert 0 < loop["teacher_updates"] < loop["student_updates"]  # the teacher's rate stays high, the student's is 0


# --- the --fast path --------------------------------------------------------------------------------------------------


def student_batches(agent, n: int) -> list[dict[str, torch.Tensor]]:
    """`n` learner batches of 2 rollouts of 8 steps from one collected rollout, each with its own rewards, episode ends
    and behaviour log-probabilities (off-policy ratios), as student_batch's tensors."""
    rollout, last = collect(amigo.MiniGridVecEnv(DOORKEY, 2), agent, steps=8)
    rng = np.random.default_rng(1)
    batches = []
    for _ in range(n):
        varied = rollout | {
            "rewards": (rng.random((8, 2)) < 0.3).astype(np.float32),
            "dones": (rng.random((8, 2)) < 0.1).astype(np.float32),
            "logps": (rollout["logps"] + rng.normal(0.0, 0.3, (8, 2))).astype(np.float32),
        }
        batches.append(amigo.student_batch(varied, last, "cpu"))
    return batches


def teacher_batches(n: int, size: int = 8) -> list[dict[str, torch.Tensor]]:
    """`n` teacher batches of `size` goal outcomes on the reset frames of `size` envs, as teacher_tensors' tensors."""
    frames = amigo.MiniGridVecEnv(DOORKEY, size).reset(seed=0)[0]["grid"]
    rng = np.random.default_rng(2)
    batches = []
    for _ in range(n):
        batch = {
            "frame": frames,
            "goal": rng.integers(25, size=size),
            "logp": rng.uniform(-4.0, -2.0, size).astype(np.float32),
        }
        batches.append(amigo.teacher_tensors(batch, rng.choice([-0.3, 0.7, 1.0], size), "cpu"))
    return batches


@pytest.mark.parametrize("groups", [0, 4])
def test_fast_student_update_equals_eager_and_is_free_of_host_syncs(groups):
    """--fast compile: student_update compiled (goal encoder with the codebook's EMA and dead-code restarts under
    DGRL, V-trace, backward, gradient clipping, RMSprop step) and equal to eager."""
    agent = tiny_agent(groups, vq_dead_code_steps=3)
    batches = student_batches(agent, 31)

    def call(function, state, i):
        metrics = function(state, batches[i], STUDENT_ARGS)
        return {name: value for name, value in metrics.items() if value is not None}  # AMIGo has no codes

    check_fast_update(amigo, amigo.student_update, agent, call, lambda state: [state.student_optimizer])


def test_fast_teacher_update_equals_eager_and_is_free_of_host_syncs():
    """--fast compile: teacher_update compiled (the teacher's loss, backward, gradient clipping, RMSprop step)."""
    agent = tiny_agent(groups=0)
    batches = teacher_batches(31)
    args = amigo.Args(teacher_baseline_coef=0.5, teacher_entropy_coef=0.05, max_grad_norm=40.0)

    def call(function, state, i):
        return function(state, batches[i], args)

    check_fast_update(amigo, amigo.teacher_update, agent, call, lambda state: [state.teacher_optimizer])


def test_learning_rates_as_tensors_keep_eager_steps_identical():
    """The decaying learning rate as a 0-d tensor set in place (what --fast compile uses) steps RMSprop exactly as the
    float it replaces; and back to floats for eager."""
    import copy

    agents = [tiny_agent(groups=4)]
    agents.append(copy.deepcopy(agents[0]))
    amigo.learning_rates_as_tensors([agents[1].student_optimizer], as_tensors=True)
    assert agents[1].student_optimizer.param_groups[0]["lr"].shape == ()
    batches = student_batches(agents[0], 3)
    for i, batch in enumerate(batches):
        for agent in agents:
            amigo.set_learning_rate(agent.student_optimizer, 1e-3 * amigo.linear_decay(i * 300, 1000))
            amigo.student_update(agent, batch, STUDENT_ARGS)
    expected, got = training_tensors(agents[0]), training_tensors(agents[1])
    assert expected.keys() == got.keys()
    for key, tensor in expected.items():
        assert torch.equal(got[key], tensor), key
    amigo.learning_rates_as_tensors([agents[1].student_optimizer], as_tensors=False)
    assert agents[1].student_optimizer.param_groups[0]["lr"] == pytest.approx(1e-3 * 0.4)


def test_fast_student_update_follows_a_decaying_learning_rate_without_recompiling():
    """--fast compile with the run's schedule: a 0-d tensor learning rate written in place before every update; the
    compiled update equals the eager one with float learning rates, and never recompiles."""
    import copy

    torch._dynamo.reset()
    agent = tiny_agent(groups=4)
    batches = student_batches(agent, 6)
    eager, fast = agent, copy.deepcopy(agent)
    amigo.learning_rates_as_tensors([fast.student_optimizer], as_tensors=True)
    update = amigo.fast_update(amigo.student_update, "compile", [fast.student_optimizer])
    with torch._dynamo.config.patch(recompile_limit=1):
        for i, batch in enumerate(batches):
            for state, function in ((eager, amigo.student_update), (fast, update)):
                amigo.set_learning_rate(state.student_optimizer, 1e-3 * amigo.linear_decay(i * 100, 1000))
                function(state, batch, STUDENT_ARGS)
    for key, value in training_tensors(eager).items():
        torch.testing.assert_close(training_tensors(fast)[key], value, rtol=1e-5, atol=1e-5)


# --- evaluation with scripted networks --------------------------------------------------------------------------------


class ForwardStudent(nn.Module):
    """Always moves forward."""

    embed_dim = 16

    def forward(self, grids, carried, goals, goal_embedding):
        logits = torch.full((len(grids), 7), -50.0)
        logits[:, FORWARD] = 50.0
        return logits, torch.zeros(len(grids))


class FixedTeacher(nn.Module):
    """Always proposes the same cell."""

    def __init__(self, goal: int, cells: int):
        super().__init__()
        self.goal, self.cells = goal, cells

    def forward(self, grids):
        logits = torch.full((len(grids), self.cells), -50.0)
        logits[:, self.goal] = 50.0
        return logits, torch.zeros(len(grids))


def scripted_agent(goal: int) -> amigo.Agent:
    return dataclasses.replace(tiny_agent(groups=0), student=ForwardStudent(), teacher=FixedTeacher(goal, 25))


def test_evaluate_counts_goals_on_the_frame_before_the_reset():
    # Empty-5x5: the agent starts at (1, 1) facing right and walks to (3, 1), the goal cell, in two steps, then stays
    # against the wall until the 100-step limit. The goal re-issued there never changes again, and the reset frame
    # (where (3, 1) is empty) must not count as reaching it.
    envs = amigo.MiniGridVecEnv(EMPTY, 1)
    result = amigo.evaluate(scripted_agent(cell(3, 1, 5)), envs, 2, 0, "cpu")
    assert result == {"episodes": 2, "return": 0.0, "success": 0.0, "goals_per_episode": 1.0}


def test_evaluate_stops_when_a_signal_came():
    envs = amigo.MiniGridVecEnv(EMPTY, 1)
    result = amigo.evaluate(scripted_agent(cell(3, 1, 5)), envs, 2, 0, "cpu", stop=[signal.SIGINT])
    assert result["episodes"] == 0 and math.isnan(result["return"])


# --- flags ------------------------------------------------------------------------------------------------------------


def refusal(capsys, **overrides) -> str:
    """validate's message for Args(**overrides), after asserting it exits with status 2 (as for an unknown flag)."""
    with pytest.raises(SystemExit) as error:
        amigo.validate(amigo.Args(**overrides))
    assert error.value.code == 2
    message = capsys.readouterr().err
    assert message.startswith("dgrl_amigo.py: invalid arguments:")
    return message


@pytest.mark.parametrize(
    ("overrides", "messages"),
    [
        ({"env_id": "DoorKey-5x5"}, ["--env-id 'DoorKey-5x5' is not a MiniGrid id", "did you mean MiniGrid-DoorKey-5x5-v0"]),
        ({"env_id": "CartPole-v1"}, ["--env-id 'CartPole-v1'", "choices: ", "MiniGrid-KeyCorridorS3R3-v0"]),
        ({"groups": 5}, ["--groups must be 0 (AMIGo) or divide --embed-dim 128", "got 5"]),
        ({"groups": 3, "embed_dim": 32}, ["divide --embed-dim 32: one of [1, 2, 4, 8, 16, 32]"]),
        ({"groups": -1}, ["--groups must be 0 (AMIGo) or divide --embed-dim 128", "got -1"]),
        ({"num_envs": 16, "batch_envs": 3}, ["--batch-envs (3) must divide --num-envs (16)"]),
        ({"num_envs": 8, "batch_envs": 16}, ["--batch-envs (16) must divide --num-envs (8)"]),
        ({"total_timesteps": 1599}, ["--total-timesteps (1599) must cover one collection", "(1600)"]),
        ({"t_star_start": 20, "t_star_max": 10}, ["--t-star-start (20) must be in [0, --t-star-max (10)]"]),
        ({"t_star_threshold": 1.5}, ["--t-star-threshold must be <= 1", "got 1.5"]),
        ({"teacher_batch_size": 0}, ["--teacher-batch-size must be >= 1; got 0"]),
        ({"num_envs": 0}, ["--num-envs must be >= 1; got 0"]),
        ({"video_frequency": 0}, ["--video-frequency must be >= 1; got 0"]),
        ({"seed": -1}, ["--seed must be in [0, 2**64) (what numpy, gymnasium and torch accept); got -1"]),
        ({"gamma": 0.0}, ["--gamma must be in (0, 1]; got 0.0"]),
        ({"gamma": 1.5}, ["--gamma must be in (0, 1]; got 1.5"]),
        ({"learning_rate": -1.0}, ["--learning-rate must be > 0; got -1.0"]),
        ({"teacher_learning_rate": 0.0}, ["--teacher-learning-rate must be > 0; got 0.0"]),
        ({"max_grad_norm": 0.0}, ["--max-grad-norm must be > 0; got 0.0"]),
        ({"rmsprop_alpha": 1.0}, ["--rmsprop-alpha must be in [0, 1); got 1.0"]),
        ({"intrinsic_coef": -1.0}, ["--intrinsic-coef must be >= 0; got -1.0"]),
        ({"entropy_coef": math.inf}, ["--entropy-coef must be a finite number; got inf"]),
        ({"vq_decay": 1.5}, ["--vq-decay must be in [0, 1); got 1.5"]),
        ({"vq_decay": 1.0}, ["--vq-decay must be in [0, 1); got 1.0"]),
        ({"vq_beta": -0.25}, ["--vq-beta must be >= 0; got -0.25"]),
        ({"n_embed": 0}, ["--n-embed must be >= 1; got 0"]),
        ({"vq_dead_code_steps": -1}, ["--vq-dead-code-steps must be >= 0; got -1"]),
        ({"checkpoint": "missing.pt"}, ["--checkpoint missing.pt: no such file"]),
    ],
)
def test_validate_names_the_flag(capsys, overrides, messages):
    message = refusal(capsys, **overrides)
    for expected in messages:
        assert expected in message


def test_validate_refuses_training_flags_with_a_checkpoint(capsys, tmp_path):
    (tmp_path / "saved.pt").write_bytes(b"")
    message = refusal(capsys, checkpoint=str(tmp_path / "saved.pt"), save_model=True)
    assert "--save-model and --capture-video apply to training" in message


def test_validate_refuses_a_minigrid_id_that_fails_to_build(capsys):
    class Broken(gym.Env):  # e.g. minigrid's WFC envs when the package was installed without their pattern images
        observation_space = action_space = gym.spaces.Discrete(2)

        def reset(self, *, seed=None, options=None):
            raise FileNotFoundError("patterns/SimpleMaze.png")

    gym.register("MiniGrid-BrokenForTest-v0", entry_point=Broken)
    try:
        message = refusal(capsys, env_id="MiniGrid-BrokenForTest-v0")
    finally:
        del gym.registry["MiniGrid-BrokenForTest-v0"]
    assert "--env-id MiniGrid-BrokenForTest-v0 fails to build or reset here (FileNotFoundError: patterns/SimpleMaze.png)" in (
        message
    )


def test_validate_accepts_the_defaults_and_a_tiny_run():
    amigo.validate(amigo.Args())
    amigo.validate(amigo.Args(env_id=DOORKEY, num_envs=4, batch_envs=2, num_steps=8, total_timesteps=32, groups=0))
    assert DOORKEY in amigo.minigrid_ids() and all(name.startswith("MiniGrid-") for name in amigo.minigrid_ids())


# --- smoke runs -------------------------------------------------------------------------------------------------------

TINY = [
    "--env-id", DOORKEY, "--num-envs", "10", "--batch-envs", "1", "--num-steps", "8", "--total-timesteps", "160",
    "--progress-frequency", "80", "--teacher-batch-size", "1", "--seed", "4",
]  # fmt: skip


def assert_clean_refusal(result, *words: str) -> None:
    assert result.returncode == 2, result.stdout + result.stderr
    assert "Traceback" not in result.stderr, result.stderr
    for word in words:
        assert word in result.stderr, (word, result.stderr)


def test_smoke_run_amigo_saves_evaluates_and_refuses_other_settings(run_script, tmp_path):
    result = run_script("dgrl_amigo.py", *TINY, "--groups", "0", "--save-model")
    assert result.returncode == 0, result.stderr
    assert re.search(r"frame +80/160  return .* t\* 7 .* SPS \d+", result.stdout)
    done = re.search(r"done: 160 frames, 20 student and (\d+) teacher updates, t\* 7; \d+s; logs in runs/", result.stdout)
    assert done and int(done.group(1)) >= 1, result.stdout
    checkpoint = next(tmp_path.glob("runs/*/dgrl_amigo.cleanrl_model"))
    saved = torch.load(checkpoint, weights_only=True)  # tensors and plain values only
    assert saved["script"] == "dgrl_amigo.py" and saved["format"] == amigo.CHECKPOINT_FORMAT
    assert saved["t_star"] == 7 and saved["step"] == 160 and saved["args"]["groups"] == 0
    assert {"student", "goal_encoder", "teacher"} <= set(saved)
    assert not any(key.startswith("vq.") for key in saved["goal_encoder"])
    events = next(tmp_path.glob("runs/*/events.out.tfevents.*")).read_bytes()
    for tag in (b"teacher/t_star", b"teacher/reward", b"losses/baseline_loss", b"charts/SPS"):
        assert tag in events
    assert b"vq/perplexity" not in events
    evaluation = run_script(
        "dgrl_amigo.py", "--env-id", DOORKEY, "--groups", "0", "--num-envs", "2", "--batch-envs", "2", "--eval-episodes", "2",
        "--checkpoint", str(checkpoint),
    )  # fmt: skip
    assert evaluation.returncode == 0, evaluation.stderr
    assert re.search(
        r"2 episodes \(t\* 7 at save\): return [\d.]+, success \d+%, goals reached per episode [\d.]+", evaluation.stdout
    )
    assert saved["args"]["goal_channel"] == "on" and saved["student"]["trunk.0.weight"].shape[1] == 11  # auto, resolved
    mismatched = run_script("dgrl_amigo.py", "--env-id", DOORKEY, "--groups", "16", "--checkpoint", str(checkpoint))
    assert_clean_refusal(mismatched, "was saved with other settings: pass --groups 0 --goal-channel on")
    unmapped = run_script(
        "dgrl_amigo.py", "--env-id", DOORKEY, "--groups", "0", "--goal-channel", "off", "--checkpoint", str(checkpoint)
    )
    assert_clean_refusal(unmapped, "was saved with other settings: pass --goal-channel on")


def test_smoke_run_dgrl_with_video(run_script, tmp_path):
    flags = [
        "--env-id", EMPTY, "--groups", "16", "--num-envs", "10", "--batch-envs", "1", "--num-steps", "10",
        "--total-timesteps", "1000", "--progress-frequency", "500", "--teacher-batch-size", "4",
        "--capture-video", "--video-frequency", "1",
    ]  # fmt: skip
    result = run_script("dgrl_amigo.py", *flags)
    assert result.returncode == 0, result.stderr
    assert re.search(r"done: 1000 frames, 100 student and \d+ teacher updates", result.stdout)
    assert list(tmp_path.glob("videos/*/episode_0.mp4"))  # env 0's first episode ends within 100 steps
    events = next(tmp_path.glob("runs/*/events.out.tfevents.*")).read_bytes()
    for tag in (b"vq/perplexity", b"vq/active_codes", b"vq/commit_loss", b"teacher/t_star"):
        assert tag in events


def test_bad_flags_fail_before_any_work(run_script, tmp_path):
    result = run_script(
        "dgrl_amigo.py", "--groups", "5", "--batch-envs", "3", "--gamma", "0", "--learning-rate", "-1", "--vq-decay", "1.5",
        "--seed", "-1", "--total-timesteps", "100",
    )  # fmt: skip
    assert_clean_refusal(
        result, "--groups must be 0 (AMIGo) or divide --embed-dim 128", "--batch-envs (3) must divide --num-envs (16)",
        "--gamma must be in (0, 1]", "--learning-rate must be > 0", "--vq-decay must be in [0, 1)",
        "--seed must be in [0, 2**64)",
        "--total-timesteps (100) must cover one collection",
    )  # fmt: skip
    assert not (tmp_path / "runs").exists()


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--goal-channel", "maybe"], "invalid choice 'maybe'"),
        (["--no-goal-channel"], "Unrecognized options: --no-goal-channel"),
    ],
)
def test_goal_channel_takes_auto_on_or_off_only(run_script, tmp_path, flags, message):
    result = run_script("dgrl_amigo.py", *TINY, *flags)
    assert_clean_refusal(result, message, "--goal-channel {auto,on,off}" if "--no-goal-channel" in flags else "'off'")
    assert not (tmp_path / "runs").exists()


# --- stopping and resuming --------------------------------------------------------------------------------------------

RESUME_FLAGS = [
    "--env-id", DOORKEY, "--num-envs", "4", "--batch-envs", "2", "--num-steps", "20", "--total-timesteps", "4000",
    "--progress-frequency", "800", "--teacher-batch-size", "20", "--seed", "3", "--save-model",
]  # fmt: skip


def test_resume_after_the_first_progress_line_equals_a_straight_run(resume_check):
    """DGRL stopped early (envs mid-episode, goals pending, teacher outcomes waiting, a codebook with dead-code restarts)."""
    output = resume_check("dgrl_amigo.py", [*RESUME_FLAGS, "--groups", "16", "--vq-dead-code-steps", "5"], r"^frame +800/")
    assert 800 <= int(re.search(r"stopped: (\d+) frames", output).group(1)) < 4000


def test_resume_after_the_second_progress_line_equals_a_straight_run_and_its_videos(resume_check, tmp_path):
    """AMIGo (G = 0) stopped later, recording every episode of env 0: the video in progress at the stop carries on."""
    flags = [*RESUME_FLAGS, "--groups", "0", "--capture-video", "--video-frequency", "1"]
    output = resume_check("dgrl_amigo.py", flags, r"^frame +1600/")
    assert 1600 <= int(re.search(r"stopped: (\d+) frames", output).group(1)) < 4000
    straight = {path.name: path.stat().st_size for path in tmp_path.glob("straight/videos/*/*.mp4")}
    resumed = {path.name: path.stat().st_size for path in tmp_path.glob("stopped/videos/*/*.mp4")}
    assert resumed == straight and len(straight) >= 2


def test_resume_after_a_kill_continues_from_the_last_periodic_save(kill_check):
    """SIGKILL (no grace) at the progress line of frame 3240, mid-window after the periodic save at frame 3024 (every 1000
    frames: saves where a collection of 108 frames passes a multiple): the resumed run purges what the killed run logged
    after the save and ends like a straight run. KeyCorridorS3R1 with 27-step unrolls: episodes end by truncation on a
    collection's last step (270 = 10 x 27) and a random student never solves it, so no episode ends on a collection's
    first step, whose scalars would be logged at the saved frame and kept twice (see the docs)."""
    flags = [
        "--env-id", CORRIDOR, "--num-envs", "4", "--batch-envs", "2", "--num-steps", "27", "--total-timesteps", "6480",
        "--progress-frequency", "1080", "--teacher-batch-size", "20", "--seed", "5", "--groups", "16", "--save-model",
        "--checkpoint-every", "0", "--checkpoint-every-steps", "1000",
    ]  # fmt: skip
    saved, resumed = kill_check("dgrl_amigo.py", flags, r"^frame +3240/")
    assert saved["loop"]["step"] == 3024 and "resume.pt at frame 3024" in resumed


def test_resume_refuses_changed_flags_and_keeps_images_uint8(run_script, tmp_path):
    model = ["--groups", "4", "--embed-dim", "16", "--n-embed", "8"]
    result = run_script("dgrl_amigo.py", *TINY, *model)
    assert result.returncode == 0, result.stderr
    (run_dir,) = (tmp_path / "runs").iterdir()
    saved = torch.load(run_dir / "resume.pt", weights_only=False)
    assert saved["loop"]["step"] == 160 and saved["envs"]["grids"].dtype == saved["goal_book"]["frame"].dtype == np.uint8
    assert saved["args"]["goal_channel"] == "off"  # auto, resolved for DGRL before the run started
    assert saved["networks"]["student"]["trunk.0.weight"].shape[1] == 10  # no goal map: the goal only as codes
    resume = ["--resume", f"runs/{run_dir.name}"]
    changed = run_script("dgrl_amigo.py", *TINY, *model, "--seed", "5", "--goal-channel", "on", *resume)
    assert_clean_refusal(changed, "was started with other settings: pass --goal-channel off --seed 4")
    finished = run_script("dgrl_amigo.py", *TINY, *model, *resume, "--no-save-model")  # a free flag may change
    assert finished.returncode == 0, finished.stderr
    assert "resumed from" in finished.stdout and "done: 160 frames" in finished.stdout
