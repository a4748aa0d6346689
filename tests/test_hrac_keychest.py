"""dgrl_hrac_keychest.py: Key-Chest layout and dynamics, BFS and adjacency labels, HRAC's losses, the subgoal
autoencoder, subgoal proposals, smoke runs."""

import re

import numpy as np
import pytest
import torch

import dgrl_hrac_keychest as kc

# The reference layout (shared/reference/hrac-keychest.md): K key, B chest, S nominal start.
REFERENCE_LAYOUT = """\
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


def test_layout_matches_the_reference():
    lines = REFERENCE_LAYOUT.splitlines()
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
    env.episode_return[:] = 1.0
    observations, reward, terminated, truncated, infos = env.step([DOWN])
    assert reward[0] == kc.CHEST_REWARD == 5.0 and terminated[0] and not truncated[0]
    np.testing.assert_array_equal(infos["final_obs"][0], [2, 1, 1])  # the true last state, with the key
    assert infos["_final_obs"][0] and infos["episode"]["r"][0] == 6.0 and infos["episode"]["l"][0] == 2
    assert observations[0, 2] == 0 and env.elapsed[0] == 0  # reset in the same step (SAME_STEP autoreset)


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
    assert (infos["episode"]["l"] == 5).all()


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
    rewards = np.array([0, 0, 1, 0, 1, 1, 0, 1], dtype=float)
    returns = kc.segment_returns(rewards, gamma=0.5, k=3)
    expected = [0.25, 0.5, 1.0, 0.5 + 0.25, 1 + 0.5, 1.0, 0.5, 1.0]  # segments [0..2], [3..5], [6..7]
    np.testing.assert_allclose(returns, expected)
    np.testing.assert_allclose(kc.segment_returns(np.ones(4), 0.9, k=10), [1 + 0.9 + 0.81 + 0.729, 1 + 0.9 + 0.81, 1.9, 1])


def test_goal_reached_is_a_box_of_half_width_threshold():
    next_states = torch.tensor([[3.0, 4.0, 0.0]] * 4)
    goals = torch.tensor([[3.5, 4.5], [3.51, 4.0], [2.6, 3.6], [3.0, 5.0]])
    np.testing.assert_array_equal(kc.goal_reached(next_states, goals, 0.5).numpy(), [1, 0, 1, 0])


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


def test_goal_autoencoder_round_trip_separates_cells():
    torch.manual_seed(0)
    ae = kc.GoalAutoencoder(embed_dim=64, hidden_dim=128, groups=16, n_embed=64, beta=0.25, decay=0.99, dead=0)
    optimizer = torch.optim.Adam(ae.parameters(), lr=1e-3)
    scale = torch.as_tensor(kc.GOAL_SCALE)
    for _ in range(2000):  # the script's --ae-init-steps
        goals = torch.rand(256, 2) * scale
        _, vq_loss, _, reconstruction = ae(goals, update=True)
        loss = torch.nn.functional.mse_loss(reconstruction, goals / scale) + vq_loss
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
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
    ae = kc.GoalAutoencoder(embed_dim=16, hidden_dim=32, groups=4, n_embed=8, beta=0.25, decay=0.99, dead=0)
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
    args = kc.Args(n_noisy_goals=20, man_noise_sigma=5.0)
    actor = kc.ManagerActor(16)
    states = torch.tensor([[11.0, 7.0, 0.0], [1.0, 1.0, 1.0]])

    class Coordinates(torch.nn.Module):  # embedding = the cell itself: "reachable" means within 1.1 cells
        def forward(self, cells):
            return cells

    raw = actor(states)
    assert torch.equal(kc.propose_subgoals(actor, Coordinates(), states, args, 1.1, explore=False), raw)
    goals = kc.propose_subgoals(actor, Coordinates(), states, args, 1.1, explore=True)
    assert goals.shape == (2, 2) and (goals >= 0).all() and (goals <= torch.as_tensor(kc.GOAL_SCALE)).all()
    chosen_near = (goals - states[:, :2]).norm(dim=1) < 1.1
    assert (chosen_near | (goals == raw).all(1)).all()  # a reachable candidate, or else the noiseless output

    class Far(torch.nn.Module):  # nothing is reachable: the noiseless output is kept
        def forward(self, cells):
            return cells * 100

    assert torch.equal(kc.propose_subgoals(actor, Far(), states, args, 1.1, explore=True), raw)


def test_manager_replay_is_a_ring():
    replay = kc.ManagerReplay(4, np.random.default_rng(0))
    for start in range(0, 6, 3):
        values = np.arange(start, start + 3, dtype=np.float32)
        replay.add(np.tile(values[:, None], 3), np.tile(values[:, None], 2), values, np.tile(values[:, None], 3), values * 0)
    assert replay.size == 4 and replay.started()
    assert sorted(replay.rewards.tolist()) == [2.0, 3.0, 4.0, 5.0]  # 0 and 1 were overwritten
    states, goals, rewards, next_states, terminals = replay.sample(4, torch.device("cpu"))
    assert torch.equal(next_states[:, 2], rewards) and not terminals.any()
    assert sorted(rewards.tolist()) == [2.0, 3.0, 4.0, 5.0]  # without replacement
    assert torch.equal(states[:, 0], rewards) and torch.equal(goals[:, 1], rewards)


# --- smoke runs -------------------------------------------------------------------------------------------------------

TINY = [
    "--total-timesteps", "3000", "--num-envs", "4", "--max-episode-steps", "100", "--adj-init-steps", "800",
    "--adj-init-epochs", "1", "--adj-training-freq", "1200", "--adj-training-epochs", "1", "--man-buffer-size", "200",
    "--eval-frequency", "4", "--eval-episodes", "4", "--hidden-dim", "32", "--ae-init-steps", "5",
]  # fmt: skip


@pytest.mark.parametrize(("groups", "dgrl_goal"), [("0", "decoded"), ("16", "decoded"), ("16", "embedding")])
def test_smoke_run_trains_evaluates_and_reloads(run_script, tmp_path, groups, dgrl_goal):
    flags = ("--groups", groups, "--dgrl-goal", dgrl_goal)
    result = run_script("dgrl_hrac_keychest.py", *TINY, *flags, "--save-model", "--capture-video")
    assert result.returncode == 0, result.stderr
    assert "adjacency pre-training" in result.stdout and "eval return" in result.stdout
    assert ("distinct cells" in result.stdout) == (groups != "0")
    checkpoint = next(tmp_path.glob("runs/*/dgrl_hrac_keychest.cleanrl_model"))
    saved = torch.load(checkpoint, weights_only=False)
    assert (saved["goal_autoencoder"] is None) == (groups == "0")
    if groups != "0":
        assert "vq.codebook" in saved["goal_autoencoder"] and "vq.ema_count" in saved["goal_autoencoder"]
    assert list(tmp_path.glob("videos/*/eval_*.mp4"))
    events = next(tmp_path.glob("runs/*/events.out.tfevents.*")).read_bytes()
    for tag in (b"eval/return", b"eval/return_random_subgoals", b"charts/SPS", b"charts/adjacency_accuracy"):
        assert tag in events
    assert (b"vq/perplexity" in events) == (groups != "0")
    reloaded = run_script(
        "dgrl_hrac_keychest.py", *flags, "--hidden-dim", "32", "--eval-episodes", "3", "--checkpoint", str(checkpoint)
    )
    assert reloaded.returncode == 0, reloaded.stderr
    assert re.search(r"3 episodes: return [\d.]+", reloaded.stdout)
    assert re.search(r"3 episodes with uniform random subgoals: return [\d.]+", reloaded.stdout)
    mismatched = run_script("dgrl_hrac_keychest.py", "--groups", "8", "--checkpoint", str(checkpoint))
    assert mismatched.returncode != 0 and "was saved with other networks: pass --groups" in mismatched.stderr


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--groups", "5"], "--groups must be 0 (HRAC) or divide --embed-dim 64"),
        (["--num-envs", "0"], "--num-envs must be >= 1"),
        (["--random-action-prob", "1.5"], "--random-action-prob must be in [0, 1]"),
        (["--man-buffer-size", "100"], "--man-batch-size (64) must be <= half of --man-buffer-size (100)"),
        (["--checkpoint", "missing.pt"], "--checkpoint missing.pt: no such file"),
    ],
)
def test_bad_flags_fail_before_any_work(run_script, tmp_path, flags, message):
    result = run_script("dgrl_hrac_keychest.py", *flags)
    assert result.returncode != 0
    assert message in result.stderr
    assert not (tmp_path / "runs").exists()
