"""Dataset generation, caching, normalization and the Lightning data module."""
from .dataset import build_dataset, load_or_build_dataset
from .datamodule import EquilibriumDataModule
from .normalizer import Normalizer
from .recorded import ModelFreeRobot, RecordedDataModule, read_recorded, write_recorded
from ..npz import load_npz, save_npz

__all__ = ["build_dataset", "load_or_build_dataset", "EquilibriumDataModule", "Normalizer", "ModelFreeRobot",
           "RecordedDataModule", "read_recorded", "write_recorded", "load_npz", "save_npz"]
