"""The Lightning side of body schemas: the fit-loop facts the schema, the callbacks and the CLI read
(``fit_loop``), the per-step gradient check (``finite``) and the LightningModule every schema inherits
(``lightning_module.SchemaLightningModule``)."""
from .fit_loop import (check_val_check_interval, fit_ends_with_this_epoch, half_precision_refusal, limited_batches,
                       monitors_train_metrics)
from .lightning_module import SchemaLightningModule

__all__ = ["SchemaLightningModule", "check_val_check_interval", "fit_ends_with_this_epoch", "half_precision_refusal",
           "limited_batches", "monitors_train_metrics"]
