"""Static optimization on the true body: MuJoCo's own muscle curves, the QP against proxsuite, MuJoCo's equilibrium
and a MuJoCo rollout with the activations, the objectives, the faults and the statuses."""
from __future__ import annotations

import mujoco
import numpy as np
import pytest

from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.solvers import BoxQP, proxsuite_solve
from lightning_bodyschema.status import Status

pytest.importorskip("myo_sim")
from lightning_bodyschema.statics import StaticBody, static_optimization  # noqa: E402
from lightning_bodyschema.statics.check import mujoco_drift_rad, mujoco_residual_nm  # noqa: E402

ELBOW = "myo:myoelbow_2dof"


@pytest.fixture(scope="module")
def elbow():
    return StaticBody(ELBOW)


@pytest.fixture(scope="module")
def postures(elbow):
    return elbow.model.sample_q(np.random.default_rng(0), 60)


def test_muscle_curves_are_mujocos(elbow):
    """s a + p equals -(mju_muscleGain a + mju_muscleBias) at zero velocity, inside and outside the length range."""
    c, rng = elbow.curves, np.random.default_rng(1)
    lr = c.lengthrange_m
    length = lr[:, 0] + (lr[:, 1] - lr[:, 0]) * rng.uniform(-1.0, 2.0, (300, len(lr)))
    s, p = c.affine(length)
    gain = np.array([[mujoco.mju_muscleGain(x * c.gear[k], 0.0, lr[k], 1.0, c.gainprm[k]) for k, x in enumerate(row)]
                     for row in length])
    bias = np.array([[mujoco.mju_muscleBias(x * c.gear[k], lr[k], 1.0, c.biasprm[k]) for k, x in enumerate(row)]
                     for row in length])
    assert (s == 0).any() and (s > 0).any() and (p > 0).any()  # every branch of the curves is visited
    np.testing.assert_allclose(s, -c.gear * gain, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(p, -c.gear * bias, rtol=1e-12, atol=1e-9)


@pytest.mark.parametrize("faults", [None, {"cut": ["BRA_tendon"]}])
def test_mujoco_holds_the_ok_rows(elbow, postures, faults):
    """Where ok: MuJoCo's own forces with the activations balance every free joint to 1e-6 N m, its tendon tensions are
    the result's, and a 0.3 s rollout from rest stays put; rows above full activation fall (the check can fail)."""
    result = elbow.solve(postures, faults)
    ok = result.ok
    above = np.array([s is Status.ACTIVATION_ABOVE_ONE for s in result.status])
    assert ok.sum() >= 5 and above.sum() >= 5
    residual, miss = mujoco_residual_nm(elbow, result)
    assert residual[ok].max() <= 1e-6 and miss[ok].max() <= 1e-8
    drift = mujoco_drift_rad(elbow, result.take(np.flatnonzero(ok | above)[:16]), duration_s=0.3)
    kept = ok[np.flatnonzero(ok | above)[:16]]
    assert drift[kept].max() < 1e-6
    assert drift[~kept].max() > 1e-2  # MuJoCo caps activation at 1: these cannot hold
    assert (result.activation[ok] <= 1.0 + 1e-12).all() and (result.activation[ok] >= 0).all()
    assert (result.activation[above].max(1) > 1.0).all()


def _proxsuite(body, q, objective):
    """Tensions (B, M) [N] of the healthy static-optimization QP solved by proxsuite alone, tightly, in the objective's
    own variable (activations; tensions in newtons), and which rows it solved."""
    from lightning_bodyschema.faults.faults import Faults

    l_geo, G, tau = body.model.kinematics(q)
    lo, hi, s, p = body.tension_bounds(l_geo, Faults.none(len(q), body.model.n_muscles))
    hi = np.minimum(hi, p + s)
    if objective == "tension":
        return _reference(G, tau, np.zeros_like(lo), lo, hi)
    a_hi = np.where(s > 0, (hi - p) / np.where(s > 0, s, 1.0), 0.0)
    a, solved = _reference(G * s[..., None], tau + np.einsum("bmn,bm->bn", G, p), np.zeros_like(lo),
                           np.zeros_like(lo), a_hi)
    return s * a + p, solved


def _reference(G, tau, x_ref, lo, hi):
    """proxsuite alone on ``min ||x - x_ref||^2 s.t. -G^T x = tau, lo <= x <= hi``, tightly: (x, solved) as numpy."""
    x, solved = proxsuite_solve(BoxQP.build(G, tau, x_ref, lo, hi), 10000, eps_abs=1e-12)
    return x.numpy(), solved.numpy()


@pytest.mark.parametrize("objective", ["activation", "tension"])
def test_answers_equal_proxsuite(elbow, postures, objective):
    """The batched dual Newton's tensions equal those of proxsuite solving the same QP tightly to 1e-8 N (rows that
    hold with activations in [0, 1]); ``solver="proxqp"`` gives the same statuses."""
    ours = elbow.solve(postures, objective=objective)
    theirs, solved = _proxsuite(elbow, postures[ours.ok], objective)
    assert ours.ok.sum() >= 5 and solved.all()
    assert np.abs(ours.tension_n[ours.ok] - theirs).max() <= 1e-8
    assert (elbow.solve(postures, objective=objective, solver="proxqp").status == ours.status).all()


def test_each_objective_is_the_minimum_of_its_own_criterion(elbow, postures):
    """min sum a^2 and min sum f^2 differ, and each answer is the better one under its own criterion."""
    by_a, by_f = elbow.solve(postures, objective="activation"), elbow.solve(postures, objective="tension")
    both = by_a.ok & by_f.ok
    assert np.abs(by_a.tension_n[both] - by_f.tension_n[both]).max() > 1.0
    assert ((by_a.activation[both] ** 2).sum(1) <= (by_f.activation[both] ** 2).sum(1) + 1e-9).all()
    assert ((by_f.tension_n[both] ** 2).sum(1) <= (by_a.tension_n[both] ** 2).sum(1) + 1e-6).all()


def test_faults_bound_the_answer(elbow, postures):
    """A cut muscle carries nothing, a weakened one stays under its limit, a jammed motor under its length."""
    healthy = elbow.solve(postures)
    held = []
    for b in np.flatnonzero(healthy.ok):  # postures that still hold under all three faults
        l_fixed = healthy.l_motor_m[b, 3] - 0.0005  # the jam pulls BIClong's motor 0.5 mm in: a tension floor
        weak = 200.0
        faults = {"cut": ["BRA_tendon"], "weak": {"TRIlat_tendon": weak}, "jam": {"BIClong_tendon": l_fixed}}
        result = elbow.solve(postures[b:b + 1], faults)
        if result.status[0] in (Status.OK, Status.ACTIVATION_ABOVE_ONE):
            held.append(b)
            assert result.tension_n[0, 5] == 0.0 and result.activation[0, 5] == 0.0
            assert result.tension_n[0, 1] <= weak + 1e-9
            assert result.l_motor_m[0, 3] <= l_fixed + 1e-12 and result.tension_n[0, 3] > healthy.tension_n[b, 3]
            if result.ok[0]:
                assert mujoco_residual_nm(elbow, result)[0][0] <= 1e-6
    assert len(held) >= 3


def test_infeasible_rows_are_nan_and_named(elbow, postures):
    """Cutting every flexor leaves postures nothing can hold: status infeasible, NaN answers."""
    result = elbow.solve(postures, {"cut": ["BIClong_tendon", "BICshort_tendon", "BRA_tendon"]})
    bad = np.array([s is Status.INFEASIBLE for s in result.status])
    assert bad.any()
    assert np.isnan(result.tension_n[bad]).all() and np.isnan(result.activation[bad]).all()


def test_spring_body_tension_objective_is_the_dataset_qp():
    """A body without muscle actuators (the paper arm): min ||f - f_ref||^2 over [0, f_max], as the dataset solves it,
    equal to proxsuite's to 1e-8 N; activations are None."""
    rng = np.random.default_rng(2)
    body = StaticBody("paper_arm")
    q = body.model.sample_q(rng, 40)
    f_ref = 150.0 * rng.random((40, body.model.n_muscles))
    result = static_optimization(body, q, f_ref=f_ref)
    assert result.objective == "tension" and result.activation is None and result.ok.sum() >= 20
    _, G, tau = body.model.kinematics(q)
    ok = result.ok
    lo, hi = np.zeros((ok.sum(), 6)), np.full((ok.sum(), 6), 150.0)
    f, solved = _reference(G[ok], tau[ok], f_ref[ok], lo, hi)
    assert solved.all() and np.abs(f - result.tension_n[ok]).max() <= 1e-8
    with pytest.raises(BodySchemaInputError, match="objective='activation' needs"):
        body.solve(q, objective="activation")


@pytest.mark.parametrize("call, match", [
    (lambda b: b.solve([[0.0, 9.0]]), "outside its range"),
    (lambda b: b.solve([[0.0, np.nan]]), "NaN"),
    (lambda b: b.solve([[0.0, 1.0]], {"cut": ["nope"]}), "unknown muscle 'nope'"),
    (lambda b: b.solve([[0.0, 1.0]], {"weak": {"BRA": 50.0}}), r"unknown muscle 'BRA' \(did you mean 'BRA_tendon'\?\)"),
    (lambda b: b.solve([[0.0, 1.0]], {"snap": ["BRA_tendon"]}), "unknown fault kind"),
    (lambda b: b.solve([[0.0, 1.0]], objective="effort"), "objective='effort'"),
])
def test_bad_input_is_one_clear_error(elbow, call, match):
    with pytest.raises(BodySchemaInputError, match=match):
        call(elbow)


def test_top_level_export():
    import lightning_bodyschema as package

    assert package.static_optimization is static_optimization and package.StaticBody is StaticBody


@pytest.mark.slow
def test_myoarm_postures_hold_in_mujoco():
    """myoArm (7 free joints, 50 muscles) with the config's locks: ok rows balance in MuJoCo and stay."""
    import yaml

    with open("configs/myoarm.yaml") as fh:
        locks = yaml.safe_load(fh)["data"]["locked_joints"]
    body = StaticBody("myo:myoarm", locked_joints=locks)
    result = body.solve(body.model.sample_q(np.random.default_rng(0), 12), {"cut": ["BIClong_tendon"]})
    assert result.ok.sum() >= 4
    residual, miss = mujoco_residual_nm(body, result)
    assert residual[result.ok].max() <= 1e-6 and miss[result.ok].max() <= 1e-8
    assert mujoco_drift_rad(body, result.take(np.flatnonzero(result.ok)[:4]), 0.3).max() < 1e-3


@pytest.mark.slow
def test_readme_example(readme_block):
    """README "Static optimization": the Python block runs from the repository root and its answers are physical."""
    namespace = readme_block("static_optimization(arm")
    ruptured, standing = namespace["ruptured"], namespace["standing"]
    assert ruptured.tension_n.shape == (1000, 50) and ruptured.ok.mean() > 0.3
    assert (ruptured.tension_n[ruptured.ok, ruptured.muscles.index("BIClong_tendon")] == 0).all()
    assert standing.tension_n.shape == (1, 80)
