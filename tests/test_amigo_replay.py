"""benchmark/analysis/amigo_replay.py: its measurement patch still fits dgrl_amigo.py, and a script without the anchors
is refused."""

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmark" / "analysis"))

import amigo_replay

ROOT = Path(__file__).resolve().parents[1]


def test_the_patch_applies_to_the_script_once_and_compiles():
    source = (ROOT / "dgrl_amigo.py").read_text()
    patched = amigo_replay.patch(source, 3, 7)
    compile(patched, "dgrl_amigo.py", "exec")
    assert patched.count('REPLAY["update"] += 1') == 1
    assert 'REPLAY = {"update": 0, "first": 3, "last": 7' in patched
    assert 'REPLAY["grad_norm"] = float(torch.nn.utils.clip_grad_norm_(' in patched
    assert patched.index("REPLAY = {") < patched.index("\ndef learn(optimizer")  # defined before learn() uses it


def test_a_script_without_the_anchors_is_refused():
    with pytest.raises(SystemExit, match="no longer has the student's learn call"):
        amigo_replay.patch("print('another script')\n", 1, 2)
