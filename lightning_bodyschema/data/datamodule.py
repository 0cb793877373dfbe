"""``EquilibriumDataModule``: the healthy (q, l_motor, f) dataset of one robot, as Lightning data.

The train split is served as Lightning batches, one per optimizer step: a seeded permutation per epoch, cut
into one disjoint shard per process (``ShardSampler``: ``DistributedSampler``'s contract), then into
minibatches of the module's own ``batch_size``, sliced from tensors held in memory (``MinibatchLoader``: index
tensors, no per-sample Python, no collate). On this tiny dataset a ``DataLoader`` over samples would cost more
than the maths (docs/design.md, data and training). Validation and test get the whole held-out split as one batch.
"""
from __future__ import annotations

import math
from typing import Callable, Optional, Sequence

import lightning as L
import numpy as np
import torch
from torch.utils.data import DataLoader

from ..errors import BodySchemaInputError
from ..sim import MusculoskeletalModel
from ..sim.sampling import check_workers
from ..sim.spring import spring_for_model
from ..training.fit_loop import batches_trained_this_epoch
from .dataset import load_or_build_dataset
from .normalizer import Normalizer


class _WholeSplit(torch.utils.data.Dataset):
    """A dataset of one item: the whole split (q (n, N), x (n, 2M)) in SI units."""

    def __init__(self, q, x):
        self.tensors = (q, x)

    def __len__(self):
        return 1

    def __getitem__(self, i):
        return self.tensors


class ShardSampler:
    """A seeded permutation of ``n`` indices per epoch, split into ``world_size`` disjoint shards.

    The contract of ``torch.utils.data.DistributedSampler``: every rank draws the same permutation (seeded by
    ``seed + epoch``, so independent of any global RNG and the same on resume), pads it by wrapping around to a
    multiple of ``world_size`` so that every rank runs the same number of steps, and takes every
    ``world_size``-th index from its ``rank``. When ``world_size`` divides ``n`` the shards are disjoint and
    cover the split. Lightning calls ``set_epoch`` at the start of every epoch.
    """

    def __init__(self, n: int, seed: int, rank: int = 0, world_size: int = 1):
        if not 0 <= rank < world_size:
            raise BodySchemaInputError(f"rank={rank!r} must lie in 0..world_size-1 (world_size={world_size!r})")
        self.n, self.seed, self.rank, self.world_size = int(n), int(seed), int(rank), int(world_size)
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return math.ceil(self.n / self.world_size)

    def indices(self) -> torch.Tensor:
        """This rank's shard of this epoch's permutation (int64, CPU)."""
        order = torch.randperm(self.n, generator=torch.Generator().manual_seed(self.seed + self.epoch))
        padding = len(self) * self.world_size - self.n
        if padding:
            order = torch.cat([order, order[:padding]])
        return order[self.rank::self.world_size]


def _n_train(n_samples: int, val_fraction: float) -> int:
    """Rows of the train split; the rest validate."""
    return int(round(n_samples * (1.0 - val_fraction)))


def check_loader_args(seed, val_fraction, batch_size) -> None:
    """Refuse a negative or fractional seed, a ``val_fraction`` outside (0, 1) and a ``batch_size`` below 1."""
    if int(seed) != seed or seed < 0:
        raise BodySchemaInputError(f"seed={seed!r} must be an integer >= 0")
    if not 0.0 < val_fraction < 1.0:
        raise BodySchemaInputError(f"val_fraction={val_fraction!r} must lie strictly between 0 and 1")
    if isinstance(batch_size, bool) or int(batch_size) != batch_size or batch_size <= 0:
        raise BodySchemaInputError(f"batch_size={batch_size!r} must be a positive integer")


def check_split(n_samples: int, val_fraction: float) -> None:
    """Refuse a split that leaves a side empty (the normalizer needs 2 train rows; validation needs 1)."""
    n_train = _n_train(n_samples, val_fraction)
    if not 2 <= n_train <= n_samples - 1:
        raise BodySchemaInputError(
            f"val_fraction={val_fraction!r} of {n_samples} samples leaves {n_train} train and {n_samples - n_train} "
            f"validation samples; both splits need samples (train at least 2)")


class MinibatchLoader:
    """The minibatches ``(q, x)`` of one rank's shard for one epoch, sliced from in-memory tensors.

    Not a ``DataLoader`` (Lightning leaves other iterables alone: it injects no sampler of its own), but it
    has what Lightning looks for: ``len`` (batches per epoch), ``sampler.set_epoch``, and ``state_dict`` /
    ``load_state_dict``, so a fit resumed from a mid-epoch checkpoint continues the epoch where it stopped
    (same order, the remaining batches) instead of replaying its start.

    batches_done: how many of this epoch's batches have been trained on (the trainer's count; without it the
        loader's own count of batches handed out, which runs ahead of training by Lightning's prefetch).
    """

    def __init__(self, q: torch.Tensor, x: torch.Tensor, batch_size: int, sampler: ShardSampler,
                 batches_done: Optional[Callable[[], int]] = None):
        if int(batch_size) != batch_size or batch_size <= 0:
            raise BodySchemaInputError(f"batch_size={batch_size!r} must be a positive integer")
        self.q, self.x, self.batch_size, self.sampler = q, x, int(batch_size), sampler
        self._batches_done, self._handed_out = batches_done, 0
        self._resume_at: Optional[tuple[int, int]] = None  # (epoch, batches already trained) from a checkpoint

    def __len__(self) -> int:
        return math.ceil(len(self.sampler) / self.batch_size)

    def state_dict(self) -> dict:
        done = self._batches_done() if self._batches_done is not None else self._handed_out
        return {"epoch": self.sampler.epoch, "batches_done": int(done)}

    def load_state_dict(self, state: dict) -> None:
        self._resume_at = (int(state["epoch"]), int(state["batches_done"]))

    def __iter__(self):
        # one gather per epoch, then each minibatch is a view (cheaper than a gather per minibatch)
        idx = self.sampler.indices()
        q, x = self.q[idx], self.x[idx]
        first = 0
        if self._resume_at is not None and self._resume_at[0] == self.sampler.epoch:
            first = self._resume_at[1]  # the resumed epoch: its order, minus the batches already trained on
        self._resume_at, self._handed_out = None, first
        for start in range(first * self.batch_size, len(idx), self.batch_size):
            self._handed_out += 1
            yield q[start:start + self.batch_size], x[start:start + self.batch_size]


class EquilibriumDataModule(L.LightningDataModule):
    """Healthy equilibrium samples of a musculoskeletal robot.

    Args:
        model: ``"paper_arm"``, ``myo:<name>`` (a MyoSuite model, needs ``myo-sim``) or a path to an MJCF with
            spatial tendons.
        n_samples: dataset size (paper: 800).
        seed: seeds the postures, reference tensions and the split.
        val_fraction: share held out for validation/test (paper: 0.2).
        batch_size: training minibatch size per optimizer step and process (the CLI links it to
            ``--model.batch_size``, which a schema's checkpoint records).
        muscles: tendon names that are muscles (default: the tendons muscle actuators drive, else every
            spatial tendon).
        k_n, alpha_per_m, f_max_n: spring constants (paper: 1000 N, 20 1/m, 150 N); scalar or per muscle;
            f_max_n and k_n also ``"model"`` (peak forces of the model's muscle actuators, k scaled with
            them; the default for models with muscle actuators): see ``sim.spring.spring_for_model``.
        gravity: optional gravity override [m/s^2].
        qp_solver: ``"newton"`` (default: batched, the same bytes in every process), ``"proxqp"`` or any qpsolvers
            solver name.
        cache_dir: where generated datasets are cached by content hash (None: no cache); under runs/, with
            every other output of a run, so a checkout stays clean.
        locked_joints: ``{joint: value}`` [rad or m] held fixed; joints no muscle crosses are locked at
            their reference position anyway (one summary line).
        fixed_base: weld a floating base (free joint, e.g. MyoSuite's legs' pelvis) at the model's reference
            pose; see ``MusculoskeletalModel``.
        workers: processes that generate the dataset (None: every core; 0 or 1: this process); the data are the
            same bytes for any number, and the cache key does not depend on it (``sim.sampling``). A progress bar
            shows on a terminal.
    """

    def __init__(self, model: str = "paper_arm", n_samples: int = 800, seed: int = 0, val_fraction: float = 0.2,
                 muscles: Optional[Sequence[str]] = None, k_n: float | list[float] | str | None = None,
                 alpha_per_m: float | list[float] = 20.0, f_max_n: float | list[float] | str | None = None,
                 gravity: Optional[Sequence[float]] = None, qp_solver: str = "newton",
                 cache_dir: Optional[str] = "runs/cache", locked_joints: Optional[dict[str, float]] = None,
                 batch_size: int = 64, fixed_base: bool = False, workers: Optional[int] = None):
        super().__init__()
        check_workers(workers)
        if int(n_samples) != n_samples or n_samples < 10:
            raise BodySchemaInputError(f"n_samples={n_samples!r} must be an integer >= 10")
        check_loader_args(seed, val_fraction, batch_size)
        check_split(int(n_samples), val_fraction)
        self.save_hyperparameters()
        self.robot_model = MusculoskeletalModel(model, muscles=muscles, gravity=gravity, locked_joints=locked_joints,
                                                fixed_base=fixed_base)
        self.spring = spring_for_model(self.robot_model, k_n, alpha_per_m, f_max_n)
        self.normalizer = Normalizer(2 * self.robot_model.n_muscles, self.robot_model.n_joints)
        self.arrays: dict[str, np.ndarray] | None = None

    @property
    def robot(self) -> dict:
        """What a schema needs to rebuild the robot anywhere: XML text, muscles, spring, gravity."""
        return {"model_xml": self.robot_model.xml, "muscles": self.robot_model.muscle_names,
                "spring": self.spring.as_dict()}

    def prepare_data(self):
        self._load()

    def _load(self):
        if self.arrays is None:
            hp = self.hparams
            self.arrays = load_or_build_dataset(self.robot_model, hp.n_samples, hp.seed, self.spring,
                                                hp.qp_solver, hp.cache_dir, hp.get("workers"))
        return self.arrays

    def setup(self, stage: str | None = None):
        arrays = self._load()
        q = torch.as_tensor(arrays["q"], dtype=torch.float64)
        x = torch.as_tensor(np.concatenate([arrays["l_motor"], arrays["f"]], axis=1), dtype=torch.float64)
        order = torch.randperm(len(q), generator=torch.Generator().manual_seed(self.hparams.seed))
        n_train = _n_train(len(q), self.hparams.val_fraction)
        self.train_idx, self.val_idx = order[:n_train], order[n_train:]
        self.splits = {"train": (q[self.train_idx], x[self.train_idx]), "val": (q[self.val_idx], x[self.val_idx])}
        self.normalizer.fit(self.splits["train"][1], self.robot_model.q_range)

    def _loader(self, split):
        return DataLoader(_WholeSplit(*self.splits[split]), batch_size=None, shuffle=False)

    def train_dataloader(self):
        """Minibatches of this process's shard of the train split, reshuffled every epoch (seeded by ``seed``).

        Minibatches of ``batch_size``; the rank and the number of processes come from the trainer's strategy (one
        process, rank 0, without a trainer).
        """
        q, x = self.splits["train"]
        trainer = self.trainer
        shards = (trainer.distributed_sampler_kwargs if trainer is not None else None) or {}
        sampler = ShardSampler(len(q), self.hparams.seed, shards.get("rank", 0), shards.get("num_replicas", 1))
        progress = (lambda: batches_trained_this_epoch(trainer)) if trainer is not None else None
        return MinibatchLoader(q, x, self.batch_size, sampler, batches_done=progress)

    def transfer_batch_to_device(self, batch, device: torch.device, dataloader_idx: int):
        """Lightning's hook, called for every batch: a tuple of CPU tensors bound for the CPU (this module's
        batches in a CPU fit) is already there and is returned as it is, without Lightning's walk of a general
        collection; every other batch is moved by Lightning."""
        if device.type == "cpu" and type(batch) is tuple and all(
                isinstance(t, torch.Tensor) and t.device.type == "cpu" for t in batch):
            return batch
        return super().transfer_batch_to_device(batch, device, dataloader_idx)

    @property
    def batch_size(self) -> int:
        return int(self.hparams.get("batch_size", 64))

    def train_batches_per_epoch(self, world_size: int = 1) -> int:
        """Minibatches of one rank's shard per epoch (what ``train_dataloader`` serves), known before any data."""
        n_samples = len(self.arrays["q"]) if self.arrays is not None else int(self.hparams.n_samples)
        return math.ceil(math.ceil(_n_train(n_samples, self.hparams.val_fraction) / world_size) / self.batch_size)

    def val_dataloader(self):
        return self._loader("val")

    def test_dataloader(self):
        return self._loader("val")  # the paper evaluates on its 20 % held-out split

    def predict_dataloader(self):
        return self._loader("val")

    def state_dict(self):
        return {"normalizer": self.normalizer.state_dict()}

    def load_state_dict(self, state_dict):
        self.normalizer.load_state_dict(state_dict["normalizer"])
