"""benchmark/analysis/factor_map.py: the summary's maths on a hand-made code table, and the tool's figure and table from
tiny checkpoints of each setting it draws (written by the script's own save_checkpoint, untrained)."""

import re
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmark" / "analysis"))
import factor_map  # noqa: E402

import dgrl_amigo as amigo  # noqa: E402
import dgrl_goal_dqn as goal_dqn  # noqa: E402
import dgrl_hrac as hrac  # noqa: E402
import dgrl_hrac_keychest as keychest  # noqa: E402
import dgrl_ris as ris  # noqa: E402
import dgrl_ris_sawyer as sawyer  # noqa: E402

CPU = torch.device("cpu")


def test_the_shares_and_gaps_of_a_hand_made_code_table():
    """On a 4 x 4 grid: a factor that is the column (x), one that is the top or bottom half (y // 2), a constant one,
    and one with a code per cell (x + 4 y), whose 4 bits are 2 of x and 2 of y."""
    y, x = np.divmod(np.arange(16), 4)
    coords = np.stack((y, x), 1)
    codes = np.stack((x, y // 2, np.zeros(16, int), x + 4 * y), 1)
    rows = factor_map.summarise(codes, coords, ("y", "x"))
    assert [row["codes"] for row in rows] == [4, 2, 1, 16]
    assert rows[0]["share"] == pytest.approx({"y": 0.0, "x": 1.0}) and rows[0]["gap"] == pytest.approx(1.0)
    assert rows[1]["share"] == pytest.approx({"y": 1.0, "x": 0.0}) and rows[1]["gap"] == pytest.approx(1.0)
    assert rows[2]["share"] == {"y": 0.0, "x": 0.0} and rows[2]["gap"] == 0.0
    assert rows[3]["share"] == pytest.approx({"y": 0.5, "x": 0.5}) and rows[3]["gap"] == pytest.approx(0.0)
    assert factor_map.mean_gap(rows) == pytest.approx(2 / 3)  # the constant factor left out
    assert factor_map.entropy(codes[:, 3]) == pytest.approx(4.0) and factor_map.entropy(codes) == pytest.approx(4.0)


def test_kmeans_finds_separated_clusters():
    rng = np.random.default_rng(0)
    centres = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0]])
    points = np.concatenate([centre + rng.normal(0, 0.1, (20, 2)) for centre in centres])
    labels = factor_map.kmeans(points, 3)
    assert [len(set(labels[i : i + 20])) for i in (0, 20, 40)] == [1, 1, 1] and len(set(labels)) == 3


def untrained_checkpoint(script: str, folder: Path, groups: int, **flags) -> str:
    """A checkpoint as the script's --save-model writes it (its own save_checkpoint and entries), of an untrained agent."""
    torch.manual_seed(0)
    if script == "keychest":
        args = keychest.Args(groups=groups, seed=3, **flags)
        module, entries = keychest, keychest.make_agent(args, CPU).state_dicts()
    elif script == "goal_dqn":
        args = goal_dqn.Args(groups=groups, seed=3, **flags)
        agent = goal_dqn.make_agent(args, CPU)
        module, entries = goal_dqn, {"representation": agent.rep.state_dict(), "q_network": agent.q_network.state_dict()}
    elif script == "ris":
        args = ris.Args(groups=groups, seed=3, **flags)
        goal_dim = 31 if args.env_id in ris.ANT_MAZES else 2
        module, entries = ris, ris.make_agent(goal_dim if goal_dim == 31 else 6, goal_dim, 8, args, CPU).state_dicts()
    elif script == "hrac":
        args = hrac.Args(groups=groups, seed=3, **flags)
        module, entries = hrac, hrac.make_agent(30, 8, args, CPU).state_dicts()
    elif script == "amigo":
        args = amigo.Args(groups=groups, seed=3, **flags)
        module, entries = amigo, amigo.make_agent(5, 5, 7, args, CPU).state_dicts()
    else:
        args = sawyer.Args(groups=groups, seed=3, **flags)
        module, entries = sawyer, sawyer.make_agent(sawyer.IMAGE_SIZE, 2, args, CPU).state_dicts()
    path = str(folder / f"{script}_G{groups}.cleanrl_model")
    module.save_checkpoint(path, entries, args)
    return path


XY = "| run | factor | codes | share x | share y | gap |"
# script, flags, the first line of the table, the goals of one map, the maps per checkpoint
SETTINGS = [
    ("keychest", {}, "| run | factor | codes | share row | share col | gap |", 128, 1),
    ("goal_dqn", {"env_id": "SpiralWorld"}, "| run | factor | codes | share row | share col | gap |", 36, 1),
    ("ris", {"env_id": "PointMaze_UMaze-v3"}, XY, 7 * 16, 1),
    ("ris", {"env_id": "AntU"}, XY, None, 1),
    ("hrac", {"env_id": "AntMaze"}, XY, 21 * 21, 1),
    ("amigo", {"env_id": "MiniGrid-DoorKey-5x5-v0"}, XY.replace("share y", "share y | share object"), None, 1),
    ("sawyer", {}, XY, None, 2),
]

SETTING_IDS = [f"{script}-{flags.get('env_id')}" for script, flags, *_ in SETTINGS]


@pytest.mark.parametrize("script, flags, header, goals, maps", SETTINGS, ids=SETTING_IDS)
def test_the_factor_map_of_a_dgrl_and_a_baseline_checkpoint(script, flags, header, goals, maps, tmp_path, capsys):
    """The tool on untrained G = 4 and G = 0 checkpoints of each setting: the figure, and the table it prints and writes,
    with a k-means row, a row per factor and the mean gap for DGRL, the k-means row alone for the baseline."""
    paths = (untrained_checkpoint(script, tmp_path, 4, **flags), untrained_checkpoint(script, tmp_path, 0, **flags))
    factor_map.main(factor_map.Args(checkpoints=paths, out=str(tmp_path / "map"), cut_to=str(tmp_path / "cut")))
    table = (tmp_path / "map.md").read_text().splitlines()
    assert (tmp_path / "map.png").stat().st_size > 10_000 and table == capsys.readouterr().out.splitlines()[: len(table)]
    assert table[0] == header
    cut = sorted(str(path) for path in (tmp_path / "cut").iterdir())
    saved = torch.load(paths[0], weights_only=True)
    stem = Path(saved["script"]).stem.removeprefix("dgrl_")  # e.g. hrac_keychest, and the env if the script has several
    stem += f"_{saved['args']['env_id'].removeprefix('MiniGrid-')}" if "env_id" in saved["args"] else ""
    assert [Path(path).name for path in cut] == [f"{stem}_G0_s3.pt", f"{stem}_G4_s3.pt"]
    factor_map.main(factor_map.Args(checkpoints=(cut[1], cut[0]), out=str(tmp_path / "from_cut")))
    assert (tmp_path / "from_cut.md").read_text().splitlines() == table  # the cut checkpoints draw the same map
    labels = sorted({line.split(" | ")[0].removeprefix("| ") for line in table[2:]})
    assert len(labels) == 2 * maps and all(" G = " in f" {label}" for label in labels)
    for label in labels:
        rows = [line.split(" | ")[1] for line in table if line.startswith(f"| {label} |")]
        expected = ["k-means", "0", "1", "2", "3", "mean gap (factors with > 1 code)"] if "G = 4" in label else ["k-means"]
        assert rows == expected, label
    saved = torch.load(paths[0], weights_only=True)
    args_n_embed = saved["args"]["n_embed"]
    for grid in factor_map.SETTINGS[saved["script"]][0](saved):
        assert grid.codes.shape == (len(grid.coords), 4) and 0 <= grid.codes.min() <= grid.codes.max() < args_n_embed
        assert len(grid.places) == len(grid.coords) == len(grid.embedding) and not grid.blocked[tuple(grid.places.T)].any()
        assert goals is None or len(grid.coords) == goals


def test_the_maps_put_each_goal_where_the_environment_has_it():
    """Places against the environments: goal-DQN's cell (row, col) at (2 row + 1, 2 col + 1) of its character layout;
    PointMaze's U-maze (baseline: the embedding is the goal's xy) on its three free rows, largest y at the top; HRAC's
    offsets a full square; AMIGo's walls blocked and every other cell a goal."""
    args = goal_dqn.Args(env_id="SpiralWorld", groups=4)
    (grid,) = factor_map.goal_dqn({"args": vars(args), "representation": goal_dqn.make_agent(args, CPU).rep.state_dict()})
    assert (grid.places[7] == (3, 3)).all() and (grid.coords[7] == (1, 1)).all() and len(grid.coords) == 36
    layout = goal_dqn.LAYOUTS["SpiralWorld"]
    assert all(layout[row][col] == "." for row, col in grid.places) and grid.blocked[0].all()

    args = ris.Args(env_id="PointMaze_UMaze-v3", groups=0)
    (grid,) = factor_map.ris({"args": vars(args)}, step=0.5)  # 2 x 2 goals a cell
    xy = grid.embedding
    assert grid.blocked.shape == (10, 10) and len(xy) == 4 * 7 and sorted(set(grid.places[:, 0] // 2)) == [1, 2, 3]
    assert xy[grid.places[:, 0].argmin(), 1] == xy[:, 1].max() and xy[grid.places[:, 1].argmin(), 0] == xy[:, 0].min()
    assert np.allclose(np.unique(np.round(xy[:, 1], 2)), (-1.25, -0.75, -0.25, 0.25, 0.75, 1.25))  # the rows of 3 cells

    args = hrac.Args(env_id="AntMaze", groups=4)
    (grid,) = factor_map.hrac({"args": vars(args), "subgoal_encoder": hrac.make_agent(30, 8, args, CPU).encoder.state_dict()})
    assert grid.blocked.shape == (21, 21) and not grid.blocked.any() and len(grid.coords) == 21 * 21

    args = amigo.Args(env_id="MiniGrid-DoorKey-5x5-v0", groups=4)
    encoder = amigo.make_agent(5, 5, 7, args, CPU).goal_encoder
    (grid,) = factor_map.amigo({"args": vars(args), "goal_encoder": encoder.state_dict()})
    assert grid.blocked[0].all() and grid.blocked[:, 0].all() and len(grid.coords) == 25 - grid.blocked.sum()
    assert set(grid.coords[:, 2]) >= {amigo.OBJECT_TO_IDX[name] for name in ("key", "door", "goal", "agent")}


def test_a_checkpoint_of_a_script_without_a_map_is_refused_by_name(tmp_path):
    path = tmp_path / "other.cleanrl_model"
    torch.save({"script": "dgrl_mnist.py", "args": {}}, path)
    refusal = "a checkpoint of dgrl_mnist.py; factor maps exist for dgrl_goal_dqn.py, dgrl_ris.py"
    with pytest.raises(SystemExit, match=re.escape(refusal)):
        factor_map.main(factor_map.Args(checkpoints=(str(path),)))
    with pytest.raises(SystemExit, match=re.escape("no such checkpoint: nowhere.pt")):
        factor_map.main(factor_map.Args(checkpoints=("nowhere.pt",)))
    with pytest.raises(SystemExit, match="give one or more checkpoints"):
        factor_map.main(factor_map.Args(checkpoints=()))
