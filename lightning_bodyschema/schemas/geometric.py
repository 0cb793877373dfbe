"""``StructuredSchema``'s geometric paths (``length_model="geometric"``): MuJoCo's path topology from the robot's MJCF,
each muscle's numbers (site positions, wrapping geoms' centres and radii, side sites) fitted to the train split's
exact lengths by ``paths.fit``, evaluated in torch by ``paths.module.GeometricPath``."""
from __future__ import annotations

import os

import numpy as np
import torch
from lightning.pytorch.utilities import rank_zero_info

from ..errors import BodySchemaInputError
from ..paths.fit import PathFitOptions, fit_path_numbers
from ..paths.layout import path_layout
from ..paths.module import GeometricPath

# restarts refit the muscles whose train RMS exceeds 1e-4 mm and 3 medians: exact targets leave every muscle fitted
# at ~1e-11 mm but a few at a local minimum of a few micrometres (myoLegs' tibant_r: 0.006 mm, whose moment-arm error
# times tensions of ~1 kN is a torque error of 0.04 N m; refitted: 1e-11 mm); noisy targets leave all at the noise
RETRY_MM, RETRY_MEDIANS = 1e-4, 3.0
PRIOR_RADIUS_ERROR = 0.05  # with a simulated CAD error, each wrapping radius also off by 5 % (about 1 mm on myoArm)


def check_geometric_options(robot_model, prior_error_mm, fit_postures, fit_seed) -> None:
    """One ``BodySchemaInputError`` naming a bad ``path_prior_error_mm``, ``path_fit_postures`` or
    ``path_fit_seed``, or a robot without an MJCF."""
    if not robot_model.has_physics:
        raise BodySchemaInputError("length_model='geometric' needs the robot's MJCF (its path topology); recorded "
                                   "logs have none: use 'per_muscle'")
    if isinstance(prior_error_mm, bool) or not 0.0 <= float(prior_error_mm) < float("inf"):
        raise BodySchemaInputError(f"path_prior_error_mm={prior_error_mm!r} must be a finite number >= 0 [mm]")
    for name, value, low in (("path_fit_postures", fit_postures, 1), ("path_fit_seed", fit_seed, 0)):
        if isinstance(value, bool) or not isinstance(value, int) or value < low:
            raise BodySchemaInputError(f"{name}={value!r} must be an integer >= {low}")


def geometric_path(robot_model) -> GeometricPath:
    """The robot's muscle paths at the MJCF's numbers."""
    return GeometricPath(path_layout(robot_model))


def fit_geometry(schema, q: torch.Tensor, x: torch.Tensor, fit_torque: bool) -> None:
    """``schema``'s paths fitted to the train split's exact lengths ``l_motor + delta(f)`` (``q (S, N)`` [rad],
    ``x (S, 2M)`` in SI), then (``fit_torque``) its least-squares torque to the fitted moment arms."""
    q, x, m = q.to(torch.float64), x.to(torch.float64), schema.n_muscles
    schema.length_net.to(schema.device)
    schema.torque_net.to(schema.device)
    norm = schema.normalizer
    target_m = schema._length_target_n(x) * norm.x_std[:m] + norm.x_mean[:m]
    fit_geometric_numbers(schema.length_net, schema.robot_model, q, target_m, schema.hparams)
    schema.clear_caches()
    if fit_torque:
        schema._fit_torque(norm.encode_q(q).to(schema.device), x[:, m:].to(schema.device))


def fit_geometric_numbers(path: GeometricPath, robot_model, q: torch.Tensor, target_m: torch.Tensor,
                          hparams) -> None:
    """``path``'s numbers fitted on ``hparams.path_fit_postures`` seeded train postures ``q (S, N)`` [rad] to their
    lengths ``target_m (S, M)`` (from the MJCF moved by ``hparams.path_prior_error_mm``); one log line."""
    rng = np.random.default_rng(hparams.path_fit_seed)
    rows = np.sort(rng.choice(len(q), min(len(q), hparams.path_fit_postures), replace=False))
    error_mm = float(hparams.path_prior_error_mm)
    options = PathFitOptions(prior_error_mm=error_mm, radius_error=PRIOR_RADIUS_ERROR if error_mm > 0 else 0.0,
                             seed=hparams.path_fit_seed, retry_mm=RETRY_MM, retry_medians=RETRY_MEDIANS,
                             threads=max(1, min(2, os.cpu_count() or 1)))
    progress = lambda done, most: rank_zero_info(f"geometric paths: {done} of at most {most} MuJoCo passes over "
                                                 f"{len(rows)} postures")  # noqa: E731
    fit = fit_path_numbers(robot_model, q[rows].cpu().numpy(), target_m[rows].cpu().numpy(), options, progress)
    path.set_numbers(fit.numbers)
    worst = int(np.argmax(fit.train_rms_mm))
    rank_zero_info(f"geometric paths fitted on {len(rows)} postures: train RMS median "
                   f"{np.median(fit.train_rms_mm):.2g} mm, worst {robot_model.muscle_names[worst]} "
                   f"{fit.train_rms_mm[worst]:.2g} mm")


SWITCH_STEP_RAD = 1e-6  # the forward difference of the wrap margins' slopes (they are smooth where they cross zero)
# a margin moving less than this with the posture [m/rad] never crosses zero: its points ride one body (a side site
# on its geom's body: myoArm's FCR, whose fitted side site sits on its geom's surface, 3e-13 m inside), and its
# forward difference is rounding
SWITCH_SLOPE_FLOOR = 1e-6


@torch.no_grad()
def geometric_switches(path: GeometricPath, q_rad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """How far each posture ``q_rad (B, N)`` is from a switch of the fitted paths' wrapping, to first order: over every
    muscle's wrap margins whose zero switches its path (``GeometricPath.margins``: an end crossing the ray opposite a
    side site, the side site crossing into its geom, an end entering its geom while wrapped) that move with the
    posture (``SWITCH_SLOPE_FLOOR``), the least ``|m| / |grad m|`` [rad], and the muscle it belongs to (``inf``, -1:
    none). The exact margins of the fitted model: no learned gate."""
    q = torch.as_tensor(q_rad, dtype=torch.float64, device=path.numbers.device)
    batch, n = q.shape
    steps = torch.cat([torch.zeros(1, n, dtype=q.dtype, device=q.device),
                       SWITCH_STEP_RAD * torch.eye(n, dtype=q.dtype, device=q.device)])
    margins = torch.stack(path.margins((q[:, None, :] + steps).reshape(-1, n)))  # (kinds, B (N+1), M, K)
    margins = margins.reshape(len(margins), batch, n + 1, *margins.shape[2:])
    value, slope = margins[:, :, 0], (margins[:, :, 1:] - margins[:, :, :1]) / SWITCH_STEP_RAD
    rate = torch.linalg.vector_norm(slope, dim=2)
    moves = torch.isfinite(value) & (rate > SWITCH_SLOPE_FLOOR)
    distance = torch.where(moves, value.abs() / rate.clamp_min(SWITCH_SLOPE_FLOOR), torch.inf).amin(dim=(0, 3))
    best, muscle = distance.min(dim=1)
    return best.cpu().numpy(), torch.where(torch.isfinite(best), muscle, -1).cpu().numpy()
