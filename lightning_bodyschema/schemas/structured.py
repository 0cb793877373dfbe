"""Structured body schema: a learned body (muscle lengths, moment arms, joint torques) and a QP on it.

Trained from (q, l_motor, f) samples and the spring law alone (no MJCF: recorded data trains it too):

* the geometric muscle lengths ``l_geo(q)``, regressed on ``l_motor + delta(f)`` (eq:muscle-elongation), with the
  moment arms ``G(q) = d l_geo / dq`` their exact derivative: one dense network over all joints
  (``length_model="mlp"``, ``networks.structured.JacobianMLP``), or each muscle's path over only the joints it
  crosses (``"per_muscle"``, ``networks.per_muscle.PerMusclePath``: a least-squares polynomial per muscle, two and
  a gate where the path jumps with ``path_branches=2``, plus a small per-muscle network), its moment arm exactly 0
  on every other joint, or each muscle's MuJoCo path (``"geometric"``, ``paths.module.GeometricPath``: the MJCF's
  path topology, its sites, wrapping geoms and side sites placed by a fit to the lengths; needs the MJCF);
* the joint torque the muscles must balance ``tau(q)`` (static equilibrium ``-G^T f = tau``), regressed on
  ``-G(q)^T f`` of the samples: the gradient of a learned potential ``V(q)`` (gravity and joint springs are
  conservative; ``torque_model="potential"``), a plain regression (``"direct"``), or a polynomial per joint fitted
  by least squares (``"polynomial"``, with the per-muscle lengths: refitted to the learned moment arms before every
  validation and checkpoint), or the gravity torque of the MJCF's kinematic tree, linear in each moving body's mass
  and first mass moment, fitted the same way (``"gravity"``, ``networks.gravity.GravityTorque``; needs the MJCF).

Every command is a small QP on that body per posture (``faults.qp``): tensions closest to ``f_ref`` (half of each
muscle's f_max) that balance ``tau`` within their box, each fault an exact constraint (cut f = 0; jammed or banded
motor lengths as tension bounds through the spring; weakened: a lower f_max), then ``l_motor = l_geo - delta(f)``.
"""
from __future__ import annotations

from typing import Optional

import numpy as np
import torch

from ..adaptation.pipeline import Adapter
from ..errors import BodySchemaInputError
from ..faults import Faults
from ..faults.bounds import FaultBounds
from ..faults.qp import bounds_command
from ..networks.gravity import GravityTorque
from ..networks.path_config import PathConfig
from ..networks.per_muscle import PerMusclePath, degrees_within_tolerance
from ..networks.snapshot import GravitySnapshot
from ..networks.structured import JacobianMLP, check_architecture
from ..sim.gravity_tree import gravity_tree
from ..sim.separable import separable_blocks
from .base import BodySchema
from .structured_body import LearnedBody
from .crossing import crossing_from_data, resolve_crossing
from .geometric import check_geometric_options, fit_geometry, geometric_path

TORQUE_MODELS = ("potential", "direct", "polynomial", "gravity")
FITTED_TORQUES = ("polynomial", "gravity")  # least squares on the learned moment arms, not the optimizer
TORQUE_FIT_POSTURES = 40000  # the polynomial torque's least squares uses at most this many train postures
TORQUE_TRIM = 3.0  # its refits drop postures missed by more than this many medians (RESULTS.md "Per-muscle paths")
TORQUE_TRIM_ROUNDS = 8
LENGTH_MODELS = ("mlp", "per_muscle", "geometric")
FITTED_LENGTHS = ("per_muscle", "geometric")  # fitted by least squares when the fit starts, not by the optimizer


class StructuredSchema(LearnedBody, BodySchema):
    """A learned body ``(l_geo(q), G(q), tau(q))`` answered by a QP (module docstring).

    Args:
        hidden, n_hidden: width and depth of both networks (SiLU).
        block: ``"plain"`` (the default) or ``"residual"`` (pre-norm residual hidden layers), both networks
            (``networks.structured.JacobianMLP``); the moment arms stay the exact derivative of the lengths.
        norm: ``"none"`` (the default) or ``"layer"`` (LayerNorm before every activation), both networks.
        torque_model: ``"potential"`` (tau = dV/dq of a learned scalar V), ``"direct"`` (tau regressed per joint) or
            ``"polynomial"`` (per joint, total degree ``torque_degree``, least squares; needs ``"per_muscle"``) or
            ``"gravity"`` (the MJCF tree's gravity torque with fitted masses and first moments, plus a linear spring
            per joint, least squares; needs ``"per_muscle"`` and a robot with physics).
        torque_degree: total degree of the polynomial torque.
        stiffness_weighted: weigh each muscle's length error by its spring stiffness at the sample's tension,
            ``alpha (f + k)`` [N/m] (a length error then counts as the tension error it causes); False: unit weights.
        torque_weight: weight of the torque regression next to the length regression (both in normalized units).
        qp_reg: weight of ``||f - f_ref||^2`` in the least-squares answer of an unholdable posture (dimensionless).
        length_model: ``"mlp"`` (the default: one dense network, ``hidden`` x ``n_hidden``), ``"per_muscle"``
            (each muscle's path over the joints it crosses; ``path_degree``, ``path_hidden``, ``path_layers``) or
            ``"geometric"`` (each muscle's MuJoCo path, its numbers fitted; needs the robot's MJCF).
        path_degree, path_terms: each muscle's polynomial has the highest total degree ``<= path_degree`` with at
            most ``path_terms`` terms over the joints it crosses (``"per_muscle"``).
        path_term_budget: None, or the most polynomial terms over all muscles together: what ``path_terms`` leaves
            raises the lowest degrees first, one degree at a time up to ``path_degree`` (the muscles that cross many
            joints, which ``path_terms`` holds low; ``networks.polynomial.muscle_degrees``).
        path_tolerance_mm: None, or with ``path_term_budget`` a length error [mm]: the budget goes only to the
            muscles whose p99 training residual after a first fit at ``path_terms`` exceeds it
            (``networks.per_muscle.degrees_within_tolerance``).
        path_degrees: each muscle's degree, set by the fit when ``path_tolerance_mm`` is given (a checkpoint then
            rebuilds the same polynomials); given, it replaces the rule above.
        path_hidden, path_layers: width and hidden layers of each muscle's residual network (0 layers: none).
        path_branches: 1 (one polynomial per muscle) or 2 (where a muscle's path jumps, a wrap switching sides: two
            polynomials and a gate of total degree <= ``path_gate_degree`` that picks one; ``networks.branches``).
        path_cells: 1 (none), or pieces per joint: the muscles a smooth polynomial fits worst (a median residual four
            times the median muscle's) get one polynomial per cell of their joints' box cut that many times per
            joint, kept where it halves their median residual (``networks.cells``).
        path_cell_degrees: each muscle's cell degree (0: no cells), set by the fit when ``path_cells > 1`` (a
            checkpoint then rebuilds the same cells).
        path_separable: False, or True: each muscle's length a sum of one polynomial per group of its joints whose
            effects add up (a path's segments between bodies), the groups from the MJCF
            (``sim.separable.separable_blocks``); no term mixes two groups, so the same terms reach a higher
            degree. Needs the robot's MJCF.
        path_blocks: each muscle's group per joint (``(M, N)`` ints, -1 uncrossed), set when ``path_separable``
            (a checkpoint then rebuilds the same polynomials); given, it is used as is.
        path_cell_trim: None, or each cell refitted without the samples it misses by more than this many times the
            kept ones' median (a wrap switching sides inside a cell then costs the smaller side, not a ring over
            the whole cell; ``networks.cells``).
        path_cell_joints: which joints cut a celled muscle's box: ``"crossed"`` (every joint it crosses) or
            ``"largest_group"`` (with ``path_separable``, only those of its largest group of joints, the others
            whole in each cell's polynomial: myoArm's BIClong then has 8 cells over its shoulder, not 32 over its
            shoulder and elbow; ``networks.cells.cell_cuts``).
        path_cell_keep: what a muscle's cells must improve on the fitted samples to be kept: ``"median_and_p99"``
            (halve its median residual without a larger p99) or ``"median"`` (halve its median: myoArm's LAT1 and
            LAT2, two branches each, then keep cells whose moment arms are far better on all but their jumps' smaller
            sides; ``networks.cell_fit._kept``).
        path_prior_error_mm, path_fit_postures, path_fit_seed: with ``length_model="geometric"`` (MuJoCo's path
            topology from the robot's MJCF, each muscle's numbers fitted to the train split's lengths: ``paths``), the
            fit starts from the MJCF's numbers each moved by +-``path_prior_error_mm`` [mm] (a seeded sign per
            number: a simulated CAD error for data the MJCF itself generated; 0 for a real robot, whose MJCF is its
            CAD), on ``path_fit_postures`` train postures drawn with ``path_fit_seed``.
        muscle_joints: ``{muscle: [joints]}``, the joints each muscle crosses (``"per_muscle"``). Default: the
            robot's MJCF (MuJoCo's tendon Jacobian), else the recorded data's ``muscle_joints``, else detected from
            the training data when the fit starts; the fit stores the answer here, so a checkpoint knows it.
        robot, lr, lr_final, batch_size: see ``BodySchema``.
    """

    VARIANTS = ("default",)
    MIXED_PRECISION = False  # 16-bit matmuls are coarser than the lengths it learns (training.fit_loop)
    # contract.ADAPTS_IN_SI: a QP on the learned body, in SI units; REFRESHES_DERIVED_STATE: the polynomial torque
    capabilities = frozenset({"adapts_in_si", "refreshes_derived_state"})

    def __init__(self, hidden: int = 256, n_hidden: int = 3, torque_model: str = "potential",
                 stiffness_weighted: bool = True, torque_weight: float = 1.0, qp_reg: float = 1e-6,
                 robot: Optional[dict] = None, lr: float = 1e-3, lr_final: Optional[float] = 1e-5,
                 batch_size: int = 256, block: str = "plain", norm: str = "none", length_model: str = "mlp",
                 path_degree: int = 6, path_terms: int = 500, path_hidden: int = 32, path_layers: int = 0,
                 muscle_joints: Optional[dict] = None, torque_degree: int = 6, path_branches: int = 1,
                 path_gate_degree: int = 8, path_term_budget: Optional[int] = None,
                 path_tolerance_mm: Optional[float] = None, path_degrees: Optional[list] = None,
                 path_cells: int = 1, path_cell_degrees: Optional[list] = None, path_separable: bool = False,
                 path_blocks: Optional[list] = None, path_cell_trim: Optional[float] = None,
                 path_cell_joints: str = "crossed", path_cell_keep: str = "median_and_p99",
                 path_prior_error_mm: float = 0.0, path_fit_postures: int = 2000, path_fit_seed: int = 0):
        super().__init__(robot=robot, lr=lr, lr_final=lr_final, batch_size=batch_size)
        if torque_model not in TORQUE_MODELS:
            raise BodySchemaInputError(f"torque_model={torque_model!r}; allowed: {list(TORQUE_MODELS)}")
        for name, value in (("torque_weight", torque_weight), ("qp_reg", qp_reg)):
            if isinstance(value, bool) or not 0.0 <= float(value) < float("inf"):
                raise BodySchemaInputError(f"{name}={value!r} must be a finite number >= 0")
        if length_model not in LENGTH_MODELS:
            raise BodySchemaInputError(f"length_model={length_model!r}; allowed: {list(LENGTH_MODELS)}")
        if torque_model == "gravity" and not self.robot_model.has_physics:
            raise BodySchemaInputError("torque_model='gravity' needs the robot's MJCF (recorded data has none); "
                                       "use 'polynomial', 'direct' or 'potential'")
        if torque_model in FITTED_TORQUES and length_model not in FITTED_LENGTHS:
            raise BodySchemaInputError(f"torque_model={torque_model!r} needs length_model='per_muscle' or "
                                       f"'geometric'")
        if length_model == "geometric":
            check_geometric_options(self.robot_model, path_prior_error_mm, path_fit_postures, path_fit_seed)
        if path_separable and length_model != "per_muscle":
            raise BodySchemaInputError("path_separable=True needs length_model='per_muscle'")
        check_architecture(block, norm)
        if path_tolerance_mm is not None and (path_term_budget is None or isinstance(path_tolerance_mm, bool) or
                                              not 0.0 < float(path_tolerance_mm) < float("inf")):
            raise BodySchemaInputError(f"path_tolerance_mm={path_tolerance_mm!r} must be a finite number > 0 [mm], "
                                       f"with a path_term_budget to share")
        self.save_hyperparameters()
        PathConfig.from_schema(self.hparams)  # every path option checked, whichever length model
        if length_model == "geometric":  # rebuilt from the robot's XML: a checkpoint carries only the numbers
            self.length_net = geometric_path(self.robot_model)
        elif length_model == "per_muscle":
            self.hparams.muscle_joints = resolve_crossing(self.robot_model, robot, muscle_joints)
            if path_separable and path_blocks is None:
                self.hparams.path_blocks = self._separable_blocks()
            self._build_paths()
        else:
            self.length_net = JacobianMLP(self.n_joints, self.n_muscles, hidden, n_hidden, block, norm)
        if torque_model == "polynomial":  # the joints as the "muscles" of a polynomial over every joint
            self.torque_net = PerMusclePath(np.ones((self.n_joints, self.n_joints), bool), degree=torque_degree,
                                            n_hidden=0)
        elif torque_model == "gravity":  # rebuilt from the robot's XML: a checkpoint carries only the coefficients
            self.torque_net = GravityTorque(gravity_tree(self.robot_model))
        else:
            self.torque_net = JacobianMLP(self.n_joints, 1 if torque_model == "potential" else self.n_joints,
                                          hidden, n_hidden, block, norm)
        # typical muscle torque per joint [N m]: the unit of the torque networks (set from the data when a fit starts)
        self.register_buffer("tau_scale_nm", torch.ones(self.n_joints, dtype=torch.float64))

    def checkpoint_refusal(self, meta: dict) -> Optional[str]:
        """A gravity torque fitted before format 2 on a tree with slide joints: its masses were fitted to kinematics
        that rotated each slide's body by its displacement (myoLegs' knees), so they do not fit the fixed ones."""
        if self.hparams.torque_model != "gravity" or meta.get("format", 1) >= 2 or bool(self.torque_net.slides == 0):
            return None
        return (f"its gravity torque was fitted before slide joints were fixed (they rotated their bodies; this "
                f"robot's tree has {int(self.torque_net.slides)}): refit it with `bodyschema fit` (its config)")

    def on_load_checkpoint(self, checkpoint):
        """Lightning's own loading (``--ckpt_path``): ``checkpoint_refusal`` as ``load_schema``'s."""
        refusal = self.checkpoint_refusal(checkpoint.get("bodyschema") or {})
        if refusal:
            raise BodySchemaInputError(f"checkpoint: {refusal}")
        super().on_load_checkpoint(checkpoint)

    def _separable_blocks(self) -> list:
        """``hparams.path_blocks`` from the MJCF, for the crossings ``hparams.muscle_joints`` names."""
        if not self.robot_model.has_physics or self.hparams.muscle_joints is None:
            raise BodySchemaInputError("path_separable=True needs the robot's MJCF (MuJoCo's moment arms show which "
                                       "joints' effects on a length add up); recorded logs have none: use "
                                       "path_separable=False")
        return separable_blocks(self.robot_model, self._crossing()).tolist()

    def _crossing(self) -> np.ndarray:
        """``(M, N)`` bool from ``hparams.muscle_joints`` (None: every joint, until the fit detects them)."""
        if self.hparams.muscle_joints is None:
            return np.ones((self.n_muscles, self.n_joints), dtype=bool)
        return np.array([[j in self.hparams.muscle_joints[m] for j in self.robot_model.joint_names]
                         for m in self.robot_model.muscle_names])

    def _build_paths(self) -> None:
        """The per-muscle path model for ``hparams.muscle_joints`` (None: every joint until the fit detects them)."""
        self.length_net = PerMusclePath(self._crossing(), PathConfig.from_schema(self.hparams))

    # ------------------------------------------------------------------ units
    def setup(self, stage: str):
        super().setup(stage)
        datamodule = getattr(self.trainer, "datamodule", None) if self._trainer is not None else None
        if datamodule is not None and stage == "fit":
            self.tau_scale_nm.copy_(self.torque_scale())
            if self.hparams.get("length_model", "mlp") == "per_muscle":
                self._fit_paths(*datamodule.splits["train"])
            elif self.hparams.length_model == "geometric":
                fit_geometry(self, *datamodule.splits["train"], self.hparams.torque_model in FITTED_TORQUES)

    def _fit_paths(self, q: torch.Tensor, x: torch.Tensor) -> None:
        """Detect the crossings from the data when nothing gave them (said in the log), then fit every muscle's
        polynomial by least squares on the train split's exact lengths ``l_motor + delta(f)``."""
        q_n, target_n = self.normalizer.encode_q(q.to(torch.float64)), self._length_target_n(x.to(torch.float64))
        # Lightning calls setup before it moves the module (``self.device`` already names the fit's device)
        for part in (self.normalizer, self.length_net, self.torque_net):
            part.to(self.device)
        if self.hparams.muscle_joints is None or not self.robot_model.has_physics:  # the MJCF needs no check
            self.hparams.muscle_joints = crossing_from_data(q_n, target_n, self._arm_scale(), self.robot_model,
                                                            self.hparams.muscle_joints)
            self._build_paths()
            self.length_net.to(self.device)
        if self.hparams.get("path_tolerance_mm") is not None and self.hparams.get("path_degrees") is None:
            self._choose_degrees(q_n.to(self.device), target_n.to(self.device))
        self.length_net.fit_polynomial(q_n.to(self.device), target_n.to(self.device))
        self.clear_caches()  # the cache holds the coefficients' layouts (body), whatever the mode
        if self.hparams.get("path_cells", 1) > 1:
            self.hparams.path_cell_degrees = self.length_net.cell_degrees.tolist()
        if self.hparams.torque_model in FITTED_TORQUES:
            self._fit_torque(q_n.to(self.device), x[:, self.n_muscles:].to(self.device, torch.float64))

    def _choose_degrees(self, q_n: torch.Tensor, target_n: torch.Tensor) -> None:
        """``hparams.path_degrees`` from a first fit (``path_tolerance_mm``), and the path model rebuilt with them."""
        hp, l_std_mm = self.hparams, 1e3 * self.normalizer.x_std[:self.n_muscles]
        degrees = degrees_within_tolerance(self.length_net.crossing.cpu().numpy(), q_n, target_n, l_std_mm,
                                           hp.path_degree, hp.path_terms, hp.path_term_budget, hp.path_tolerance_mm,
                                           hp.get("path_blocks"))
        hp.path_degrees = degrees.tolist()
        self._build_paths()
        self.length_net.to(self.device)

    @torch.no_grad()
    def _fit_torque(self, q_n: torch.Tensor, f: torch.Tensor, chunk: int = 4096) -> None:
        """Least squares of the polynomial torque on ``-G(q)^T f`` of the learned moment arms, at most
        ``TORQUE_FIT_POSTURES`` postures (float64), trimmed of the postures it misses by far (``PerMusclePath.
        fit_trimmed``: where a learned moment arm swings, at a jump or a cell's edge, its torque is no smooth
        function's, and the least squares would spread that over every posture)."""
        q_n, f = q_n[:TORQUE_FIT_POSTURES].to(torch.float64), f[:TORQUE_FIT_POSTURES].to(torch.float64)
        target = torch.cat([-torch.einsum("bmn,bm->bn", self._fitted_arms(q_n[i:i + chunk]), f[i:i + chunk])
                            for i in range(0, len(q_n), chunk)])
        if self.hparams.torque_model == "gravity":  # in SI: radians and N m, as the tree's kinematics
            self.torque_net.fit_trimmed(self.normalizer.decode_q(q_n), target, TORQUE_TRIM, TORQUE_TRIM_ROUNDS)
        else:
            self.torque_net.fit_trimmed(q_n, target / self.tau_scale_nm.to(q_n), TORQUE_TRIM, TORQUE_TRIM_ROUNDS)
        self.clear_caches()  # the cache holds terms of the gravity torque's coefficients (torque)

    def _fitted_arms(self, q_n: torch.Tensor) -> torch.Tensor:
        """The fitted paths' moment arms ``(B, M, N)`` [m/rad], float64, at normalized postures (float64)."""
        if self.hparams.length_model == "geometric":
            return self.length_net(self.normalizer.decode_q(q_n))[1]
        return self.length_net.with_jacobian(q_n.to(self.dtype))[1].to(torch.float64) * self._arm_scale().to(q_n)

    def refresh_from_train_split(self, q_n, x_n) -> None:
        """The fitted torque refitted to the current moment arms (when the lengths have trained weights)."""
        if self.hparams.get("torque_model") in FITTED_TORQUES and any(True for _ in self.length_net.parameters()):
            self._fit_torque(q_n, self.normalizer.decode_x(x_n.double())[:, self.n_muscles:])

    def torque_scale(self) -> torch.Tensor:
        """(N,) [N m] from the normalizer: ``sqrt(sum_i (l_std_i / half_range_j)^2 f_mean_i^2)``, a typical torque the
        muscles exert at each joint."""
        m, norm = self.n_muscles, self.normalizer
        arm = norm.x_std[:m, None] / self._half_range()[None, :]
        return (arm.pow(2) * norm.x_mean[m:, None].pow(2)).sum(0).sqrt().clamp_min(1e-12)

    def _half_range(self) -> torch.Tensor:
        """dq / dq_n (N,) [rad per normalized unit]."""
        return 0.5 * (self.normalizer.q_hi - self.normalizer.q_lo)

    # ------------------------------------------------------------------ the learned body
    def body(self, q_n: torch.Tensor, lengths_only: bool = False):
        """At normalized postures ``q_n (B, N)``: ``l_geo (B, M)`` [m], ``G (B, M, N)`` [m/rad], ``tau (B, N)`` [N m]
        in the networks' dtype (``tau`` None with ``lengths_only``). Differentiable in the weights."""
        if self.hparams.get("length_model") == "geometric":  # in SI, float64: the paths' own units
            l_geo, G = self.length_net(self.normalizer.decode_q(q_n.to(torch.float64)))
            return l_geo.to(q_n.dtype), G.to(q_n.dtype), None if lengths_only else self.torque(q_n)
        l_mean, l_std, arm = self._length_scales(q_n.dtype)
        if isinstance(self.length_net, PerMusclePath) and not torch.compiler.is_exporting():  # fitted coefficients
            snapshot = self.inference_cache.get("path_snapshot", self.length_net.snapshot)
            l_geo_n, dl_n = self.length_net.with_jacobian(q_n, snapshot)
        else:
            l_geo_n, dl_n = self.length_net.with_jacobian(q_n)
        return l_mean + l_std * l_geo_n, dl_n * arm, None if lengths_only else self.torque(q_n)

    def _length_scales(self, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``l_mean, l_std (M,)`` [m] and ``l_std / half_range (M, N)`` [m/rad per normalized unit] in ``dtype``: a
        normalized length and slope to SI; kept in the inference cache (from the normalizer), traced when exporting."""
        def build():
            m = self.n_muscles
            l_std = self.normalizer.x_std[:m].to(dtype)
            return self.normalizer.x_mean[:m].to(dtype), l_std, l_std[:, None] / self._half_range().to(dtype)[None, :]
        return build() if torch.compiler.is_exporting() else self.inference_cache.get(("length_scales", dtype), build)

    def torque(self, q_n: torch.Tensor) -> torch.Tensor:
        """The learned torque the muscles must balance, ``tau (B, N)`` [N m] (``-G^T f = tau`` in equilibrium)."""
        if self.hparams.torque_model == "gravity":  # the tree's kinematics in radians, float64
            q = self.normalizer.decode_q(q_n.to(torch.float64))
            if torch.compiler.is_exporting():
                return self.torque_net(q).to(q_n.dtype)
            snapshot = self.inference_cache.get("gravity_snapshot", lambda: GravitySnapshot(self.torque_net))
            return snapshot(q).to(q_n.dtype)
        scale = self.tau_scale_nm.to(q_n.dtype)
        if self.hparams.torque_model in ("direct", "polynomial"):
            return scale * self.torque_net(q_n)
        # tau_j = dV/dq_j with V = c V_n and c one scalar (a gradient stays a gradient)
        c = (scale * self._half_range().to(q_n.dtype)).mean()
        _, dV_n = self.torque_net.with_jacobian(q_n)
        return c * dV_n[:, 0, :] / self._half_range().to(q_n.dtype)

    # ------------------------------------------------------------------ training
    def configure_optimizers(self):
        """``BodySchema``'s, or none when every part of the body is fitted by least squares (no trainable weight)."""
        return super().configure_optimizers() if any(True for _ in self.parameters()) else None

    def _length_target_n(self, x: torch.Tensor) -> torch.Tensor:
        """Normalized geometric lengths ``(l_motor + delta(f) - l_mean) / l_std`` of SI samples ``x (B, 2M)``."""
        m = self.n_muscles
        l_motor, f = x[:, :m], x[:, m:]
        k, alpha = self._spring_tensors(f)
        l_mean, l_std = self.normalizer.x_mean[:m], self.normalizer.x_std[:m]
        return (l_motor + torch.log1p(f.clamp_min(0.0) / k) / alpha - l_mean) / l_std

    def _arm_scale(self) -> torch.Tensor:
        """(M, N) [m/rad per normalized unit]: a normalized length slope times this is a moment arm."""
        return self.normalizer.x_std[:self.n_muscles, None] / self._half_range()[None, :]

    def training_loss(self, q_n, x_n):
        m = self.n_muscles
        x = self.normalizer.decode_x(x_n.double())
        f = x[:, m:]
        l_mean, l_std = self.normalizer.x_mean[:m], self.normalizer.x_std[:m]
        target_n = self._length_target_n(x).to(x_n.dtype)
        if self.hparams.torque_model in FITTED_TORQUES:  # least squares (refresh_from_train_split): lengths only
            l_geo_n = self.length_net(q_n) if self.hparams.length_model == "per_muscle" else \
                (self.body(q_n, lengths_only=True)[0] - l_mean.to(x_n.dtype)) / l_std.to(x_n.dtype)
            error_n, torque_loss = l_geo_n - target_n, torch.zeros((), dtype=x_n.dtype)
        else:
            l_geo, G, tau = self.body(q_n)
            error_n = (l_geo - l_mean.to(x_n.dtype)) / l_std.to(x_n.dtype) - target_n
            tau_target = -torch.einsum("bmn,bm->bn", G.detach(), f.to(x_n.dtype))
            torque_loss = ((tau - tau_target) / self.tau_scale_nm.to(x_n.dtype)).pow(2).mean()
        weight = self._length_weight(f, l_std).to(x_n.dtype)
        length_loss = (weight * error_n).pow(2).mean()
        loss = length_loss + self.hparams.torque_weight * torque_loss
        if not loss.requires_grad:  # every part fitted by least squares: nothing to train, Lightning still backprops
            loss = loss.detach().requires_grad_()
        rmse_mm = 1e3 * (error_n.detach() * l_std.to(x_n.dtype)).pow(2).mean().sqrt()
        logs = {"length_loss": length_loss.detach(), "torque_loss": torque_loss.detach(), "l_geo_rmse_mm": rmse_mm}
        return loss, logs

    def _length_weight(self, f: torch.Tensor, l_std: torch.Tensor) -> torch.Tensor:
        """(B, M): the spring stiffness ``alpha (f + k)`` times ``l_std`` (tension per normalized length error),
        divided by its mean at f = 0; ones without ``stiffness_weighted``."""
        if not self.hparams.stiffness_weighted:
            return torch.ones_like(f)
        k, alpha = self._spring_tensors(f)
        per_n = alpha * (f + k) * l_std
        return per_n / (alpha * k * l_std).mean()

    def _spring_tensors(self, like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """k [N] and alpha [1/m] as tensors like ``like`` (scalars or (M,): the spring may be per muscle)."""
        return tuple(torch.as_tensor(v, dtype=like.dtype, device=like.device)
                     for v in (self.spring.k_n, self.spring.alpha_per_m))

    # ------------------------------------------------------------------ commands
    def solve_si(self, q_rad: torch.Tensor, bounds=None, reg: Optional[float] = None):
        """The QP's best effort at ``q_rad (B, N)`` [rad] under ``bounds`` (a ``faults.bounds.FaultBounds``; None:
        healthy): ``(l_motor (B, M) [m], f (B, M) [N], status (B,))`` as float64 arrays and ``Status`` members, every
        row finite and within every fault bound; rows with status ``infeasible_learned`` are least-squares answers
        (``faults.qp``)."""
        l_geo, G, tau = self.body_si(q_rad)
        f_max = np.broadcast_to(np.asarray(self.spring.f_max_n, float), l_geo.shape)
        if bounds is None:
            bounds = FaultBounds.from_faults(Faults.none(*l_geo.shape), self.spring.f_max_n, self.spring)
        reg = self.hparams.qp_reg if reg is None else reg
        return bounds_command(l_geo, G, tau, 0.5 * f_max, bounds.on_host(), reg)

    @torch.inference_mode()  # numpy out: no tensor here needs autograd's version counters
    def adapt_si(self, q_rad: torch.Tensor, bounds, variant: str = "default", reg: Optional[float] = None):
        """Adapted commands at ``q_rad (B, N)`` [rad] under ``bounds`` (the faults' ``FaultBounds``), the contract's
        ``adapts_in_si`` with the status: ``solve_si``'s ``(l_motor_m (B, M), f_n (B, M), status (B,))``; rows whose
        status is not ``ok`` (``infeasible_learned``: the learned body cannot hold them) are least-squares best
        efforts, not commands (``Adapter`` sends them as NaN rows with that status)."""
        if variant not in self.VARIANTS:
            raise BodySchemaInputError(f"unknown adaptation variant {variant!r}; allowed: {list(self.VARIANTS)}")
        return self.solve_si(q_rad, bounds, reg)

    def generate(self, q_n):
        """Healthy normalized command: the healthy QP's answer (its least-squares best effort where the learned
        torques are unholdable; ``solve_si`` gives the status)."""
        l_motor, f, _ = self.solve_si(self.normalizer.decode_q(q_n.to(torch.float64)))
        x = torch.as_tensor(np.concatenate([l_motor, f], 1), device=q_n.device)
        return self.normalizer.encode_x(x).to(q_n.dtype)

    ADAPT_OPTIONS = ("reg",)  # adapt_si's options (``qp_reg`` by default)

    def adapter(self, faults, variant: str = "default", check_physics: bool = True, **options) -> Adapter:
        """``BodySchema.adapter``; the one option is ``reg`` (``qp_reg``). Rows the learned body cannot hold read
        ``"infeasible_learned"`` (NaN; their least-squares answer in ``diagnostics``: ``qp_l_motor_m``,
        ``qp_f_n``), not ``non_finite``."""
        unknown = sorted(set(options) - set(self.ADAPT_OPTIONS))
        if unknown:
            raise BodySchemaInputError(f"unknown adaptation option(s) {unknown} for {type(self).__name__}; "
                                       f"allowed: {list(self.ADAPT_OPTIONS)}")
        return Adapter(self, faults, variant, check_physics, options)
