"""A callback for the DDP test (loaded by the CLI in each rank's process): what each rank trained on and ended with."""
import os

import torch
from lightning.pytorch.callbacks import Callback


class RecordRank(Callback):
    """Writes ``rank<R>.pt``: the q rows of this rank's first epoch, its final weights and validation residual."""

    def __init__(self, out_dir: str):
        self.out_dir, self.rows = out_dir, []

    def on_validation_batch_start(self, trainer, pl_module, batch, batch_idx, dataloader_idx=0):
        self.val_rows = getattr(self, "val_rows", 0) + len(batch[0])

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        if trainer.current_epoch == 0:
            self.rows.append(batch[0].detach().cpu())
            if batch_idx == 0:  # the stream the loss draws its noise and timesteps from
                self.rng_state = torch.random.get_rng_state()

    def on_train_end(self, trainer, pl_module):
        record = {"rows": torch.cat(self.rows), "world_size": trainer.world_size, "global_step": trainer.global_step,
                  "state_dict": {k: v.detach().cpu() for k, v in pl_module.state_dict().items()},
                  "val_eq_residual": float(trainer.callback_metrics["val/eq_residual_N_m"]),
                  "val_rows": getattr(self, "val_rows", 0), "rng_state": self.rng_state}
        path = os.path.join(self.out_dir, f"rank{trainer.global_rank}.pt")
        torch.save(record, path + ".tmp")
        os.replace(path + ".tmp", path)
