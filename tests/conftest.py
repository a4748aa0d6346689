import pytest
import torch


@pytest.fixture(autouse=True)
def _seed_everything():
    """Every test starts from the same torch random state, so a failure reproduces."""
    torch.manual_seed(0)
