"""A training minibatch is normalized as one multiply-add per tensor (``_normalized_minibatch``): the same numbers as
the normalizer's ``encode_q`` / ``encode_x``, which validation, inference and adaptation use."""
import numpy as np
import torch
from physics_checks import rounding_tol

from lightning_bodyschema.schemas import DiffusionSchema


def test_the_minibatch_maps_equal_the_normalizer(dm):
    schema = DiffusionSchema(robot=dm.robot)
    schema.normalizer.load_state_dict(dm.normalizer.state_dict())
    batch = dm.splits["train"]
    for dtype in (torch.float32, torch.float64):  # the weights' dtype; the normalizer's buffers stay float64
        if dtype == torch.float64:
            schema.double()
        assert schema.normalizer.x_mean.dtype == torch.float64
        reference = schema._normalized(batch)
        assert schema._minibatch_affine is None  # outside a fit: the normalizer's own maps
        schema._minibatch_affine = affine = schema.normalizer.affine()
        fast = schema._normalized_minibatch(batch)
        schema._minibatch_affine = None
        for ours, theirs in zip(fast, reference):
            assert ours.dtype == theirs.dtype == dtype
            # float64: a rounding apart (a multiply-add, not a subtraction and a division); float32: the same
            # float after the cast except where a value lies within that rounding of a float32 boundary. Near 0
            # that rounding is float64's at the multiply-add's terms (the normalized data and the shifts), not at
            # the value's (atol); a wrong mean or scale is off by O(0.1)
            np.testing.assert_allclose(ours.numpy(), theirs.numpy(), rtol=4 * torch.finfo(dtype).eps,
                                       atol=rounding_tol(4, theirs, affine[1], affine[3]))
            assert theirs.abs().max() > 0.5  # real data, not zeros on both sides
    q_n = schema._normalized(batch)[0]
    assert float(q_n.min()) >= -1.0 and float(q_n.max()) <= 1.0  # the joint range maps into [-1, 1]


def test_the_fit_takes_the_maps_at_its_start_and_drops_them_at_its_end(dm):
    import lightning as L

    seen = []

    class Probe(DiffusionSchema):
        def training_step(self, batch, batch_idx):
            seen.append(self._minibatch_affine)
            return super().training_step(batch, batch_idx)

    schema = Probe(robot=dm.robot)
    L.Trainer(max_epochs=1, limit_train_batches=2, logger=False, enable_checkpointing=False, enable_progress_bar=False,
              enable_model_summary=False, num_sanity_val_steps=0, check_val_every_n_epoch=10).fit(schema, dm)
    assert len(seen) == 2 and all(s is not None for s in seen)
    torch.testing.assert_close(seen[0][3], -dm.normalizer.x_mean / dm.normalizer.x_std)  # x_shift of this data
    assert schema._minibatch_affine is None
