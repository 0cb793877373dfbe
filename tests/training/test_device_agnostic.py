"""No tensor on a fixed device in training, adaptation or evaluation; a schema keeps training and adapting after
moving between dtypes (the device-dependent paths that a CPU-only machine can run)."""
import os
import re

import lightning as L
import numpy as np
import pytest
import torch

from lightning_bodyschema.faults import Faults
from lightning_bodyschema.schemas import AutoEncoderSchema, DiffusionSchema

PACKAGE = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))),
                       "lightning_bodyschema")
FIXED_DEVICE = re.compile(r"""device\s*=\s*["'](cpu|cuda)|\.to\(\s*["'](cpu|cuda)|torch\.device\(\s*["'](cpu|cuda)|\w\.cuda\(""")


@pytest.mark.parametrize("folder", ["schemas", "data", "networks", "adaptation", "evaluation", "samplers", "faults",
                                    "callbacks"])
def test_no_tensor_is_created_on_a_fixed_device(folder):
    assert os.path.isdir(os.path.join(PACKAGE, folder)), folder  # a scan of a folder that is gone would pass vacuously
    hits = []
    for root, _, files in os.walk(os.path.join(PACKAGE, folder)):
        for name in files:
            if name.endswith(".py"):
                with open(os.path.join(root, name)) as f:
                    hits += [f"{name}:{i}: {line.strip()}" for i, line in enumerate(f, 1) if FIXED_DEVICE.search(line)]
    assert not hits, "tensors on a fixed device:\n" + "\n".join(hits)


def _fit(schema, dm, precision, epochs):
    trainer = L.Trainer(max_epochs=epochs, precision=precision, logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False, num_sanity_val_steps=0,
                        check_val_every_n_epoch=epochs)
    trainer.fit(schema, dm)
    return trainer


@pytest.mark.parametrize("cls", [DiffusionSchema, AutoEncoderSchema], ids=["diff", "ae"])
def test_training_continues_after_a_dtype_move_and_adapts_in_the_new_dtype(dm, cls):
    L.seed_everything(0)
    schema = cls(robot=dm.robot)
    _fit(schema, dm, "32-true", 2)
    trainer = _fit(schema, dm, "64-true", 2)  # Lightning moves the module to float64; batches follow it
    assert all(p.dtype == torch.float64 for p in schema.parameters())
    assert np.isfinite(float(trainer.callback_metrics["val/eq_residual_N_m"]))
    schema.eval()
    q = dm.splits["val"][0][:3].numpy()
    faults = Faults.from_names(schema.robot_model.muscle_names, cut=[["shoulder_flexor"]] * 3)
    result = schema.adapt(q, faults, check_physics=False, **({"n_steps": 20} if cls is DiffusionSchema else {}))
    # a 4-epoch schema may propose commands out of the motors' range (status says so, row NaN); the float64
    # pipeline must run through and every row be either an ok finite command or flagged
    ok = np.asarray(result.status) == "ok"
    assert np.isfinite(result.l_motor_m[ok]).all() and np.isnan(result.l_motor_m[~ok]).all()
    assert all(np.isfinite(np.asarray(v, dtype=float)).all() for k, v in result.diagnostics.items()
               if k.endswith("_m") and np.asarray(v).dtype.kind == "f")
    l_motor64, _ = schema.infer(q)
    l_motor32, _ = schema.float().infer(q)  # and back: the caches follow the move
    np.testing.assert_allclose(l_motor32, l_motor64, atol=1e-4)
