"""The structured schema's learned body at postures in SI units: ``body_si`` (numpy ``BodySnapshot`` for few
postures on the CPU, the torch modules otherwise), the frozen snapshot, and where the learned paths switch branch.
A mixin of ``StructuredSchema`` (its networks, normalizer and inference cache)."""
from __future__ import annotations

from typing import Optional

import numpy as np
import torch
from lightning.pytorch.utilities import rank_zero_info

from .._numpy import to_numpy
from ..evaluation.body_errors import bad_regions, bad_regions_table, summary, worst_per_posture

from ..networks.per_muscle import PerMusclePath
from ..networks.snapshot import BodySnapshot, GravitySnapshot
from ..networks.switches import PostureSwitches, switch_diagnostics
from ..paths.module import GeometricPath
from .geometric import geometric_switches

BODY_ERROR_ROWS = 1024  # validation postures of the worst-muscle-per-posture figures (physical_errors): ~0.4 s
# ``body_si`` in numpy up to this many postures (and the path's few-postures budget, ``PathSnapshot.max_postures``): on
# myoArm numpy is the faster up to about 100 postures, myoLegs about 16 (BENCHMARKS.md "Per-muscle body evaluation,
# myoArm")
HOST_ROWS = 16


class LearnedBody:
    """``StructuredSchema``'s learned-body methods (``body_si``, ``learned_body_si``, ``body_snapshot``,
    ``snapshot_covers``, ``path_switches``, ``physical_errors``)."""

    def body_si(self, q_rad: torch.Tensor) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The learned body at postures ``q_rad (B, N)`` [rad] as float64 arrays: l_geo [m], G [m/rad], tau [N m]
        (a per-muscle path without hidden layers and a gravity torque on the CPU, up to ``HOST_ROWS`` postures: its
        ``BodySnapshot`` in numpy)."""
        host = self._host_body(q_rad)
        if host is not None:
            return host(q_rad.detach().cpu().numpy().astype(np.float64))
        with torch.no_grad():
            q_n = self.normalizer.encode_q(q_rad.to(self.device, torch.float64)).to(self.dtype)
            return tuple(t.cpu().numpy().astype(np.float64) for t in self.body(q_n))  # a copy: the caller owns it

    def learned_body_si(self, q_rad) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``body_si``: the learned body itself (``BodySchema.learned_body_si``'s contract)."""
        return self.body_si(torch.as_tensor(np.asarray(q_rad, np.float64)))

    def _host_body(self, q_rad: torch.Tensor) -> Optional[BodySnapshot]:
        """``body_si``'s numpy ``BodySnapshot`` for postures ``q_rad``: in eval mode, not exporting, up to
        ``HOST_ROWS`` postures within the path's few-postures budget, for the body it covers on the CPU; else None."""
        if self.training or torch.compiler.is_exporting() or len(q_rad) > HOST_ROWS:
            return None
        host = self.inference_cache.get("body_snapshot", self._numpy_body)
        return host if host is not None and len(q_rad) <= host.path.max_postures else None

    def _numpy_body(self) -> Optional[BodySnapshot]:
        """``body_snapshot().on_host()``, or None for a body it does not cover (``snapshot_covers``) or off the CPU."""
        return self.body_snapshot().on_host() if self.snapshot_covers() and self.device.type == "cpu" else None

    def snapshot_covers(self) -> bool:
        """Whether ``body_snapshot()`` is the whole body: a per-muscle path without hidden layers and the gravity
        torque (not an MLP in the path, nor another torque model)."""
        path = self.length_net
        return isinstance(path, PerMusclePath) and not path.n_hidden and self.hparams.torque_model == "gravity"

    def body_snapshot(self) -> BodySnapshot:
        """The fitted body (a per-muscle path without hidden layers and a gravity torque) frozen, in torch
        (``on_host()``: numpy), from the snapshots ``body`` and ``torque`` keep: ``body_si``'s arithmetic."""
        cache = self.inference_cache
        path = cache.get("path_snapshot", self.length_net.snapshot)
        gravity = cache.get("gravity_snapshot", lambda: GravitySnapshot(self.torque_net))
        norm = self.normalizer
        return BodySnapshot(norm.q_lo, norm.q_hi, self.dtype, path, gravity, self._length_scales(self.dtype))

    def path_switches(self, q_rad) -> dict:
        """Where the learned paths switch branch, at postures ``q_rad (B, N)`` [rad]: ``near_path_switch (B,)`` bool
        (within ``networks.switches.SWITCH_REACH_RAD`` of a two-branch muscle's gate where its branches differ by
        ``JUMP_FLOOR_M`` or more: the learned length may sit on the wrong side of the true jump, so a command there is
        not exact; its status is unchanged; geometric paths: within that reach of a switch of a fitted path's wrapping,
        ``schemas.geometric.geometric_switches``), ``path_switch_distance_rad`` and ``path_switch_muscle`` (``inf``,
        -1: no such switch; an MLP path has none). The adapter's diagnostics."""
        q = np.asarray(q_rad.detach().cpu() if torch.is_tensor(q_rad) else q_rad, np.float64)
        path, norm = self.length_net, self.normalizer
        if isinstance(path, GeometricPath):  # the fitted paths' own wrap margins
            return switch_diagnostics(*geometric_switches(path, q))
        if not isinstance(path, PerMusclePath):
            return switch_diagnostics(np.full(len(q), np.inf), np.full(len(q), -1, dtype=np.int64))
        switches = self.inference_cache.get("switch_snapshot", lambda: PostureSwitches(
            path, self.inference_cache.get("path_snapshot", path.snapshot), norm.q_lo, norm.q_hi,
            norm.x_std[:self.n_muscles]).on_host())
        recent = getattr(self._host_body(q), "recent", None)  # the body just evaluated at these postures (the
        # adapter's call): the flag reads its rows instead of evaluating the gates again
        same = recent is not None and recent[0].shape == q.shape and np.array_equal(recent[0], q)
        return switch_diagnostics(*switches(q, recent[1] if same else None))

    def physical_errors(self, q: torch.Tensor, x_true: torch.Tensor) -> dict[str, float]:
        """``BodySchema.physical_errors`` and the learned body's worst muscle per posture against MuJoCo
        (``evaluation.body_errors.summary``: length, moment arm, torque), on the first ``BODY_ERROR_ROWS`` postures
        (cheap: validation runs it; their MuJoCo kinematics is the cached one). ``last_bad_regions`` keeps where
        the bad postures are (``evaluation.body_errors.bad_regions``) for the log line and for callers."""
        errors = super().physical_errors(q, x_true)
        if not self.has_physics:
            return errors
        q_np = to_numpy(q)
        l_geo, G, tau = (a[:BODY_ERROR_ROWS] for a in self._physics(q_np))
        q_np = q_np[:BODY_ERROR_ROWS]
        crossed = np.abs(G).max(axis=0) > 1e-12  # MuJoCo's nonzero moment arms: tools/body_errors.py's pairs
        worst = worst_per_posture(self.body_si(torch.as_tensor(q_np)), (l_geo, G, tau), crossed)
        self.last_bad_regions = bad_regions(worst, q_np, self.robot_model.q_range, crossed, k=3)
        if self.last_bad_regions:
            rank_zero_info("learned body, worst muscle per posture:\n" + bad_regions_table(
                self.last_bad_regions, self.robot_model.muscle_names, self.robot_model.joint_names))
        return {**errors, **summary(worst)}
