"""The evaluator's posture solve on weakened muscles and banded motors (issue 48, item 6): it must move q_hat the
way MuJoCo's settle moves the same command, and leave a command that the fault does not touch exactly alone."""
import numpy as np
import pytest

from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.evaluation import FaultCases, ForwardSolverParams, evaluate_commands, solve_posture
from lightning_bodyschema.evaluation.forward_solver import classify_muscles
from lightning_bodyschema.evaluation.posture_command import prepare_command
from lightning_bodyschema.sim.settle import settle

N_CASES = 12


@pytest.fixture(scope="module")
def exact(healthy):
    """Exact equilibrium commands (q, l_motor, f) and each case's strongest muscle (taut, so a fault on it acts)."""
    q, l_motor, f = healthy.q[:N_CASES], healthy.l_motor[:N_CASES], healthy.f[:N_CASES]
    return q, l_motor, f, np.argmax(f, axis=1)


def _on(values, muscle, shape_tail=()):
    """(B, M, *shape_tail) NaN array holding ``values`` (B, *shape_tail) at each case's ``muscle``."""
    out = np.full((len(muscle), 6) + shape_tail, np.nan)
    out[np.arange(len(muscle)), muscle] = values
    return out


def _cases(q, cond, f_max=None, l_band=None):
    b = len(q)
    none = np.zeros((b, 6), bool)
    return FaultCases(q, none, none.copy(), np.full((b, 6), np.nan), np.full(b, cond), f_max=f_max, l_band=l_band)


def _direction_and_size(arm, cases, l_motor, f):
    """cos(q_hat - q_ref, q_settle - q_ref) (B,), E_q (B,) and E_q_phys (B,) of the same command."""
    ev = evaluate_commands(arm, cases, l_motor, f)
    phys = settle(arm, l_motor, f, cases)
    assert phys.settled.all()
    dq, dp = ev["q_hat"] - cases.q_ref, phys.q_settle - cases.q_ref
    cos = np.sum(dq * dp, axis=1) / (np.linalg.norm(dq, axis=1) * np.linalg.norm(dp, axis=1))
    return cos, ev["E_q"], phys.E_q_phys


def test_a_banded_motor_that_clips_moves_q_hat_as_the_settle_does(arm, exact):
    """Band [l - 4 mm, l - 2 mm] on a taut muscle: the winch stops 2 mm short, the arm swings ~0.01-0.02 rad. The
    band enters the solve exactly (a shorter rest length), so q_hat lands where MuJoCo rests, within the two
    readings' own difference (the solver's tension is the command's, settle's the spring's: a few percent)."""
    q, l_motor, f, muscle = exact
    lo_hi = np.stack([l_motor[np.arange(len(q)), muscle] - 0.004, l_motor[np.arange(len(q)), muscle] - 0.002], -1)
    cos, e_q, e_q_phys = _direction_and_size(arm, _cases(q, "BAND", l_band=_on(lo_hi, muscle, (2,))), l_motor, f)
    assert np.all(e_q_phys >= 0.005)  # the fault moves the arm: the comparison has something to compare
    assert np.all(cos >= 0.99)
    assert np.all(np.abs(e_q / e_q_phys - 1.0) <= 0.2)


def test_a_weakened_muscle_that_saturates_moves_q_hat_as_the_settle_does(arm, exact):
    """f_max' = half the command's tension: the muscle pulls f_max' and slips, the arm sags toward where MuJoCo
    rests. The posture solve has no tension stiffness (the other muscles pull their commanded tensions; only the
    length residuals resist), so, as on a cut muscle, it moves less far than the physics: same direction,
    a fraction of the distance."""
    q, l_motor, f, muscle = exact
    f_max = _on(0.5 * f[np.arange(len(q)), muscle], muscle)
    cos, e_q, e_q_phys = _direction_and_size(arm, _cases(q, "WEAK", f_max=f_max), l_motor, f)
    assert np.all(e_q_phys >= 0.01)
    assert np.median(cos) >= 0.9 and np.mean(cos > 0.5) >= 0.75
    assert np.all(e_q >= 1e-3)  # the healthy command alone rests within 1e-6 rad of q_ref
    assert np.median(e_q / e_q_phys) >= 0.1 and np.all(e_q <= 1.2 * e_q_phys)


def test_an_unsaturated_weak_muscle_and_an_unclipped_band_change_nothing(arm, exact):
    """A limit above the command's tension and a band around the command's length (a bound on it included) leave
    every output bit for bit as without the fault (and an all-NaN fault array is no fault)."""
    q, l_motor, f, muscle = exact
    rows = np.arange(len(q))
    limit = f[rows, muscle] + np.where(rows % 2 == 0, 1.0, 10.0)  # its slip margin 0.03-0.3 mm: never reached
    band = np.stack([l_motor[rows, muscle] - 0.001, l_motor[rows, muscle] + np.where(rows % 2, 0.0, 0.001)], -1)
    plain = evaluate_commands(arm, _cases(q, "NONE"), l_motor, f)
    for faulty in (_cases(q, "WEAK", f_max=_on(limit, muscle)), _cases(q, "BAND", l_band=_on(band, muscle, (2,))),
                   _cases(q, "NONE", f_max=np.full((len(q), 6), np.nan), l_band=np.full((len(q), 6, 2), np.nan))):
        met = evaluate_commands(arm, faulty, l_motor, f)
        for name in ("q_hat", "E_q", "E_tau", "status", "n_iter", "objective"):
            assert np.array_equal(met[name], plain[name]), name


def test_residual_jacobians_match_finite_differences(arm, healthy):
    """d r / d q = sign * G against central differences of r (float64), at postures 0.05 rad off the commands' own
    (every hinge state occurs), with a saturated weak muscle, a banded motor and a jam; and the torque balance
    counts the saturated muscle at f_max'."""
    rng = np.random.default_rng(3)
    b = 40
    q = np.clip(healthy.q[:b] + rng.uniform(-0.05, 0.05, (b, 2)), *arm.q_range.T)
    l_motor, f = healthy.l_motor[:b], healthy.f[:b]
    fix = np.zeros((b, 6), bool)
    fix[:, 0] = True
    l_fixed = np.where(fix, l_motor + 0.001, np.nan)
    f_max = np.full((b, 6), np.nan)
    f_max[:, 1], f_max[:, 0] = 0.5 * f[:, 1], 0.5 * f[:, 0]  # muscle 0: jammed and weakened
    f_max[:, 3] = f[:, 3] + 2.0  # below its limit: slips only past a ~0.1 mm margin
    band = np.full((b, 6, 2), np.nan)
    band[:, 2] = np.stack([l_motor[:, 2] - 0.003, l_motor[:, 2] - 0.001], -1)
    cmd, _ = prepare_command(arm, l_motor, f, q, np.zeros((b, 6), bool), fix, l_fixed, f_max_n=f_max,
                             l_band_m=band)
    params, h = ForwardSolverParams(), 1e-6

    def residuals(q_at):
        l_geo, G, bias = arm.kinematics(q_at)
        return classify_muscles(l_geo, cmd, params), G, bias

    (taut, r, sign), G, bias = residuals(q)
    checked = np.zeros((b, 6), bool)
    for k in range(2):
        step = h * np.eye(2)[k]
        (tp, rp, sp), _, _ = residuals(q + step)
        (tm, rm, sm), _, _ = residuals(q - step)
        smooth = (sp == sign) & (sm == sign) & (tp == taut) & (tm == taut)  # no kink within the stencil
        fd = (rp - rm) / (2 * h)
        np.testing.assert_allclose(fd[smooth], (sign * G[..., k])[smooth], rtol=0, atol=1e-6 * np.abs(G).max())
        checked |= smooth
    saturated = (cmd.slip_m == 0) & checked
    assert np.all(cmd.slip_m[:, 1] == 0) and np.all(cmd.slip_m[:, 3] > 0)  # at/above its limit: no margin left
    assert (saturated & (sign == -1)).any() and (saturated & (sign == 0) & taut).any()  # both hinge states checked
    margin = checked[:, 3] & taut[:, 3]
    assert (margin & (sign[:, 3] == -1)).any() and (margin & (sign[:, 3] == 0)).any()  # inside and past its margin
    f_eff = np.where(taut, np.fmin(f, f_max), 0.0)  # paper reading: jammed muscles pull nothing
    res = solve_posture(arm, l_motor, f, q, np.zeros((b, 6), bool), fix, l_fixed, f_max_n=f_max, l_band_m=band,
                        params=ForwardSolverParams(max_iter=1))
    np.testing.assert_allclose(res.tau_nm, -np.einsum("bmn,bm->bn", G, f_eff) - bias, rtol=0, atol=1e-9)


@pytest.mark.parametrize("f_max, band, match", [
    (np.full((2, 6), -1.0), None, "f_max_n has the limit -1.0"),
    (np.full((2, 6), np.inf), None, "finite and >= 0"),
    (np.full((2, 5), 1.0), None, "f_max_n has shape"),
    (None, np.stack([np.full((2, 6), 0.2), np.full((2, 6), 0.1)], -1), "lo > hi"),
    (None, np.stack([np.full((2, 6), 0.2), np.full((2, 6), np.nan)], -1), "NaN/inf bound"),
])
def test_bad_new_fault_arrays_are_refused_by_name(arm, healthy, f_max, band, match):
    none = np.zeros((2, 6), bool)
    with pytest.raises(BodySchemaInputError, match=match):
        solve_posture(arm, healthy.l_motor[:2], healthy.f[:2], healthy.q[:2], none, none, np.full((2, 6), np.nan),
                      f_max_n=f_max, l_band_m=band)
