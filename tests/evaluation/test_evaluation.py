"""Evaluation: forward posture solver, metrics, fault cases and feasibility (paper section IV-B)."""
import os
import subprocess
import sys

import numpy as np
import pytest

from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.evaluation import (
    FaultCases, ForwardSolverParams, SolverStatus, check_feasible, evaluate_commands,
    make_fault_cases, oracle_commands, solve_posture, summarize_metrics,
)
from lightning_bodyschema.sim import (
    MusculoskeletalModel, SpringParams, elongation_from_tension, generate_equilibrium_samples,
)


@pytest.fixture(scope="module")
def model():
    return MusculoskeletalModel("paper_arm")


@pytest.fixture(scope="module")
def data(model):
    return generate_equilibrium_samples(model, 200, seed=0)


def healthy_cases(q):
    """Cases with no fault at postures q (B, N)."""
    b, m = q.shape[0], 6
    return FaultCases(q.copy(), np.zeros((b, m), bool), np.zeros((b, m), bool), np.full((b, m), np.nan),
                      np.full(b, "NONE"))


def paper_cases(data, n=20, seed=0):
    return make_fault_cases(data.q[160:], data.l_motor[160:], n_per_condition=n, seed=seed)


# ---------------------------------------------------------------------------- forward solver
def test_healthy_commands_realize_their_own_posture(model, data):
    met = evaluate_commands(model, healthy_cases(data.q), data.l_motor, data.f)
    assert np.all(met["E_q"] <= 1e-6)
    assert np.all(met["E_tau"] <= 1e-6)  # the dataset QP holds equilibrium to 1e-6 N m
    assert np.all(np.isnan(met["E_cut"])) and np.all(np.isnan(met["E_fix"]))  # empty sets -> NaN
    assert np.all(met["converged"])


def test_solver_recovers_true_posture_from_a_perturbed_start(model, data):
    """q_ref 0.1 rad off on each joint: q_hat returns to the data posture.

    The only bias is the prior lambda_q ||q - q_ref||^2 (measured max 5.0e-5 rad for |dq_ref| = 0.14
    rad); without it the solver lands on the true posture to ~1e-13 rad.
    """
    q, n = data.q[:60], 60
    q_ref = np.clip(q + 0.1 * np.random.default_rng(1).choice([-1.0, 1.0], size=q.shape), -1, 1)
    none, nan = np.zeros((n, 6), bool), np.full((n, 6), np.nan)
    res = solve_posture(model, data.l_motor[:n], data.f[:n], q_ref, none, none, nan)
    assert np.all(res.converged)
    assert np.linalg.norm(res.q_hat - q, axis=1).max() <= 1e-4
    exact = solve_posture(model, data.l_motor[:n], data.f[:n], q_ref, none, none, nan,
                          params=ForwardSolverParams(lambda_q=0.0))
    assert np.linalg.norm(exact.q_hat - q, axis=1).max() <= 1e-9


def test_cutting_a_muscle_with_zero_tension_changes_nothing(model, data):
    rows, muscles = np.nonzero(data.f == 0.0)
    rows, first = np.unique(rows, return_index=True)
    assert len(rows) >= 5  # the QP puts ~5 % of tensions on the bound
    cases = healthy_cases(data.q[rows])
    cases.cut[np.arange(len(rows)), muscles[first]] = True
    cases.cond[:] = "CUT"
    met = evaluate_commands(model, cases, data.l_motor[rows], data.f[rows])
    assert np.all(met["E_cut"] == 0.0)
    assert np.all(met["E_q"] <= 1e-6) and np.all(met["E_tau"] <= 1e-6)


def test_jammed_motor_above_the_command_changes_nothing(model, data):
    """l_fixed 1 mm above l_motor: the command already obeys the jam (E_fix = 0), q_hat = q.

    Counting the jammed muscle's tension needs ``jammed_tension_in_torque``: the paper's taut set
    excludes jammed muscles, so its E_tau would miss their pull.
    """
    n = 20
    cases = healthy_cases(data.q[:n])
    cases.fix[:, 3] = True
    cases.l_fixed[:, 3] = data.l_motor[:n, 3] + 1e-3
    params = ForwardSolverParams(jammed_tension_in_torque=True)
    met = evaluate_commands(model, cases, data.l_motor[:n], data.f[:n], params=params)
    assert np.all(met["E_fix"] == 0.0)
    assert np.all(met["E_q"] <= 1e-6) and np.all(met["E_tau"] <= 1e-6)


def test_oracle_commands_score_perfectly(model, data):
    """Feasible cases have a perfect command; both torque conventions agree with their own QP."""
    cases = paper_cases(data)
    for counted in (False, True):
        feasible, l_motor, f = oracle_commands(model, cases, jammed_tension_in_torque=counted)
        sub = cases.take(feasible)
        met = evaluate_commands(model, sub, l_motor[feasible], f[feasible],
                                params=ForwardSolverParams(jammed_tension_in_torque=counted))
        assert np.nansum(met["E_cut"]) == 0.0 and np.nansum(met["E_fix"]) == 0.0
        assert np.all(met["E_q"] <= 1e-6) and np.all(met["E_tau"] <= 1e-6)


def test_solver_stays_inside_joint_limits(model, data):
    """A command made for a posture beyond the limit drives q_hat onto the limit, not past it."""
    q_out = np.array([[1.2, 0.3], [-0.4, -1.3]])
    l_geo, _, _ = model.kinematics(q_out)
    f = np.full((2, 6), 50.0)
    l_motor = l_geo - elongation_from_tension(f, SpringParams())
    cases = healthy_cases(np.array([[0.9, 0.3], [-0.4, -0.9]]))
    met = evaluate_commands(model, cases, l_motor, f)
    assert np.all(np.abs(met["q_hat"]) <= 1.0)
    np.testing.assert_allclose(met["q_hat"][[0, 1], [0, 1]], [1.0, -1.0])


def test_forward_difference_torque_jacobian_matches_central_differences(model, data):
    """The solver's d(sqrt(lambda_tau) tau / s_tau)/dq (forward differences) against central ones."""
    from lightning_bodyschema.evaluation import forward_solver as fs
    from lightning_bodyschema.evaluation.posture_command import prepare_command

    n, params = 8, ForwardSolverParams()
    cmd, _ = prepare_command(model, data.l_motor[:n], data.f[:n], data.q[:n], np.zeros((n, 6), bool),
                             np.zeros((n, 6), bool), np.full((n, 6), np.nan))
    q = data.q[:n] * 0.9  # off the data postures, all muscles keep their class for small steps
    point = fs._evaluate(model, q, cmd, params)
    h = 1e-5
    for k in range(2):
        e = np.eye(2)[k] * h
        central = (fs._evaluate(model, q + e, cmd, params).rt - fs._evaluate(model, q - e, cmd, params).rt) / (2 * h)
        np.testing.assert_allclose(point.Jt[:, :, k], central, atol=1e-6)


def test_nonfinite_command_is_reported_not_solved(model, data):
    f = data.f[:3].copy()
    f[1, 2] = np.nan
    met = evaluate_commands(model, healthy_cases(data.q[:3]), data.l_motor[:3], f)
    assert met["status"][1] == SolverStatus.NONFINITE_COMMAND
    assert np.isnan(met["E_q"][1]) and np.all(met["E_q"][[0, 2]] <= 1e-6)


def test_metrics_follow_the_paper_definitions(model, data):
    cases = paper_cases(data, n=5)
    l_motor, f = data.l_motor[:15].copy(), data.f[:15].copy()
    met = evaluate_commands(model, cases, l_motor, f)
    for row in range(len(cases)):
        cut, fix = cases.cut[row], cases.fix[row]
        if cut.any():
            assert met["E_cut"][row] == pytest.approx(np.mean(np.abs(f[row, cut])))
        if fix.any():
            over = np.maximum(0.0, l_motor[row, fix] - cases.l_fixed[row, fix])
            assert met["E_fix"][row] == pytest.approx(np.mean(over))
    assert np.all(np.isnan(met["E_fix"][cases.cond == "CUT"])) and np.all(np.isnan(met["E_cut"][cases.cond == "FIX"]))
    np.testing.assert_allclose(met["E_q"], np.linalg.norm(cases.q_ref - met["q_hat"], axis=1))
    summary = summarize_metrics(met, cases.cond)
    assert set(summary) == {"CUT", "FIX", "BOTH"} and summary["CUT"]["E_fix"]["n"] == 0


# ---------------------------------------------------------------------------- feasibility
def test_healthy_cases_are_feasible(model, data):
    feasible, f_star = check_feasible(model, healthy_cases(data.q[:50]))
    assert feasible.all()
    _, G, tau_bias = model.kinematics(data.q[:50])
    np.testing.assert_allclose(np.einsum("bmn,bm->bn", -G, f_star), tau_bias, atol=1e-6)


def test_cutting_every_flexor_where_flexion_is_needed_is_infeasible(model, data):
    _, _, tau_bias = model.kinematics(data.q)
    need = np.flatnonzero(tau_bias[:, 0] > 1.0)[:5]  # flexors give +torque: -G^T f > 0 for G < 0
    cases = healthy_cases(data.q[need])
    flexors = np.array(["flexor" in name for name in model.muscle_names])
    cases.cut[:, flexors] = True
    feasible, f_star = check_feasible(model, cases)
    assert not feasible.any() and np.all(np.isnan(f_star))


def test_jam_beyond_full_stretch_is_infeasible_and_slack_jam_is_harmless(model, data):
    q = data.q[:10]
    l_geo, _, _ = model.kinematics(q)
    cases = healthy_cases(q)
    cases.fix[:, 0] = True
    cases.l_fixed[:, 0] = l_geo[:, 0] + 0.01  # motor stuck 1 cm long: the muscle may go slack
    assert check_feasible(model, cases)[0].all()
    cases.l_fixed[:, 0] = l_geo[:, 0] - 2 * SpringParams().delta_max_m  # needs > f_max
    assert not check_feasible(model, cases)[0].any()


# ---------------------------------------------------------------------------- cases
def test_case_generator_is_seeded_and_draws_distinct_faults(data):
    a, b = paper_cases(data, n=40, seed=7), paper_cases(data, n=40, seed=7)
    for name in ("q_ref", "cut", "fix", "l_fixed", "cond"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert not np.array_equal(paper_cases(data, n=40, seed=8).cut, a.cut)
    expect = {"CUT": (2, 0), "FIX": (0, 2), "BOTH": (1, 1)}
    for cond, (n_cut, n_fix) in expect.items():
        rows = a.cond == cond
        assert rows.sum() == 40
        assert np.all(a.cut[rows].sum(1) == n_cut) and np.all(a.fix[rows].sum(1) == n_fix)
    assert not np.any(a.cut & a.fix)


def test_faulty_muscles_are_uniform_and_l_fixed_comes_from_another_posture(data):
    pool_q, pool_l = data.q[160:], data.l_motor[160:]
    cases = make_fault_cases(pool_q, pool_l, n_per_condition=400, seed=1)
    counts = (cases.cut | cases.fix).sum(0)
    expected = counts.sum() / 6
    assert np.all(np.abs(counts - expected) < 5 * np.sqrt(expected))  # ~5 sigma
    for row in np.flatnonzero(cases.fix.any(1))[:50]:
        j = np.flatnonzero(cases.fix[row])
        src = np.flatnonzero(np.all(pool_l[:, j] == cases.l_fixed[row, j], axis=1))
        assert src.size == 1 and not np.array_equal(pool_q[src[0]], cases.q_ref[row])


def test_npz_round_trip_is_exact_and_atomic(data, tmp_path):
    cases = paper_cases(data)
    path = tmp_path / "cases.npz"
    cases.save(path)
    assert os.listdir(tmp_path) == ["cases.npz"]  # no temp file left behind
    back = FaultCases.load(path, n_joints=2, n_muscles=6)
    for name in ("q_ref", "cut", "fix", "l_fixed", "cond"):
        np.testing.assert_array_equal(getattr(back, name), getattr(cases, name))
        assert getattr(back, name).dtype == getattr(cases, name).dtype
    assert set(np.load(path).files) == {"q_ref", "cut", "fix", "l_fixed", "cond"}


@pytest.mark.parametrize("bad, name", [
    (lambda a: a["q_ref"].__setitem__((0, 0), np.nan), "q_ref"),
    (lambda a: a.__setitem__("cut", a["cut"][:, :5]), "cut"),
    (lambda a: a.__setitem__("fix", a["fix"].astype(int)), "fix"),
    (lambda a: a["l_fixed"].__setitem__(a["fix"], np.nan), "l_fixed"),
    (lambda a: a.__setitem__("cond", a["cond"][:-1]), "cond"),
    (lambda a: a.pop("l_fixed"), "l_fixed"),
])
def test_bad_npz_raises_input_error_naming_the_array(data, tmp_path, bad, name):
    cases = paper_cases(data)
    arrays = {k: getattr(cases, k).copy() for k in ("q_ref", "cut", "fix", "l_fixed", "cond")}
    bad(arrays)
    path = tmp_path / "bad.npz"
    np.savez(path, **arrays)
    with pytest.raises(BodySchemaInputError, match=name):
        FaultCases.load(path)


def test_load_checks_model_sizes(data, tmp_path):
    path = tmp_path / "c.npz"
    paper_cases(data).save(path)
    with pytest.raises(BodySchemaInputError, match="muscles"):
        FaultCases.load(path, n_muscles=8)


# ---------------------------------------------------------------------------- boundary
def test_evaluation_does_not_import_lightning():
    code = ("import sys, lightning_bodyschema.evaluation; "
            "bad = [m for m in sys.modules if m.split('.')[0] in ('lightning', 'pytorch_lightning')]; "
            "print(bad); sys.exit(1 if bad else 0)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr


# ---------------------------------------------------------------------------- case files from other programs
def _file_with(tmp_path, name, arrays):
    path = tmp_path / f"{name}.npz"
    np.savez(path, **arrays)
    return path


@pytest.mark.parametrize("filler", [0.0, 0.151, -3.0])
def test_values_where_a_muscle_has_no_such_fault_are_ignored(data, tmp_path, filler):
    """l_fixed where not jammed, f_max on a cut muscle, and f_max / l_band outside the file's weak / band masks:
    any finite filler loads exactly as NaN; the masks themselves are not kept."""
    cases = paper_cases(data)
    weak, band = np.zeros_like(cases.cut), np.zeros_like(cases.cut)
    weak[:, 0] = ~cases.cut[:, 0]
    band[:, 1] = ~cases.cut[:, 1]
    f_max = np.where(weak, 40.0, np.nan)
    l_band = np.where(band[..., None], [0.30, 0.32], np.nan)
    clean = FaultCases(cases.q_ref, cases.cut, cases.fix, cases.l_fixed, np.full(len(cases), "MIXED"), f_max, l_band)
    messy = {**clean.arrays(), "l_fixed": np.where(cases.fix, cases.l_fixed, filler),
             "f_max": np.where(weak, 40.0, filler), "l_band": np.where(band[..., None], [0.30, 0.32], filler),
             "weak": weak, "band": band}
    loaded = FaultCases.load(_file_with(tmp_path, "messy", messy))
    for name, array in clean.arrays().items():
        np.testing.assert_array_equal(getattr(loaded, name), array)
    assert sorted(loaded.arrays()) == sorted(clean.arrays())
    # f_max on a cut muscle means nothing (the muscle carries no tension at all)
    on_cut = FaultCases(cases.q_ref, cases.cut, cases.fix, cases.l_fixed, cases.cond,
                        f_max=np.where(cases.cut, 10.0 + filler, np.nan))
    assert not on_cut.weak.any() and set(on_cut.cond.tolist()) == {"CUT", "FIX", "BOTH"}


def test_a_jammed_muscle_needs_a_finite_l_fixed_and_masks_must_fit(data, tmp_path):
    cases = paper_cases(data)
    arrays = {k: getattr(cases, k).copy() for k in ("q_ref", "cut", "fix", "l_fixed", "cond")}
    arrays["l_fixed"] = np.where(cases.fix, np.nan, 0.0)
    with pytest.raises(BodySchemaInputError, match="jammed muscle has a NaN/inf l_fixed"):
        FaultCases.load(_file_with(tmp_path, "nan_jam", arrays))
    arrays = {**cases.arrays(), "f_max": np.full(cases.cut.shape, 50.0), "weak": np.ones(5, bool)}
    with pytest.raises(BodySchemaInputError, match=r"weak must be a bool \(B, M\) mask"):
        FaultCases.load(_file_with(tmp_path, "bad_mask", arrays))
