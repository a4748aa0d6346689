"""dgrl_goal_dqn.py: maze layouts and dynamics, rendering, goal split, bonuses, InfoNCE, evaluation, smoke runs."""

import math
import re

import gymnasium as gym
import numpy as np
import pytest
import torch
import torch.nn.functional as F

import dgrl_goal_dqn as gdqn

SPIRAL_ORDER = [0, 6, 12, 18, 24, 30, 31, 32, 33, 34, 35, 29, 23, 17, 11, 5, 4, 3, 2, 1, 7, 13, 19, 25, 26, 27, 28, 22, 16, 10]
SPIRAL_ORDER += [9, 8, 14, 20, 21, 15]  # the corridor of the reference layout, from the start corner to the centre


def undirected_edges(layout: gdqn.MazeLayout) -> set[tuple[int, int]]:
    return {
        tuple(sorted((cell, int(target))))
        for cell in range(layout.n_cells)
        for target in layout.next_cell[cell]
        if target != cell
    }


# --- layouts and dynamics ---------------------------------------------------------------------------------------------


def test_spiralworld_is_one_corridor_from_the_start_corner():
    layout = gdqn.MazeLayout("SpiralWorld")
    assert (layout.distances >= 0).all()  # connected
    assert len(undirected_edges(layout)) == layout.n_cells - 1  # connected with n-1 edges: a tree
    assert np.argsort(layout.distances[gdqn.START_CELL], kind="stable").tolist() == SPIRAL_ORDER
    assert layout.distances[0, 1] == 19  # adjacent cells, but the wall between them forces the long way round
    assert layout.distances.max() == 35


def test_loopworld_has_exactly_one_cycle_through_the_extra_opening():
    spiral, loop = gdqn.MazeLayout("SpiralWorld"), gdqn.MazeLayout("LoopWorld")
    assert (loop.distances >= 0).all()
    assert len(undirected_edges(loop)) == loop.n_cells  # connected with n edges: exactly one cycle
    assert undirected_edges(loop) - undirected_edges(spiral) == {(28, 34)}
    assert (spiral.distances[0, 28], loop.distances[0, 28]) == (26, 10)
    assert loop.distances[0, 1] == 17


def test_emptyworld_is_an_open_grid():
    layout = gdqn.MazeLayout("EmptyWorld")
    assert len(undirected_edges(layout)) == 2 * 6 * 5
    rows, cols = np.divmod(np.arange(36), 6)
    manhattan = np.abs(rows[:, None] - rows[None]) + np.abs(cols[:, None] - cols[None])
    np.testing.assert_array_equal(layout.distances, manhattan)


@pytest.mark.parametrize("name", ["SpiralWorld", "LoopWorld", "EmptyWorld"])
def test_moves_are_reversible_and_walls_block(name):
    layout = gdqn.MazeLayout(name)
    opposite = [1, 0, 3, 2]
    for cell in range(layout.n_cells):
        row, col = divmod(cell, 6)
        for action, (d_row, d_col) in enumerate(gdqn.MOVES):
            target = layout.next_cell[cell, action]
            if target != cell:
                assert target == (row + d_row) * 6 + col + d_col
                assert layout.next_cell[target, opposite[action]] == cell
            else:
                assert gdqn.LAYOUTS[name][2 * row + 1 + d_row][2 * col + 1 + d_col] == "#"


def test_rendering_draws_walls_and_the_agent_and_noise_only_on_the_floor():
    layout = gdqn.MazeLayout("SpiralWorld")
    assert layout.images.shape == (36, 80, 80, 3) and layout.images.dtype == np.uint8
    assert len({image.tobytes() for image in layout.images}) == 36
    top = left = gdqn.BORDER + gdqn.PIXELS_PER_CHAR  # cell 0 starts one character in from the border
    assert (layout.images[0, top : top + 6, left : left + 6] == gdqn.AGENT_RGB).all()
    assert (layout.images[0, 0, 0] == gdqn.WALL_RGB).all()
    assert (layout.images[:, ~layout.floor] == gdqn.WALL_RGB).all()
    rng = np.random.default_rng(0)
    np.testing.assert_array_equal(layout.render(np.array([3, 3]), 0.0, rng), layout.images[[3, 3]])
    noisy = layout.render(np.array([3, 3]), 0.5, rng)
    changed = (noisy != layout.images[[3, 3]]).any(-1)
    assert changed.any() and not (changed & ~layout.floor[None]).any() and not (changed & layout.agent_mask[[3, 3]]).any()
    assert not np.array_equal(noisy[0], noisy[1])  # fresh noise for every observation
    assert noisy[layout.floor[None] & ~layout.agent_mask[[3, 3]]].max() <= int(0.5 * 255)  # black floor + noise


def test_env_rewards_termination_truncation_and_goal_observation():
    layout = gdqn.MazeLayout("SpiralWorld")
    env = gym.wrappers.TimeLimit(gdqn.VisualMazeEnv(layout, np.array([12]), False, 0.0), 5)
    observation, info = env.reset(seed=0)
    assert info == {"cell": 0, "goal_cell": 12}
    np.testing.assert_array_equal(observation["observation"], layout.images[0])
    np.testing.assert_array_equal(observation["desired_goal"], layout.images[12])
    _, reward, terminated, truncated, info = env.step(1)  # right: a wall in SpiralWorld
    assert (info["cell"], reward, terminated, truncated) == (0, -1.0, False, False)
    _, reward, terminated, _, info = env.step(3)  # down to 6
    assert (info["cell"], reward, terminated) == (6, -1.0, False)
    _, reward, terminated, truncated, info = env.step(3)  # down to 12: the goal
    assert (info["cell"], reward, terminated, truncated) == (12, 5.0, True, False)
    env.reset(seed=1)
    for _ in range(4):
        _, _, terminated, truncated, _ = env.step(0)  # left into the outer wall
        assert not terminated and not truncated
    _, _, terminated, truncated, _ = env.step(0)
    assert (terminated, truncated) == (False, True)


def test_env_goal_and_random_start_distributions():
    layout = gdqn.MazeLayout("LoopWorld")
    goals = np.array([4, 21, 22, 27])
    env = gdqn.VisualMazeEnv(layout, goals, True, 0.0)
    env.reset(seed=0)
    seen_goals, seen_starts = set(), set()
    for _ in range(400):
        _, info = env.reset()
        assert info["goal_cell"] in goals and info["cell"] != info["goal_cell"]
        seen_goals.add(info["goal_cell"])
        seen_starts.add(info["cell"])
    assert seen_goals == set(goals.tolist()) and len(seen_starts) == 36
    fixed = gdqn.VisualMazeEnv(layout, goals, False, 0.0)
    assert all(fixed.reset(seed=seed)[1]["cell"] == gdqn.START_CELL for seed in range(20))


def test_goal_split_is_disjoint_fixed_and_nested():
    layout = gdqn.MazeLayout("SpiralWorld")
    splits = {k: gdqn.goal_split(layout, k, goal_seed=0) for k in (4, 8, 16)}
    novel = splits[4][1]
    assert len(novel) == 4
    for k, (train, novel_k) in splits.items():
        assert len(train) == k and len(set(train.tolist())) == k
        np.testing.assert_array_equal(novel_k, novel)  # the same novel goals for every K
        assert not set(train.tolist()) & set(novel.tolist())
        assert gdqn.START_CELL not in train and gdqn.START_CELL not in novel
    assert set(splits[4][0].tolist()) < set(splits[8][0].tolist()) < set(splits[16][0].tolist())
    assert not np.array_equal(gdqn.goal_split(layout, 4, goal_seed=1)[1], novel)


# --- the agent's math -------------------------------------------------------------------------------------------------


def test_bonuses_factor_match_and_cosine():
    codes_state = torch.tensor([[1, 2, 3, 4], [5, 6, 7, 8]])
    codes_goal = torch.tensor([[1, 2, 0, 0], [5, 6, 7, 8]])
    torch.testing.assert_close(gdqn.intrinsic_bonus(None, None, codes_state, codes_goal), torch.tensor([0.5, 1.0]))
    z_state = torch.tensor([[1.0, 0.0], [1.0, 1.0], [2.0, 0.0]])
    z_goal = torch.tensor([[0.0, 3.0], [2.0, 2.0], [-1.0, 0.0]])
    torch.testing.assert_close(gdqn.intrinsic_bonus(z_state, z_goal, None, None), torch.tensor([0.0, 1.0, -1.0]))


def test_bonus_quality_of_perfect_constant_and_reversed_bonuses():
    layout = gdqn.MazeLayout("LoopWorld")
    distances = layout.distances.astype(float)
    assert gdqn.bonus_quality(-distances, layout) == pytest.approx((1.0, 1.0))
    assert gdqn.bonus_quality(np.ones_like(distances), layout) == (0.0, 0.0)
    correlation, step_closer = gdqn.bonus_quality(distances, layout)
    assert correlation == pytest.approx(-1.0) and step_closer == 0.0


def test_infonce_loss_on_a_toy_batch():
    anchors = torch.tensor([[1.0, 0.0], [0.0, 1.0]])
    positives = torch.tensor([[2.0, 0.0], [1.0, 1.0]])
    scores = (anchors @ positives.t()) / math.sqrt(2)
    scores = 20 * torch.tanh(scores / 20)
    by_hand = -0.5 * (
        torch.log_softmax(scores[0], 0)[0] + torch.log_softmax(scores[1], 0)[1]
    )  # row i must pick column i among all columns
    torch.testing.assert_close(gdqn.infonce_loss(anchors, positives), by_hand)
    aligned = 30 * torch.eye(4)
    assert gdqn.infonce_loss(aligned, aligned) < 1e-6  # clipped scores of 20 vs 0: loss log(1 + 3 e^-20)
    assert gdqn.infonce_loss(aligned, aligned.flip(0)) > 19  # every anchor prefers a wrong positive


def test_random_walks_follow_the_maze():
    layout = gdqn.MazeLayout("LoopWorld")
    cells, actions, next_cells = gdqn.random_walks(layout, 1000, 50, np.random.default_rng(0))
    assert len(cells) == len(actions) == len(next_cells) == 1000
    np.testing.assert_array_equal(next_cells, layout.next_cell[cells, actions])
    walks = next_cells.reshape(-1, 50)[:, :-1]
    np.testing.assert_array_equal(walks, cells.reshape(-1, 50)[:, 1:])  # each walk continues where it stood
    default_cells, _, _ = gdqn.random_walks(layout, 20000, 100, np.random.default_rng(0))
    assert np.bincount(default_cells, minlength=36).min() > 100  # the default data covers every cell well


class _OneHotEmbedder:
    """Stands in for CellEmbedder: the embedding of a cell is its one-hot vector."""

    device, noise = torch.device("cpu"), 0.0

    def __call__(self, rep, cells):
        return F.one_hot(cells, 36).float()


def _identity_rep(z):
    return z, z.new_zeros(()), None


@pytest.mark.parametrize("name", ["SpiralWorld", "LoopWorld"])
def test_evaluate_with_an_optimal_q_function_takes_shortest_paths(name):
    layout = gdqn.MazeLayout(name)
    distances = torch.as_tensor(layout.distances)
    next_cell = torch.as_tensor(layout.next_cell)

    def optimal_q(state_features, goal_features):
        cells, goals = state_features.argmax(1), goal_features.argmax(1)
        return -distances[next_cell[cells], goals.unsqueeze(1)].float()

    goals = np.array([1, 15, 28, 35])
    reached, steps = gdqn.evaluate(_identity_rep, optimal_q, _OneHotEmbedder(), layout, goals, max_steps=100)
    assert reached.all()
    np.testing.assert_array_equal(steps, layout.distances[gdqn.START_CELL, goals])

    def stuck_q(state_features, goal_features):
        return torch.tensor([[1.0, 0.0, 0.0, 0.0]]).expand(len(state_features), 4)  # always left: never moves

    reached, steps = gdqn.evaluate(_identity_rep, stuck_q, _OneHotEmbedder(), layout, goals, max_steps=7)
    assert not reached.any() and (steps == 7).all()


def test_cell_embedder_matches_encoding_the_batch():
    """The noiseless shortcut (encode the 36 distinct images, gather) equals encoding the batch, values and gradients."""
    layout = gdqn.MazeLayout("SpiralWorld")
    rep = gdqn.Representation(16, "infomax", 4, 8, 0.25, 0.99)
    embedder = gdqn.CellEmbedder(layout, 0.0, torch.device("cpu"), np.random.default_rng(0))
    cells = torch.tensor([3, 3, 7, 35, 0])
    shortcut = embedder(rep, cells)
    direct = rep.embed(torch.as_tensor(layout.images[cells.numpy()]))
    torch.testing.assert_close(shortcut, direct)
    grad_shortcut = torch.autograd.grad(shortcut.pow(2).sum(), rep.encoder[0].weight)[0]
    grad_direct = torch.autograd.grad(direct.pow(2).sum(), rep.encoder[0].weight)[0]
    torch.testing.assert_close(grad_shortcut, grad_direct)


# --- the script, end to end -------------------------------------------------------------------------------------------

TINY = ["--total-timesteps", "400", "--learning-starts", "100", "--rep-steps", "5", "--rep-transitions", "500"]
TINY += ["--eval-frequency", "200", "--batch-size", "16", "--buffer-size", "1000", "--max-episode-steps", "30"]


@pytest.mark.parametrize(
    "flags",
    [
        ["--groups", "0"],
        ["--groups", "8", "--save-model"],
        ["--groups", "4", "--finetune", "--noise", "0.3", "--rep", "autoencoder", "--no-double-dqn"],
        ["--groups", "0", "--finetune", "--env-id", "LoopWorld", "--random-start", "--capture-video"],
    ],
    ids=["baseline", "dgrl-checkpoint", "dgrl-finetune-noise-ae", "baseline-finetune-video"],
)
def test_smoke_run(tmp_path, run_script, flags):
    result = run_script("dgrl_goal_dqn.py", *TINY, *flags)
    assert result.returncode == 0, result.stderr[-3000:]
    assert result.stdout.count("step ") == 2 and "novel" in result.stdout
    assert len(list((tmp_path / "runs").glob("*/events.out.tfevents.*"))) == 1
    if "--save-model" in flags:
        (checkpoint,) = (tmp_path / "runs").glob("*/dgrl_goal_dqn.cleanrl_model")
        saved = torch.load(checkpoint)
        assert "vq.codebook" in saved["representation"] and "vq.ema_count" in saved["representation"]
        evaluated = run_script("dgrl_goal_dqn.py", "--groups", "8", "--checkpoint", str(checkpoint))
        assert evaluated.returncode == 0, evaluated.stderr[-3000:]
        assert "train goals" in evaluated.stdout and "novel goals" in evaluated.stdout
    if "--capture-video" in flags:
        assert list((tmp_path / "videos").glob("*/*.mp4"))


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--groups", "5"], r"--groups must be 0 \(baseline\) or divide --embed-dim 64: one of \[1, 2, 4, 8, 16, 32, 64\]"),
        (["--n-train-goals", "40"], r"--n-train-goals must be in \[1, 31\]"),
        (["--noise", "2"], r"--noise must be in \[0, 1\]"),
        (["--env-id", "Nowhere"], "SpiralWorld"),
    ],
)
def test_bad_flags_fail_before_any_work(tmp_path, run_script, flags, message):
    result = run_script("dgrl_goal_dqn.py", *flags)
    assert result.returncode != 0
    assert re.search(message, result.stderr), result.stderr[-2000:]
    assert not (tmp_path / "runs").exists()
