"""A schema's learned body as the diagnosis reads it, and that body's own error, measured on held-out samples.

A schema with an explicit body (``StructuredSchema.body_si``) answers directly. Any other schema implies one through
its healthy command: at posture q it commands ``(l_motor, f)``, so its path lengths are ``l_geo(q) = l_motor +
delta(f)`` (eq:muscle-elongation), its moment arms their central differences over ``step_rad``, and the torque its
muscles balance ``tau(q) = -G(q)^T f``.
"""
from __future__ import annotations

import logging

import numpy as np

from ..diagnosis.noise import BodyError
from ..errors import BodySchemaInputError
from ..sim.spring import elongation_from_tension

log = logging.getLogger(__name__)
STEP_RAD = 1e-3  # central differences of a generative schema's path lengths (float32 commands: ~1e-7 m each)
CALIBRATION_POSTURES = 2000  # held-out samples the body's error is measured on
ERROR_QUANTILE = 0.95  # the error's scale: its 95th percentile over those samples, as one Gaussian sigma (/1.96)


def implied_body(schema, q_rad: np.ndarray, step_rad: float = STEP_RAD):
    """``(l_geo (B, M), G (B, M, N), tau (B, N))`` float64 of a schema's healthy commands (module docstring): one
    batched ``infer`` at q and at q +- step on each joint."""
    q = np.asarray(q_rad, float)
    B, N = q.shape
    shifts = np.concatenate([np.zeros((1, N)), step_rad * np.eye(N), -step_rad * np.eye(N)])
    l_motor, f = schema.infer((q[None] + shifts[:, None]).reshape(-1, N))
    l_geo = (l_motor + elongation_from_tension(f, schema.spring)).reshape(2 * N + 1, B, -1)
    G = ((l_geo[1:N + 1] - l_geo[N + 1:]) / (2 * step_rad)).transpose(1, 2, 0)
    tau = -np.einsum("bmn,bm->bn", G, f[:B])
    return l_geo[0], G, tau


def measure_body_error(body, spring, q_rad, l_motor_m, f_n) -> BodyError:
    """The body's error on healthy samples (exact equilibria): path lengths against ``l_motor + delta(f)``, and the
    torque balance ``-G^T f - tau`` with the samples' own tensions; each the ``ERROR_QUANTILE`` of its absolute
    value as one sigma."""
    l_geo, G, tau = body(np.asarray(q_rad, float))
    length = np.abs(l_geo - (l_motor_m + elongation_from_tension(f_n, spring)))
    torque = np.abs(-np.einsum("bmn,bm->bn", G, f_n) - tau)
    z = 1.959963984540054  # the standard normal's 97.5 % quantile: |e| <= z sigma for 95 % of samples
    return BodyError(np.quantile(length, ERROR_QUANTILE, axis=0) / z, np.quantile(torque, ERROR_QUANTILE, axis=0) / z)


def held_out_samples(schema):
    """(q, l_motor, f) numpy arrays of the schema's validation split: from the fit's data module, else from the
    checkpoint it was loaded from (``load_schema``); at most ``CALIBRATION_POSTURES`` of them."""
    datamodule = getattr(getattr(schema, "_trainer", None), "datamodule", None)
    if datamodule is None and getattr(schema, "checkpoint_path", None):
        from .loading import load_datamodule

        log.info("measuring the learned body's error on the held-out split of %s (once per schema)",
                 schema.checkpoint_path)
        datamodule = load_datamodule(schema.checkpoint_path)
    if datamodule is None:
        raise BodySchemaInputError("diagnose needs the learned body's error: load the schema with load_schema(ckpt) "
                                   "(its held-out split is used), or call schema.calibrate_body_error(q, l_motor, f) "
                                   "with held-out healthy samples, or pass body_error=")
    q, x = datamodule.splits["val"]
    q, x = np.asarray(q.cpu(), float)[:CALIBRATION_POSTURES], np.asarray(x.cpu(), float)[:CALIBRATION_POSTURES]
    m = schema.n_muscles
    return q, x[:, :m], x[:, m:]
