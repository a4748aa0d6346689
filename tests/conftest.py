import os
import subprocess
import sys
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")  # headless in-process rendering; read when mujoco is first imported

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(autouse=True)
def _seed_everything():
    """Every test starts from the same torch random state, so a failure reproduces; one torch thread per test worker
    (pytest -n auto already fills the cores, and two threads per worker made small-network tests 3x slower)."""
    torch.manual_seed(0)
    torch.set_num_threads(1)


@pytest.fixture
def run_script(tmp_path):
    """Run a project script as a user would, in a fresh working directory, on one thread, with a 5-minute cap; `env`
    adds environment variables (e.g. MUJOCO_GL)."""

    def run(script: str, *flags: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
        base = {"PATH": "/usr/bin:/bin", "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1", "MPLBACKEND": "Agg"}
        return subprocess.run(
            [sys.executable, str(ROOT / script), *flags],
            cwd=tmp_path,
            capture_output=True,
            text=True,
            timeout=300,
            env=base | (env or {}),
        )

    return run
