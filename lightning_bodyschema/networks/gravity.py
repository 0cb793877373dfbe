"""``GravityTorque``: the gravity torque of a known kinematic tree with unknown masses, linear in its parameters.

With ``V(q) = sum_f -g . (m_f p_f(q) + R_f(q) s_f)`` over the moving frames f (``sim.gravity_tree``), the torque
``tau = dV/dq`` is ``Y(q) pi`` with ``pi = (m_f, s_f)`` per frame. For a hinge joint j (world axis ``a_j``, anchor
``o_j``) that moves frame f: ``dp_f/dq_j = a_j x (p_f - o_j)`` and ``dR_f/dq_j = a_j x R_f``, so by the triple
product the mass column is ``-(g x a_j) . (p_f - o_j)`` and moment column k is ``-(g x a_j) . R_f[:, k]``; a slide
joint's mass column is ``-g . a_j`` (its moment columns 0). Coupled joints add their columns times their slope
``d q_j / d q_free`` (``tau_free = E^T tau_full``). Per free joint an offset and a linear spring
(``tau_j += c0_j + c1_j q_j``) represent joint springs.

Forward kinematics is MuJoCo's in closed form, float64, batched, traceable under ``torch.export`` with a symbolic batch
(``networks.snapshot.GravitySnapshot.kinematics``). Plain PyTorch, no Lightning.
"""
from __future__ import annotations

import numpy as np
import torch
from torch import nn

from ..errors import BodySchemaInputError
from .arrays import apply_keeping_dtype
from .snapshot import GravitySnapshot
from .trim import solve_triangular, trimmed_refits

_HINGE = 3  # mujoco.mjtJoint's hinge; the tree's other joints are slides (sim.model refuses any other kind)


def _cross_matrices(axes: np.ndarray) -> torch.Tensor:
    """(J, 3, 3) ``K`` with ``K v = axis x v`` per axis (numpy: a schema's skeleton is built on the meta device)."""
    x, y, z = np.asarray(axes, float).reshape(-1, 3).T
    zero = np.zeros_like(x)
    return torch.tensor(np.stack([[zero, -z, y], [z, zero, -x], [-y, x, zero]]).transpose(2, 0, 1).copy(),
                        dtype=torch.float64)


def _motion_terms(tree, chain: list) -> torch.Tensor:
    """``(3, C, 4, 4)``: each chain joint's motion ``I + sin M_sin + versine M_versine + angle M_angle`` in its body's
    frame (Rodrigues about the axis through the anchor for a hinge, a shift along the axis for a slide)."""
    f64, hinge = dict(dtype=torch.float64), torch.tensor(tree.jnt_type[chain] == _HINGE, dtype=torch.float64)[:, None]
    cross = _cross_matrices(tree.jnt_axis[chain]) * hinge[:, :, None]  # a slide does not rotate
    pos = torch.tensor(tree.jnt_pos[chain], **f64)[..., None]
    terms = torch.zeros(3, len(chain), 4, 4, **f64)
    terms[0, :, :3, :3], terms[0, :, :3, 3] = cross, -hinge * (cross @ pos)[..., 0]
    terms[1, :, :3, :3], terms[1, :, :3, 3] = cross @ cross, -hinge * (cross @ cross @ pos)[..., 0]
    terms[2, :, :3, 3] = (1.0 - hinge) * torch.tensor(tree.jnt_axis[chain], **f64)
    return terms


class GravityTorque(nn.Module):
    """``tau (B, N)`` [N m] at free-joint postures ``q (B, N)`` [rad or m] of a ``sim.gravity_tree.GravityTree``.

    ``features(q) (B, N, P)``; ``forward(q) = features(q) @ coef``; ``fit_trimmed`` sets ``coef`` by least squares.
    ``coef`` (P,) is the only state-dict entry (float64): per frame ``(m [kg], s [kg m] x3)``, then N offsets [N m]
    and N spring rates [N m per rad or m]. The tree's arrays are non-persistent float64 buffers (the schema rebuilds
    them from the robot).
    """

    def __init__(self, tree):
        super().__init__()
        n_free, n_frames = tree.free_select.shape[0], tree.n_frames
        if n_frames == 0:
            raise BodySchemaInputError("gravity torque: no body moves with a free joint")
        self.n_free, self.n_frames, self.coupled = n_free, n_frames, bool(tree.dep_joint.size)
        f64, moving = dict(dtype=torch.float64), tree.moving_joint
        chain = [j for joints in tree.body_joints for j in joints]  # the joints of the bodies the FK visits
        qpos0 = torch.tensor(tree.qpos0, **f64)
        anchor_axis = torch.zeros(len(moving), 4, 2, **f64)  # per moving joint [anchor; 1], [axis; 0]
        anchor_axis[:, :3, 0], anchor_axis[:, 3, 0] = torch.tensor(tree.jnt_pos[moving], **f64), 1.0
        anchor_axis[:, :3, 1] = torch.tensor(tree.jnt_axis[moving], **f64)
        self.slides = int((tree.jnt_type[chain] != _HINGE).sum())  # slide joints the kinematics visits
        lists = dict(dep_follows_index=tree.dep_follows.tolist(), dep_index=tree.dep_joint.tolist(),
                     slope_index=tree.slope_of.tolist(), chain_joint_index=chain)
        # the couplings' and slopes' polynomials as ``GravitySnapshot.full`` and ``slopes`` take them: each
        # one's gather and ``qpos0`` there, its coefficient columns the highest power first
        horner = lambda coef: torch.tensor(coef, **f64).T.flip(0).contiguous()  # noqa: E731
        buffers = dict(gravity=torch.tensor(tree.gravity, **f64),
                       gravity_cross_T=_cross_matrices(tree.gravity)[0].T.clone(),  # g x v as a product (vmap)
                       free_select=torch.tensor(tree.free_select, **f64), full_base=torch.tensor(tree.full_base, **f64),
                       dep_scatter=torch.eye(len(tree.qpos0), **f64)[tree.dep_joint],  # one-hot rows
                       motion_eye=torch.eye(4, **f64), motion_terms=_motion_terms(tree, chain), anchor_axis=anchor_axis,
                       chain_qpos0=qpos0[chain],
                       moves_frame=torch.tensor(tree.moves_frame, **f64),
                       hinge=torch.tensor(tree.jnt_type[moving] == _HINGE, **f64),
                       free_scatter=torch.eye(n_free, **f64)[tree.free_column],
                       dep_follows_qpos0=qpos0[lists["dep_follows_index"]], dep_qpos0=qpos0[lists["dep_index"]],
                       slope_qpos0=qpos0[lists["slope_index"]], dep_horner=horner(tree.dep_coef),
                       slope_horner=horner(tree.slope_coef),
                       **{name: torch.as_tensor(rows, dtype=torch.long) for name, rows in lists.items()})
        for name, value in buffers.items():
            self.register_buffer(name, value, persistent=False)
        self._register_nodes(tree, chain)
        self.register_buffer("coef", torch.zeros(4 * n_frames + 2 * n_free, **f64))
        self.all_hinges = bool(moving.size) and bool((tree.jnt_type[moving] == _HINGE).all())

    def _apply(self, fn, *args, **kwargs):
        """Device moves apply to every buffer; dtype casts do not (the kinematics and coefficients stay float64)."""
        return apply_keeping_dtype(self, list(self._buffers), super()._apply, fn, *args, **kwargs)

    # ------------------------------------------------------------------ the kinematics' tables
    def _register_nodes(self, tree, chain: list) -> None:
        """The node tree of ``GravitySnapshot.kinematics``: per body its offset, then each of its joints in order, each
        node's parent the node before it (a body's offset: its parent body's last node), an identity node last (every
        root's parent): ``node_parent``, ``node_chain`` (a joint node's motion, or -1), each node's constant transform
        (0 on a joint's node), the one-hot map of the joint motions onto their nodes, and the rows each pick of
        ``GravitySnapshot.kinematics`` takes (``pick_names``)."""
        parent, last, joint_node, self.node_chain, const = [], {}, {}, [], []
        for i, p in enumerate(tree.body_parent.tolist()):
            parent.append(last[p] if p >= 0 else -1)
            self.node_chain.append(-1)
            const.append(np.eye(4))
            const[-1][:3, :3], const[-1][:3, 3] = tree.body_rot[i], tree.body_pos[i]
            for j in tree.body_joints[i]:
                parent.append(len(parent) - 1)
                self.node_chain.append(chain.index(j))
                const.append(np.zeros((4, 4)))
                joint_node[j] = len(parent) - 1
            last[i] = len(parent) - 1
        n, self.node_parent = len(parent), parent
        motion = np.zeros((n + 1, len(chain)))
        motion[[k for k, c in enumerate(self.node_chain) if c >= 0], [c for c in self.node_chain if c >= 0]] = 1.0
        for name, value in dict(node_const=np.stack(const + [np.eye(4)]), node_motion=motion).items():
            self.register_buffer(name, torch.tensor(value, dtype=torch.float64), persistent=False)
        pointer, picks = np.array([q if q >= 0 else n for q in parent] + [n]), {}
        while (pointer[:n] < n).any():  # log2(depth) rounds
            picks[f"node_pointer{len(picks)}"], pointer = pointer, pointer[pointer]
        picks.update(frame_node=[last[i] for i in tree.frame_body.tolist()],
                     before_node=[joint_node[j] - 1 for j in tree.moving_joint.tolist()])
        self.pick_names = list(picks)  # the pointer rounds in order, then the frames' and the moving joints' nodes
        for name, rows in picks.items():
            self.register_buffer(name, torch.as_tensor(rows, dtype=torch.long), persistent=False)

    # ------------------------------------------------------------------ the regressor
    def features(self, q: torch.Tensor) -> torch.Tensor:
        """``Y (B, N, P)`` with ``tau = Y @ coef`` (module docstring for the columns)."""
        q = q.to(torch.float64)
        tree = GravitySnapshot(self)
        full = tree.full(q)
        frames, o, a = tree.kinematics(full)  # the frames' positions p: [..., :3, 3], rotations R: [..., :3, :3]
        ga = a @ self.gravity_cross_T  # (B, J, 3)
        hinge = self.hinge[:, None]
        mass = -(torch.einsum("bjc,bfc->bjf", ga, frames[..., :3, 3]) - (ga * o).sum(-1, keepdim=True)) * hinge \
            - (a @ self.gravity)[..., None] * (1.0 - hinge)
        moment = -torch.einsum("bjc,bfck->bjfk", ga, frames[..., :3, :3]) * hinge[..., None]
        per_joint = torch.cat([mass[..., None], moment], -1) * self.moves_frame[..., None]  # (B, J, F, 4)
        weighted = per_joint.flatten(2) * tree.slopes(full)[..., None]
        per_free = torch.einsum("bjp,jn->bnp", weighted, self.free_scatter)
        return torch.cat([per_free, torch.diag_embed(torch.ones_like(q)), torch.diag_embed(q)], -1)

    def forward(self, q: torch.Tensor) -> torch.Tensor:
        """``tau (B, N)`` [N m] = ``features(q) @ coef``, by each joint's torque from the frames' world first mass
        moments ``w_f = m_f p_f + R_f s_f`` summed over the frames it moves: a ``GravitySnapshot`` built on the call
        (a caller that keeps one calls it)."""
        return GravitySnapshot(self)(q.to(torch.float64))

    # ------------------------------------------------------------------ the fit
    @torch.no_grad()
    def fit_trimmed(self, q: torch.Tensor, tau: torch.Tensor, factor: float = 3.0, rounds: int = 8,
                    chunk: int = 4096) -> torch.Tensor:
        """Least squares of ``coef`` on postures ``q (S, N)`` and torques ``tau (S, N)`` [N m], then up to ``rounds``
        refits without the postures whose residual norm exceeds ``factor`` times the kept ones' median; the kept mask
        ``(S,)``. Each fit is a QR of the features (``trim.solve_triangular``), not the normal equations, whose
        squared condition number would lose the directions the postures determine only weakly."""
        q, tau = q.to(self.coef.device, torch.float64), tau.to(self.coef.device, torch.float64)
        self._fit(q, tau, chunk)
        return trimmed_refits(self, q, tau, lambda keep, new: self._fit(q[new], tau[new], chunk), factor, rounds, chunk)

    def _fit(self, q: torch.Tensor, tau: torch.Tensor, chunk: int) -> None:
        """``coef`` from ``R`` of the QR of ``[Y | tau]`` (every posture and joint a row), one chunk of postures at a
        time: the QR of the previous ``R`` stacked on the chunk's rows (the same ``R`` up to row signs)."""
        R = torch.zeros(0, len(self.coef) + 1, dtype=torch.float64, device=q.device)
        for start in range(0, len(q), chunk):
            rows = torch.cat([self.features(q[start:start + chunk]), tau[start:start + chunk, :, None]], -1)
            R = torch.linalg.qr(torch.cat([R, rows.flatten(0, 1)]), mode="r").R
        self.coef.copy_(solve_triangular(R))

