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

import dgrl_hrac_keychest as keychest  # noqa: E402


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


def keychest_checkpoint(folder: Path, groups: int) -> str:
    args = keychest.Args(groups=groups, seed=3)
    torch.manual_seed(0)
    agent = keychest.make_agent(args, torch.device("cpu"))
    path = str(folder / f"G{groups}.cleanrl_model")
    keychest.save_checkpoint(path, agent.state_dicts(), args)
    return path


def test_the_keychest_factor_map_of_a_dgrl_and_a_baseline_checkpoint(tmp_path, capsys):
    paths = (keychest_checkpoint(tmp_path, 4), keychest_checkpoint(tmp_path, 0))
    factor_map.main(factor_map.Args(checkpoints=paths, out=str(tmp_path / "map")))
    table = (tmp_path / "map.md").read_text().splitlines()
    assert (tmp_path / "map.png").stat().st_size > 10_000 and table == capsys.readouterr().out.splitlines()[: len(table)]
    assert table[0] == "| run | factor | codes | share row | share col | gap |"
    dgrl = [line for line in table if line.startswith("| G = 4, seed 3 |")]
    assert [line.split(" | ")[1] for line in dgrl] == ["k-means", "0", "1", "2", "3", "mean gap (factors with > 1 code)"]
    baseline = [line for line in table if line.startswith("| G = 0, seed 3 |")]
    assert len(baseline) == 1 and baseline[0].split(" | ")[1] == "k-means"
    grid = factor_map.keychest(torch.load(paths[0], weights_only=True))
    assert grid.codes.shape == (len(keychest.FREE_CELLS), 4) and grid.codes.max() < keychest.Args().n_embed


def test_a_checkpoint_of_a_script_without_a_map_is_refused_by_name(tmp_path):
    path = tmp_path / "other.cleanrl_model"
    torch.save({"script": "dgrl_mnist.py", "args": {}}, path)
    refusal = "a checkpoint of dgrl_mnist.py; factor maps exist for dgrl_hrac_keychest.py"
    with pytest.raises(SystemExit, match=re.escape(refusal)):
        factor_map.main(factor_map.Args(checkpoints=(str(path),)))
    with pytest.raises(SystemExit, match=re.escape("no such checkpoint: nowhere.pt")):
        factor_map.main(factor_map.Args(checkpoints=("nowhere.pt",)))
    with pytest.raises(SystemExit, match="give one or more checkpoints"):
        factor_map.main(factor_map.Args(checkpoints=()))
