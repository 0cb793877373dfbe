import atexit
import copy
import os
import shutil
import sys
import tempfile

# inductor's on-disk cache does not key on ATEN_CPU_CAPABILITY: a kernel cached under one capability returns NaN
# (avx2) or does not build (default) under another. Tests run under a capability compile into a cache of its own.
if os.environ.get("ATEN_CPU_CAPABILITY"):
    os.environ.setdefault("TORCHINDUCTOR_CACHE_DIR", os.path.join(
        tempfile.gettempdir(), f"torchinductor_{os.getuid()}_aten_{os.environ['ATEN_CPU_CAPABILITY']}"))

import numpy as np  # noqa: E402
import pytest  # noqa: E402
import torch  # noqa: E402

torch.set_num_threads(1)
torch.set_flush_denormal(True)
os.environ.setdefault("MPLBACKEND", "Agg")
# what the tools remember between runs (tools/static_opt.py: a body's names) stays out of the user's cache
os.environ["BODYSCHEMA_CACHE_DIR"] = tempfile.mkdtemp(prefix="bodyschema-cache-")
atexit.register(shutil.rmtree, os.environ["BODYSCHEMA_CACHE_DIR"], ignore_errors=True)
# the tests live in one folder per subpackage; their shared checks (physics_checks.py) live here
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from physics_checks import train_schema  # noqa: E402

from lightning_bodyschema.data import EquilibriumDataModule  # noqa: E402
from lightning_bodyschema.schemas import AutoEncoderSchema, DiffusionSchema, VAESchema  # noqa: E402


# ---------------------------------------------------------------------------- the run spread over the cores
MAX_AUTO_WORKERS = 8  # each worker imports torch and builds its own session fixtures: up to ~2.5 GB apiece


def pytest_addoption(parser, pluginmanager):
    """pyproject's addopts run the tests on every core with pytest-xdist (the dev extra). Where xdist is absent
    (not installed, or ``-p no:xdist``) the same command runs them in this one process: its ``-n`` and ``--dist``
    are then accepted and ignored (under names of their own, so that no plugin takes the run for a distributed
    one), and no one's test command breaks for want of a plugin."""
    if pluginmanager.has_plugin("xdist"):
        return
    group = parser.getgroup("xdist", "distributed testing (pytest-xdist absent: the tests run in this process)")
    group._addoption("-n", "--numprocesses", dest="absent_xdist_numprocesses", help="ignored without pytest-xdist")
    group.addoption("--dist", dest="absent_xdist_dist", help="ignored without pytest-xdist")


@pytest.hookimpl(optionalhook=True)  # an xdist hook: unknown, and never called, where xdist is absent
def pytest_xdist_auto_num_workers(config):
    """``-n auto``: one worker per core this process may run on, at most MAX_AUTO_WORKERS; the environment's
    PYTEST_XDIST_AUTO_NUM_WORKERS, where set, as xdist documents."""
    if os.environ.get("PYTEST_XDIST_AUTO_NUM_WORKERS", "").isdigit():
        return int(os.environ["PYTEST_XDIST_AUTO_NUM_WORKERS"])
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    return min(cores, MAX_AUTO_WORKERS)


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


# ---------------------------------------------------------------------------- briefly trained schemas (60 epochs)
@pytest.fixture(scope="session")
def dm():
    """The paper arm's data module (800 samples, seed 0), set up: ``dm.splits["val"]`` is the test split."""
    datamodule = EquilibriumDataModule(cache_dir=None)
    datamodule.prepare_data()
    datamodule.setup("fit")
    return datamodule


@pytest.fixture(scope="session")
def diff60(dm):
    """(schema, trainer): the paper's diffusion schema after 60 epochs, float32, eval mode."""
    return train_schema(DiffusionSchema, 60, dm)[:2]


@pytest.fixture(scope="session")
def diff60_f64(diff60):
    """A float64 copy. (Converting back with ``.float()`` would round the float64 noise-schedule buffers for
    good, and the reference then works with other coefficients than a fresh schema.)"""
    return copy.deepcopy(diff60[0]).double()


@pytest.fixture(scope="session")
def diff400():
    """(schema, dm): the paper's diffusion schema after 400 epochs on its own data module, float32, eval mode
    (tests/adaptation and tests/faults share it: copy before changing its dtype)."""
    schema, _, datamodule = train_schema(DiffusionSchema, 400)
    return schema, datamodule


@pytest.fixture(scope="session", params=[AutoEncoderSchema, VAESchema], ids=["AE", "VAE"])
def latent60(request, dm):
    """AE-10 and VAE-10 after 60 epochs, float32, eval mode."""
    return train_schema(request.param, 60, dm)[0]


@pytest.fixture(scope="session")
def latent60_f64(latent60):
    return copy.deepcopy(latent60).double()


