import os
import sys

import numpy as np
import pytest
import torch

torch.set_num_threads(1)
torch.set_flush_denormal(True)
os.environ.setdefault("MPLBACKEND", "Agg")
# the tests live in one folder per subpackage; their shared checks (physics_checks.py) live here
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))


@pytest.fixture(scope="session")
def arm():
    from lightning_bodyschema.sim import MusculoskeletalModel

    return MusculoskeletalModel("paper_arm")


@pytest.fixture(scope="session")
def healthy(arm):
    """400 healthy equilibrium samples of the paper arm (seed 0)."""
    from lightning_bodyschema.sim import generate_equilibrium_samples

    return generate_equilibrium_samples(arm, 400, seed=0)


@pytest.fixture
def rng():
    return np.random.default_rng(1234)
