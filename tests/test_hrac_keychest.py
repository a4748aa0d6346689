"""dgrl_hrac_keychest.py: Key-Chest layout and dynamics, BFS and adjacency labels, HRAC's losses, the agent and its
updates, the subgoal autoencoder, subgoal proposals, smoke runs, checkpoints, Ctrl-C and flag validation."""

import re

import gymnasium as gym
import numpy as np
import pytest
import torch
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

import dgrl_hrac_keychest as kc
from tests.conftest import check_fast_update

# HRAC's Key-Chest layout as its authors' code draws it: 13 rows x 17 columns, `w` wall, K key at (row 6, col 1), B chest
# at (2, 1), S the nominal start (11, 7); 128 free cells. The state is (row, col, has_key); the high level's goal space is
# the cell (row, col). Rewards: +1 on first entering K, +5 on entering B with the key (the episode ends); 500 steps at most.
HRAC_LAYOUT = """\
wwwwwwwwwwwwwwwww
w               w
wB              w
wwwwwwwwwwwwww  w
w               w
w               w
wK wwwwwwwwwww  w
w               w
w               w
wwwwwwwwwwwwww  w
w               w
w      S        w
wwwwwwwwwwwwwwwww"""
UP, DOWN, LEFT, RIGHT = 0, 1, 2, 3


def make_env(num_envs: int = 1, noise: float = 0.0, **kwargs) -> kc.KeyChestVecEnv:
    env = kc.KeyChestVecEnv(num_envs, random_action_prob=noise, **kwargs)
    env.reset(seed=0)
    return env


def place(env: kc.KeyChestVecEnv, row: int, col: int, has_key: bool = False) -> None:
    env.position[:] = (row, col)
    env.has_key[:] = has_key


# --- layout and dynamics ----------------------------------------------------------------------------------------------


def test_layout_matches_hracs():
    lines = HRAC_LAYOUT.splitlines()
    assert kc.WALLS.shape == (13, 17)
    np.testing.assert_array_equal(kc.WALLS, np.array([[c == "w" for c in line] for line in lines]))
    assert lines[kc.KEY_CELL[0]][kc.KEY_CELL[1]] == "K" and kc.KEY_CELL == (6, 1)
    assert lines[kc.CHEST_CELL[0]][kc.CHEST_CELL[1]] == "B" and kc.CHEST_CELL == (2, 1)
    assert len(kc.FREE_CELLS) == 128
    assert not kc.WALLS[11, 7]  # the nominal start is free


def test_walls_block_and_free_cells_are_entered():
    cells = np.repeat(kc.FREE_CELLS, 4, axis=0)
    actions = np.tile(np.arange(4), len(kc.FREE_CELLS))
    env = make_env(len(cells))
    env.position[:] = cells
    observations, rewards, *_ = env.step(actions)
    target = cells + kc.MOVES[actions]
    expected = np.where(kc.WALLS[target[:, 0], target[:, 1]][:, None], cells, target)
    np.testing.assert_array_equal(observations[:, :2], expected)
    moved = (observations[:, :2] != cells).any(1)
    assert moved.sum() == 2 * 192  # the grid's 192 open edges between free cells, each crossed both ways
    # Entering the key cell is the only rewarded move here (no env holds the key, so the chest pays nothing).
    np.testing.assert_array_equal(rewards > 0, (expected == kc.KEY_CELL).all(1) & moved)
    assert (kc.shortest_path_lengths() >= 0).all()  # one connected maze


def test_key_is_picked_up_once():
    env = make_env()
    place(env, 7, 1)
    _, reward, terminated, _, _ = env.step([UP])
    assert reward[0] == kc.KEY_REWARD == 1.0 and env.has_key[0] and not terminated[0]
    env.step([DOWN])
    _, reward, _, _, _ = env.step([UP])  # entering the key cell again pays nothing
    assert reward[0] == 0.0 and env.has_key[0]
    _, reward, _, _, _ = env.step([LEFT])  # bumping into the wall from the key cell is not "entering" it
    assert reward[0] == 0.0 and tuple(env.position[0]) == kc.KEY_CELL


def test_starting_on_the_key_does_not_give_it():
    env = make_env()
    place(env, *kc.KEY_CELL)
    _, reward, _, _, _ = env.step([LEFT])  # blocked by the wall: no move, no key
    assert reward[0] == 0.0 and not env.has_key[0]


def test_chest_pays_and_terminates_only_with_the_key():
    env = make_env()
    place(env, 1, 1)
    _, reward, terminated, truncated, _ = env.step([DOWN])
    assert reward[0] == 0.0 and not terminated[0] and tuple(env.position[0]) == kc.CHEST_CELL
    place(env, 1, 1, has_key=True)
    observations, reward, terminated, truncated, infos = env.step([DOWN])
    assert reward[0] == kc.CHEST_REWARD == 5.0 and terminated[0] and not truncated[0]
    np.testing.assert_array_equal(infos["final_obs"][0], [2, 1, 1])  # the true last state, with the key
    assert infos["_final_obs"][0] and "episode" not in infos  # episode statistics are the wrapper's (next test)
    assert observations[0, 2] == 0 and env.elapsed[0] == 0  # reset in the same step (SAME_STEP autoreset)


def test_record_episode_statistics_wraps_the_env():
    """gymnasium's vector RecordEpisodeStatistics refuses an env that writes infos["episode"] itself; this one does not,
    so the wrapper reports the episodes' returns and lengths, SAME_STEP autoreset included."""
    env = kc.KeyChestVecEnv(2, max_episode_steps=4, random_action_prob=0.0)
    wrapped = gym.wrappers.vector.RecordEpisodeStatistics(env)
    wrapped.reset(seed=0)
    env.position[:] = [(7, 1), (4, 5)]  # env 0 below the key
    wrapped.step(np.array([UP, LEFT]))  # env 0 takes the key: +1
    env.position[0] = (1, 1)
    _, _, terminated, _, infos = wrapped.step(np.array([DOWN, LEFT]))  # env 0 opens the chest: +5 in 2 steps
    assert terminated.tolist() == [True, False] and infos["_episode"].tolist() == [True, False]
    assert infos["episode"]["r"][0] == 6.0 and infos["episode"]["l"][0] == 2
    for _ in range(2):
        _, _, _, truncated, infos = wrapped.step(np.array([LEFT, LEFT]))
    assert truncated.tolist() == [False, True]  # env 1 reached its 4-step limit; env 0's new episode is 2 steps old
    assert infos["episode"]["r"][1] == 0.0 and infos["episode"]["l"][1] == 4


@pytest.mark.parametrize("actions", [[4], [-1], [1.0], [0, 1]])
def test_invalid_actions_are_refused(actions):
    env = make_env()
    with pytest.raises(ValueError, match=r"expected 1 integer actions in \[0, 3\]"):
        env.step(np.array(actions))
    env.step(np.array([UP], dtype=np.int32))  # any integer dtype is fine


def test_pure_exploration_mode_does_not_end_at_the_chest():
    env = make_env(terminate_at_chest=False)
    place(env, 1, 1, has_key=True)
    _, reward, terminated, _, _ = env.step([DOWN])
    assert reward[0] == 5.0 and not terminated[0] and tuple(env.position[0]) == kc.CHEST_CELL


def test_truncation_at_the_step_limit():
    env = make_env(2, max_episode_steps=5)
    for step in range(5):
        _, _, terminated, truncated, infos = env.step([LEFT, RIGHT])
        assert not terminated.any()
        assert truncated.all() == (step == 4)
    assert infos["_final_obs"].all() and (env.elapsed == 0).all()


def test_start_cells_are_uniform_over_all_free_cells():
    env = kc.KeyChestVecEnv(128 * 250)
    observations, _ = env.reset(seed=3)
    assert (observations[:, 2] == 0).all()
    assert not kc.WALLS[observations[:, 0].astype(int), observations[:, 1].astype(int)].any()
    flat = (observations[:, 0] * kc.WIDTH + observations[:, 1]).astype(int)
    counts = np.bincount(flat, minlength=kc.HEIGHT * kc.WIDTH)[kc.FREE_CELLS[:, 0] * kc.WIDTH + kc.FREE_CELLS[:, 1]]
    assert (counts > 0).all()  # the original's off-by-one excluded the last free cell; here every cell is a start
    chi_square = ((counts - 250) ** 2 / 250).sum()
    assert chi_square < 190  # 127 degrees of freedom: the 99.9th percentile is about 181


def test_action_noise_replaces_a_quarter_of_the_actions():
    n = 40_000
    env = make_env(n, noise=0.25)
    place(env, 4, 5)  # an open cell: every move succeeds
    observations, *_ = env.step(np.full(n, UP))
    went_up = (observations[:, 0] == 3).mean()  # (3, 5) is a wall: "up" is blocked, the agent stays
    stayed = (observations[:, :2] == (4, 5)).all(1).mean()
    assert stayed == pytest.approx(0.75 + 0.25 / 4, abs=0.01) and went_up == 0
    env.position[:] = (5, 5)
    observations, *_ = env.step(np.full(n, DOWN))
    moved_down = (observations[:, :2] == (6, 5)).all(1).mean()
    assert moved_down == 0  # (6, 5) is a wall too
    env.position[:] = (4, 5)
    observations, *_ = env.step(np.full(n, RIGHT))
    assert (observations[:, :2] == (4, 6)).all(1).mean() == pytest.approx(0.75 + 0.25 / 4, abs=0.01)
    assert (observations[:, :2] == (5, 5)).all(1).mean() == pytest.approx(0.25 / 4, abs=0.005)


def test_seeded_resets_reproduce():
    a, b = kc.KeyChestVecEnv(16), kc.KeyChestVecEnv(16)
    np.testing.assert_array_equal(a.reset(seed=5)[0], b.reset(seed=5)[0])
    actions = np.arange(16) % 4
    np.testing.assert_array_equal(a.step(actions)[0], b.step(actions)[0])


def test_frame_shows_agent_key_chest_and_subgoal():
    env = make_env()
    place(env, 11, 7)
    image = env.frame(0, subgoal=np.array([4.2, 9.8]), pixels=4)
    assert image.shape == (13 * 4, 17 * 4, 3) and image.dtype == np.uint8
    assert tuple(image[11 * 4 + 1, 7 * 4 + 1]) == (230, 30, 30)
    assert tuple(image[6 * 4 + 1, 1 * 4 + 1]) == (230, 200, 0)
    assert tuple(image[4 * 4, 10 * 4 + 2]) == (0, 220, 0)  # the subgoal (4.2, 9.8) is drawn on cell (4, 10)


# --- BFS and adjacency labels -----------------------------------------------------------------------------------------


def test_shortest_paths_go_around_the_walls():
    distances = kc.shortest_path_lengths()
    index = {tuple(cell): i for i, cell in enumerate(kc.FREE_CELLS)}
    np.testing.assert_array_equal(distances, distances.T)
    assert distances[index[kc.KEY_CELL], index[kc.CHEST_CELL]] == 2 + 13 + 2 + 13  # up, right, up the gap, left
    assert distances[index[(11, 7)], index[kc.KEY_CELL]] == 7 + 4 + 13 + 1  # right, up the gap, left, up
    assert distances[index[(1, 1)], index[(2, 1)]] == 1
    rows, cols = kc.FREE_CELLS[:, 0], kc.FREE_CELLS[:, 1]
    manhattan = np.abs(rows[:, None] - rows[None]) + np.abs(cols[:, None] - cols[None])
    assert (distances >= manhattan).all()


def test_mark_adjacent_marks_pairs_less_than_k_apart_in_one_trajectory():
    adjacency = np.zeros((kc.HEIGHT * kc.WIDTH,) * 2, dtype=bool)
    visited = np.zeros(kc.HEIGHT * kc.WIDTH, dtype=bool)
    trajectory = np.array([18, 19, 20, 21, 22, 23])  # row 1, columns 1..6
    kc.mark_adjacent(adjacency, visited, trajectory, k=3)
    marked = {(int(a), int(b)) for a, b in zip(*np.nonzero(adjacency), strict=True)}
    expected = {(a, b) for i, a in enumerate(trajectory) for b in trajectory[i + 1 : i + 3]}
    assert marked == expected | {(b, a) for a, b in expected}
    np.testing.assert_array_equal(np.flatnonzero(visited), trajectory)


def test_adjacency_labels_from_random_walks_agree_with_bfs():
    """Every pair marked from real trajectories is truly within k-1 steps; with long walks almost all such pairs are
    found, so the labels the adjacency network trains on match BFS k-step reachability."""
    k, distances = 10, kc.shortest_path_lengths()
    env = make_env(64, noise=0.0, max_episode_steps=2000, terminate_at_chest=False)  # no reset breaks a walk
    adjacency = np.zeros((kc.HEIGHT * kc.WIDTH,) * 2, dtype=bool)
    visited = np.zeros(kc.HEIGHT * kc.WIDTH, dtype=bool)
    rng = np.random.default_rng(0)
    cells = [env._observe()[:, :2].astype(int) @ [kc.WIDTH, 1]]
    for _ in range(1500):
        observations, *_ = env.step(rng.integers(4, size=64))
        cells.append(observations[:, :2].astype(int) @ [kc.WIDTH, 1])
    for trajectory in np.stack(cells, 1):
        kc.mark_adjacent(adjacency, visited, trajectory, k)
    flat = kc.FREE_CELLS @ [kc.WIDTH, 1]
    labels = adjacency[np.ix_(flat, flat)]
    np.fill_diagonal(labels, True)
    assert (distances[labels] <= k - 1).all()  # no false positive: a marked pair is always within k - 1 steps
    assert labels[distances <= 2].all()  # and the walks find every pair two steps apart
    assert labels[distances <= k - 1].mean() > 0.5


def test_adjacency_accuracy_of_a_perfect_and_a_useless_embedding():
    distances = kc.shortest_path_lengths()

    class Constant(torch.nn.Module):  # every cell at one point: "all reachable"
        def __init__(self):
            super().__init__()
            self.weight = torch.nn.Parameter(torch.zeros(1))

        def forward(self, cells):
            return torch.zeros(len(cells), 4) + self.weight

    first, second = np.triu_indices(128, 1)
    reachable_fraction = (distances[first, second] <= 10).mean()
    assert kc.adjacency_accuracy(Constant(), distances, 10, 1.1) == pytest.approx(reachable_fraction)


# --- losses -----------------------------------------------------------------------------------------------------------


def test_segment_returns_stop_at_segment_ends():
    rewards = torch.tensor([0, 0, 1, 0, 1, 1, 0, 1], dtype=torch.float32)
    returns = kc.segment_returns(rewards, kc.segment_discounts(0.5, 3))
    expected = [0.25, 0.5, 1.0, 0.5 + 0.25, 1 + 0.5, 1.0, 0.5, 1.0]  # segments [0..2], [3..5], [6..7]
    assert returns.dtype == torch.float64
    np.testing.assert_allclose(returns.numpy(), expected)
    returns = kc.segment_returns(torch.ones(4), kc.segment_discounts(0.9, 10)).numpy()
    np.testing.assert_allclose(returns, [1 + 0.9 + 0.81 + 0.729, 1 + 0.9 + 0.81, 1.9, 1])


def test_segment_discounts_are_numpys_powers():
    """The discounts are numpy's float64 powers, bit for bit (what the returns were always computed with)."""
    for gamma in (0.99, 0.9, 0.97):
        expected = np.triu(gamma ** np.maximum(np.arange(10)[None, :] - np.arange(10)[:, None], 0))
        assert np.array_equal(kc.segment_discounts(gamma, 10).numpy(), expected)


def test_goal_reached_by_euclidean_distance_below_the_threshold_or_by_hracs_box():
    next_states = torch.tensor([[3.0, 4.0, 0.0]] * 7)
    goals = torch.tensor([[3.5, 4.5], [3.51, 4.0], [2.6, 3.6], [3.0, 5.0], [3.3, 4.3], [3.49, 4.0], [3.5, 4.0]])
    euclidean = kc.goal_reached(next_states, goals, 0.5, "euclidean").numpy()
    np.testing.assert_array_equal(euclidean, [0, 0, 0, 0, 1, 1, 0])  # distance < 0.5, strictly
    np.testing.assert_array_equal(kc.goal_reached(next_states, goals, 0.5, "box").numpy(), [1, 0, 1, 0, 1, 1, 1])


def test_a_subgoal_point_no_free_cell_reaches_is_counted_unreachable_under_its_rule():
    """(1, 1) is a free cell, (0, 0) a wall. A point 0.4 from a free cell's centre in both coordinates (0.57 away) is
    reached under HRAC's box only; a wall's centre by no cell under either rule; over the grid, uniform points (the
    warm-up's subgoals) are unreachable about 54% of the time under the Euclidean rule and 42% under the box."""
    assert kc.WALLS[0, 0] and not kc.WALLS[1, 1]
    goals = np.array([[1.0, 1.0], [1.4, 1.4], [0.0, 0.0], [1.45, 1.0]], dtype=np.float32)
    np.testing.assert_array_equal(kc.unreachable_subgoals(goals, 0.5, "euclidean"), [False, True, True, False])
    np.testing.assert_array_equal(kc.unreachable_subgoals(goals, 0.5, "box"), [False, False, True, False])
    uniform = np.random.default_rng(0).uniform((0, 0), kc.GOAL_SCALE, (4000, 2))
    assert 0.50 < kc.unreachable_subgoals(uniform, 0.5, "euclidean").mean() < 0.58
    assert 0.38 < kc.unreachable_subgoals(uniform, 0.5, "box").mean() < 0.46


def test_the_defaults_are_the_papers_wiring():
    """The paper's appendix: the low level is conditioned on the discrete embedding of the subgoal and rewarded when its
    Euclidean distance to the subgoal is below 0.5; HRAC (G = 0) is rewarded by the same rule."""
    args = kc.Args(n_embed=8, **SMALL)
    assert (args.dgrl_goal, args.reach_rule, args.goal_threshold) == ("embedding", "euclidean", 0.5)
    torch.manual_seed(0)
    agent = agent_from(args)
    assert agent.controller.policy[0].in_features == 3 + args.embed_dim
    goals = torch.tensor([[3.0, 4.0], [11.0, 15.0]])
    inputs, targets, _ = kc.controller_goals(agent.goal_ae, goals, agent.dgrl_goal)
    assert torch.equal(inputs, agent.goal_ae(goals)[0]) and torch.equal(targets, goals)
    states = torch.tensor([[11.0, 7.0, 0.0]] * 10)
    next_states = torch.tensor([[11.0, 8.0, 0.0]] * 10)
    for groups in (0, args.groups):
        agent = agent_from(kc.Args(groups=groups, n_embed=8, **SMALL))
        rewards = {}
        for offset in (0.3, 0.4):  # diagonal offsets 0.42 and 0.57 from the cell: inside, then outside the radius
            figures = kc.controller_update(
                agent, states, next_states[:, :2] + offset, torch.zeros(10, dtype=torch.long), next_states,
                kc.segment_discounts(0.9, 5), args,
            )  # fmt: skip
            rewards[offset] = figures["charts/intrinsic_reward"].item()
        assert rewards == {0.3: 1.0, 0.4: 0.0}


def test_a2c_loss_matches_its_formula():
    logits = torch.tensor([[0.0, 1.0, 2.0, 3.0], [1.0, 1.0, 1.0, 1.0]], requires_grad=True)
    values = torch.tensor([0.5, 2.0], requires_grad=True)
    actions, returns = torch.tensor([3, 0]), torch.tensor([1.5, 1.0])
    loss, policy_loss, value_loss, entropy = kc.a2c_loss(logits, values, actions, returns, entropy_coef=0.1)
    log_probs = torch.log_softmax(logits, 1)
    advantages = torch.tensor([1.0, -1.0])
    assert policy_loss.item() == pytest.approx(-(advantages * log_probs[[0, 1], [3, 0]]).mean().item())
    assert value_loss.item() == pytest.approx(1.0)  # mean of 1^2 and (-1)^2, not halved
    assert entropy.item() == pytest.approx((-(log_probs.exp() * log_probs).sum(1)).mean().item())
    assert loss.item() == pytest.approx(policy_loss.item() + value_loss.item() - 0.1 * entropy.item())
    loss.backward()
    assert values.grad.tolist() == pytest.approx([-1.0, 1.0])  # d/dV of mean (R - V)^2; the policy term is detached


def test_contrastive_loss_matches_its_formula():
    a = torch.tensor([[0.0, 0.0], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0]])
    b = torch.tensor([[3.0, 4.0], [0.6, 0.8], [0.6, 0.8], [3.0, 4.0]])  # distances 5, 1, 1, 5
    labels = torch.tensor([1.0, 1.0, 0.0, 0.0])
    loss = kc.contrastive_loss(a, b, labels, margin_pos=1.0, margin_neg=1.2)
    assert loss.item() == pytest.approx((4.0 + 0.0) / 4 + (0.2 + 0.0) / 4, abs=1e-5)


# --- agent pieces -----------------------------------------------------------------------------------------------------


def agent_from(args: kc.Args) -> kc.Agent:
    """The script's make_agent on the CPU."""
    return kc.make_agent(args, torch.device("cpu"))


def test_goal_autoencoder_round_trip_separates_cells():
    torch.manual_seed(0)
    agent = agent_from(kc.Args(groups=16, hidden_dim=8))  # the paper's G = 16, L = 64, m = 64
    ae = agent.goal_ae
    for _ in range(2000):  # the script's --ae-init-steps, at its --ae-batch-size
        goals = kc.uniform_subgoals(256, torch.device("cpu"))
        _, vq_loss, _, reconstruction = ae(goals, update=True)
        kc.goal_autoencoder_step(agent, goals, reconstruction, vq_loss)
    scale = torch.as_tensor(kc.GOAL_SCALE)
    cells = torch.as_tensor(kc.FREE_CELLS, dtype=torch.float32)
    codebook = ae.vq.codebook.clone()
    with torch.no_grad():
        quantized, _, indices, reconstruction = ae(cells)  # update=False by default: acting leaves the codebook alone
    assert torch.equal(ae.vq.codebook, codebook)
    assert quantized.shape == (128, 64) and indices.shape == (128, 16)
    segments = quantized.view(128, 16, 4)
    assert torch.equal(segments, ae.vq.codebook[indices])  # every factor is exactly one shared code
    decoded_cells = torch.round(reconstruction * scale)
    assert (decoded_cells == cells).all(1).float().mean() > 0.8  # the discrete embedding keeps the cell
    assert len(torch.unique(indices, dim=0)) > 110  # and almost every cell has a code tuple of its own


def test_controller_goals_in_each_mode():
    torch.manual_seed(0)
    ae_flags = {"embed_dim": 16, "ae_hidden_dim": 32, "groups": 4, "n_embed": 8, "vq_beta": 0.25, "vq_decay": 0.99}
    ae = kc.GoalAutoencoder(kc.Args(**ae_flags, vq_dead_code_steps=0))
    goals = torch.tensor([[3.0, 4.0], [11.0, 15.0]])
    inputs, targets, extra = kc.controller_goals(None, goals, "decoded")
    assert inputs is goals and targets is goals and extra is None  # HRAC: the raw subgoal, rewarded as it is
    quantized, _, _, reconstruction = ae(goals)
    inputs, targets, _ = kc.controller_goals(ae, goals, "decoded")
    assert torch.allclose(inputs, reconstruction * torch.as_tensor(kc.GOAL_SCALE)) and torch.equal(inputs, targets)
    assert not inputs.requires_grad  # the low level's loss never reaches the autoencoder
    inputs, targets, _ = kc.controller_goals(ae, goals, "embedding")
    assert torch.equal(inputs, quantized) and inputs.shape == (2, 16) and torch.equal(targets, goals)
    codebook = ae.vq.codebook.clone()
    kc.controller_goals(ae, goals, "decoded")  # acting
    assert torch.equal(ae.vq.codebook, codebook)
    kc.controller_goals(ae, goals, "decoded", update=True)  # the autoencoder's training step
    assert not torch.equal(ae.vq.codebook, codebook)


def test_propose_subgoals_filters_by_adjacency():
    torch.manual_seed(0)
    noise = {"threshold": 1.1, "n_noisy_goals": 20, "noise": 5.0}
    actor = kc.ManagerActor(16)
    states = torch.tensor([[11.0, 7.0, 0.0], [1.0, 1.0, 1.0]])

    class Coordinates(torch.nn.Module):  # embedding = the cell itself: "reachable" means within 1.1 cells
        def forward(self, cells):
            return cells

    raw = actor(states)
    assert torch.equal(kc.propose_subgoals(actor, Coordinates(), states, explore=False, **noise), raw)
    goals = kc.propose_subgoals(actor, Coordinates(), states, explore=True, **noise)
    assert goals.shape == (2, 2) and (goals >= 0).all() and (goals <= torch.as_tensor(kc.GOAL_SCALE)).all()
    chosen_near = (goals - states[:, :2]).norm(dim=1) < 1.1
    assert (chosen_near | (goals == raw).all(1)).all()  # a reachable candidate, or else the noiseless output

    class Far(torch.nn.Module):  # nothing is reachable: the noiseless output is kept
        def forward(self, cells):
            return cells * 100

    assert torch.equal(kc.propose_subgoals(actor, Far(), states, explore=True, **noise), raw)


def test_manager_replay_is_a_ring():
    replay = kc.ManagerReplay(4, np.random.default_rng(0))
    for start in range(0, 6, 3):
        values = np.arange(start, start + 3, dtype=np.float32)
        replay.add(np.tile(values[:, None], 3), np.tile(values[:, None], 2), values, np.tile(values[:, None], 3), values * 0)
    assert replay.size == 4 and replay.started()
    assert sorted(replay.rewards.tolist()) == [2.0, 3.0, 4.0, 5.0]  # 0 and 1 were overwritten
    states, goals, rewards, next_states, terminals = replay.sample(4, torch.device("cpu"))
    assert all(column.dtype == torch.float32 for column in (states, goals, rewards, next_states, terminals))
    assert torch.equal(next_states[:, 2], rewards) and not terminals.any()
    assert sorted(rewards.tolist()) == [2.0, 3.0, 4.0, 5.0]  # without replacement
    assert torch.equal(states[:, 0], rewards) and torch.equal(goals[:, 1], rewards)


# --- the agent and its updates ----------------------------------------------------------------------------------------

SMALL = {"hidden_dim": 16, "adj_hidden_dim": 8, "adj_embed_dim": 4, "embed_dim": 16, "ae_hidden_dim": 8}


def parameters(module: torch.nn.Module) -> torch.Tensor:
    return torch.cat([p.detach().flatten() for p in module.parameters()]).clone()


@pytest.mark.parametrize(
    ("groups", "dgrl_goal", "goal_inputs"), [(0, "embedding", 2), (4, "decoded", 2), (4, "embedding", 16)]
)
def test_make_agent_wires_the_flags(groups, dgrl_goal, goal_inputs):
    agent = agent_from(kc.Args(groups=groups, dgrl_goal=dgrl_goal, **SMALL))
    assert (agent.goal_ae is None) == (agent.ae_optimizer is None) == (groups == 0)
    assert agent.controller.policy[0].in_features == 3 + goal_inputs  # the embedding replaces the 2-d subgoal
    assert agent.actor.net[0].out_features == 16 and agent.adjacency.net[-1].out_features == 4
    assert agent.actor_target is not agent.actor and torch.equal(parameters(agent.actor_target), parameters(agent.actor))
    assert not any(p.requires_grad for p in agent.actor_target.parameters())
    assert not any(p.requires_grad for p in agent.adjacency.parameters())  # only train_adjacency trains it
    for optimizer, module in [
        (agent.actor_optimizer, agent.actor),
        (agent.critic_optimizer, agent.critic),
        (agent.controller_optimizer, agent.controller),
        (agent.adjacency_optimizer, agent.adjacency),
        *([(agent.ae_optimizer, agent.goal_ae)] if groups else []),
    ]:
        assert {id(p) for group in optimizer.param_groups for p in group["params"]} == {id(p) for p in module.parameters()}
    if groups:
        assert "vq.codebook" in agent.state_dicts()["goal_autoencoder"]  # the checkpoint keeps the codebook
    else:
        assert agent.state_dicts()["goal_autoencoder"] is None


def test_manager_update_trains_both_nets_and_moves_the_targets_but_not_the_adjacency_net():
    agent = agent_from(kc.Args(groups=0, **SMALL))
    replay = kc.ManagerReplay(64, np.random.default_rng(0))
    rng = np.random.default_rng(1)
    replay.add(rng.random((64, 3)) * 10, rng.random((64, 2)) * 10, rng.random(64), rng.random((64, 3)) * 10, np.zeros(64))
    before = {name: parameters(getattr(agent, name)) for name in ("actor", "critic", "actor_target", "critic_target")}
    adjacency = parameters(agent.adjacency)
    flags = kc.Args(man_gamma=0.99, man_tau=0.5, adj_weight=20.0)
    figures = kc.manager_update(agent, replay.sample(32, torch.device("cpu")), flags, threshold=0.0, policy_term=True)
    for name, values in before.items():
        assert not torch.equal(parameters(getattr(agent, name)), values), name
    assert torch.equal(parameters(agent.adjacency), adjacency)
    assert all(p.grad is None for p in agent.adjacency.parameters())
    assert figures["losses/man_goal_loss"] > 0  # threshold 0: every proposal is "too far", so the adjacency term acts
    assert set(figures) == {"losses/man_critic_loss", "losses/man_goal_loss", "losses/man_q_values"}


@pytest.mark.parametrize("groups", [0, 4])
def test_controller_update_trains_the_low_level_and_under_dgrl_the_autoencoder(groups):
    agent = agent_from(kc.Args(groups=groups, n_embed=8, **SMALL))
    states = torch.tensor([[11.0, 7.0, 0.0]] * 12)
    goals = torch.tensor([[11.0, 8.0]] * 12)
    next_states = torch.tensor([[11.0, 8.0, 0.0]] * 12)  # every step ends on the raw subgoal
    controller = parameters(agent.controller)
    autoencoder = None if agent.goal_ae is None else (parameters(agent.goal_ae), agent.goal_ae.vq.codebook.clone())
    flags = kc.Args(ctrl_entropy=0.01, ctrl_reward_scale=1.0, goal_threshold=0.5, reach_rule="euclidean")
    figures = kc.controller_update(
        agent, states, goals, torch.zeros(12, dtype=torch.long), next_states, kc.segment_discounts(0.9, 5), flags
    )
    assert not torch.equal(parameters(agent.controller), controller)
    if groups:  # the autoencoder's step, and the EMA update of its codebook
        assert not torch.equal(parameters(agent.goal_ae), autoencoder[0])
        assert not torch.equal(agent.goal_ae.vq.codebook, autoencoder[1])
        assert {"vq/perplexity", "vq/active_codes", "vq/commit_loss", "losses/goal_reconstruction"} <= set(figures)
    else:  # HRAC's reward: every step reaches the raw subgoal, so every 5-step segment counts as reached
        assert figures["charts/intrinsic_reward"] == 1.0 and figures["charts/subgoal_reach_rate"] == 1.0
        assert not any(key.startswith("vq/") for key in figures)
    assert all(isinstance(value, torch.Tensor) and not value.requires_grad for value in figures.values())


def test_manager_update_with_a_tensor_policy_term_equals_the_bool_one():
    """policy_term as a 0-d tensor (--fast cudagraphs: one graph for both) gives what the bool gives, bit for bit."""
    import copy

    agent = agent_from(kc.Args(groups=0, **SMALL))
    replay = kc.ManagerReplay(64, np.random.default_rng(0))
    rng = np.random.default_rng(1)
    replay.add(rng.random((64, 3)) * 10, rng.random((64, 2)) * 10, rng.random(64), rng.random((64, 3)) * 10, np.zeros(64))
    batches = [replay.sample(32, torch.device("cpu")) for _ in range(6)]
    with_bools, with_tensors = agent, copy.deepcopy(agent)
    flags = kc.Args(man_gamma=0.99, man_tau=0.5, adj_weight=20.0)
    for i, batch in enumerate(batches):
        expected = kc.manager_update(with_bools, batch, flags, threshold=1.1, policy_term=i % 2 == 0)
        got = kc.manager_update(with_tensors, batch, flags, threshold=1.1, policy_term=torch.tensor(float(i % 2 == 0)))
        assert all(torch.equal(got[key], expected[key]) for key in expected)
    for name in ("actor", "critic", "actor_target", "critic_target"):
        assert torch.equal(parameters(getattr(with_tensors, name)), parameters(getattr(with_bools, name))), name


# --- the --fast path: each update compiled equals eager and is free of host syncs ---------------------------------------


def trained_agent(groups: int) -> kc.Agent:
    """A tiny agent (hidden 16-32) whose adjacency network is not the initial one; under DGRL dead-code restarts on."""
    torch.manual_seed(0)
    agent = agent_from(kc.Args(groups=groups, n_embed=8, **SMALL))
    for parameter in agent.adjacency.parameters():
        parameter.add_(0.3 * torch.randn_like(parameter))
    if groups:
        agent.goal_ae.vq.dead_code_steps = 3
    return agent


def episode(rng: np.random.Generator, length: int) -> tuple[torch.Tensor, ...]:
    """(states, raw subgoals, actions, next states) of a random walk-like episode, some steps ending on the subgoal."""
    states = torch.as_tensor(np.c_[rng.integers(1, 12, (length, 2)), rng.integers(0, 2, length)], dtype=torch.float32)
    goals = states[:, :2] + torch.as_tensor(rng.integers(-1, 2, (length, 2)), dtype=torch.float32)
    next_states = torch.where(torch.as_tensor(rng.random((length, 1)) < 0.3), torch.cat([goals, states[:, 2:]], 1), states)
    return states, goals, torch.as_tensor(rng.integers(4, size=length)), next_states


@pytest.mark.parametrize("groups", [0, 4])
def test_fast_controller_update_equals_eager_and_is_free_of_host_syncs(groups):
    """--fast compile: controller_update compiled (under DGRL the codebook's EMA with dead-code restarts and the
    autoencoder's Adam step, then the A2C step), over episodes of different lengths (a dynamic length), equal to eager."""
    agent = trained_agent(groups)
    rng = np.random.default_rng(0)
    episodes = [episode(rng, int(length)) for length in rng.integers(20, 60, 30)]
    discounts = kc.segment_discounts(0.9, 5)
    flags = kc.Args(ctrl_entropy=0.01, ctrl_reward_scale=1.0, goal_threshold=0.5, reach_rule="euclidean")

    def call(function, state, i):
        return function(state, *episodes[i], discounts, flags)

    optimizers = lambda state: [state.controller_optimizer] + ([state.ae_optimizer] if groups else [])  # noqa: E731
    check_fast_update(kc, kc.controller_update, agent, call, optimizers)


@pytest.mark.parametrize("groups", [0, 4])
def test_fast_manager_update_equals_eager_and_is_free_of_host_syncs(groups):
    """--fast compile: manager_update compiled (critic, actor with the adjacency term and, every other update, the
    critic term as a tensor switch, Polyak targets), equal to eager. The goal autoencoder takes no part in it."""
    agent = trained_agent(groups)
    replay = kc.ManagerReplay(256, np.random.default_rng(0))
    rng = np.random.default_rng(1)
    replay.add(rng.random((256, 3)) * 10, rng.random((256, 2)) * 10, rng.random(256), rng.random((256, 3)) * 10,
               rng.random(256) < 0.1)  # fmt: skip
    batches = [replay.sample(32, torch.device("cpu")) for _ in range(31)]
    switches = (torch.tensor(0.0), torch.tensor(1.0))
    flags = kc.Args(man_gamma=0.99, man_tau=0.01, adj_weight=20.0)

    def call(function, state, i):
        return function(state, batches[i], flags, threshold=1.1, policy_term=switches[i % 2 == 0])

    optimizers = lambda state: [state.critic_optimizer, state.actor_optimizer]  # noqa: E731
    check_fast_update(kc, kc.manager_update, agent, call, optimizers)


def test_fast_goal_autoencoder_update_equals_eager_and_is_free_of_host_syncs():
    """--fast compile: the autoencoder's pre-training update (codebook EMA with dead-code restarts, Adam step)."""
    agent = trained_agent(4)
    torch.manual_seed(1)
    batches = [kc.uniform_subgoals(32, torch.device("cpu")) for _ in range(31)]

    def call(function, state, i):
        return function(state, batches[i])

    check_fast_update(kc, kc.goal_autoencoder_update, agent, call, lambda state: [state.ae_optimizer])


# --- smoke runs, checkpoints, Ctrl-C ----------------------------------------------------------------------------------

TINY = {
    "total_timesteps": 3000, "num_envs": 4, "max_episode_steps": 100, "adj_init_steps": 800, "adj_init_epochs": 1,
    "adj_frequency": 1200, "adj_epochs": 1, "man_buffer_size": 200, "eval_frequency": 400, "log_frequency": 400,
    "eval_episodes": 4, "hidden_dim": 32, "ae_init_steps": 5,
}  # fmt: skip


def tiny(**changes) -> list[str]:
    """The flags of a few-second run: exploration to frame 800, updates from 1800, evaluations every 400 frames."""
    return [text for key, value in (TINY | changes).items() for text in (f"--{key.replace('_', '-')}", str(value))]


def scalars(run_dir) -> dict[str, list[float]]:
    accumulator = EventAccumulator(str(run_dir), size_guidance={"scalars": 0})
    accumulator.Reload()
    return {tag: [event.value for event in accumulator.Scalars(tag)] for tag in accumulator.Tags()["scalars"]}


@pytest.mark.parametrize(("groups", "dgrl_goal"), [("0", None), ("16", None), ("16", "decoded")])
def test_smoke_run_trains_evaluates_and_reloads(run_script, tmp_path, groups, dgrl_goal):
    flags = ("--groups", groups, *(("--dgrl-goal", dgrl_goal) if dgrl_goal else ()))
    result = run_script("dgrl_hrac_keychest.py", *tiny(), *flags, "--save-model", "--capture-video")
    assert result.returncode == 0, result.stderr
    assert "adjacency pre-training" in result.stdout and "eval return" in result.stdout
    assert ("distinct cells" in result.stdout) == (groups != "0")
    checkpoint = next(tmp_path.glob("runs/*/dgrl_hrac_keychest.cleanrl_model"))
    saved = torch.load(checkpoint, weights_only=True)
    assert saved["script"] == "dgrl_hrac_keychest.py" and saved["format"] == kc.CHECKPOINT_FORMAT
    assert saved["args"]["hidden_dim"] == 32 and saved["args"]["reach_rule"] == "euclidean"
    low_level_inputs = 3 + (64 if groups != "0" and dgrl_goal is None else 2)  # by default the 64-d discrete embedding
    assert saved["controller"]["policy.0.weight"].shape == (32, low_level_inputs)
    assert (saved["goal_autoencoder"] is None) == (groups == "0")
    if groups != "0":
        assert "vq.codebook" in saved["goal_autoencoder"] and "vq.ema_count" in saved["goal_autoencoder"]
    assert list(tmp_path.glob("videos/*/eval_*.mp4"))
    logged = scalars(checkpoint.parent)
    assert len(logged["eval/return"]) == 5  # frames 1200, 1600, ..., 2800: every 400 frames after the exploration
    for tag in ("eval/return_random_subgoals", "charts/SPS", "charts/adjacency_accuracy", "losses/man_critic_loss"):
        assert tag in logged
    assert ("vq/perplexity" in logged) == (groups != "0")
    # Flags that leave the networks and what evaluation measures alone (here --n-noisy-goals) may differ.
    reload_flags = (*flags, "--hidden-dim", "32", "--max-episode-steps", "100", "--eval-episodes", "3", "--n-noisy-goals", "3")
    reloaded = run_script("dgrl_hrac_keychest.py", *reload_flags, "--checkpoint", str(checkpoint))
    assert reloaded.returncode == 0, reloaded.stderr
    assert re.search(r"3 episodes: return [\d.]+", reloaded.stdout)
    assert re.search(r"3 episodes with uniform random subgoals: return [\d.]+", reloaded.stdout)
    if dgrl_goal == "decoded":  # a checkpoint saved with other settings names the flags to pass
        changed = run_script("dgrl_hrac_keychest.py", "--groups", "8", "--reach-rule", "box", "--checkpoint", str(checkpoint))
        assert changed.returncode == 2 and "Traceback" not in changed.stderr
        pass_flags = "pass --max-episode-steps 100 --reach-rule euclidean --hidden-dim 32 --groups 16 --dgrl-goal decoded"
        assert f"was saved with other settings: {pass_flags}" in changed.stderr


# --- bad flags: a clean exit 2 before any work, naming the flag -------------------------------------------------------


def assert_refused(result, tmp_path, *messages: str) -> None:
    assert result.returncode == 2, result.stdout + result.stderr
    assert "Traceback" not in result.stderr, result.stderr
    for message in messages:
        assert message in result.stderr, (message, result.stderr)
    assert not (tmp_path / "runs").exists()


def test_out_of_range_flags_are_refused(run_script, tmp_path):
    result = run_script(
        "dgrl_hrac_keychest.py", "--man-gamma", "1.5", "--ctrl-gamma", "0", "--man-tau", "0", "--goal-threshold", "-1",
        "--ctrl-lr", "-1", "--vq-decay", "1.5", "--seed", "-1", "--num-envs", "0", "--random-action-prob", "1.5",
        "--man-noise", "nan", "--adj-weight", "-1", "--adj-margin-neg", "0", "--log-frequency", "0",
    )  # fmt: skip
    assert_refused(
        result,
        tmp_path,
        "--man-gamma must be in (0, 1]; got 1.5",
        "--ctrl-gamma must be in (0, 1]; got 0.0",
        "--man-tau must be in (0, 1]; got 0.0",
        "--goal-threshold must be > 0; got -1.0",
        "--ctrl-lr must be > 0; got -1.0",  # Adam's own ValueError came after runs/ was created
        "--vq-decay must be in [0, 1); got 1.5",  # so did the codebook's
        "--seed must be in [0, 2**64) (what numpy, gymnasium and torch accept); got -1",  # numpy's seeding raised a ValueError
        "--num-envs must be >= 1; got 0",
        "--random-action-prob must be in [0, 1]; got 1.5",
        "--man-noise must be a finite number; got nan",
        "--adj-weight must be >= 0; got -1.0",
        "--adj-margin-neg must be > 0; got 0.0",
        "--log-frequency must be >= 1; got 0",
    )


def test_inconsistent_flags_are_refused(run_script, tmp_path):
    result = run_script(
        "dgrl_hrac_keychest.py", "--groups", "5", "--k", "200", "--max-episode-steps", "100", "--man-buffer-size", "100",
        "--adj-margin-pos", "2",
    )  # fmt: skip
    assert_refused(
        result,
        tmp_path,
        "--groups must be 0 (HRAC) or divide --embed-dim 64",
        "--k (200) must be <= --max-episode-steps (100)",  # evaluation found no complete segment and crashed
        "--man-batch-size (64) must be <= half of --man-buffer-size (100)",
        "--adj-margin-pos (2.0) must be <= --adj-margin-neg (1.2)",
    )


def test_a_budget_without_updates_or_evaluations_is_refused(run_script, tmp_path):
    # 800 frames of exploration, then half of 200 transitions at one per 10 frames: the first update comes at 1800.
    assert_refused(
        run_script("dgrl_hrac_keychest.py", *tiny(total_timesteps=1500, eval_frequency=2000)),
        tmp_path,
        "--total-timesteps (1500) must be >= 1800, or no update runs",
        "--eval-frequency (2000) leaves no evaluation: the first would be at frame 2000, after --total-timesteps (1500)",
    )


# --- stopping and resuming --------------------------------------------------------------------------------------------


def test_resume_from_a_stop_during_the_exploration(resume_check):
    # HRAC (--groups 0): 1000 exploration steps of 2 envs; the first output line comes right before them.
    flags = tiny(num_envs=2, adj_init_steps=2000, total_timesteps=3400, max_episode_steps=90)
    output = resume_check("dgrl_hrac_keychest.py", [*flags, "--groups", "0", "--save-model"], stop_after=r"device cpu")
    assert "adjacency pre-training" not in output  # it stopped before the exploration ended
    assert int(re.search(r"stopped: (\d+) frames", output)[1]) < 2000


def test_resume_from_a_stop_inside_episodes_while_both_levels_train(resume_check):
    # DGRL. 87-step episodes, all four envs' from frame 800 on: updates from 1844; at the evaluation of frame 2400 each env
    # is at step 52 of its episode, in the middle of a subgoal's segment, and the stop comes then or a few steps later.
    # After it: a loss log of the updates before it (frame 2500), the episodes' ends (2540) with their returns, and an
    # adjacency retraining (2600).
    flags = [*tiny(max_episode_steps=87, adj_frequency=600, log_frequency=100), "--save-model"]
    output = resume_check("dgrl_hrac_keychest.py", flags, stop_after=r"frame +2400/3000")
    assert 2400 <= int(re.search(r"stopped: (\d+) frames", output)[1]) < 3000


def test_resume_after_kill_9_continues_from_the_last_periodic_resume_file(kill_check):
    """A run killed outright (SIGKILL: no clean stop) at the progress line of frame 2400 goes on from its last periodic
    resume file (every 2000 frames, written between two steps: at frame 2000, with both levels training): TensorBoard
    drops what the killed run logged after the file, and the resumed run's scalars and final checkpoint equal a straight
    run's."""
    flags = [*tiny(max_episode_steps=85, adj_frequency=600), "--save-model"]
    flags += ["--checkpoint-every", "0", "--checkpoint-every-steps", "2000"]
    saved, resumed = kill_check("dgrl_hrac_keychest.py", flags, r"^frame +2400/3000")
    assert saved["variables"]["frames"] == 2000 and "resumed at frame 2000" in resumed
