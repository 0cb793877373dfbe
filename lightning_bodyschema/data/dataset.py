"""The healthy dataset as a file: generate once, cache by content hash, reload when nothing changed."""
from __future__ import annotations

import hashlib
import json
import os
import sys
from dataclasses import dataclass

import numpy as np

from ..sim import MusculoskeletalModel, SpringParams
from ..sim.sampling import generate_samples
from ..npz import load_npz, save_npz

DATASET_FORMAT_VERSION = 2  # bump when the generator changes what it draws (2: in chunks, sim.sampling)


@dataclass
class DatasetSpec:
    """Everything that shapes the data; its hash names the cache file."""

    model_xml: str
    muscles: tuple[str, ...]
    spring: dict
    n_samples: int
    seed: int
    qp_solver: str

    def key(self) -> str:
        payload = json.dumps({**self.__dict__, "muscles": list(self.muscles), "version": DATASET_FORMAT_VERSION},
                             sort_keys=True)
        return hashlib.sha256(payload.encode()).hexdigest()


def build_dataset(model: MusculoskeletalModel, n_samples: int, seed: int, spring: SpringParams,
                  qp_solver: str = "newton", workers: int | None = None,
                  progress: bool | None = None) -> dict[str, np.ndarray]:
    """Generate the arrays written to a dataset file: q, l_motor, f (SI units) and the model XML.

    workers, progress: as ``sim.sampling.generate_samples`` (the same bytes for any number of workers).
    """
    samples = generate_samples(model, n_samples, seed, spring, qp_solver, workers, progress)
    print(f"equilibrium dataset: {n_samples} samples of {model.n_joints} joints / {model.n_muscles} muscles; accepted "
          f"fraction of drawn postures {samples.accepted_fraction:.3f} ({samples.n_redrawn} unholdable re-drawn)",
          file=sys.stderr)
    return {"q": samples.q, "l_motor": samples.l_motor, "f": samples.f, "model_xml": np.array(model.xml),
            "muscle_names": np.array(model.muscle_names), "n_redrawn": np.array(samples.n_redrawn)}


def load_or_build_dataset(model: MusculoskeletalModel, n_samples: int, seed: int, spring: SpringParams,
                          qp_solver: str = "newton", cache_dir: str | None = None, workers: int | None = None,
                          progress: bool | None = None) -> dict[str, np.ndarray]:
    """Return the dataset, from ``cache_dir`` if a file with the same content key is there and intact.

    A cache file whose stored key does not match (stale, corrupted, or edited) is regenerated, on ``workers``
    processes (``build_dataset``); the key does not depend on them (the bytes do not).
    """
    spec = DatasetSpec(model.xml, tuple(model.muscle_names), spring.as_dict(), int(n_samples), int(seed), qp_solver)
    key = spec.key()
    path = os.path.join(cache_dir, f"equilibrium-{key[:16]}.npz") if cache_dir else None
    if path and os.path.isfile(path):
        try:
            arrays = load_npz(path, required=("q", "l_motor", "f", "cache_key"))
            if str(arrays["cache_key"]) == key and _consistent(arrays, n_samples, model) \
                    and str(arrays.get("content_sha256")) == content_digest(arrays):
                return arrays
        except ValueError:
            pass  # unreadable cache: fall through and regenerate it
    arrays = build_dataset(model, n_samples, seed, spring, qp_solver, workers, progress)
    if path:
        save_npz(path, cache_key=np.array(key), content_sha256=np.array(content_digest(arrays)), **arrays)
    return arrays


def content_digest(arrays) -> str:
    """sha256 of the sample arrays, so a cache file edited or damaged after writing is detected."""
    digest = hashlib.sha256()
    for name in ("q", "l_motor", "f"):
        digest.update(np.ascontiguousarray(arrays[name], dtype=np.float64))  # the buffer itself: no copy
    return digest.hexdigest()


def _consistent(arrays, n_samples, model) -> bool:
    q, l_motor, f = arrays["q"], arrays["l_motor"], arrays["f"]
    shapes_ok = q.shape == (n_samples, model.n_joints) and l_motor.shape == f.shape == (n_samples, model.n_muscles)
    return shapes_ok and all(np.all(np.isfinite(a)) for a in (q, l_motor, f))
