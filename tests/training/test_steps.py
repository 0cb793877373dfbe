"""Training through Lightning's automatic optimization: one training step per minibatch, so the Trainer's options
mean what Lightning documents (global_step = optimizer steps, max_steps, val_check_interval, log_every_n_steps,
ModelCheckpoint(every_n_train_steps), gradient_clip_val, accumulate_grad_batches) for every schema."""
import csv
import glob
import os
import warnings

import lightning as L
import pytest
import torch
from lightning.pytorch.callbacks import Callback, EarlyStopping, ModelCheckpoint
from lightning.pytorch.loggers import CSVLogger

from lightning_bodyschema.data.datamodule import MinibatchLoader, ShardSampler
from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.schemas import AutoEncoderSchema, DiffusionSchema, VAESchema

SCHEMAS = {"diff": DiffusionSchema, "ae": AutoEncoderSchema, "vae": VAESchema}
warnings.filterwarnings("ignore", message=".*does not have many workers.*")


def trainer(**options):
    defaults = dict(logger=False, enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False,
                    num_sanity_val_steps=0, check_val_every_n_epoch=10 ** 6)
    return L.Trainer(**{**defaults, **options})


def adam_steps(schema) -> int:
    """Optimizer steps Adam has taken (its per-parameter step count)."""
    optimizer = schema.trainer.optimizers[0]
    return int(next(iter(optimizer.state.values()))["step"])


# ------------------------------------------------------------------------------------------ serving minibatches
def test_shards_are_disjoint_cover_the_split_and_reshuffle_per_epoch():
    n = 640
    shards = [ShardSampler(n, seed=3, rank=r, world_size=2) for r in range(2)]
    first = [s.indices() for s in shards]
    assert len(first[0]) == len(first[1]) == n // 2
    assert set(first[0].tolist()).isdisjoint(first[1].tolist())
    assert sorted(first[0].tolist() + first[1].tolist()) == list(range(n))
    for s in shards:
        s.set_epoch(1)
    second = [s.indices() for s in shards]
    assert not torch.equal(first[0], second[0])  # a new permutation each epoch
    again = ShardSampler(n, seed=3, rank=0, world_size=2)
    again.set_epoch(1)
    assert torch.equal(again.indices(), second[0])  # from the seed and the epoch alone
    odd = [ShardSampler(641, seed=0, rank=r, world_size=2).indices() for r in range(2)]
    assert len(odd[0]) == len(odd[1]) == 321  # equal step counts on every rank (DistributedSampler's padding)
    assert set(odd[0].tolist()) | set(odd[1].tolist()) == set(range(641))


def test_minibatches_slice_the_split_in_the_shards_order():
    q, x = torch.arange(10.0)[:, None], torch.arange(10.0)[:, None] * 10
    loader = MinibatchLoader(q, x, 4, ShardSampler(10, seed=0))
    batches = list(loader)
    assert len(loader) == len(batches) == 3 and [len(b[0]) for b in batches] == [4, 4, 2]
    order = torch.cat([b[0][:, 0] for b in batches])
    assert torch.equal(order, ShardSampler(10, seed=0).indices().double())
    assert all(torch.equal(bx, 10 * bq) for bq, bx in batches)  # q and x rows stay paired
    with pytest.raises(BodySchemaInputError, match="batch_size"):
        MinibatchLoader(q, x, 0, ShardSampler(10, seed=0))


# ------------------------------------------------------------------------------------------ steps as Lightning means them
@pytest.mark.parametrize("name", SCHEMAS)
def test_global_step_counts_optimizer_steps_and_max_steps_ends_the_fit(dm, name):
    L.seed_everything(0)
    schema = SCHEMAS[name](robot=dm.robot)
    fit = trainer(max_steps=25, max_epochs=100)
    fit.fit(schema, dm)
    assert fit.global_step == 25 and adam_steps(schema) == 25
    assert fit.num_training_batches == 10  # 640 samples in batches of 64: the fit stopped inside its third epoch
    (config,) = fit.lr_scheduler_configs
    assert config.scheduler.T_max == 3  # the cosine spans the epochs max_steps allows, not max_epochs


@pytest.mark.parametrize("limit, epochs", [(5, 8), (0.5, 8), (3, 14)])
def test_the_cosine_schedule_spans_the_epochs_max_steps_allows_under_limit_train_batches(dm, limit, epochs):
    """It counted the full 10 batches per epoch, so T_max came out too short and the rate rose again."""
    L.seed_everything(0)
    schema = VAESchema(robot=dm.robot)
    fit = trainer(max_steps=40, max_epochs=100, limit_train_batches=limit)
    fit.fit(schema, dm)
    (config,) = fit.lr_scheduler_configs
    assert fit.current_epoch == epochs and config.scheduler.T_max == epochs
    assert config.scheduler.last_epoch <= epochs  # never past the cosine's period, where the rate rises again
    if 40 % (limit if isinstance(limit, int) else 5) == 0:  # the last epoch completes: the schedule ends at lr_final
        assert fit.optimizers[0].param_groups[0]["lr"] == pytest.approx(schema.hparams.lr_final)


@pytest.fixture(scope="module")
def logged_fit(dm, tmp_path_factory):
    """A 20-step diffusion fit validating every 5 steps, logging every 3, checkpointing every 7."""
    root = tmp_path_factory.mktemp("steps")

    class CountValidations(Callback):
        steps = []

        def on_validation_end(self, trainer, pl_module):
            self.steps.append(trainer.global_step)

    L.seed_everything(0)
    schema = DiffusionSchema(robot=dm.robot)
    every7 = ModelCheckpoint(dirpath=root / "ckpt", every_n_train_steps=7, save_top_k=-1, filename="{step}")
    counter = CountValidations()
    fit = trainer(max_steps=20, val_check_interval=5, check_val_every_n_epoch=None, log_every_n_steps=3,
                  logger=CSVLogger(root, name="csv"), enable_checkpointing=True, callbacks=[every7, counter])
    fit.fit(schema, dm)
    return fit, counter.steps, root


def test_val_check_interval_counts_training_steps(logged_fit):
    _, validated_at, _ = logged_fit
    assert validated_at == [5, 10, 15, 20]


def test_log_every_n_steps_writes_train_loss_every_n_optimizer_steps(logged_fit):
    fit, _, _ = logged_fit
    with open(os.path.join(fit.logger.log_dir, "metrics.csv")) as f:
        rows = [r for r in csv.DictReader(f) if r.get("train/loss")]
    assert [int(r["step"]) for r in rows] == [2, 5, 8, 11, 14, 17]  # steps 3, 6, ..., 18 (0-based in the file)
    assert all(float(r["train/loss"]) > 0 for r in rows)


def test_checkpoint_every_n_train_steps(logged_fit):
    _, _, root = logged_fit
    names = sorted(os.path.basename(p) for p in glob.glob(str(root / "ckpt" / "*.ckpt")))
    assert names == ["step=14.ckpt", "step=7.ckpt"]


@pytest.mark.parametrize("ckpt", ["step=7.ckpt", "step=14.ckpt"])
def test_a_fit_resumed_mid_epoch_ends_with_the_weights_of_the_uninterrupted_fit(logged_fit, dm, ckpt):
    """Both checkpoints fall inside an epoch (10 batches each): the resumed epoch continues with the batches not yet
    trained on, in the same order, with the same diffusion noise, validating at the same steps."""
    fit, _, root = logged_fit
    L.seed_everything(123)  # a different start: everything must come from the checkpoint
    resumed = DiffusionSchema(robot=dm.robot)
    again = trainer(max_steps=20, val_check_interval=5, check_val_every_n_epoch=None)
    again.fit(resumed, dm, ckpt_path=str(root / "ckpt" / ckpt))
    assert again.global_step == 20
    expected = fit.lightning_module.state_dict()
    assert all(torch.equal(expected[k], v) for k, v in resumed.state_dict().items())


def test_gradient_clip_val_bounds_every_step(dm):
    class GradNorms(Callback):
        norms = []

        def on_train_start(self, trainer, pl_module):  # the gradients the optimizer used (the closure runs in step)
            trainer.optimizers[0].register_step_post_hook(lambda opt, *_: self.norms.append(float(torch.linalg.vector_norm(
                torch.stack([p.grad.norm() for p in pl_module.parameters() if p.grad is not None])))))

    L.seed_everything(0)
    schema = DiffusionSchema(robot=dm.robot)
    recorder = GradNorms()
    trainer(max_steps=12, gradient_clip_val=1e-3, callbacks=[recorder]).fit(schema, dm)
    assert len(recorder.norms) == 12 and max(recorder.norms) <= 1e-3 * (1 + 1e-5)


def test_accumulate_grad_batches_with_max_steps(dm):
    L.seed_everything(0)
    schema = AutoEncoderSchema(robot=dm.robot)
    fit = trainer(max_steps=7, max_epochs=100, accumulate_grad_batches=2)
    fit.fit(schema, dm)
    assert fit.global_step == 7 and adam_steps(schema) == 7  # 14 batches: into the second epoch (5 steps each)
    (config,) = fit.lr_scheduler_configs
    assert config.scheduler.T_max == 2


def test_accumulate_grad_batches_steps_once_per_n_batches(dm):
    L.seed_everything(0)
    schema = VAESchema(robot=dm.robot)
    fit = trainer(max_epochs=3, accumulate_grad_batches=2)
    fit.fit(schema, dm)
    assert fit.global_step == 15 and adam_steps(schema) == 15


@pytest.mark.parametrize("name, metric", [("ae", "val/eq_residual_N_m"), ("diff", "val/eq_residual_N_m"),
                                          ("vae", "val/eq_residual_N_m")])
def test_early_stopping_on_the_validation_residual_stops_a_fit(dm, name, metric):
    L.seed_everything(0)
    schema = SCHEMAS[name](robot=dm.robot)
    # an improvement of 1e3 N m per validation is impossible: the fit stops after patience + 1 validations
    stop = EarlyStopping(monitor=metric, mode="min", patience=1, min_delta=1e3)
    fit = trainer(max_epochs=50, check_val_every_n_epoch=2, callbacks=[stop])
    fit.fit(schema, dm)
    assert fit.should_stop and stop.stopped_epoch == 3 and fit.current_epoch == 4
    assert metric in fit.callback_metrics


def _fresh_latent_reference(schema, dm):
    q_n, x_n = schema._normalized(dm.splits["train"])
    with torch.no_grad():
        return schema.latent_reference(x_n)


def test_every_checkpoint_and_an_early_stopped_fit_carry_the_latent_reference_of_their_weights(dm, tmp_path):
    """Lightning validates and saves before on_train_epoch_end, where the AE refreshes z_ref every 10 epochs: the
    saved and the early-stopped z_ref used to lag the weights (by up to 0.04 here)."""
    L.seed_everything(0)
    schema = AutoEncoderSchema(robot=dm.robot)
    saves = ModelCheckpoint(dirpath=tmp_path, every_n_train_steps=7, save_top_k=-1, save_last=True, filename="{step}")
    trainer(max_epochs=5, check_val_every_n_epoch=5, enable_checkpointing=True, callbacks=[saves]).fit(schema, dm)
    for name in ("step=7.ckpt", "step=49.ckpt", "last.ckpt"):  # mid-epoch, late, and after the last validation
        saved = torch.load(tmp_path / name, weights_only=True)["state_dict"]
        probe = AutoEncoderSchema(robot=dm.robot)
        probe.load_state_dict(saved)
        probe.normalizer.load_state_dict(dm.normalizer.state_dict())
        assert torch.allclose(saved["z_latent_ref"], _fresh_latent_reference(probe, dm), atol=1e-6), name

    L.seed_everything(0)
    stopped = AutoEncoderSchema(robot=dm.robot)
    stop = EarlyStopping(monitor="val/eq_residual_N_m", mode="min", patience=0, min_delta=1e3)
    trainer(max_epochs=50, check_val_every_n_epoch=1, callbacks=[stop]).fit(stopped, dm)
    assert stop.stopped_epoch == 1  # not a multiple of 10: only the validation-time refresh can be fresh
    assert torch.allclose(stopped.z_latent_ref, _fresh_latent_reference(stopped, dm), atol=1e-6)


@pytest.mark.parametrize("max_steps", [25, 30])  # inside the third epoch, and at its end
def test_a_fit_ended_by_max_steps_validates_and_benchmarks_at_its_end(dm, tmp_path, max_steps):
    """Lightning validates at an epoch's last batch only: a fit stopped by max_steps inside an epoch ended with no
    physical metric, and the end-of-fit fault benchmark and figure looked at max_epochs only."""
    from lightning_bodyschema.callbacks import FaultBenchmark, FinalValidation, ReconstructionFigure

    L.seed_everything(0)
    schema = AutoEncoderSchema(robot=dm.robot)
    callbacks = [FaultBenchmark(every_n_epochs=100, n_per_condition=2, settle_check=False), FinalValidation(),
                 ReconstructionFigure(every_n_validations=100)]
    logger = L.pytorch.loggers.TensorBoardLogger(tmp_path)
    fit = trainer(max_steps=max_steps, max_epochs=100, check_val_every_n_epoch=1000, logger=logger, callbacks=callbacks)
    fit.fit(schema, dm)
    assert fit.global_step == max_steps and "val/eq_residual_N_m" in fit.callback_metrics
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
    events = EventAccumulator(fit.logger.log_dir, size_guidance={"images": 0, "scalars": 0})
    events.Reload()
    assert any(tag.startswith("fault/") for tag in events.Tags()["scalars"])
    assert "val/reconstruction" in events.Tags()["images"]
