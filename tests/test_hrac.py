"""dgrl_hrac.py's environments (the HIRO Ant suite; the agent is not written yet, issue 8): structure-to-MJCF geometry
against the reference tables, movable joints and their ranges, the elevated platform of AntFall, the ant's edits,
observations, resets, goals, rewards, success tests and AntGather's sensors."""

import mujoco
import numpy as np
import pytest
import torch

import dgrl_hrac as hrac
from vq import make_target

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


def test_script_steps_an_env_and_rejects_an_unknown_id(run_script):
    out = run_script("dgrl_hrac.py", "--env-id", "AntFall", "--steps", "50")
    assert out.returncode == 0, out.stderr
    assert "AntFall: 17 qpos, observation 30-d, 50 random steps" in out.stdout
    bad = run_script("dgrl_hrac.py", "--env-id", "AntMaze2")
    assert bad.returncode != 0
    assert "--env-id" in bad.stderr and "AntMazeSparse" in bad.stderr


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


def test_off_policy_correction_keeps_a_true_stored_subgoal_and_finds_a_true_achieved_one():
    rng = np.random.default_rng(0)
    controller, scale = LinearController(), np.array([10.0, 10.0])
    states = np.cumsum(rng.normal(0, 0.3, (16, 11, 30)), 1)  # 16 segments of k = 10 steps
    true_goals = rng.uniform(-5, 5, (16, 2))
    kept = hrac.off_policy_correction(controller, states, actions_for(controller, states, true_goals), true_goals, scale, rng)
    np.testing.assert_allclose(kept, true_goals)
    # The stored subgoals are stale (an older manager's); the actions were taken for the achieved offset s_k - s_0.
    achieved = states[:, -1, :2] - states[:, 0, :2]
    stale = rng.uniform(-5, 5, (16, 2))
    corrected = hrac.off_policy_correction(controller, states, actions_for(controller, states, achieved), stale, scale, rng)
    np.testing.assert_allclose(corrected, achieved, rtol=1e-6, atol=1e-6)


def test_off_policy_correction_candidates_are_clipped_to_the_scale():
    rng = np.random.default_rng(1)
    controller = LinearController()
    states = np.zeros((4, 11, 30))
    states[:, -1, :2] = 100.0  # an achieved offset far outside the subgoal range
    actions = np.zeros((4, 10, 8))
    scale = np.array([10.0, 10.0])
    chosen = hrac.off_policy_correction(controller, states, actions, np.zeros((4, 2)), scale, rng)
    assert np.all(np.abs(chosen) <= 100.0)
    np.testing.assert_allclose(chosen, 0.0)  # zero actions are explained exactly by the stored zero subgoal


def test_contrastive_and_adjacency_losses_by_hand():
    a = torch.tensor([[0.0, 0.0], [0.0, 0.0], [0.0, 0.0]])
    b = torch.tensor([[3.0, 4.0], [0.6, 0.8], [0.3, 0.4]])  # distances 5, 1, 0.5
    labels = torch.tensor([1.0, 0.0, 0.0])
    # positives: max(0, 5 - 1) = 4 -> mean over 3 = 4/3; negatives: max(0, 1.2 - 1) + max(0, 1.2 - 0.5) = 0.9 -> 0.3
    assert hrac.contrastive_loss(a, b, labels).item() == pytest.approx(4 / 3 + 0.3, abs=1e-5)
    anet = hrac.AdjacencyNet(2)
    positions, subgoals = torch.randn(6, 30), torch.randn(6, 2) * 5
    distance = (anet(positions[:, :2]) - anet(positions[:, :2] + subgoals)).norm(dim=-1)
    expected = (distance - 1.1).clamp(min=0).mean()
    assert hrac.adjacency_loss(anet, positions, subgoals).item() == pytest.approx(expected.item())


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


def test_replay_is_a_ring_of_preallocated_arrays():
    replay = hrac.Replay(3, states=(2,), rewards=())
    for i in range(5):
        replay.add(states=(i, -i), rewards=float(i))
    assert replay.size == 3 and sorted(replay.fields["rewards"].tolist()) == [2.0, 3.0, 4.0]
    batch = replay.sample(7, np.random.default_rng(0))
    assert batch["states"].shape == (7, 2) and set(batch["rewards"].tolist()) <= {2.0, 3.0, 4.0}


def bandit_nets(max_action: float):
    actor, critic = hrac.Actor(3, 2, 2, max_action, hidden_dim=64), hrac.TwinCritic(3, 2, 2, hidden_dim=64)
    nets = {"actor": actor, "critic": critic, "actor_target": make_target(actor), "critic_target": make_target(critic)}
    optimizers = {
        "actor": torch.optim.Adam(actor.parameters(), lr=1e-3),
        "critic": torch.optim.Adam(critic.parameters(), lr=1e-3, weight_decay=1e-4),
    }
    return nets, optimizers


def test_td3_update_learns_a_one_step_task_and_moves_the_targets_by_tau():
    """Reward -||a - g||^2 with every transition terminal: the actor must learn to output its goal."""
    rng = np.random.default_rng(0)
    nets, optimizers = bandit_nets(max_action=1.0)
    before = [p.detach().clone() for p in nets["actor_target"].parameters()]
    online_before = [p.detach().clone() for p in nets["actor"].parameters()]
    for step in range(600):
        states, goals = torch.randn(128, 3), torch.as_tensor(rng.uniform(-0.8, 0.8, (128, 2)), dtype=torch.float32)
        actions = torch.as_tensor(rng.uniform(-1, 1, (128, 2)), dtype=torch.float32)
        batch = dict(
            states=states, goals=goals, actions=actions, rewards=-((actions - goals) ** 2).sum(1),
            next_states=states, next_goals=goals, dones=torch.ones(128),
        )  # fmt: skip
        metrics = hrac.td3_update(nets, optimizers, batch, gamma=0.99, max_action=1.0, tau=0.05)
        if step == 0:
            online_after = list(nets["actor"].parameters())
            for target, old_target, old_online, new_online in zip(
                nets["actor_target"].parameters(), before, online_before, online_after, strict=True
            ):
                # the actor stepped before the Polyak update: target = old_target + tau * (new_online - old_target)
                torch.testing.assert_close(target, old_target + 0.05 * (new_online.detach() - old_target))
                assert not torch.equal(new_online.detach(), old_online)
    goals = torch.tensor([[0.5, -0.3], [-0.6, 0.2]])
    with torch.no_grad():
        actions = nets["actor"](torch.zeros(2, 3), goals)
    assert (actions - goals).abs().max() < 0.15, actions
    assert torch.isfinite(metrics["critic_loss"])


def test_td3_update_adds_the_actor_extra_term():
    batch = dict(
        states=torch.randn(8, 3), goals=torch.randn(8, 2), actions=torch.rand(8, 2), rewards=torch.randn(8),
        next_states=torch.randn(8, 3), next_goals=torch.randn(8, 2), dones=torch.zeros(8),
    )  # fmt: skip
    losses = []
    for extra in (None, lambda actions: 7.0 + 0 * actions.sum()):
        torch.manual_seed(0)  # the same networks and the same target noise in both runs
        nets, optimizers = bandit_nets(max_action=1.0)
        losses.append(hrac.td3_update(nets, optimizers, batch, 0.99, 1.0, actor_extra=extra)["actor_loss"].item())
    assert losses[1] == pytest.approx(losses[0] + 7.0, abs=1e-5)


def test_td3_target_is_the_smaller_of_the_two_target_critics():
    nets, optimizers = bandit_nets(max_action=1.0)
    for head, value in ((nets["critic_target"].q1, 10.0), (nets["critic_target"].q2, -5.0)):
        torch.nn.init.zeros_(head[-1].weight)
        torch.nn.init.constant_(head[-1].bias, value)
    batch = dict(
        states=torch.randn(8, 3), goals=torch.randn(8, 2), actions=torch.rand(8, 2), rewards=torch.zeros(8),
        next_states=torch.randn(8, 3), next_goals=torch.randn(8, 2), dones=torch.zeros(8),
    )  # fmt: skip
    assert hrac.td3_update(nets, optimizers, batch, 0.99, 1.0)["target_q"].item() == pytest.approx(-5.0)
