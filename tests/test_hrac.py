"""dgrl_hrac.py: the HIRO Ant suite's environments (structure-to-MJCF geometry against the reference tables, movable
joints and their ranges, the elevated platform of AntFall, the ant's edits, observations, resets, goals, rewards, success
tests and AntGather's sensors), HRAC's computations (subgoal transition, controller reward, off-policy correction,
adjacency labels and losses, the TD3 step), the agent's updates under DGRL, evaluation, flag validation and smoke runs of
every env id in both modes (train, checkpoint, evaluate, video, Ctrl-C), and exact resumes (the envs', replays' and
adjacency memory's states alone; whole runs stopped by SIGTERM, or killed outright after a periodic resume write, and
continued with --resume)."""

import re
import subprocess
from pathlib import Path

import mujoco
import numpy as np
import pytest
import torch
from conftest import HANG_TIMEOUT, check_fast_update, signal_at_line, tensorboard_scalars

import dgrl_hrac as hrac

ROOT = Path(__file__).resolve().parent.parent
ENV_IDS = ("AntMaze", "AntMazeSparse", "AntPush", "AntFall", "AntGather")


def geom(model, name):
    return model.geom(mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, name))


def test_maze_blocks_match_the_reference_layout():
    """AntMaze (scaling 8, robot at row 1 col 1): every 1 cell is a box of half-size 4 x 4 x 2 centred at z = 2."""
    blocks = {b["name"]: b for b in hrac.structure_blocks("AntMaze")}
    expected = [(i, j) for i, row in enumerate(hrac.STRUCTURES["AntMaze"][1]) for j, c in enumerate(row) if c == 1]
    assert sorted(blocks) == sorted(f"block_{i}_{j}" for i, j in expected)
    assert blocks["block_0_0"]["pos"] == (-8.0, -8.0, 2.0)
    assert blocks["block_2_2"]["pos"] == (8.0, 8.0, 2.0)  # the U's inner wall, between start and evaluation goal
    for block in blocks.values():
        assert block["size"] == (4.0, 4.0, 2.0) and block["axes"] == ""


def test_goals_lie_in_free_cells_and_starts_at_the_origin():
    for env_id, goal in hrac.EVAL_GOALS.items():
        scaling, structure = hrac.STRUCTURES[env_id]
        origin = hrac.structure_origin(structure)
        i, j = round(goal[1] / scaling) + origin[0], round(goal[0] / scaling) + origin[1]
        assert structure[i][j] in (0, "r"), env_id


def test_push_block_slides_freely_in_x_and_y():
    model = mujoco.MjModel.from_xml_string(hrac.hiro_ant_xml("AntPush"))
    body = model.body("movable_2_2")
    np.testing.assert_allclose(body.pos, (0.0, 8.0, 2.0))
    joints = [model.joint(j) for j in range(model.njnt) if model.joint(j).name.startswith("movable_2_2")]
    assert sorted(j.name for j in joints) == ["movable_2_2_x", "movable_2_2_y"]
    assert all(j.type[0] == mujoco.mjtJoint.mjJNT_SLIDE and not j.limited[0] for j in joints)
    np.testing.assert_allclose(geom(model, "movable_2_2_geom").size, (4.0, 4.0, 2.0))
    assert geom(model, "movable_2_2_geom").solimp[:3].tolist() == pytest.approx([0.995, 0.995, 0.01])
    assert model.nq == 17 and model.nv == 16  # the ant's 15 / 14 first, then the block's two slides


def test_fall_has_a_platform_with_a_chasm_and_a_falling_block():
    blocks = {b["name"]: b for b in hrac.structure_blocks("AntFall")}
    structure = hrac.STRUCTURES["AntFall"][1]
    for i, row in enumerate(structure):
        for j, cell in enumerate(row):
            assert (f"platform_{i}_{j}" in blocks) == (cell != -1)
    assert blocks["platform_1_1"]["pos"][2] == 2.0 and blocks["platform_1_1"]["size"][2] == 2.0  # height 4
    assert blocks["block_0_0"]["pos"][2] == 6.0  # walls stand on the platform
    falling = blocks["movable_2_2"]
    assert falling["axes"] == "yz" and falling["size"] == (3.96, 3.96, 2.0) and falling["mass"] == 0.001
    model = mujoco.MjModel.from_xml_string(hrac.hiro_ant_xml("AntFall"))
    z = model.joint("movable_2_2_z")
    assert z.limited[0] and z.range.tolist() == [-4.0, 0.0]
    assert model.joint("movable_2_2_y").range.tolist() == [-8.0, 8.0]
    assert model.body("torso").pos[2] == pytest.approx(4.75)


def test_ant_is_edited_as_hiro():
    model = mujoco.MjModel.from_xml_string(hrac.hiro_ant_xml("AntMaze"))
    assert model.opt.timestep == pytest.approx(0.02) and model.opt.integrator == mujoco.mjtIntegrator.mjINT_RK4
    assert np.all(model.actuator_gear[:, 0] == 1) and np.all(model.actuator_ctrlrange == [-30, 30])
    assert model.nu == 8


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_every_env_resets_and_steps(env_id):
    env = hrac.HiroAntEnv(env_id)
    obs, _ = env.reset(seed=0)
    assert obs.shape == env.observation_space.shape == ((50,) if env_id == "AntGather" else (30,))
    rng = np.random.default_rng(0)
    for _ in range(5):
        obs, reward, terminated, truncated, _ = env.step(rng.uniform(-30, 30, 8))
        assert np.isfinite(obs).all() and np.isfinite(reward) and not terminated and not truncated
    assert obs[29 if env_id != "AntGather" else 49] == pytest.approx(5 * (0.01 if env_id == "AntGather" else 0.001))


def test_reset_noise_and_truncation():
    env = hrac.HiroAntEnv("AntMaze")
    obs, _ = env.reset(seed=3)
    assert np.all(np.abs(obs[:2]) <= 0.1) and abs(obs[2] - 0.75) <= 0.1
    for _ in range(hrac.EPISODE_STEPS - 1):
        *_, truncated, _ = env.step(np.zeros(8))
        assert not truncated
    *_, truncated, _ = env.step(np.zeros(8))
    assert truncated


def test_maze_goals_rewards_and_success():
    train, test = hrac.HiroAntEnv("AntMaze"), hrac.HiroAntEnv("AntMaze", evaluate=True)
    goals = []
    for seed in range(200):
        train.reset(seed=seed)
        goals.append(train.goal)
    goals = np.array(goals)
    assert goals.min() >= -4 and goals.max() <= 20 and goals.min() < -3 and goals.max() > 19
    test.reset(seed=0)
    assert test.goal.tolist() == [0.0, 16.0]
    test.data.qpos[:2] = (0.0, 12.0)
    _, reward, _, _, info = test.step(np.zeros(8))
    xy = test.data.qpos[:2]
    assert reward == pytest.approx(-np.linalg.norm(xy - (0, 16)))
    assert info["success"] == (np.linalg.norm(xy - (0, 16)) < 5)


def test_sparse_starts_on_robot_cells_and_rewards_one_within_one():
    env = hrac.HiroAntEnv("AntMazeSparse")
    scaling, structure = hrac.STRUCTURES["AntMazeSparse"]
    starts = set()
    for seed in range(300):
        env.reset(seed=seed)
        i, j = round(env.data.qpos[1] / scaling) + 1, round(env.data.qpos[0] / scaling) + 1
        assert structure[i][j] == "r"
        starts.add((i, j))
    assert len(starts) > 40  # 56 robot cells
    env.reset(seed=0)
    env.data.qpos[:2] = (2.0, 9.0)
    _, reward, _, _, info = env.step(np.zeros(8))
    assert reward == 1.0 and info["success"]
    env.data.qpos[:2] = (6.0, 9.0)
    _, reward, _, _, info = env.step(np.zeros(8))
    assert reward == 0.0 and not info["success"]


def test_fall_reward_uses_height():
    env = hrac.HiroAntEnv("AntFall")
    env.reset(seed=0)
    _, reward, *_ = env.step(np.zeros(8))
    np.testing.assert_allclose(-reward, np.linalg.norm(env.data.qpos[:3] - (0, 27, 4.5)))


def test_ant_stands_on_the_fall_platform():
    env = hrac.HiroAntEnv("AntFall")
    env.reset(seed=0)
    for _ in range(30):
        env.step(np.zeros(8))
    assert 4.2 < env.data.qpos[2] < 5.0  # on the 4 m platform, not through it


def test_gather_sensors_and_catching():
    readings = hrac.gather_readings(np.zeros(2), 0.0, np.array([[3.0, 0.0], [0.0, 7.0]]))
    # straight ahead falls in the middle bin (span 2*pi centred on the heading); the second object is out of range
    assert readings[hrac.GATHER["bins"] // 2] == pytest.approx(0.5) and readings.sum() == pytest.approx(0.5)
    behind = hrac.gather_readings(np.zeros(2), 0.0, np.array([[-3.0, 0.1]]))
    assert behind[-1] == pytest.approx(0.5, abs=1e-2) or behind[0] == pytest.approx(0.5, abs=1e-2)
    env = hrac.HiroAntEnv("AntGather")
    env.reset(seed=1)
    assert len(env.objects) == 16 and np.all(np.linalg.norm(env.objects, axis=1) >= 2)
    env.objects[0] = env.data.qpos[:2]  # an apple under the ant
    env.objects[8] = env.data.qpos[:2] + np.array([0.3, 0.0])  # a bomb next to it
    _, reward, *_ = env.step(np.zeros(8))
    assert reward == 0.0 and len(env.objects) == 14


def test_push_block_slides_when_pushed_and_fixed_blocks_are_world_geoms():
    """A push of 0.5 N in +x on the block, centred in its cell, slides it in x only. (Whether the ant itself can push
    it far enough, given the block's contacts with the floor and the walls it touches edge to edge, is for the agent's
    runs to show; with the reset noise on its joints the block can start pressed into a neighbouring wall.)"""
    env = hrac.HiroAntEnv("AntPush")
    env.reset(seed=0)
    env.data.qpos[15:17], env.data.qvel[14:16] = 0.0, 0.0
    mujoco.mj_forward(env.model, env.data)
    body = mujoco.mj_name2id(env.model, mujoco.mjtObj.mjOBJ_BODY, "movable_2_2")
    env.data.xfrc_applied[body, :3] = (0.5, 0.0, 0.0)
    for _ in range(20):
        env.step(np.zeros(8))
    assert env.data.qpos[15] > 0.3 and abs(env.data.qpos[16]) < 0.05
    assert mujoco.mj_name2id(env.model, mujoco.mjtObj.mjOBJ_BODY, "block_0_0") == -1


def test_fall_block_drops_into_the_chasm_but_not_on_the_platform():
    env = hrac.HiroAntEnv("AntFall")
    env.reset(seed=0)
    y, z = env.model.joint("movable_2_2_y").qposadr[0], env.model.joint("movable_2_2_z").qposadr[0]
    for _ in range(20):
        env.step(np.zeros(8))
    assert env.data.qpos[z] > -0.2  # resting on the platform
    env.data.qpos[y] = 8.0  # slid one cell on: over the chasm row
    for _ in range(40):
        env.step(np.zeros(8))
    assert env.data.qpos[z] < -3.5  # fell to the bottom of its range (-4)


# --- HRAC's building blocks -------------------------------------------------------------------------------------------


def test_subgoal_transition_keeps_the_absolute_target_and_the_reward_measures_it():
    rng = np.random.default_rng(0)
    s, s_next, g = rng.normal(size=(5, 30)), rng.normal(size=(5, 30)), rng.normal(size=(5, 2))
    g_next = hrac.subgoal_transition(s, g, s_next)
    np.testing.assert_allclose(s[:, :2] + g, s_next[:, :2] + g_next)
    np.testing.assert_allclose(hrac.controller_reward(s, g, s_next), -np.linalg.norm(s[:, :2] + g - s_next[:, :2], axis=1))
    s_next[:, :2] = s[:, :2] + g
    np.testing.assert_allclose(hrac.controller_reward(s, g, s_next), 0.0, atol=1e-12)
    g3 = rng.normal(size=(5, 3))  # AntFall's 3-d goals use xyz
    np.testing.assert_allclose(s[:, :3] + g3, s_next[:, :3] + hrac.subgoal_transition(s, g3, s_next))
    torch_reward = hrac.controller_reward(torch.as_tensor(s), torch.as_tensor(g), torch.as_tensor(s_next))
    np.testing.assert_allclose(torch_reward.numpy(), 0.0, atol=1e-12)


def test_controller_input_hides_only_xy():
    s = np.arange(1.0, 31.0)
    masked = hrac.controller_input(s)
    assert masked[:2].tolist() == [0, 0] and masked[2:].tolist() == s[2:].tolist() and s[0] == 1.0


class LinearController(torch.nn.Module):
    """A stand-in controller whose action is a fixed linear map of the relative subgoal (and of z)."""

    def __init__(self):
        super().__init__()
        self.weight = torch.nn.Parameter(
            torch.tensor([[1.0, 0.0, -2.0, 0.5, 0.0, 1.0, 0.3, -1.0], [0.0, 1.0, 1.0, 0.0, -1.0, 2.0, 0.0, 0.4]])
        )

    def forward(self, states, goals):
        return goals @ self.weight + 0.1 * states[..., 2:3]


def actions_for(controller, states, first_goals):
    """The controller's actions along stored states when its relative subgoal starts at `first_goals` and is
    re-targeted by the subgoal transition at every step."""
    batch, k = len(states), states.shape[1] - 1
    goals = np.empty((batch, k, 2))
    goals[:, 0] = first_goals
    for t in range(1, k):
        goals[:, t] = hrac.subgoal_transition(states[:, t - 1], goals[:, t - 1], states[:, t])
    with torch.no_grad():
        states_t = torch.as_tensor(hrac.controller_input(states[:, :k]), dtype=torch.float32)
        return controller(states_t, torch.as_tensor(goals, dtype=torch.float32)).numpy()


def correct(controller, states, actions, subgoals, scale, rng, n_samples=10, goal_encoder=None) -> np.ndarray:
    """off_policy_correction on numpy inputs, its noise drawn from `rng` as the training loop draws it."""
    noise = hrac.correction_noise(rng, len(subgoals), n_samples, scale)
    inputs = (torch.as_tensor(x) for x in (states, actions, subgoals, scale, noise))
    return hrac.off_policy_correction(controller, *inputs, goal_encoder=goal_encoder).numpy()


def numpy_correction(controller, states, actions, subgoals, scale, rng, n_samples=10, goal_encoder=None) -> np.ndarray:
    """The script's former numpy off-policy correction (the device's predictions read back to the host), the reference
    that the torch one must reproduce exactly, so that seeded runs are unchanged."""
    batch, k = actions.shape[:2]
    d = subgoals.shape[-1]
    achieved = states[:, -1, :d] - states[:, 0, :d]
    noise = rng.normal(0.0, 0.5 * scale, (batch, n_samples, d))
    candidates = np.concatenate([subgoals[:, None], achieved[:, None], np.clip(achieved[:, None] + noise, -scale, scale)], 1)
    n = candidates.shape[1]
    goals = np.empty((batch, n, k, d))
    goals[:, :, 0] = candidates
    for t in range(1, k):
        goals[:, :, t] = hrac.subgoal_transition(states[:, None, t - 1], goals[:, :, t - 1], states[:, None, t])
    observed = np.broadcast_to(states[:, None, :k], (batch, n, k, states.shape[-1]))
    with torch.no_grad():
        goals_in = hrac.controller_goal_input(goal_encoder, torch.as_tensor(goals, dtype=torch.float32))
        observed_in = torch.as_tensor(hrac.controller_input(observed), dtype=torch.float32)
        predicted = controller(observed_in, goals_in).numpy()
    log_likelihood = -0.5 * ((predicted - actions[:, None]) ** 2).sum(-1).sum(-1)
    return candidates[np.arange(batch), log_likelihood.argmax(1)]


def test_off_policy_correction_keeps_a_true_stored_subgoal_and_finds_a_true_achieved_one():
    rng = np.random.default_rng(0)
    controller, scale = LinearController(), np.array([10.0, 10.0])
    states = np.cumsum(rng.normal(0, 0.3, (16, 11, 30)), 1)  # 16 segments of k = 10 steps
    true_goals = rng.uniform(-5, 5, (16, 2))
    kept = correct(controller, states, actions_for(controller, states, true_goals), true_goals, scale, rng)
    np.testing.assert_allclose(kept, true_goals)
    # The stored subgoals are stale (an older manager's); the actions were taken for the achieved offset s_k - s_0.
    achieved = states[:, -1, :2] - states[:, 0, :2]
    stale = rng.uniform(-5, 5, (16, 2))
    corrected = correct(controller, states, actions_for(controller, states, achieved), stale, scale, rng)
    np.testing.assert_allclose(corrected, achieved, rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("groups", [0, 16])
def test_off_policy_correction_on_the_device_equals_the_former_numpy_one_exactly(groups):
    """On float32 replay samples, with the noise from the same generator: the same candidates, picked the same way,
    bit for bit (AntFall's 3-d subgoals, the real controller, under DGRL through the encoder)."""
    _, bounds, trained = agent(groups=groups, env_id="AntFall")
    rng = np.random.default_rng(5)
    states = np.cumsum(rng.normal(0, 0.3, (64, 11, 30)), 1).astype(np.float32)
    actions = rng.uniform(-30, 30, (64, 10, 8)).astype(np.float32)
    subgoals = rng.uniform(-bounds, bounds, (64, 3)).astype(np.float32)
    inputs = (trained.controller.actor, states, actions, subgoals, bounds)
    expected = numpy_correction(*inputs, np.random.default_rng(6), goal_encoder=trained.encoder)
    got = correct(*inputs, np.random.default_rng(6), goal_encoder=trained.encoder)
    assert got.dtype == expected.dtype == np.float64 and np.array_equal(got, expected)


def test_off_policy_correction_candidates_are_clipped_to_the_scale():
    rng = np.random.default_rng(1)
    controller = LinearController()
    states = np.zeros((4, 11, 30))
    states[:, -1, :2] = 100.0  # an achieved offset far outside the subgoal range
    actions = np.zeros((4, 10, 8))
    scale = np.array([10.0, 10.0])
    chosen = correct(controller, states, actions, np.zeros((4, 2)), scale, rng)
    assert np.all(np.abs(chosen) <= 100.0)
    np.testing.assert_allclose(chosen, 0.0)  # zero actions are explained exactly by the stored zero subgoal


def test_a_sparse_training_episode_terminates_at_the_first_segment_end_after_a_success():
    """HRAC's AntMazeSparse (envs/__init__.py:114-117): once the ant has been within 1 of the goal, the training episode
    ends, terminated, at the next multiple of the manager's period; leaving the goal does not undo it. An evaluation
    episode, and the other envs, never terminate."""
    env = hrac.HiroAntEnv("AntMazeSparse", segment=10)
    env.reset(seed=0)
    ends = []
    for step in range(1, 31):
        env.data.qpos[:2] = (2.0, 9.0) if step == 13 else (6.0, 9.0)  # the goal reached at step 13 only
        _, reward, terminated, truncated, _ = env.step(np.zeros(8))
        assert reward == float(step == 13) and not truncated
        ends.append(terminated)
        if terminated:
            break
    assert ends.index(True) == 19 and len(ends) == 20  # step 20: the first multiple of 10 after step 13
    state = env.state_dict()
    assert state["succeeded"]
    env.reset(seed=1)
    assert not env.succeeded
    env.load_state_dict(state)
    assert env.succeeded and env.steps == 20
    for evaluate, env_id in ((True, "AntMazeSparse"), (False, "AntMaze")):
        other = hrac.HiroAntEnv(env_id, evaluate=evaluate)
        other.reset(seed=0)
        other.data.qpos[:2] = other.goal[:2]
        assert not any(other.step(np.zeros(8))[2] for _ in range(20))


def test_an_episodes_end_is_a_terminal_for_both_levels(tmp_path, monkeypatch):
    """As in HRAC (train.py: the controller's done is the env's, which its envs/__init__.py:123 sets at 500 steps): the
    last step of an episode is stored done in the controller's replay, and its segment done in the manager's, so neither
    level bootstraps past it; the other steps stay not done. With every position a success, each training episode of
    AntMazeSparse lasts one segment (k = 10 steps); an AntMaze episode lasts 500."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setitem(hrac.SUCCESS_DISTANCE, "AntMazeSparse", 1e9)
    flags = {"eval_frequency": 10**6, "adj_frequency": 10**6, "hidden_dim": 16, "eval_episodes": 1, "ctrl_updates": 1}
    hrac.main(hrac.Args(env_id="AntMazeSparse", groups=0, total_timesteps=30, exp_name="sparse", **flags, man_updates=1))
    (resume,) = tmp_path.glob("runs/*/resume.pt")
    saved = torch.load(resume, weights_only=False)
    assert saved["ctrl_replay"]["size"] == 30 and saved["man_replay"]["size"] == 3
    assert saved["ctrl_replay"]["fields"]["dones"].tolist() == ([0.0] * 9 + [1.0]) * 3
    assert saved["man_replay"]["fields"]["dones"].tolist() == [1.0] * 3
    assert saved["loop"]["episodes"] == 3
    monkeypatch.chdir(tmp_path / "runs")
    hrac.main(hrac.Args(env_id="AntMaze", groups=0, total_timesteps=510, exp_name="maze", **flags, man_updates=1))
    (resume,) = tmp_path.glob("runs/runs/*/resume.pt")
    saved = torch.load(resume, weights_only=False)
    assert saved["ctrl_replay"]["fields"]["dones"][:510].tolist() == [0.0] * 499 + [1.0] + [0.0] * 10
    assert saved["man_replay"]["fields"]["dones"][:51].tolist() == [0.0] * 49 + [1.0, 0.0]


def test_contrastive_and_adjacency_losses_by_hand():
    a = torch.tensor([[0.0, 0.0], [0.0, 0.0], [0.0, 0.0]])
    b = torch.tensor([[3.0, 4.0], [0.6, 0.8], [0.3, 0.4]])  # distances 5, 1, 0.5
    labels = torch.tensor([1.0, 0.0, 0.0])
    # positives: max(0, 5 - 1) = 4 -> mean over 3 = 4/3; negatives: max(0, 1.2 - 1) + max(0, 1.2 - 0.5) = 0.9 -> 0.3
    assert hrac.contrastive_loss(a, b, labels).item() == pytest.approx(4 / 3 + 0.3, abs=1e-5)
    anet = hrac.AdjacencyNet(2)
    positions, subgoals = torch.randn(6, 30), torch.randn(6, 2) * 5
    distance = (anet(positions[:, :2]) - anet(positions[:, :2] + subgoals) + 1e-6).norm(dim=-1)  # HRAC's eps
    expected = (distance - 1.1).clamp(min=0).mean()
    assert hrac.adjacency_loss(anet, positions, subgoals).item() == pytest.approx(expected.item(), rel=1e-6)
    same = torch.zeros(1, 30)  # a zero subgoal: phi(s) - phi(s) = 0, distance sqrt(32) * 1e-6 (32 outputs), not 0
    assert hrac.adjacency_loss(anet, same, torch.zeros(1, 2), threshold=0.0).item() == pytest.approx(32**0.5 * 1e-6)


def test_adjacency_memory_marks_pairs_within_k_steps_of_one_trajectory():
    memory = hrac.AdjacencyMemory(k=3)
    memory.add_trajectory(np.array([[0.1, 0.0], [1.2, 0.0], [1.9, 0.2], [3.0, 0.0]]))  # cells (0,0) (1,0) (2,0) (3,0)
    memory.add_trajectory(np.array([[0.0, 5.2], [0.0, 5.4]]))  # one cell (0,5): no pair with itself
    cells_a, cells_b, labels = memory.labelled_pairs()
    pairs = {(tuple(a), tuple(b)): label for a, b, label in zip(cells_a, cells_b, labels, strict=True)}
    assert len(pairs) == 10  # 5 distinct cells
    assert pairs[((0, 0), (1, 0))] == 1 and pairs[((0, 0), (2, 0))] == 1  # 1 and 2 steps apart (j <= k - 1 = 2)
    assert pairs[((0, 0), (3, 0))] == 0  # 3 steps apart
    assert pairs[((0, 0), (0, 5))] == 0  # other trajectory
    assert sum(labels) == 5  # (0,1) (0,2) (1,2) (1,3) (2,3)


def test_networks_shapes_and_action_range():
    actor = hrac.Actor(30, 2, 8, max_action=30.0)
    actions = actor(torch.randn(5, 30) * 100, torch.randn(5, 2) * 100)
    assert actions.shape == (5, 8) and actions.abs().max() <= 30.0
    q1, q2 = hrac.TwinCritic(30, 2, 8)(torch.randn(5, 30), torch.randn(5, 2), actions)
    assert q1.shape == q2.shape == (5,) and not torch.equal(q1, q2)
    assert hrac.AdjacencyNet(2)(torch.randn(4, 2)).shape == (4, 32)


def test_replay_is_a_ring_of_preallocated_arrays_and_a_small_one_is_sampled_whole():
    replay = hrac.Replay(5, states=(2,), rewards=())
    for i in range(3):
        replay.add(states=(i, -i), rewards=float(i))
    rng = np.random.default_rng(0)
    before = rng.bit_generator.state
    batch = replay.sample(3, rng)  # no more entries than a batch: all of them, in order, no draw (HRAC's utils.py:34-35)
    assert batch["rewards"].tolist() == [0.0, 1.0, 2.0] and rng.bit_generator.state == before
    for i in range(3, 8):
        replay.add(states=(i, -i), rewards=float(i))
    assert replay.size == 5 and sorted(replay.fields["rewards"].tolist()) == [3.0, 4.0, 5.0, 6.0, 7.0]
    batch = replay.sample(4, rng)  # more than a batch: draws with replacement
    assert batch["states"].shape == (4, 2) and set(batch["rewards"].tolist()) <= {3.0, 4.0, 5.0, 6.0, 7.0}
    assert rng.bit_generator.state != before


def bandit_level(max_action: float) -> hrac.Level:
    """A small TD3 level built as the script builds its levels (targets, fused Adam, critic weight decay)."""
    actor, critic = hrac.Actor(3, 2, 2, max_action, hidden_dim=64), hrac.TwinCritic(3, 2, 2, hidden_dim=64)
    return hrac.make_level(actor, critic, hrac.Args(actor_lr=1e-3, critic_lr=1e-3, critic_weight_decay=1e-4))


TD3 = {"gamma": 0.99, "args": hrac.Args()}  # tau 0.005, policy_noise 0.2, noise_clip 0.5


def test_td3_update_learns_a_one_step_task_and_moves_the_targets_by_tau():
    """Reward -||a - g||^2 with every transition terminal: the actor must learn to output its goal."""
    rng = np.random.default_rng(0)
    level = bandit_level(max_action=1.0)
    before = [p.detach().clone() for p in level.actor_target.parameters()]
    online_before = [p.detach().clone() for p in level.actor.parameters()]
    for step in range(600):
        states, goals = torch.randn(128, 3), torch.as_tensor(rng.uniform(-0.8, 0.8, (128, 2)), dtype=torch.float32)
        actions = torch.as_tensor(rng.uniform(-1, 1, (128, 2)), dtype=torch.float32)
        batch = dict(
            states=states,
            goals=goals,
            actions=actions,
            rewards=-((actions - goals) ** 2).sum(1),
            next_states=states,
            next_goals=goals,
            dones=torch.ones(128),
        )
        metrics = hrac.td3_update(level, batch, **TD3 | {"args": hrac.Args(tau=0.05)})
        if step == 0:
            online_after = list(level.actor.parameters())
            for target, old_target, old_online, new_online in zip(
                level.actor_target.parameters(), before, online_before, online_after, strict=True
            ):
                # the actor stepped before the Polyak update: target = old_target + tau * (new_online - old_target)
                torch.testing.assert_close(target, old_target + 0.05 * (new_online.detach() - old_target))
                assert not torch.equal(new_online.detach(), old_online)
    goals = torch.tensor([[0.5, -0.3], [-0.6, 0.2]])
    with torch.no_grad():
        actions = level.actor(torch.zeros(2, 3), goals)
    assert (actions - goals).abs().max() < 0.15, actions
    assert torch.isfinite(metrics["critic_loss"])


def test_td3_update_adds_the_actor_extra_term():
    batch = dict(
        states=torch.randn(8, 3),
        goals=torch.randn(8, 2),
        actions=torch.rand(8, 2),
        rewards=torch.randn(8),
        next_states=torch.randn(8, 3),
        next_goals=torch.randn(8, 2),
        dones=torch.zeros(8),
    )
    losses = []
    for extra in (None, lambda actions: 7.0 + 0 * actions.sum()):
        torch.manual_seed(0)  # the same networks and the same target noise in both runs
        level = bandit_level(max_action=1.0)
        losses.append(hrac.td3_update(level, batch, **TD3, actor_extra=extra)["actor_loss"].item())
    assert losses[1] == pytest.approx(losses[0] + 7.0, abs=1e-5)


def test_td3_target_is_the_smaller_of_the_two_target_critics():
    level = bandit_level(max_action=1.0)
    for head, value in ((level.critic_target.q1, 10.0), (level.critic_target.q2, -5.0)):
        torch.nn.init.zeros_(head[-1].weight)
        torch.nn.init.constant_(head[-1].bias, value)
    batch = dict(
        states=torch.randn(8, 3),
        goals=torch.randn(8, 2),
        actions=torch.rand(8, 2),
        rewards=torch.zeros(8),
        next_states=torch.randn(8, 3),
        next_goals=torch.randn(8, 2),
        dones=torch.zeros(8),
    )
    assert hrac.td3_update(level, batch, **TD3)["target_q"].item() == pytest.approx(-5.0)


# --- the agent: DGRL's controller update, the manager update, adjacency training, evaluation --------------------------


def make_agent(args: hrac.Args, state_dim: int = 30, action_dim: int = 8) -> hrac.Agent:
    """The script's make_agent with the flags of `args`."""
    return hrac.make_agent(state_dim, action_dim, args, torch.device("cpu"))


def agent(groups: int, env_id: str = "AntMaze", **overrides):
    """The script's agent, small and seeded: (args, subgoal bounds, agent)."""
    torch.manual_seed(0)
    args = hrac.Args(env_id=env_id, groups=groups, hidden_dim=32, batch_size=16, **overrides)
    return args, hrac.subgoal_bounds(env_id, args.subgoal_scale), make_agent(args)


def filled_controller_replay(rng, n=64, goal_dim=2):
    replay = hrac.Replay(n, states=(30,), goals=(goal_dim,), actions=(8,), rewards=(), next_states=(30,),
                         next_goals=(goal_dim,), dones=())  # fmt: skip
    for _ in range(n):
        replay.add(states=rng.normal(size=30), goals=rng.uniform(-10, 10, goal_dim), actions=rng.uniform(-30, 30, 8),
                   rewards=-rng.uniform(0, 5), next_states=rng.normal(size=30), next_goals=rng.uniform(-10, 10, goal_dim),
                   dones=0.0)  # fmt: skip
    return replay


def test_make_agent_builds_both_levels_the_adjacency_network_and_the_encoder_only_under_dgrl():
    args, _, dgrl_agent = agent(groups=16)
    assert dgrl_agent.controller.actor.net[0].in_features == 30 + args.embed_dim  # the controller sees z_q
    assert dgrl_agent.manager.actor.net[0].in_features == 30 + 2  # the manager sees the state and the task's goal
    critic_groups = dgrl_agent.controller.critic_optimizer.param_groups
    assert [group["weight_decay"] for group in critic_groups] == [args.critic_weight_decay, 0.0]
    assert critic_groups[1]["lr"] == args.encoder_lr
    assert {id(p) for p in critic_groups[1]["params"]} == {id(p) for p in dgrl_agent.encoder.parameters()}
    assert len(dgrl_agent.manager.critic_optimizer.param_groups) == 1
    _, _, hrac_agent = agent(groups=0, env_id="AntFall")
    assert hrac_agent.encoder is None
    assert hrac_agent.controller.actor.net[0].in_features == 30 + 3  # AntFall's 3-d subgoal
    assert len(hrac_agent.controller.critic_optimizer.param_groups) == 1
    assert set(hrac_agent.state_dicts()) == {
        "manager_actor",
        "manager_critic",
        "controller_actor",
        "controller_critic",
        "adjacency",
    }
    assert "vq.codebook" in dgrl_agent.state_dicts()["subgoal_encoder"]


def test_controller_update_under_dgrl_moves_the_codebook_the_encoder_and_both_networks():
    args, bounds, dgrl_agent = agent(groups=16)
    encoder, controller = dgrl_agent.encoder, dgrl_agent.controller
    rng = np.random.default_rng(0)
    buffers = {name: value.clone() for name, value in encoder.vq.named_buffers()}
    hrac.act(dgrl_agent, rng.normal(size=30), np.array([3.0, -2.0]), manager=False, noise=1.0, rng=rng)  # no EMA update
    correct(
        controller.actor,
        rng.normal(size=(4, 11, 30)),
        rng.normal(size=(4, 10, 8)),
        rng.normal(size=(4, 2)),
        bounds,
        rng,
        goal_encoder=encoder,
    )
    for name, value in encoder.vq.named_buffers():
        torch.testing.assert_close(value, buffers[name])
    watched = [*controller.actor.named_parameters(), *controller.critic.named_parameters(), *encoder.named_parameters()]
    before = {name: p.detach().clone() for name, p in watched}
    sample = hrac.as_tensors(filled_controller_replay(rng).sample(args.batch_size, rng), "cpu")
    metrics = hrac.controller_update(dgrl_agent, sample, args)
    assert not torch.equal(encoder.vq.codebook, buffers["codebook"])
    for name, p in watched:
        assert not torch.equal(p, before[name]), name  # the encoder's decoder too: the reconstruction loss reaches it
    assert metrics["codes"].shape == (2 * args.batch_size, 16)  # the subgoals and the next subgoals in one call
    assert metrics["vq_loss"].item() > 0 and metrics["reconstruction_loss"].item() > 0


def test_the_controller_critic_loss_shapes_the_subgoal_encoder():
    """The reconstruction and commitment losses do not depend on rewards; the critic loss does. If the critic's
    gradient reaches the encoder (straight-through), one update on the same batch with other rewards moves it
    differently."""

    def encoder_after_update(reward: float) -> list[torch.Tensor]:
        args, _, dgrl_agent = agent(groups=16)
        replay = filled_controller_replay(np.random.default_rng(0))
        replay.fields["rewards"][:] = reward
        sample = hrac.as_tensors(replay.sample(args.batch_size, np.random.default_rng(1)), "cpu")
        hrac.controller_update(dgrl_agent, sample, args)
        return [p.detach().clone() for p in dgrl_agent.encoder.encoder.parameters()]

    same = [torch.equal(a, b) for a, b in zip(encoder_after_update(0.0), encoder_after_update(0.0), strict=True)]
    differ = [torch.equal(a, b) for a, b in zip(encoder_after_update(0.0), encoder_after_update(-50.0), strict=True)]
    assert all(same) and not any(differ)


def test_the_controller_sees_the_discrete_embedding_under_dgrl_and_the_raw_subgoal_under_hrac():
    _, _, dgrl_agent = agent(groups=16)
    subgoals = torch.tensor([[3.0, -2.0], [3.01, -2.0]])
    z_q = hrac.controller_goal_input(dgrl_agent.encoder, subgoals)
    assert z_q.shape == (2, 64)
    codebook = dgrl_agent.encoder.vq.codebook
    assert all((codebook == segment).all(-1).any() for segment in z_q.reshape(-1, 4))  # every factor is a code
    _, _, hrac_agent = agent(groups=0)
    assert torch.equal(hrac.controller_goal_input(hrac_agent.encoder, subgoals), subgoals)


def test_manager_update_learns_from_corrected_subgoals_with_the_weighted_adjacency_term(monkeypatch):
    """The stored subgoals are stale; the controller took the actions it takes for the achieved offset, so the TD3 step
    must see the achieved offsets, and its actor term must be adj_weight x the adjacency loss."""
    args, bounds, hrac_agent = agent(groups=0, adj_weight=7.0)
    rng = np.random.default_rng(1)
    n, k = args.batch_size, args.k
    states = np.cumsum(rng.normal(0, 0.3, (n, k + 1, 30)), axis=1)
    achieved = states[:, -1, :2] - states[:, 0, :2]
    goals = np.empty((n, k, 2))
    goals[:, 0] = achieved
    for t in range(1, k):
        goals[:, t] = hrac.subgoal_transition(states[:, t - 1], goals[:, t - 1], states[:, t])
    with torch.no_grad():
        actions = hrac_agent.controller.actor(
            torch.as_tensor(hrac.controller_input(states[:, :k]), dtype=torch.float32),
            torch.as_tensor(goals, dtype=torch.float32),
        ).numpy()
    replay = hrac.Replay(
        n,
        states=(30,),
        goals=(2,),
        actions=(2,),
        rewards=(),
        next_states=(30,),
        dones=(),
        state_seq=(k + 1, 30),
        action_seq=(k, 8),
    )
    for i in range(n):
        replay.add(
            states=states[i, 0],
            goals=np.array([0.0, 16.0]),
            actions=np.array([-9.0, 9.0]),
            rewards=-1.0,
            next_states=states[i, -1],
            dones=0.0,
            state_seq=states[i],
            action_seq=actions[i],
        )
    seen = {}

    def spy(level, batch, *, actor_extra=None, **hyper_parameters):
        seen["level"], seen["actions"], seen["states"], seen["extra"] = level, batch["actions"], batch["states"], actor_extra
        return {"critic_loss": torch.tensor(0.0)}

    monkeypatch.setattr(hrac, "td3_update", spy)
    sampler = np.random.default_rng(2)
    hrac.manager_update(
        hrac_agent,
        hrac.manager_batch(
            replay.sample(n, sampler), sampler, bounds=bounds, correction_samples=args.correction_samples, device="cpu"
        ),
        args,
        bounds=torch.as_tensor(bounds),
    )
    assert seen["level"] is hrac_agent.manager
    np.testing.assert_allclose(seen["actions"].numpy(), achieved, atol=1e-5)  # n entries, a batch of n: all, in order
    proposals = torch.full((n, 2), 9.0)
    expected = 7.0 * hrac.adjacency_loss(hrac_agent.adjacency, seen["states"][:, :2], proposals, threshold=1.1)
    torch.testing.assert_close(seen["extra"](proposals), expected)


def filled_manager_replay(rng, n=64, k=4, goal_dim=3):
    """AntFall's shapes: its task goal and its subgoals are 3-d (xyz)."""
    replay = hrac.Replay(n, states=(30,), goals=(goal_dim,), actions=(goal_dim,), rewards=(), next_states=(30,), dones=(),
                         state_seq=(k + 1, 30), action_seq=(k, 8))  # fmt: skip
    for _ in range(n):
        seq = np.cumsum(rng.normal(0, 0.3, (k + 1, 30)), 0)
        replay.add(states=seq[0], goals=rng.uniform(-4, 20, goal_dim), actions=rng.uniform(-10, 10, goal_dim),
                   rewards=-rng.uniform(0, 2), next_states=seq[-1], dones=0.0, state_seq=seq,
                   action_seq=rng.uniform(-30, 30, (k, 8)))  # fmt: skip
    return replay


@pytest.mark.parametrize("groups", [0, 4])
def test_fast_controller_update_equals_eager_and_is_free_of_host_syncs(groups):
    """--fast compile: controller_update compiled (both backward passes, both Adam steps, Polyak, under DGRL the
    encoder and the codebook's EMA with dead-code restarts, the critic's weight decay) and equal to eager."""
    args, _, trained = agent(groups=groups)
    if groups:
        trained.encoder.vq.dead_code_steps = 3
    rng = np.random.default_rng(0)
    replay = filled_controller_replay(rng)
    batches = [hrac.as_tensors(replay.sample(32, rng), "cpu") for _ in range(31)]

    def call(function, state, i):
        return function(state, batches[i], args)

    optimizers = lambda state: [state.controller.critic_optimizer, state.controller.actor_optimizer]  # noqa: E731
    check_fast_update(hrac, hrac.controller_update, trained, call, optimizers)


@pytest.mark.parametrize("groups", [0, 4])
def test_fast_manager_update_equals_eager_and_is_free_of_host_syncs(groups):
    """--fast compile: manager_update compiled, HIRO's off-policy correction (under DGRL through the encoder, its
    codebook untouched) and the adjacency term included, and equal to eager. On AntFall: 3-d subgoals."""
    args, bounds, trained = agent(groups=groups, env_id="AntFall")
    rng = np.random.default_rng(0)
    replay = filled_manager_replay(rng)
    batches = [
        hrac.manager_batch(replay.sample(32, rng), rng, bounds=bounds, correction_samples=4, device="cpu") for _ in range(31)
    ]

    def call(function, state, i):
        return function(state, batches[i], args, bounds=torch.as_tensor(bounds))

    optimizers = lambda state: [state.manager.critic_optimizer, state.manager.actor_optimizer]  # noqa: E731
    check_fast_update(hrac, hrac.manager_update, trained, call, optimizers)


def test_train_adjacency_separates_near_from_far_cells_along_a_corridor():
    memory = hrac.AdjacencyMemory(k=10)
    memory.add_trajectory(np.stack([np.arange(0, 30, 0.5), np.zeros(60)], 1))  # 1 m cells 0..29 along x
    torch.manual_seed(0)
    anet = hrac.AdjacencyNet(2)
    epochs, loss, accuracy = hrac.train_adjacency(
        anet,
        torch.optim.Adam(anet.parameters(), lr=1e-3),
        memory,
        np.random.default_rng(0),
        hrac.Args(adj_batch_size=64, adj_margin_pos=1.0, adj_margin_neg=1.2),
        epochs=60,
        device="cpu",
    )
    assert epochs == 60 and accuracy > 0.9 and loss < 0.05
    with torch.no_grad():
        near = (anet(torch.tensor([[10.0, 0.0]])) - anet(torch.tensor([[13.0, 0.0]]))).norm()
        far = (anet(torch.tensor([[10.0, 0.0]])) - anet(torch.tensor([[25.0, 0.0]]))).norm()
    assert near < 1.1 < far


class StopAfter:
    """A stop request that turns up after `polls` polls (the signal handler appends to a list; this counts the checks)."""

    def __init__(self, polls: int):
        self.polls = polls

    def __bool__(self) -> bool:
        self.polls -= 1
        return self.polls < 0


def test_train_adjacency_stops_between_epochs_and_the_rest_continues_it_exactly():
    """A stop request seen before the third of five epochs ends the training after two (NaN figures); the three epochs
    left, run later with the same generator and optimizer, leave the network as five epochs in a row do."""
    memory = hrac.AdjacencyMemory(k=10)
    memory.add_trajectory(np.stack([np.arange(0, 30, 0.5), np.zeros(60)], 1))
    settings = {"args": hrac.Args(adj_batch_size=64, adj_margin_pos=1.0, adj_margin_neg=1.2), "device": "cpu"}
    results, networks = [], []
    for stop in (None, StopAfter(2)):
        torch.manual_seed(0)
        anet, rng = hrac.AdjacencyNet(2), np.random.default_rng(0)
        optimizer = torch.optim.Adam(anet.parameters(), lr=1e-3)
        if stop is not None:
            epochs, *figures = hrac.train_adjacency(anet, optimizer, memory, rng, epochs=5, **settings, stop=stop)
            assert epochs == 2 and np.isnan(figures).all()
        results.append(hrac.train_adjacency(anet, optimizer, memory, rng, epochs=5 if stop is None else 3, **settings))
        networks.append(anet)
    assert results[0][1:] == results[1][1:] and results[1][0] == 3
    assert all(torch.equal(a, b) for a, b in zip(networks[0].parameters(), networks[1].parameters(), strict=True))


def test_train_adjacency_reports_nan_without_pairs():
    single_cell = hrac.AdjacencyMemory(k=10)
    single_cell.add_trajectory(np.zeros((20, 2)))
    anet = hrac.AdjacencyNet(2)
    settings = {"epochs": 5, "args": hrac.Args(adj_batch_size=64, adj_margin_pos=1.0, adj_margin_neg=1.2), "device": "cpu"}
    optimizer = torch.optim.Adam(anet.parameters(), lr=1e-3)
    epochs, *figures = hrac.train_adjacency(anet, optimizer, single_cell, np.random.default_rng(0), **settings)
    assert epochs == 5 and np.isnan(figures).all()


def test_evaluate_ends_an_episode_at_the_first_success(monkeypatch):
    """With the evaluation goal put at the start, the first step passes the distance test and ends the episode: success
    1, and the return is that one step's reward."""
    monkeypatch.setitem(hrac.EVAL_GOALS, "AntMaze", (1.0, 0.0))
    args, _, dgrl_agent = agent(groups=16)
    env = hrac.HiroAntEnv("AntMaze", evaluate=True)
    env.reset(seed=0)
    result = hrac.evaluate(env, dgrl_agent, k=args.k, rng=np.random.default_rng(0), episodes=2)
    assert result["success"] == 1.0 and env.steps == 1 and result["episodes"] == 2
    assert result["return"] == pytest.approx(-result["distance"]) and result["distance"] < 5.0
    monkeypatch.setitem(hrac.EVAL_GOALS, "AntMaze", (0.0, 16.0))
    result = hrac.evaluate(env, dgrl_agent, k=args.k, rng=np.random.default_rng(0), episodes=1)
    assert result["success"] == 0.0 and env.steps == hrac.EPISODE_STEPS and result["distance"] > 10
    # A stop request ends the evaluation after its first episode.
    monkeypatch.setitem(hrac.EVAL_GOALS, "AntMaze", (1.0, 0.0))
    result = hrac.evaluate(env, dgrl_agent, k=args.k, rng=np.random.default_rng(0), episodes=50, stop=[2])
    assert result["episodes"] == 1


def test_manager_goal_and_subgoal_bounds_per_env():
    for env_id in ENV_IDS:
        env = hrac.HiroAntEnv(env_id, evaluate=True)
        env.reset(seed=0)
        assert hrac.manager_goal(env).shape == (hrac.MANAGER_GOAL_DIMS[env_id],)
    np.testing.assert_array_equal(hrac.subgoal_bounds("AntFall", 10.0), [10.0, 10.0, 0.5])
    np.testing.assert_array_equal(hrac.subgoal_bounds("AntPush", 10.0), [10.0, 10.0])
    env = hrac.HiroAntEnv("AntFall", evaluate=True)
    env.reset(seed=0)
    np.testing.assert_array_equal(hrac.manager_goal(env), [0.0, 27.0, 4.5])


# --- flags and smoke runs ---------------------------------------------------------------------------------------------


def assert_clean_refusal(result, *messages: str) -> None:
    """Exit status 2 before any work, every message in stderr, no traceback."""
    assert result.returncode == 2, result.stdout + result.stderr
    assert "Traceback" not in result.stderr, result.stderr
    for message in messages:
        assert message in result.stderr, (message, result.stderr)


@pytest.mark.parametrize(
    ("overrides", "messages"),
    [
        (
            {"env_id": "AntMaze2"},
            ["--env-id 'AntMaze2' is unknown: use one of AntMaze, AntMazeSparse, AntPush, AntFall, AntGather"],
        ),
        ({"groups": 5}, ["--groups must be 0 (HRAC) or divide --embed-dim 64: one of [1, 2, 4, 8, 16, 32, 64]; got 5"]),
        ({"k": 7}, ["--k must divide the episode length 500", "got 7"]),
        ({"k": 1}, ["--k must be >= 2; got 1"]),
        ({"k": 0}, ["--k must be >= 2; got 0"]),  # no ZeroDivisionError from the episode-length check
        ({"ctrl_gamma": 1.01, "man_gamma": 0.0}, ["--ctrl-gamma must be in (0, 1]", "--man-gamma must be in (0, 1]"]),
        ({"adj_margin_pos": 2.0}, ["--adj-margin-neg (1.2) must be >= --adj-margin-pos (2.0)"]),
        ({"adj_margin_pos": -1.0}, ["--adj-margin-pos must be > 0; got -1.0"]),
        ({"batch_size": 0, "man_noise": -1.0}, ["--batch-size must be >= 1; got 0", "--man-noise must be >= 0; got -1.0"]),
        ({"batch_size": 300_000}, ["--batch-size (300000) must be <= --buffer-size (200000)"]),
        ({"subgoal_scale": 0.0}, ["--subgoal-scale must be in (0, 100]; got 0.0"]),
        ({"subgoal_scale": 1e30}, ["--subgoal-scale must be in (0, 100]; got 1e+30"]),
        ({"vq_decay": 1.0, "vq_beta": -1.0}, ["--vq-decay must be in [0, 1); got 1.0", "--vq-beta must be >= 0; got -1.0"]),
        (
            {"tau": 0.0, "seed": -1},
            [
                "--tau must be in (0, 1]; got 0.0",
                "--seed must be in [0, 2**64) (what numpy, gymnasium and torch accept); got -1",
            ],
        ),
        ({"total_timesteps": 5}, ["--total-timesteps (5) must be >= --k (10)"]),
        ({"checkpoint": "missing.pt"}, ["--checkpoint missing.pt: no such file"]),
    ],
)
def test_validate_names_the_flag(overrides, messages, capsys):
    with pytest.raises(SystemExit) as error:
        hrac.validate(hrac.Args(**overrides))
    assert error.value.code == 2
    stderr = capsys.readouterr().err
    for message in messages:
        assert message in stderr, (message, stderr)


def test_validate_accepts_the_defaults():
    hrac.validate(hrac.Args())
    hrac.validate(hrac.Args(env_id="AntGather", groups=0, k=25))


def test_bad_flags_fail_before_any_work(run_script, tmp_path):
    """What used to reach MuJoCo or a constructor after runs/ was created (a NaN subgoal scale drove NaN torques into the
    simulator; a negative learning rate and a codebook decay above 1 raised inside torch and vq.py) is refused at once,
    every bad flag named in one message."""
    result = run_script(
        "dgrl_hrac.py",
        "--env-id",
        "AntMaze2",
        "--groups",
        "5",
        "--subgoal-scale",
        "nan",
        "--actor-lr",
        "-1",
        "--vq-decay",
        "1.5",
        "--ctrl-gamma",
        "1.5",
        "--batch-size",
        "500",
        "--buffer-size",
        "100",
    )
    assert_clean_refusal(
        result,
        "--env-id 'AntMaze2' is unknown: use one of AntMaze, AntMazeSparse",
        "--groups must be 0 (HRAC) or divide",
        "--subgoal-scale must be a finite number; got nan",
        "--actor-lr must be > 0; got -1.0",
        "--vq-decay must be in [0, 1); got 1.5",
        "--ctrl-gamma must be in (0, 1]",
        "--batch-size (500) must be <= --buffer-size (100)",
    )
    assert not (tmp_path / "runs").exists()
    unrenderable = run_script("dgrl_hrac.py", "--capture-video", env={"MUJOCO_GL": "glfw"})  # glfw without a display
    assert_clean_refusal(unrenderable, "--capture-video cannot render with MUJOCO_GL=glfw")
    assert not (tmp_path / "runs").exists()


TINY = ["--total-timesteps", "30", "--ctrl-updates", "4", "--man-updates", "2", "--batch-size", "8", "--eval-episodes", "1",
        "--adj-frequency", "20", "--adj-epochs", "1", "--hidden-dim", "32"]  # fmt: skip


@pytest.mark.parametrize("groups", [0, 16])
@pytest.mark.parametrize("env_id", ENV_IDS)
def test_smoke_run_every_env_in_both_modes(run_script, tmp_path, env_id, groups):
    result = run_script("dgrl_hrac.py", "--env-id", env_id, "--groups", str(groups), *TINY)
    assert result.returncode == 0, result.stderr
    assert "adjacency network trained on" in result.stdout
    assert re.search(r"done: 30 steps, 1 episodes, last eval success \d+% distance", result.stdout), result.stdout
    events = next(tmp_path.glob("runs/*/events.out.tfevents.*")).read_bytes()
    tags = ("eval/final_distance", "eval/return", "charts/subgoal_distance", "charts/subgoal_norm", "charts/SPS",
            "losses/manager_critic_loss", "losses/controller_actor_loss", "adjacency/accuracy")  # fmt: skip
    for tag in (tag.encode() for tag in tags):
        assert tag in events, tag
    assert (b"vq/perplexity" in events) == (groups > 0)


def test_smoke_run_saves_evaluates_refuses_other_settings_and_records_video_headless(run_script, tmp_path):
    """--capture-video in an environment without MUJOCO_GL and without DISPLAY (the script defaults to EGL there)."""
    result = run_script("dgrl_hrac.py", "--env-id", "AntPush", "--groups", "16", *TINY, "--save-model", "--capture-video")
    assert result.returncode == 0, result.stderr
    assert list(tmp_path.glob("videos/*/eval_30.mp4"))
    checkpoint = next(tmp_path.glob("runs/*/dgrl_hrac.cleanrl_model"))
    saved = torch.load(checkpoint, weights_only=True)  # tensors and plain values only
    assert saved["script"] == "dgrl_hrac.py" and saved["format"] == hrac.CHECKPOINT_FORMAT
    assert saved["args"]["groups"] == 16 and saved["args"]["adj_margin_pos"] == 1.0
    assert set(saved) == {
        "script",
        "format",
        "args",
        "manager_actor",
        "manager_critic",
        "controller_actor",
        "controller_critic",
        "adjacency",
        "subgoal_encoder",
    }
    assert "vq.codebook" in saved["subgoal_encoder"] and "vq.ema_count" in saved["subgoal_encoder"]
    evaluation = run_script(
        "dgrl_hrac.py", "--env-id", "AntPush", "--hidden-dim", "32", "--eval-episodes", "1", "--checkpoint", str(checkpoint)
    )
    assert evaluation.returncode == 0, evaluation.stderr
    assert re.search(r"1 evaluation episodes: success \d+%, distance [\d.]+, return -?[\d.]+", evaluation.stdout)
    mismatched = run_script("dgrl_hrac.py", "--env-id", "AntPush", "--groups", "0", "--checkpoint", str(checkpoint))
    assert_clean_refusal(mismatched, "was saved with other settings: pass --groups 16 --hidden-dim 32")
    flags = ["--env-id", "AntPush", "--hidden-dim", "32", "--n-embed", "32", "--checkpoint", str(checkpoint)]
    other_codebook = run_script("dgrl_hrac.py", *flags)
    assert_clean_refusal(other_codebook, "was saved with other settings: pass --n-embed 64")
    flags = ["--env-id", "AntPush", "--hidden-dim", "32", "--eval-episodes", "1000", "--checkpoint", str(checkpoint)]
    stopped = subprocess.run(
        signal_at_line("SIGTERM", r"^evaluating", "dgrl_hrac.py", *flags), cwd=tmp_path, capture_output=True, text=True,
        env={"PATH": "/usr/bin:/bin", "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}, timeout=HANG_TIMEOUT,
    )  # fmt: skip
    assert stopped.returncode == 0, stopped.stderr[-3000:]
    episodes = int(re.search(r"(\d+) evaluation episodes: success", stopped.stdout).group(1))
    assert 1 <= episodes < 1000  # SIGTERM during a long evaluation ends it after its current episode


# --- exact resume (--resume) ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("env_id", ENV_IDS)
def test_an_env_continues_exactly_from_its_state_dict(env_id):
    """Mid-episode (and across the next reset): a fresh env loaded with another's state_dict steps, observes, rewards and
    resets exactly as the original (MuJoCo's integration state, the step counter, the goal, the objects, the generator)."""
    original, copy = hrac.HiroAntEnv(env_id), hrac.HiroAntEnv(env_id)
    original.reset(seed=1)
    copy.reset(seed=2)
    actions = np.random.default_rng(0).uniform(-30, 30, (600, 8))
    for action in actions[:37]:
        original.step(action)
    copy.load_state_dict(original.state_dict())
    for action in actions[37:]:
        expected, got = original.step(action), copy.step(action)
        assert np.array_equal(expected[0], got[0]) and expected[1:4] == got[1:4]
        if expected[3]:
            assert np.array_equal(original.reset()[0], copy.reset()[0])
    if env_id == "AntMaze":
        assert np.array_equal(original.goal, copy.goal)


def test_replay_and_adjacency_memory_round_trip_their_state_dicts():
    replay = hrac.Replay(5, states=(2,), rewards=())
    for i in range(3):
        replay.add(states=(i, -i), rewards=float(i))
    saved = replay.state_dict()
    assert saved["fields"]["states"].shape == (3, 2) and saved["fields"]["states"].dtype == torch.float32  # filled part
    copy = hrac.Replay(5, states=(2,), rewards=())
    copy.load_state_dict(saved)
    assert (copy.size, copy.position) == (3, 3)
    assert all(np.array_equal(copy.fields[name], replay.fields[name]) for name in replay.fields)
    memory = hrac.AdjacencyMemory(k=3)
    memory.add_trajectory(np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [2.0, 1.0], [5.0, 5.0]]))
    restored = hrac.AdjacencyMemory(k=3)
    restored.load_state_dict(memory.state_dict())
    assert restored.index == memory.index and restored.edges == memory.edges
    for expected, got in zip(memory.labelled_pairs(), restored.labelled_pairs(), strict=True):
        assert np.array_equal(expected, got)


RESUME = ["--ctrl-updates", "10", "--man-updates", "4", "--batch-size", "16", "--eval-episodes", "1", "--eval-frequency",
          "500", "--adj-frequency", "500", "--adj-epochs", "2", "--hidden-dim", "32", "--save-model"]  # fmt: skip


STOP_MID_EPISODE = """
import runpy, mujoco
mj_step, seen = mujoco.mj_step, dict(model=None, steps=0)

def counting_step(model, data, nstep=1):
    if seen["model"] is None:  # the first model stepped is the training env's; the evaluation env's steps come later
        seen["model"] = model
    if model is seen["model"]:
        seen["steps"] += 1
        if seen["steps"] == {marker}:
            print("marker: training step {marker}", flush=True)
    mj_step(model, data, nstep)

mujoco.mj_step = counting_step
runpy.run_path({script!r}, run_name="__main__")
"""


def test_a_run_stopped_in_its_first_episode_resumes_exactly(resume_check, tmp_path):
    """SIGTERM at training step 3 (a few steps into the first episode and its first segment), before any update or
    adjacency training: the env, the segment, the replays so far and the generators carry over."""
    wrapper = tmp_path / "stop_mid_episode.py"
    wrapper.write_text(STOP_MID_EPISODE.format(marker=3, script=str(ROOT / "dgrl_hrac.py")))
    flags = ["--env-id", "AntFall", "--groups", "0", "--seed", "3", "--total-timesteps", "1000", *RESUME]
    output = resume_check(str(wrapper), flags, r"^marker: training step 3$")
    assert 3 <= int(re.search(r"stopped: (\d+) steps", output).group(1)) < 10, output


def test_a_run_stopped_mid_segment_after_its_first_updates_resumes_exactly(resume_check, tmp_path):
    """SIGTERM at training step 537 (a line printed there by a wrapper that counts the training env's steps), 37 steps
    into the second episode, 7 into a segment: after the first updates, adjacency training (with pairs: this seed's
    first episode crosses two cells), evaluation and checkpoint. The networks, targets, optimizers, codebook, adjacency
    memory, evaluation stream and the episode in progress all carry over; a resume file is also written every 250 steps,
    by the straight run as well, which must change nothing."""
    wrapper = tmp_path / "stop_mid_episode.py"
    wrapper.write_text(STOP_MID_EPISODE.format(marker=537, script=str(ROOT / "dgrl_hrac.py")))
    flags = ["--env-id", "AntMazeSparse", "--groups", "16", "--seed", "2", "--total-timesteps", "1500",
             "--checkpoint-every-steps", "250", *RESUME]  # fmt: skip
    output = resume_check(str(wrapper), flags, r"^marker: training step 537")
    stopped_at = int(re.search(r"stopped: (\d+) steps", output).group(1))
    assert 537 <= stopped_at < 1000 and "adjacency network trained on 2 cells, 1 adjacent pairs" in output, output


STOP_IN_ADJACENCY_TRAINING = """
import runpy, torch
sqrt, calls = torch.sqrt, []

def counting_sqrt(*args, **kwargs):  # called once per batch of an adjacency training, by contrastive_loss (only there)
    calls.append(None)
    if len(calls) == 100:
        print("marker: adjacency batch 100", flush=True)
    return sqrt(*args, **kwargs)

torch.sqrt = counting_sqrt
runpy.run_path({script!r}, run_name="__main__")
"""


def test_a_run_stopped_during_an_adjacency_training_resumes_exactly(resume_check, tmp_path):
    """SIGTERM at the 100th of 400 epochs of the adjacency training at step 1000 (the training at step 500 has one cell,
    no pair; the one at 1000 has two cells, one pair: one batch an epoch): the training stops between two epochs, the
    evaluation due after it waits, and --resume runs the epochs left, then the evaluation, as a straight run does."""
    wrapper = tmp_path / "stop_in_adjacency_training.py"
    wrapper.write_text(STOP_IN_ADJACENCY_TRAINING.format(script=str(ROOT / "dgrl_hrac.py")))
    flags = ["--env-id", "AntMazeSparse", "--groups", "0", "--seed", "2", "--total-timesteps", "1500", "--adj-epochs", "400",
             *RESUME[: RESUME.index("--adj-epochs")], *RESUME[RESUME.index("--adj-epochs") + 2 :]]  # fmt: skip
    output = resume_check(str(wrapper), flags, r"^marker: adjacency batch 100")
    assert "stopped: 1000 steps" in output and "step      1000: adjacency" not in output, output
    assert "step      1000/1500" not in output, output


def test_a_run_killed_after_a_periodic_resume_write_resumes_exactly(kill_check, tmp_path):
    """SIGKILL (no clean stop) at step 1010, after the periodic resume write at step 700 (--checkpoint-every-steps 700)
    and the episode end at 1000, whose scalars and evaluation are on disk: --resume continues from step 700, TensorBoard
    drops what the killed run logged after it, and the scalars and the final checkpoint equal a straight run's."""
    wrapper = tmp_path / "stop_mid_episode.py"
    wrapper.write_text(STOP_MID_EPISODE.format(marker=1010, script=str(ROOT / "dgrl_hrac.py")))
    flags = ["--env-id", "AntMazeSparse", "--groups", "16", "--seed", "2", "--total-timesteps", "1500",
             "--checkpoint-every", "0", "--checkpoint-every-steps", "700", *RESUME]  # fmt: skip

    def logged_the_episode_end(run_dir):
        logged = {(step, tag) for tag, points in tensorboard_scalars(run_dir).items() for step, _ in points}
        assert (1000, "eval/return") in logged

    saved, resumed = kill_check(str(wrapper), flags, r"^marker: training step 1010$", logged_the_episode_end)
    assert saved["loop"]["step"] == 700 and "resuming at step 700" in resumed


def test_a_finished_run_keeps_its_resume_file_and_resumes_to_its_end(run_script, tmp_path):
    """(Changed flags that must match are refused for every script: tests/test_skeleton.py.)"""
    flags = ["--env-id", "AntPush", "--groups", "0", "--total-timesteps", "20", "--ctrl-updates", "2", "--man-updates", "1",
             "--batch-size", "8", "--eval-episodes", "1", "--hidden-dim", "32"]  # fmt: skip
    assert run_script("dgrl_hrac.py", *flags).returncode == 0
    (run_dir,) = (tmp_path / "runs").iterdir()
    saved = torch.load(run_dir / "resume.pt", weights_only=False)  # a finished run leaves its resume file too
    assert saved["loop"]["step"] == 20 and saved["ctrl_replay"]["fields"]["states"].shape == (20, 30)
    done = run_script("dgrl_hrac.py", *flags, "--threads", "2", "--resume", f"runs/{run_dir.name}")  # a free flag
    assert done.returncode == 0 and "done: 20 steps" in done.stdout, done.stderr
