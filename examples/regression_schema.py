"""A new architecture in a few lines: direct regression q -> (l_motor, f), trained by the same CLI.

    PYTHONPATH=examples bodyschema fit --model regression_schema.RegressionSchema --trainer.max_epochs 300

Subclass ``BodySchema``, build a plain ``nn.Module``, implement ``training_loss`` and ``generate``.
Normalization, minibatching, validation in N / mm / N m, TensorBoard and checkpoints come for free.
"""
from typing import Optional

from torch import nn

from lightning_bodyschema.schemas import BodySchema


class RegressionSchema(BodySchema):
    """MLP q -> x = [l_motor, f]: the paper's "simple regression" baseline (no redundancy to adapt)."""

    def __init__(self, hidden: int = 64, robot: Optional[dict] = None, lr: float = 1e-3,
                 lr_final: Optional[float] = 1e-5, batch_size: int = 64):
        super().__init__(robot=robot, lr=lr, lr_final=lr_final, batch_size=batch_size)
        self.save_hyperparameters()
        self.net = nn.Sequential(nn.Linear(self.n_joints, hidden), nn.Tanh(), nn.Linear(hidden, hidden), nn.Tanh(),
                                 nn.Linear(hidden, self.x_dim))

    def training_loss(self, q_n, x_n):
        loss = (self.net(q_n) - x_n).pow(2).sum(-1).mean()
        return loss, {}

    def generate(self, q_n):
        return self.net(q_n)
