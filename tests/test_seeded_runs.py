"""benchmark/analysis/seeded_runs.py: two runs' outputs are equal bit for bit, or every difference is named."""

import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmark" / "analysis"))

import seeded_runs


def outputs(**changes) -> dict:
    run = {
        "scalars": {"eval/return": [(10, 1.0), (20, "nan")], "losses/td": [(10, 0.5)]},
        "tensors": {"q.weight": torch.tensor([[1.0, float("nan")]]), "vq.ema_count": torch.tensor([3, 4])},
    }
    for kind, (name, value) in changes.items():
        if value is None:
            del run[kind][name]
        else:
            run[kind][name] = value
    return run


def test_equal_outputs_have_no_difference_nan_included():
    assert seeded_runs.differences(outputs(), outputs()) == []


def test_every_kind_of_difference_is_named():
    assert seeded_runs.differences(outputs(), outputs(scalars=("eval/return", [(10, 1.0), (20, 2.0)]))) == [
        "scalar eval/return differs: [(10, 1.0), (20, 'nan')]... against [(10, 1.0), (20, 2.0)]..."
    ]
    assert seeded_runs.differences(outputs(), outputs(scalars=("losses/td", None))) == ["scalar losses/td only before"]
    assert seeded_runs.differences(outputs(), outputs(tensors=("q.weight", torch.tensor([[1.0, 2.0]])))) == [
        "tensor q.weight differs"
    ]
    one_bit = torch.tensor([[torch.nextafter(torch.tensor(1.0), torch.tensor(2.0)).item(), float("nan")]])
    assert seeded_runs.differences(outputs(), outputs(tensors=("q.weight", one_bit))) == ["tensor q.weight differs"]
    assert seeded_runs.differences(outputs(), outputs(tensors=("vq.ema_count", torch.tensor([3.0, 4.0])))) == [
        "tensor vq.ema_count differs"
    ]  # the same values in another dtype
    assert seeded_runs.differences(outputs(), outputs(tensors=("extra", torch.zeros(1)))) == ["tensor extra only after"]


def test_compare_exits_1_on_a_difference_and_0_when_identical(tmp_path, capsys):
    torch.save({"a.py --groups 0": outputs()}, tmp_path / "before.pt")
    torch.save({"a.py --groups 0": outputs()}, tmp_path / "same.pt")
    torch.save({"a.py --groups 0": outputs(scalars=("losses/td", [(10, 0.25)]))}, tmp_path / "other.pt")
    assert seeded_runs.compare(str(tmp_path / "before.pt"), str(tmp_path / "same.pt")) == 0
    assert "a.py --groups 0: IDENTICAL (2 tags, 2 tensors)" in capsys.readouterr().out
    assert seeded_runs.compare(str(tmp_path / "before.pt"), str(tmp_path / "other.pt")) == 1
    assert "a.py --groups 0: DIFFERENT" in capsys.readouterr().out


def test_compare_of_some_scripts_skips_the_others_but_not_a_missing_run(tmp_path):
    torch.save({"a.py --groups 0": outputs(), "b.py --groups 0": outputs()}, tmp_path / "before.pt")
    torch.save({"a.py --groups 0": outputs()}, tmp_path / "after.pt")
    assert seeded_runs.compare(str(tmp_path / "before.pt"), str(tmp_path / "after.pt"), ["a.py"]) == 0
    assert seeded_runs.compare(str(tmp_path / "before.pt"), str(tmp_path / "after.pt"), ["b.py"]) == 1
    assert seeded_runs.compare(str(tmp_path / "before.pt"), str(tmp_path / "after.pt")) == 1
