"""MuJoCo's muscle curves, batched: each muscle's tendon tension is affine in its activation.

For a ``<muscle>`` actuator (gain, bias and dynamics of type muscle) on a tendon with gear ``g``, MuJoCo's actuator
force is ``gain * act + bias`` with ``gain = -F0 FL(L) FV(V)`` (``mju_muscleGain``) and ``bias = -F0 FP(L)``
(``mju_muscleBias``): negative, because a muscle pulls (shortens its tendon). At rest ``FV(0) = 1``, so the tendon
tension [N] is

    f = s(l) a + p(l),   s = g F0 FL(L),   p = g F0 FP(L),   L = r0 + (g l - lr0) / L0,   L0 = (lr1 - lr0) / (r1 - r0)

with ``l`` the tendon length [m], ``lr`` the actuator's length range, ``r`` its operating range (gainprm[0:2]) and
``F0`` its peak force (gainprm[2], or scale / acc0 where MuJoCo derives it). ``FL`` and ``FP`` below are the same
piecewise quadratics as MuJoCo's (tests compare them with ``mju_muscleGain`` / ``mju_muscleBias``). At a tendon
velocity ``v`` the active part is multiplied by MuJoCo's force-velocity factor ``FV(g v / (L0 vmax))``
(``MuscleCurves.velocity_factor``); the passive part has none. numpy and MuJoCo only.
"""
from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from ..errors import BodySchemaInputError
from ..sim.mjcf import compile_spec, load_spec
from ..sim.model import MusculoskeletalModel, _weld_free_joints

MJMINVAL = 1e-15  # MuJoCo's mjMINVAL: the floor of every denominator in its muscle curves
_MUSCLE = (mujoco.mjtGain.mjGAIN_MUSCLE, mujoco.mjtBias.mjBIAS_MUSCLE)


def _gain_length(L, lmin, lmax):
    """MuJoCo's active force-length curve FL(L) (peak 1 at L = 1, zero outside [lmin, lmax])."""
    a, b = 0.5 * (lmin + 1.0), 0.5 * (1.0 + lmax)
    x_lo = (L - lmin) / np.maximum(MJMINVAL, a - lmin)
    x_mid_lo = (1.0 - L) / np.maximum(MJMINVAL, 1.0 - a)
    x_mid_hi = (L - 1.0) / np.maximum(MJMINVAL, b - 1.0)
    x_hi = (lmax - L) / np.maximum(MJMINVAL, lmax - b)
    fl = np.where(L <= a, 0.5 * x_lo ** 2, np.where(L <= 1.0, 1.0 - 0.5 * x_mid_lo ** 2,
                  np.where(L <= b, 1.0 - 0.5 * x_mid_hi ** 2, 0.5 * x_hi ** 2)))
    return np.where((lmin <= L) & (L <= lmax), fl, 0.0)


def _passive_length(L, lmax, fpmax):
    """MuJoCo's passive force-length curve FP(L): 0 up to L = 1, half-quadratic to (1 + lmax)/2, then linear."""
    b = 0.5 * (1.0 + lmax)
    x = (L - 1.0) / np.maximum(MJMINVAL, b - 1.0)
    y = (L - b) / np.maximum(MJMINVAL, b - 1.0)
    return fpmax * np.where(L <= 1.0, 0.0, np.where(L <= b, 0.5 * x ** 2, 0.5 + y))


def _gain_velocity(V, fvmax):
    """MuJoCo's force-velocity curve FV(V) (``mju_muscleGain``): 0 at V <= -1 (shortening at vmax), (V + 1)^2 up to
    V = 0, then rising to ``fvmax`` at V = fvmax - 1 (lengthening) and flat beyond."""
    y = fvmax - 1.0
    lengthening = fvmax - (y - V) ** 2 / np.maximum(MJMINVAL, y)
    return np.where(V <= -1.0, 0.0, np.where(V <= 0.0, (V + 1.0) ** 2, np.where(V <= y, lengthening, fvmax)))


@dataclass(frozen=True)
class MuscleCurves:
    """The muscle actuator of each muscle (in the model's muscle order), with what its curves need.

    actuators: actuator names; gear (M,); lengthrange_m (M, 2) of the actuator length (gear x tendon length);
    gainprm, biasprm (M, 9): MuJoCo's (range0, range1, F0, scale, lmin, lmax, vmax, fpmax, fvmax), F0 resolved [N];
    dynprm (M, 3): activation and deactivation time constants [s] and tausmooth (for rebuilding the actuators).
    """

    actuators: list
    gear: np.ndarray
    lengthrange_m: np.ndarray
    gainprm: np.ndarray
    biasprm: np.ndarray
    dynprm: np.ndarray

    def _optimal_length(self, prm):
        """MuJoCo's L0 [m of actuator length]: the length range over the operating range."""
        return (self.lengthrange_m[:, 1] - self.lengthrange_m[:, 0]) / np.maximum(MJMINVAL, prm[:, 1] - prm[:, 0])

    def _normalized_length(self, l_geo_m, prm):
        l0 = self._optimal_length(prm)
        return prm[:, 0] + (self.gear * l_geo_m - self.lengthrange_m[:, 0]) / np.maximum(MJMINVAL, l0)

    def velocity_factor(self, v_geo_m_s) -> np.ndarray:
        """(B, M) MuJoCo's force-velocity factor FV at tendon velocities ``v_geo_m_s`` (B, M) [m/s]: the active force
        at that velocity is FV times ``affine``'s ``s a``. The velocity is normalized as MuJoCo does:
        ``V = g v / (L0 vmax)``."""
        g, l0 = self.gainprm, self._optimal_length(self.gainprm)
        return _gain_velocity(self.gear * v_geo_m_s / np.maximum(MJMINVAL, l0 * g[:, 6]), g[:, 8])

    def affine(self, l_geo_m) -> tuple[np.ndarray, np.ndarray]:
        """``(s, p)`` (B, M) [N] with tension ``f = s a + p`` at tendon lengths ``l_geo_m`` (B, M), zero velocity."""
        g, b = self.gainprm, self.biasprm
        fl = _gain_length(self._normalized_length(l_geo_m, g), g[:, 4], g[:, 5])
        fp = _passive_length(self._normalized_length(l_geo_m, b), b[:, 5], b[:, 7])
        return self.gear * g[:, 2] * fl, self.gear * b[:, 2] * fp


def _resolved(prm, scale_acc0):
    """9 muscle parameters with F0 (index 2) as MuJoCo uses it: given, or scale / acc0 where negative."""
    prm = np.array(prm[:9], float)
    if prm[2] < 0:
        prm[2] = prm[3] / max(MJMINVAL, scale_acc0)
    return prm


def read_muscle_curves(source: str, tendons, fixed_base: bool = False) -> MuscleCurves | None:
    """The muscle actuators of ``source`` (any ``MusculoskeletalModel`` source) on the tendons named ``tendons``,
    one per tendon; None when some tendon has none (a robot whose tendons are driven otherwise)."""
    spec = load_spec(source)
    if fixed_base:
        _weld_free_joints(spec)
    m = compile_spec(spec)
    by_tendon = {}
    for i in range(m.nu):
        kinds = (mujoco.mjtGain(int(m.actuator_gaintype[i])), mujoco.mjtBias(int(m.actuator_biastype[i])))
        if int(m.actuator_trntype[i]) == int(mujoco.mjtTrn.mjTRN_TENDON) and kinds == _MUSCLE:
            tendon = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_TENDON, int(m.actuator_trnid[i, 0]))
            by_tendon.setdefault(tendon, []).append(i)
    doubled = [t for t in tendons if len(by_tendon.get(t, ())) > 1]
    if doubled:
        raise BodySchemaInputError(f"tendons {doubled} are driven by more than one muscle actuator; static "
                                   "optimization needs one muscle actuator per muscle")
    if not all(t in by_tendon for t in tendons) or not len(tendons):
        return None
    ids = [by_tendon[t][0] for t in tendons]
    return MuscleCurves(
        actuators=[mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_ACTUATOR, i) or f"#{i}" for i in ids],
        gear=m.actuator_gear[ids, 0].copy(), lengthrange_m=m.actuator_lengthrange[ids].copy(),
        gainprm=np.array([_resolved(m.actuator_gainprm[i], m.actuator_acc0[i]) for i in ids]),
        biasprm=np.array([_resolved(m.actuator_biasprm[i], m.actuator_acc0[i]) for i in ids]),
        dynprm=m.actuator_dynprm[ids, :3].copy())


def actuated_model(model: MusculoskeletalModel, curves: MuscleCurves, spec=None) -> mujoco.MjModel:
    """``model``'s own MuJoCo model (locks, welded base and all; ``spec``: this spec of it instead, e.g. with its
    floating root back) with the muscle actuators put back, one per muscle, activation in [0, 1]: what a MuJoCo user
    runs, for checking static activations in MuJoCo."""
    spec = mujoco.MjSpec.from_string(model.xml) if spec is None else spec
    for k, tendon in enumerate(model.muscle_names):
        actuator = spec.add_actuator(name=curves.actuators[k], target=tendon, trntype=mujoco.mjtTrn.mjTRN_TENDON)
        actuator.gaintype, actuator.biastype = _MUSCLE
        actuator.dyntype = mujoco.mjtDyn.mjDYN_MUSCLE
        actuator.gainprm[:9], actuator.biasprm[:9] = curves.gainprm[k], curves.biasprm[k]
        actuator.dynprm[:3] = curves.dynprm[k]
        actuator.gear[0], actuator.lengthrange = curves.gear[k], curves.lengthrange_m[k]
        actuator.ctrllimited, actuator.ctrlrange = mujoco.mjtLimited.mjLIMITED_TRUE, [0.0, 1.0]
    return compile_spec(spec)
