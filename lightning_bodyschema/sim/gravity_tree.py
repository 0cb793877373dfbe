"""``GravityTree``: the kinematic tree of a compiled model as the numpy arrays a gravity regressor needs.

Gravity's potential is ``V(q) = sum_b -g . (m_b p_b(q) + R_b(q) s_b)`` (``s_b = m_b c_b``, the first mass moment in
the body frame), so ``tau_bias = dV/dq`` is linear in ``(m_b, s_b)`` with coefficients from the tree alone (joint
axes, anchors, body offsets; no masses). ``networks.gravity.GravityTorque`` evaluates it in torch from these arrays.

Bodies whose every joint is constant (locked, or following a locked joint) move rigidly with their parent, so their
mass joins the nearest moving ancestor's *frame*: one group of four parameters per frame (myoArm with its hand
locked: 10 frames). Bodies welded to the world carry no torque and are dropped. Never imports Lightning.
"""
from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

_HINGE, _SLIDE = int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE)


@dataclass
class GravityTree:
    """Arrays of the bodies forward kinematics visits (parents first) and of the joints that move (module docstring).

    Joint values come from the free joints ``q (B, N)`` as ``full = q @ free_select + full_base``, then every
    coupling ``full[j] = qpos0[j] + poly(full[k] - qpos0[k])`` (``dep_*``)."""

    gravity: np.ndarray  # (3,) [m/s^2]
    qpos0: np.ndarray  # (nq,) the reference the hinge angles and couplings are measured from
    free_select: np.ndarray  # (N, nq) one-hot: free joint c is model joint free[c]
    full_base: np.ndarray  # (nq,) locked values; qpos0 elsewhere (free and followers are overwritten)
    dep_joint: np.ndarray  # (D,) followers
    dep_follows: np.ndarray  # (D,) the joint each follows (free or locked)
    dep_coef: np.ndarray  # (D, 5) a0..a4 of ``full[j] - qpos0[j] = poly(full[k] - qpos0[k])``
    body_parent: np.ndarray  # (K,) index into these bodies, -1: the world
    body_pos: np.ndarray  # (K, 3) offset in the parent's frame [m]
    body_rot: np.ndarray  # (K, 3, 3) orientation in the parent's frame
    body_joints: list  # K lists of model joint ids, in MuJoCo's order
    jnt_type: np.ndarray  # (nq,) mjtJoint codes (hinge or slide only)
    jnt_pos: np.ndarray  # (nq, 3) anchor in the body frame [m]
    jnt_axis: np.ndarray  # (nq, 3) unit axis in the body frame
    frame_body: np.ndarray  # (F,) index into the bodies of each frame's moving body
    frame_names: list  # F body names
    moving_joint: np.ndarray  # (J,) model joints that move: free, or following a free joint
    moves_frame: np.ndarray  # (J, F) bool: the joint moves that frame (the frame's body is at or below the joint's)
    free_column: np.ndarray  # (J,) the free joint (column of q) whose torque each moving joint's torque joins
    slope_coef: np.ndarray  # (J, 4): d full[j] / d q[column] = poly(x) of x = full[slope_of] - qpos0[slope_of]
    slope_of: np.ndarray  # (J,) the joint x is read from (the free joint itself when the joint is free)

    @property
    def n_frames(self) -> int:
        return len(self.frame_body)


def gravity_tree(model) -> GravityTree:
    """The ``GravityTree`` of a ``MusculoskeletalModel`` (its ``mj_model`` and ``joint_map``)."""
    m, jmap = model.mj_model, model.joint_map
    column = {int(j): c for c, j in enumerate(jmap.free)}
    follows = {int(j): (int(k), np.asarray(coef, float)) for j, k, coef in jmap.deps}
    moving = [j for j in range(m.njnt) if j in column or (j in follows and follows[j][0] in column)]
    moving_set = set(moving)
    frame_of = _frames(m, moving_set)
    frame_ids = sorted(set(frame_of.values()))
    fixed_pos, fixed_rot = _fixed_poses(model, frame_of)
    needed = [b for b in _ancestors(m, frame_ids) if b in frame_of]  # the world's bodies: folded into offsets
    index = {b: i for i, b in enumerate(needed)}
    nq = m.njnt
    free_select = np.zeros((len(jmap.free), nq))
    free_select[np.arange(len(jmap.free)), jmap.free] = 1.0
    full_base = jmap.qpos0.copy()
    full_base[jmap.free] = 0.0
    for j, value in jmap.locked.items():
        full_base[j] = value
    deps = list(follows.items())
    slope_coef, slope_of = np.zeros((len(moving), 4)), np.zeros(len(moving), dtype=np.int64)
    for i, j in enumerate(moving):
        if j in column:
            slope_coef[i, 0], slope_of[i] = 1.0, j
        else:
            k, coef = follows[j]
            slope_coef[i], slope_of[i] = coef[1:5] * np.arange(1, 5), k
    return GravityTree(
        gravity=m.opt.gravity.copy(), qpos0=jmap.qpos0.copy(), free_select=free_select, full_base=full_base,
        dep_joint=np.array([j for j, _ in deps], dtype=np.int64),
        dep_follows=np.array([k for _, (k, _) in deps], dtype=np.int64),
        dep_coef=np.array([c for _, (_, c) in deps], float).reshape(-1, 5),
        body_parent=np.array([index.get(int(m.body_parentid[b]), -1) for b in needed], dtype=np.int64),
        body_pos=np.stack([fixed_pos[int(m.body_parentid[b])] @ np.append(m.body_pos[b], 1.0) for b in needed]),
        body_rot=np.stack([fixed_rot[int(m.body_parentid[b])] @ _quat_to_mat(m.body_quat[b]) for b in needed]),
        body_joints=[list(range(m.body_jntadr[b], m.body_jntadr[b] + m.body_jntnum[b])) for b in needed],
        jnt_type=m.jnt_type.astype(np.int64), jnt_pos=m.jnt_pos.copy(),
        jnt_axis=m.jnt_axis / np.linalg.norm(m.jnt_axis, axis=1, keepdims=True),
        frame_body=np.array([index[b] for b in frame_ids], dtype=np.int64),
        frame_names=[mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, b) or f"#{b}" for b in frame_ids],
        moving_joint=np.array(moving, dtype=np.int64),
        moves_frame=np.array([[_below(m, b, int(m.jnt_bodyid[j])) for b in frame_ids] for j in moving], bool)
        .reshape(len(moving), len(frame_ids)),
        free_column=np.array([column[j] if j in column else column[follows[j][0]] for j in moving], dtype=np.int64),
        slope_coef=slope_coef, slope_of=slope_of)


def _frames(m: mujoco.MjModel, moving: set) -> dict:
    """``{body: frame body}`` for every body that moves: itself when one of its joints moves, else its parent's
    frame (a body on constant joints is rigid on its parent); bodies fixed to the world are left out."""
    frame_of = {}
    for b in range(1, m.nbody):  # parents precede children in MuJoCo's body order
        joints = range(m.body_jntadr[b], m.body_jntadr[b] + m.body_jntnum[b])
        if any(j in moving for j in joints):
            frame_of[b] = b
        elif int(m.body_parentid[b]) in frame_of:
            frame_of[b] = frame_of[int(m.body_parentid[b])]
    return frame_of


def _fixed_poses(model, frame_of: dict) -> tuple[dict, dict]:
    """``{body: (3, 4) [R | p]}`` and ``{body: R}`` in the world of the bodies nothing moves (MuJoCo's, at any
    posture), and for every other body the identity: a moving body's child keeps its offset in its parent's frame,
    a fixed body's child gets its offset in the world (fewer bodies for the forward kinematics to visit)."""
    m, data = model.mj_model, mujoco.MjData(model.mj_model)
    data.qpos[:] = model.joint_map.full_q(model.q_range.mean(axis=1)[None])[0]
    mujoco.mj_kinematics(m, data)
    identity = np.hstack([np.eye(3), np.zeros((3, 1))])
    pose = {b: (identity if b in frame_of else np.hstack([data.xmat[b].reshape(3, 3), data.xpos[b][:, None]]))
            for b in range(m.nbody)}
    return pose, {b: value[:, :3] for b, value in pose.items()}


def _ancestors(m: mujoco.MjModel, bodies: list) -> list:
    """Every body on the way from the world to ``bodies`` (and those), in MuJoCo's order (parents first)."""
    needed = set()
    for b in bodies:
        while b > 0 and b not in needed:
            needed.add(b)
            b = int(m.body_parentid[b])
    return sorted(needed)


def _below(m: mujoco.MjModel, body: int, ancestor: int) -> bool:
    """True when ``ancestor`` is ``body`` or one of its ancestors."""
    while body > 0:
        if body == ancestor:
            return True
        body = int(m.body_parentid[body])
    return ancestor == 0


def _quat_to_mat(quat: np.ndarray) -> np.ndarray:
    out = np.zeros(9)
    mujoco.mju_quat2Mat(out, np.asarray(quat, float))
    return out.reshape(3, 3)
