"""``InitFrom``: fine-tune, i.e. start a new fit from a trained checkpoint's weights (``--init_from.ckpt OLD.ckpt``).

Lightning's ``--ckpt_path`` resumes a run: it restores the optimizer, the learning-rate schedule and the epoch
counter, so a run that had finished trains no further, and the data module's normalizer is refitted to the new
data. A fine-tune wants the opposite: the old weights (and, by default, the old normalizer, the units those
weights were trained in), a fresh optimizer and schedule, and as many epochs as asked for on the new data.
"""
from __future__ import annotations

from typing import Optional

from lightning.pytorch.callbacks import Callback

from ..errors import BodySchemaInputError


class InitFrom(Callback):
    """Load a checkpoint's weights into the schema when a fit starts.

    Args:
        ckpt: a trained lightning_bodyschema checkpoint of the same schema class and robot (joint and muscle names);
            None: train from scratch.
        keep_normalizer: keep the checkpoint's normalizer (default), so the weights see inputs in the units they
            were trained in; False: refit it to the new data's train split.
    """

    def __init__(self, ckpt: Optional[str] = None, keep_normalizer: bool = True):
        from ..schemas.loading import read_checkpoint

        self.ckpt, self.keep_normalizer = ckpt, bool(keep_normalizer)
        self.checkpoint = read_checkpoint(str(ckpt)) if ckpt else None  # bad file: one line before anything runs

    def setup(self, trainer, pl_module, stage: str):
        # Lightning calls this after the data module's setup (normalizer fitted) and before the schema's (which
        # copies the data module's normalizer): the place to hand the old normalizer to both
        if stage != "fit" or self.checkpoint is None:
            return
        self._check_same_schema(pl_module)
        state = self.checkpoint["state_dict"]
        try:
            pl_module.load_state_dict(state)
        except RuntimeError as err:  # other sizes: another --model configuration
            detail = " ".join(str(err).split())[:300]
            raise BodySchemaInputError(f"--init_from.ckpt {self.ckpt!r} does not fit the --model configuration "
                                       f"({detail}); give the config it was trained with") from None
        datamodule = getattr(trainer, "datamodule", None)
        if self.keep_normalizer and datamodule is not None:
            prefix = "normalizer."
            old_normalizer = {k[len(prefix):]: v for k, v in state.items() if k.startswith(prefix)}
            datamodule.normalizer.load_state_dict(old_normalizer)

    def _check_same_schema(self, pl_module):
        meta, robot = self.checkpoint["bodyschema"], self.checkpoint.get("hyper_parameters", {}).get("robot") or {}
        here = f"{type(pl_module).__module__}.{type(pl_module).__qualname__}"
        if meta.get("class_path") != here:
            raise BodySchemaInputError(f"--init_from.ckpt {self.ckpt!r} holds a {meta.get('class_path')}, but the "
                                       f"model to fine-tune is a {here}; give the --model (config) it was trained with")
        old_muscles, new_muscles = list(robot.get("muscles", [])), pl_module.robot_model.muscle_names
        old_joints = robot.get("joints") or _model_joints(robot)
        if old_muscles != new_muscles or old_joints != pl_module.robot_model.joint_names:
            raise BodySchemaInputError(
                f"--init_from.ckpt {self.ckpt!r} was trained on joints {old_joints} and muscles {old_muscles}; the "
                f"new data has joints {pl_module.robot_model.joint_names} and muscles {new_muscles}")


def _model_joints(robot: dict) -> list:
    if not robot.get("model_xml"):
        return []
    from ..sim import MusculoskeletalModel

    return MusculoskeletalModel(robot["model_xml"], muscles=robot["muscles"]).joint_names
