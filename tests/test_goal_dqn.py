"""dgrl_goal_dqn.py: maze layouts and dynamics, rendering, goal split, bonuses, InfoNCE, evaluation, the agent's
updates, smoke runs, checkpoints, Ctrl-C and bad flags."""

import itertools
import math
import re
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
import torch.nn.functional as F

import dgrl_goal_dqn as gdqn
from tests.conftest import check_fast_update

ROOT = Path(__file__).resolve().parents[1]

SPIRAL_ORDER = [0, 6, 12, 18, 24, 30, 31, 32, 33, 34, 35, 29, 23, 17, 11, 5, 4, 3, 2, 1, 7, 13, 19, 25, 26, 27, 28, 22, 16, 10]
SPIRAL_ORDER += [9, 8, 14, 20, 21, 15]  # one corridor, from the start corner to the centre


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
    reached, steps, path = gdqn.evaluate(_identity_rep, optimal_q, _OneHotEmbedder(), layout, goals, max_steps=100)
    assert reached.all()
    np.testing.assert_array_equal(steps, layout.distances[gdqn.START_CELL, goals])
    assert path.shape == (steps.max() + 1, len(goals)) and (path[0] == gdqn.START_CELL).all()
    for index, goal in enumerate(goals):  # each path walks the maze's moves and stops at its goal
        walk = path[: steps[index] + 1, index]
        assert walk[-1] == goal and (path[steps[index] :, index] == goal).all()
        assert all(b in layout.next_cell[a] for a, b in itertools.pairwise(walk))

    def stuck_q(state_features, goal_features):
        return torch.tensor([[1.0, 0.0, 0.0, 0.0]]).expand(len(state_features), 4)  # always left: never moves

    reached, steps, path = gdqn.evaluate(_identity_rep, stuck_q, _OneHotEmbedder(), layout, goals, max_steps=7)
    assert not reached.any() and (steps == 7).all() and path.shape == (8, 4) and (path == gdqn.START_CELL).all()


def test_episode_frames_show_the_observation_beside_the_goal():
    layout = gdqn.MazeLayout("SpiralWorld")
    path = np.array([[0, 0], [6, 0], [12, 0]])  # goal 12 reached in 2 steps; the other goal never
    frames = gdqn.episode_frames(layout, path, np.array([2, 2]), np.array([12, 1]))
    assert len(frames) == 6 and all(frame.shape == (160, 324, 3) and frame.dtype == np.uint8 for frame in frames)
    np.testing.assert_array_equal(frames[1][::2, :160:2], layout.images[6])
    np.testing.assert_array_equal(frames[1][::2, 164::2], layout.images[12])
    np.testing.assert_array_equal(frames[5][::2, 164::2], layout.images[1])


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


# --- the agent: wiring and updates --------------------------------------------------------------------------------------

CPU = torch.device("cpu")


def small_agent(groups: int = 4, finetune: bool = False, objective: str = "infomax") -> gdqn.Agent:
    args = gdqn.Args(
        embed_dim=16,
        hidden_dim=32,
        rep=objective,
        groups=groups,
        n_embed=8,
        vq_beta=0.25,
        vq_decay=0.9,
        vq_dead_code_steps=0,
        learning_rate=1e-2,
        rep_learning_rate=1e-2,
        finetune=finetune,
    )
    return gdqn.make_agent(args, CPU)


def snapshot(module: torch.nn.Module) -> dict[str, torch.Tensor]:
    return {name: value.clone() for name, value in module.state_dict().items()}


def changed(before: dict[str, torch.Tensor], module: torch.nn.Module) -> set[str]:
    return {name for name, value in module.state_dict().items() if not torch.equal(value, before[name])}


def test_make_agent_wires_bottleneck_targets_and_optimizers():
    baseline = small_agent(groups=0)
    assert baseline.rep.vq is None and baseline.target_rep is None
    dgrl = small_agent(groups=4)
    assert dgrl.rep.vq.groups == 4 and dgrl.rep.vq.n_embed == 8 and dgrl.rep.vq.decay == 0.9
    assert not any(p.requires_grad for p in dgrl.target_q_network.parameters()) and not dgrl.target_q_network.training
    torch.testing.assert_close(snapshot(dgrl.target_q_network), snapshot(dgrl.q_network))
    q_only = {id(p) for group in dgrl.q_optimizer.param_groups for p in group["params"]}
    assert q_only == {id(p) for p in dgrl.q_network.parameters()}
    finetune = small_agent(groups=4, finetune=True)
    assert "vq.codebook" in finetune.target_rep.state_dict() and not finetune.target_rep.training
    with_encoder = {id(p) for group in finetune.q_optimizer.param_groups for p in group["params"]}
    assert with_encoder == {id(p) for p in [*finetune.q_network.parameters(), *finetune.rep.encoder.parameters()]}


@pytest.mark.parametrize("objective", ["infomax", "autoencoder"])
def test_pretrain_step_trains_phi_and_moves_the_codebook(objective):
    layout = gdqn.MazeLayout("SpiralWorld")
    walks = tuple(torch.as_tensor(c) for c in gdqn.random_walks(layout, 200, 20, np.random.default_rng(0)))
    embedder = gdqn.CellEmbedder(layout, 0.0, CPU, np.random.default_rng(0))
    rows = torch.arange(32)
    agent = small_agent(groups=4, objective=objective)
    before = snapshot(agent.rep)
    metrics = gdqn.pretrain_step(agent, *gdqn.pretrain_inputs(embedder, walks, rows, objective))
    assert metrics["rep_loss"] > 0 and metrics["vq_loss"] > 0 and 1 <= metrics["perplexity"] <= 8
    moved = changed(before, agent.rep)
    assert {"encoder.0.weight", "vq.codebook", "vq.ema_count"} <= moved
    head = "psi_next.weight" if objective == "infomax" else "decoder.0.weight"
    assert head in moved
    baseline = small_agent(groups=0, objective=objective)
    metrics = gdqn.pretrain_step(baseline, *gdqn.pretrain_inputs(embedder, walks, rows, objective))
    assert metrics["vq_loss"] == 0 and "perplexity" not in metrics


def transitions_batch() -> gdqn.Batch:
    """Two SpiralWorld transitions: 0 -> 6 towards goal 12, and 6 -> 12 reaching it (terminal)."""
    return gdqn.Batch(
        cells=torch.tensor([[0, 6, 12], [6, 12, 12]]),
        actions=torch.tensor([3, 3]),
        rewards=torch.tensor([-1.0, 5.0]),
        terminated=torch.tensor([0.0, 1.0]),
    )


@pytest.mark.parametrize("double_dqn", [True, False])
def test_td_update_minimises_the_double_dqn_loss_with_the_bonus_and_leaves_a_frozen_phi_alone(double_dqn):
    layout = gdqn.MazeLayout("SpiralWorld")
    embedder = gdqn.CellEmbedder(layout, 0.0, CPU, np.random.default_rng(0))
    agent = small_agent(groups=4)
    agent.rep.eval()
    agent.rep.requires_grad_(False)
    table = gdqn.cell_table(agent.rep, embedder)
    with torch.no_grad():
        for parameter in agent.target_q_network.parameters():  # a target that differs from the online network
            parameter.add_(torch.randn_like(parameter))
    batch = transitions_batch()
    gamma, bonus_coef = 0.9, 0.5
    with torch.no_grad():  # the loss by hand, from the cell table
        features, codes = table.features, table.codes
        state, next_state, goal = batch.cells.T
        bonus = (codes[next_state] == codes[goal]).float().mean(1)
        target_q = agent.target_q_network(features[next_state], features[goal])
        if double_dqn:
            chosen = agent.q_network(features[next_state], features[goal]).argmax(1)
        else:
            chosen = target_q.argmax(1)
        next_value = target_q[torch.arange(2), chosen]
        target = batch.rewards + bonus_coef * bonus + gamma * (1 - batch.terminated) * next_value
        q_taken = agent.q_network(features[state], features[goal])[torch.arange(2), batch.actions]
        expected_loss = F.smooth_l1_loss(q_taken, target)
    assert bonus[1] == 1.0  # at the goal every factor matches
    rep_before, q_before, target_before = snapshot(agent.rep), snapshot(agent.q_network), snapshot(agent.target_q_network)
    assert gdqn.td_inputs(embedder, batch, table, finetune=False, double_dqn=double_dqn) is None
    metrics = gdqn.td_update(agent, batch, table, None, gdqn.Args(gamma=gamma, bonus_coef=bonus_coef, double_dqn=double_dqn))
    torch.testing.assert_close(metrics["td_loss"], expected_loss)
    torch.testing.assert_close(metrics["bonus"], bonus.mean())
    assert changed(rep_before, agent.rep) == set()  # frozen phi and codebook
    assert changed(target_before, agent.target_q_network) == set()
    assert changed(q_before, agent.q_network) == set(q_before)


def test_td_update_with_finetune_trains_the_encoder_and_the_codebook_but_not_the_targets():
    layout = gdqn.MazeLayout("SpiralWorld")
    embedder = gdqn.CellEmbedder(layout, 0.0, CPU, np.random.default_rng(0))
    agent = small_agent(groups=4, finetune=True)
    rep_before, target_before = snapshot(agent.rep), snapshot(agent.target_rep)
    batch = transitions_batch()
    observed = gdqn.td_inputs(embedder, batch, None, finetune=True, double_dqn=True)
    metrics = gdqn.td_update(agent, batch, None, observed, gdqn.Args(gamma=0.9, bonus_coef=0.5, double_dqn=True))
    assert metrics["vq_loss"] > 0
    assert {"encoder.0.weight", "vq.codebook", "vq.ema_sum"} <= changed(rep_before, agent.rep)
    assert not any(name.startswith("psi") for name in changed(rep_before, agent.rep))  # the heads are not in the TD loss
    assert changed(target_before, agent.target_rep) == set()


def test_greedy_actions_agree_with_the_table_and_never_update_the_codebook():
    layout = gdqn.MazeLayout("LoopWorld")
    env = gdqn.VisualMazeEnv(layout, np.array([22]), True, 0.0)
    observation, info = env.reset(seed=3)
    observations = {key: value[None] for key, value in observation.items()}
    infos = {key: np.array([value]) for key, value in info.items()}
    agent = small_agent(groups=4)
    table = gdqn.cell_table(agent.rep, gdqn.CellEmbedder(layout, 0.0, CPU, np.random.default_rng(0)))
    agent.rep.train()  # even in training mode, acting must not move the codebook
    before = snapshot(agent.rep)
    encoded = gdqn.greedy_actions(agent, None, observations, infos)
    assert changed(before, agent.rep) == set()
    np.testing.assert_array_equal(encoded, gdqn.greedy_actions(agent, table, observations, infos))
    expected = agent.q_network(table.features[[info["cell"]]], table.features[[22]]).argmax(1).numpy()
    np.testing.assert_array_equal(encoded, expected)


def test_replay_buffer_wraps_around_and_samples_only_stored_rows():
    replay = gdqn.ReplayBuffer(3, CPU)
    replay.add(1, 2, 9, 0, -1.0, False)
    rows = replay.sample(50, np.random.default_rng(0))
    assert (rows.cells == torch.tensor([1, 2, 9])).all() and rows.rewards.dtype == torch.float32
    for cell in range(2, 6):
        replay.add(cell, cell + 1, 9, cell % 4, 5.0, cell == 5)
    assert replay.count == 3
    np.testing.assert_array_equal(replay.cells[:, 0], [4, 5, 3])  # 4 and 5 overwrote the two oldest rows
    np.testing.assert_array_equal(replay.terminated, [0.0, 1.0, 0.0])
    assert (replay.sample(50, np.random.default_rng(0)).cells[:, 2] == 9).all()
    restored = gdqn.ReplayBuffer(3, CPU)
    restored.load_state_dict(replay.state_dict())
    for name in gdqn.ReplayBuffer.FIELDS:
        assert torch.equal(getattr(restored, name), getattr(replay, name))
    assert (restored.position, restored.count) == (replay.position, replay.count)


def test_cell_embedder_inputs_draw_noise_on_the_host_and_embed_like_the_embedder():
    """inputs: the 36 clean images and the cells as rows without noise; with noise, one freshly drawn image per cell."""
    layout = gdqn.MazeLayout("SpiralWorld")
    rep = gdqn.Representation(16, "infomax", 4, 8, 0.25, 0.99)
    cells = torch.tensor([3, 3, 7])
    clean = gdqn.CellEmbedder(layout, 0.0, CPU, np.random.default_rng(0))
    images, rows = clean.inputs(cells)
    assert images is clean.all_images and rows is cells
    torch.testing.assert_close(gdqn.embed_images(rep, images, rows), clean(rep, cells))
    noisy = gdqn.CellEmbedder(layout, 0.5, CPU, np.random.default_rng(0))
    images, rows = noisy.inputs(cells)
    assert rows is None and images.shape == (3, 80, 80, 3) and not torch.equal(images[0], images[1])
    again = gdqn.CellEmbedder(layout, 0.5, CPU, np.random.default_rng(0))
    torch.testing.assert_close(gdqn.embed_images(rep, images, None), again(rep, cells))


# --- --fast: each update compiled equals eager and is free of host syncs ---------------------------------------------

FAST_BATCH = 32


@pytest.mark.parametrize("groups, objective", [(0, "infomax"), (4, "autoencoder")])
def test_fast_pretrain_step_equals_eager_and_is_free_of_host_syncs(groups, objective):
    """--fast compile: pretrain_step compiled (phi, its objective, Adam, and for DGRL the codebook EMA with dead-code
    restarts and the codes' perplexity) and equal to eager. InfoNCE does not change when a row's scores all shift by
    the same amount, so psi_next's bias has a gradient of exactly zero but for rounding, which Adam turns into steps of
    a whole learning rate that differ with any summation order: the infomax case leaves it out of the optimizer."""
    layout = gdqn.MazeLayout("SpiralWorld")
    walks = tuple(torch.as_tensor(c) for c in gdqn.random_walks(layout, 500, 20, np.random.default_rng(0)))
    embedder = gdqn.CellEmbedder(layout, 0.0, CPU, np.random.default_rng(0))
    agent = small_agent(groups=groups, objective=objective)
    if groups:
        agent.rep.vq.dead_code_steps = 3
        agent.rep.vq.decay = 0.99  # the script's: at small_agent's 0.9 the EMA sums carry 10x the rounding of each step
    if objective == "infomax":
        trained = [parameter for name, parameter in agent.rep.named_parameters() if name != "psi_next.bias"]
        agent.rep_optimizer = torch.optim.Adam(trained, lr=1e-3, fused=True)
    rng = np.random.default_rng(1)
    rows = [torch.as_tensor(rng.integers(500, size=FAST_BATCH)) for _ in range(31)]
    inputs = [gdqn.pretrain_inputs(embedder, walks, batch_rows, objective) for batch_rows in rows]

    def call(function, state, i):
        return function(state, *inputs[i])

    check_fast_update(gdqn, gdqn.pretrain_step, agent, call, lambda state: [state.rep_optimizer])


@pytest.mark.parametrize("groups, finetune", [(0, False), (4, True)], ids=["baseline-frozen-table", "dgrl-finetune"])
def test_fast_td_update_equals_eager_and_is_free_of_host_syncs(groups, finetune):
    """--fast compile: td_update compiled (Double DQN targets, the bonus, the TD loss and Adam; with --finetune phi's
    encoder and, for DGRL, the codebook EMA on the (state, goal) batch) and equal to eager."""
    layout = gdqn.MazeLayout("SpiralWorld")
    embedder = gdqn.CellEmbedder(layout, 0.0, CPU, np.random.default_rng(0))
    agent = small_agent(groups=groups, finetune=finetune)
    table = None
    if not finetune:
        agent.rep.eval()
        agent.rep.requires_grad_(False)
        table = gdqn.cell_table(agent.rep, embedder)
    replay = gdqn.ReplayBuffer(200, CPU)
    rng = np.random.default_rng(2)
    for _ in range(200):
        cell, goal, action = rng.integers(36), rng.integers(36), rng.integers(4)
        following = layout.next_cell[cell, action]
        replay.add(cell, following, goal, action, 5.0 if following == goal else -1.0, following == goal)
    batches = [replay.sample(FAST_BATCH, rng) for _ in range(31)]
    observed = [gdqn.td_inputs(embedder, batch, table, finetune, True) for batch in batches]

    settings = gdqn.Args(gamma=0.99, bonus_coef=0.5, double_dqn=True)

    def call(function, state, i):
        return function(state, batches[i], table, observed[i], settings)

    check_fast_update(gdqn, gdqn.td_update, agent, call, lambda state: [state.q_optimizer])


# --- the script, end to end ---------------------------------------------------------------------------------------------

TINY = ["--total-timesteps", "400", "--learning-starts", "100", "--rep-steps", "5", "--rep-transitions", "500"]
TINY += ["--eval-frequency", "200", "--batch-size", "16", "--buffer-size", "1000", "--max-episode-steps", "30"]
PROGRESS_LINE = re.compile(r"^step +(\d+)/(\d+)  train .* novel .* SPS", re.M)


def checkpoint_of(tmp_path):
    (checkpoint,) = (tmp_path / "runs").glob("*/dgrl_goal_dqn.cleanrl_model")
    return checkpoint


def assert_checkpoint_refused_with_other_flags_or_goals(tmp_path, run_script, checkpoint: str) -> None:
    """A TINY --groups 8 checkpoint: other flags of MUST_MATCH are named; a different goal split is refused."""
    other = run_script("dgrl_goal_dqn.py", "--env-id", "LoopWorld", "--n-train-goals", "4", "--checkpoint", checkpoint)
    assert other.returncode == 2 and "Traceback" not in other.stderr, other.stderr
    expected = "was saved with other settings: pass --env-id SpiralWorld --n-train-goals 8 --max-episode-steps 30 --groups 8"
    assert expected in other.stderr, other.stderr
    saved = torch.load(checkpoint, weights_only=True)
    saved["novel_goals"] = [3, 5, 31, 35]  # as if another version of goal_split had chosen the goals
    torch.save(saved, tmp_path / "moved.pt")
    moved = run_script("dgrl_goal_dqn.py", "--groups", "8", "--max-episode-steps", "30", "--checkpoint", "moved.pt")
    assert moved.returncode == 2 and "Traceback" not in moved.stderr, moved.stderr
    assert "was trained on the goal split" in moved.stderr and "[3, 5, 31, 35]" in moved.stderr


@pytest.mark.parametrize(
    "flags",
    [
        ["--groups", "0", "--rep-steps", "0"],
        ["--groups", "8", "--save-model"],
        ["--groups", "4", "--finetune", "--noise", "0.3", "--rep", "autoencoder", "--no-double-dqn"],
        ["--groups", "0", "--finetune", "--env-id", "LoopWorld", "--random-start", "--capture-video"],
    ],
    ids=["baseline-untrained-phi", "dgrl-checkpoint", "dgrl-finetune-noise-ae", "baseline-finetune-video"],
)
def test_smoke_run(tmp_path, run_script, flags):
    result = run_script("dgrl_goal_dqn.py", *TINY, *flags)
    assert result.returncode == 0, result.stderr[-3000:]
    assert [int(step) for step, _ in PROGRESS_LINE.findall(result.stdout)] == [200, 400]
    assert "\ndone: " in result.stdout
    assert len(list((tmp_path / "runs").glob("*/events.out.tfevents.*"))) == 1
    if "--save-model" in flags:
        saved = torch.load(checkpoint_of(tmp_path), weights_only=True)
        assert (saved["script"], saved["format"], saved["args"]["groups"]) == ("dgrl_goal_dqn.py", gdqn.CHECKPOINT_FORMAT, 8)
        assert "vq.codebook" in saved["representation"] and "vq.ema_count" in saved["representation"]
        assert (saved["train_goals"], saved["novel_goals"]) == ([1, 2, 4, 12, 19, 21, 22, 27], [3, 5, 31, 34])
        evaluated = run_script(
            "dgrl_goal_dqn.py", "--groups", "8", "--max-episode-steps", "30", "--checkpoint", str(checkpoint_of(tmp_path))
        )
        assert evaluated.returncode == 0, evaluated.stderr[-3000:]
        final = re.search(r"step +400/400  (train .*\))  (novel .*\))  SPS", result.stdout)
        assert evaluated.stdout.splitlines() == [
            final[1].replace("train", "train goals", 1),
            final[2].replace("novel", "novel goals", 1),
        ]
        assert_checkpoint_refused_with_other_flags_or_goals(tmp_path, run_script, str(checkpoint_of(tmp_path)))
    if "--capture-video" in flags:
        assert sorted(path.name for path in (tmp_path / "videos").glob("*/*.mp4")) == ["eval_step200.mp4", "eval_step400.mp4"]


@pytest.mark.parametrize(
    ("flags", "messages"),
    [
        (
            ["--exploration-fraction", "0", "--gamma", "1.5", "--start-e", "0.01", "--end-e", "0.5"],
            ["--exploration-fraction must be in (0, 1]; got 0.0", "--gamma must be in (0, 1]; got 1.5",
             "--start-e 0.01 must be >= --end-e 0.5"],
        ),
        (
            ["--gamma", "0", "--batch-size", "64", "--buffer-size", "32", "--total-timesteps", "500"],
            ["--gamma must be in (0, 1]; got 0.0", "--batch-size 64 must be <= --buffer-size 32",
             "--total-timesteps 500 must exceed --learning-starts 1000"],
        ),
        (
            ["--learning-rate", "-1", "--vq-decay", "1.5", "--bonus-coef", "nan", "--seed", "-1", "--vq-beta", "-0.1"],
            ["--learning-rate must be > 0; got -1.0", "--vq-decay must be in [0, 1); got 1.5",
             "--bonus-coef must be a finite number; got nan", "--seed must be in [0, 2**64)", "--vq-beta must be >= 0"],
        ),
        (
            ["--groups", "5", "--n-train-goals", "40", "--noise", "2", "--rep-batch-size", "1", "--train-frequency", "0"],
            ["--groups must be 0 (baseline) or divide --embed-dim 64: one of [1, 2, 4, 8, 16, 32, 64]; got 5",
             "--n-train-goals must be in [1, 31]", "--noise must be in [0, 1]; got 2.0",
             "--rep-batch-size must be >= 2 with --rep infomax", "--train-frequency must be >= 1; got 0"],
        ),
        (["--env-id", "Nowhere"], ["SpiralWorld"]),
    ],
    ids=["exploration-gamma-epsilon", "gamma0-batch-warmup", "lr-decay-nan-seed", "groups-goals-noise-batch", "env-id"],
)  # fmt: skip
def test_bad_flags_fail_before_any_work(tmp_path, run_script, flags, messages):
    result = run_script("dgrl_goal_dqn.py", *flags)
    assert result.returncode == 2, result.stdout + result.stderr
    assert "Traceback" not in result.stderr, result.stderr
    for message in messages:
        assert message in result.stderr, (message, result.stderr)
    assert not (tmp_path / "runs").exists()


# --- stopping and resuming ----------------------------------------------------------------------------------------------

# Pre-training logs at steps 0, 100 and 149; the DQN phase evaluates every 50 steps and trains from step 20.
RESUME = ["--rep-steps", "150", "--rep-batch-size", "16", "--rep-transitions", "500", "--total-timesteps", "300"]
RESUME += ["--learning-starts", "20", "--eval-frequency", "50", "--batch-size", "16", "--buffer-size", "1000"]
RESUME += ["--max-episode-steps", "50", "--groups", "4", "--save-model"]


def test_resume_inside_pre_training_continues_exactly(resume_check):
    """Stopped by SIGTERM after pre-training's progress line at step 101 of 150: phi, the codebook with its dead-code
    restarts, Adam and the batch generator go on from there; the DQN phase then runs as in a run never stopped."""
    output = resume_check("dgrl_goal_dqn.py", RESUME, stop_after=r"^pre-training step +101/150 ")
    stopped_at = int(re.search(r"stopped: (\d+) pre-training steps, 0 DQN steps", output)[1])
    assert 101 <= stopped_at < 150


def test_resume_inside_a_dqn_episode_continues_exactly(resume_check):
    """Stopped by SIGTERM after the first progress line (DQN step 50): inside an episode (up to 50 steps), with the
    Q-network and, with --finetune, phi and the codebook training, and --noise drawing from the env's generator at every
    step. The purge from the stop step on drops pre-training's points at steps 100 and 149, which the resumed run logs
    again."""
    flags = [*RESUME, "--finetune", "--noise", "0.2", "--train-frequency", "4"]
    output = resume_check("dgrl_goal_dqn.py", flags, stop_after=PROGRESS_LINE.pattern)
    stopped_at = int(re.search(r"stopped: 150 pre-training steps, (\d+) DQN steps", output)[1])
    assert 50 <= stopped_at < 300


def test_resume_after_kill_9_drops_what_followed_the_last_resume_file(kill_check):
    """A run killed with SIGKILL (no clean stop) at the progress line of DQN step 200 goes on from its last periodic resume
    file (every 120 steps of each phase: pre-training step 120, DQN step 120): the points it logged after that file are
    purged and logged again, none twice, none missing."""
    flags = [*RESUME, "--checkpoint-every", "0", "--checkpoint-every-steps", "120"]
    saved, resumed = kill_check("dgrl_goal_dqn.py", flags, r"^step +200/300 ")
    assert saved["loop"]["global_step"] == 120 and "resumed at DQN step 120" in resumed


def test_a_finished_run_resumed_with_free_flags_says_where_it_resumed_and_ends(tmp_path, run_script):
    """(Changed flags that must match are refused for every script: tests/test_skeleton.py.)"""
    tiny = ["--rep-steps", "0", "--total-timesteps", "30", "--learning-starts", "10", "--batch-size", "8"]
    first = run_script("dgrl_goal_dqn.py", *tiny)
    assert first.returncode == 0, first.stderr[-3000:]
    (run_dir,) = (tmp_path / "runs").iterdir()
    free = run_script(
        "dgrl_goal_dqn.py", *tiny, "--checkpoint-every", "5", "--threads", "2", "--resume", f"runs/{run_dir.name}"
    )
    assert free.returncode == 0 and "resumed at DQN step 30" in free.stdout, free.stderr[-3000:]
    assert "\ndone: 0 pre-training steps, 30 DQN steps" in free.stdout
