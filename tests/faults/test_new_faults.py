"""Beyond the paper: weakened muscles, length-banded motors and task-space targets.

One briefly trained diffusion schema for the module (as in test_adaptation.py); the evaluator parts
(feasibility bounds, E_weak / E_band, settle) run on exact healthy samples and oracle commands.
"""

import numpy as np
import pytest
import torch

from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.evaluation import (
    EXTRA_METRICS, FaultCases, band_error, check_feasible, condition_of, evaluate_commands, oracle_commands,
    tension_bounds, weak_error,
)
from lightning_bodyschema.sim.settle import settle
from lightning_bodyschema.faults import Faults
from lightning_bodyschema.sim import SpringParams, elongation_from_tension, tension_from_elongation
from physics_checks import torque_residual

M = 6
NAMES = ["shoulder_flexor", "shoulder_extensor", "elbow_flexor", "elbow_extensor", "biarticular_flexor",
         "biarticular_extensor"]
SPRING = SpringParams()


@pytest.fixture(scope="module")
def diffusion(diff400):
    return diff400  # conftest: one 400-epoch schema for tests/adaptation and tests/faults


def _val(dm, n):
    return dm.splits["val"][0][:n].numpy()


# ---------------------------------------------------------------------------- the Faults API
def test_from_names_weak_and_band_apply_per_case_or_to_every_case():
    faults = Faults.from_names(NAMES, weak={"elbow_flexor": 60.0}, n_cases=3)
    assert faults.f_max_n.shape == (3, M) and (faults.f_max_n[:, 2] == 60.0).all()
    assert faults.weak.sum() == 3 and np.isnan(faults.f_max_n[:, [0, 1, 3, 4, 5]]).all()
    np.testing.assert_array_equal(faults.f_limit(150.0)[0], [150, 150, 60, 150, 150, 150])
    faults = Faults.from_names(NAMES, cut=[[0], []], band=[{}, {"elbow_extensor": [0.10, 0.12], 5: (0.5, 0.5)}])
    assert faults.band.tolist() == [[False] * 6, [False, False, False, True, False, True]]
    np.testing.assert_array_equal(faults.l_band_m[1, 3], [0.10, 0.12])
    assert faults.f_max_n is None and faults.take([1]).l_band_m.shape == (1, M, 2)


@pytest.mark.parametrize("kwargs, message", [
    ({"band": [{"elbow_flexor": [0.12, 0.11]}]}, "lo > hi"),
    ({"band": [{"elbow_flexor": [0.12]}]}, r"\[lo, hi\]"),
    ({"band": [{"elbow_flexor": [0.1, float("nan")]}]}, "finite"),
    ({"band": [{"elbow_flexor": [0.1, 0.2]}], "cut": [["elbow_flexor"]]}, "both cut and length-banded"),
    ({"weak": [{"elbow_flexor": -1.0}]}, "negative"),
    ({"weak": [{"elbow_flexor": "strong"}]}, "finite number"),
    ({"weak": [{"no_such_muscle": 50.0}]}, "unknown muscle"),
])
def test_bad_new_faults_are_refused(kwargs, message):
    with pytest.raises(BodySchemaInputError, match=message):
        Faults.from_names(NAMES, **kwargs)


def test_band_arrays_are_validated():
    faults = Faults.none(2, M)
    faults.l_band_m = np.full((2, M), np.nan)
    with pytest.raises(BodySchemaInputError, match=r"l_band_m has shape \(2, 6\); expected \(B, 6, 2\)"):
        faults.validate(M)
    faults.l_band_m = np.full((2, M, 2), np.nan)
    faults.l_band_m[1, 4] = [0.2, np.inf]
    with pytest.raises(BodySchemaInputError, match=r"NaN/inf bound \(case 1, muscle index \[4\]"):
        faults.validate(M)


# ---------------------------------------------------------------------------- adaptation
@pytest.mark.parametrize("muscle", range(M))
def test_a_weakened_muscle_stays_under_its_limit_and_the_others_compensate(diffusion, muscle):
    schema, dm = diffusion
    q = _val(dm, 16)
    plain_l, plain_f = schema.infer(q)
    f_max = np.full(plain_f.shape, np.nan)
    f_max[:, muscle] = 0.5 * np.clip(plain_f[:, muscle], 0, None)  # half of what the healthy command asks for
    faults = Faults(np.zeros((16, M), bool), np.zeros((16, M), bool), np.full((16, M), np.nan), f_max_n=f_max)
    result = schema.adapt(q, faults, check_physics=False)
    assert (result.status == "ok").all()
    assert np.median(plain_f[:, muscle] - f_max[:, muscle]) > 10.0  # the healthy command breaks the limit
    assert (result.f_n[:, muscle] <= f_max[:, muscle] + 0.5).all()
    assert result.diagnostics["weak_violation_n"].max() < 0.5  # met by the guidance, not by the clip
    assert np.median(torque_residual(schema.robot_model, q, result.f_n)) <= np.median(torque_residual(schema.robot_model, q, plain_f)) + 1.0


def test_weak_from_names_reaches_the_command_and_its_clip(diffusion):
    schema, dm = diffusion
    q = _val(dm, 8)
    result = schema.adapt(q, Faults.from_names(schema.robot_model.muscle_names, weak={"elbow_flexor": 40.0},
                                               n_cases=8), check_physics=False)
    assert (result.status == "ok").all() and (result.f_n[:, 2] <= 40.0).all()
    assert result.f_n[:, [0, 1, 3, 4, 5]].max() > 40.0  # only the weakened muscle is held down


@pytest.mark.parametrize("side", ["above", "below"])
@pytest.mark.parametrize("muscle", range(M))
def test_a_banded_motor_stays_inside_its_band(diffusion, muscle, side):
    schema, dm = diffusion
    q = _val(dm, 12)
    plain_l, plain_f = schema.infer(q)
    shift = np.array([0.002, 0.004]) * (1 if side == "above" else -1)
    band = np.full(plain_l.shape + (2,), np.nan)
    band[:, muscle] = np.sort(plain_l[:, muscle, None] + shift, axis=1)  # excludes the healthy command by 2 mm
    faults = Faults(np.zeros((12, M), bool), np.zeros((12, M), bool), np.full((12, M), np.nan), l_band_m=band)
    result = schema.adapt(q, faults, check_physics=False)
    assert (result.status == "ok").all()
    lo, hi, l_motor = band[:, muscle, 0], band[:, muscle, 1], result.l_motor_m[:, muscle]
    assert ((lo - 1e-4 <= l_motor) & (l_motor <= hi + 1e-4)).all()
    assert result.diagnostics["band_violation_m"].max() <= 1e-4
    assert np.median(torque_residual(schema.robot_model, q, result.f_n)) <= np.median(torque_residual(schema.robot_model, q, plain_f)) + 1.0


def test_evaluator_scores_new_faults_of_adapted_commands(diffusion):
    schema, dm = diffusion
    q = _val(dm, 10)
    plain_l, plain_f = schema.infer(q)
    f_max, band = np.full((10, M), np.nan), np.full((10, M, 2), np.nan)
    f_max[:, 4] = 0.5 * plain_f[:, 4]
    band[:, 1] = plain_l[:, 1, None] + [-0.004, -0.002]
    cases = FaultCases(q, np.zeros((10, M), bool), np.zeros((10, M), bool), np.full((10, M), np.nan),
                       np.full(10, "MIXED"), f_max, band)
    adapted = schema.adapt(q, cases.faults, check_physics=False)
    met_plain = evaluate_commands(schema.robot_model, cases, plain_l, plain_f)
    met = evaluate_commands(schema.robot_model, cases, adapted.l_motor_m, adapted.f_n)
    assert np.median(met_plain["E_weak"]) > 10.0 and np.median(met_plain["E_band"]) > 1e-3
    assert met["E_weak"].max() == 0.0 and met["E_band"].max() <= 1e-4  # f is clipped; l_motor is not
    assert np.isnan(met["E_cut"]).all() and np.isnan(met["E_fix"]).all()


# ---------------------------------------------------------------------------- evaluator
def test_feasibility_bounds_of_weak_and_banded_muscles(arm, healthy):
    q, l_motor, f = healthy.q[:4], healthy.l_motor[:4], healthy.f[:4]
    l_geo = arm.kinematics(q)[0]
    f_max, band = np.full((4, M), np.nan), np.full((4, M, 2), np.nan)
    f_max[:, 0] = 30.0
    band[:, 1] = np.stack([l_motor[:, 1] - 0.001, l_motor[:, 1] + 0.001], axis=1)
    band[:, 2] = np.stack([l_geo[:, 2] + 0.01, l_geo[:, 2] + 0.02], axis=1)  # above l_geo: the wire is slack
    cases = FaultCases(q, np.zeros((4, M), bool), np.zeros((4, M), bool), np.full((4, M), np.nan),
                       condition_of(np.zeros((4, M)), np.zeros((4, M)), ~np.isnan(f_max), ~np.isnan(band).all(-1)),
                       f_max, band)
    assert (cases.cond == "MIXED").all()
    lo, hi, crossed, _ = tension_bounds(l_geo, cases.faults, SPRING)
    np.testing.assert_allclose(hi[:, 0], 30.0)
    np.testing.assert_allclose(lo[:, 1], tension_from_elongation(l_geo[:, 1] - band[:, 1, 1], SPRING))
    np.testing.assert_allclose(hi[:, 1], tension_from_elongation(l_geo[:, 1] - band[:, 1, 0], SPRING))
    assert ((lo[:, 1] <= f[:, 1]) & (f[:, 1] < hi[:, 1])).all()  # the healthy tension lies inside its band's range
    np.testing.assert_array_equal(hi[:, 2], 0.0)  # a band above l_geo allows only a slack wire
    np.testing.assert_array_equal(hi[:, 3:], 150.0)
    assert not crossed.any()
    # a jammed motor that must pull harder than its weakened limit: no command exists
    jammed = FaultCases(q, np.zeros((4, M), bool), np.eye(M, dtype=bool)[[3] * 4], np.where(np.eye(M)[[3] * 4] > 0,
                        l_geo - elongation_from_tension(100.0, SPRING), np.nan), np.full(4, "MIXED"),
                        np.where(np.eye(M)[[3] * 4] > 0, 50.0, np.nan))
    assert tension_bounds(l_geo, jammed.faults, SPRING)[2].all() and not check_feasible(arm, jammed)[0].any()


def test_oracle_commands_of_new_faults_score_zero_and_settle_at_q_ref(arm, healthy, rng):
    n = 30
    q, l_motor, f = healthy.q[:n], healthy.l_motor[:n], healthy.f[:n]
    muscle = rng.integers(0, M, size=n)
    rows = np.arange(n)
    f_max, band = np.full((n, M), np.nan), np.full((n, M, 2), np.nan)
    f_max[rows[:15], muscle[:15]] = 0.6 * f[rows[:15], muscle[:15]]  # half the cases weak, half banded
    centre = l_motor[rows[15:], muscle[15:]] + rng.uniform(-0.003, 0.003, 15)
    band[rows[15:], muscle[15:]] = np.stack([centre - 0.001, centre + 0.001], axis=1)
    weak, banded = ~np.isnan(f_max), ~np.isnan(band).all(-1)
    none = np.zeros((n, M), bool)
    cases = FaultCases(q, none, none, np.full((n, M), np.nan), condition_of(none, none, weak, banded), f_max, band)
    assert cases.cond.tolist() == ["WEAK"] * 15 + ["BAND"] * 15
    feasible, l_oracle, f_oracle = oracle_commands(arm, cases, SPRING)
    assert feasible.sum() >= 10
    sub = cases.take(feasible)
    met = evaluate_commands(arm, sub, l_oracle[feasible], f_oracle[feasible], SPRING)
    assert np.nanmax(met["E_weak"]) <= 1e-6 and np.nanmax(met["E_band"]) <= 1e-9
    assert np.nanmax(met["E_tau"]) <= 1e-3 and np.nanmax(met["E_q"]) <= 1e-3
    physical = settle(arm, l_oracle[feasible], f_oracle[feasible], sub, spring=SPRING)
    assert physical.settled.all() and physical.E_q_phys.max() <= 1e-3
    for name in EXTRA_METRICS:
        assert met[name].shape == (len(sub),)
    assert np.isnan(weak_error(cases.take(rows >= 15), f[15:])).all()  # no weakened muscle: NaN, not 0
    assert np.isnan(band_error(cases.take(rows < 15), l_motor[:15])).all()


def test_settle_caps_a_weakened_muscle_and_stops_a_banded_motor(arm, healthy):
    """A weakened muscle that would have to pull harder than f_max' lets the arm sag; a band that cuts off
    the commanded motor length moves the rest posture."""
    q, l_motor, f = healthy.q[:8], healthy.l_motor[:8], healthy.f[:8]
    strong = np.argmax(f, axis=1)
    f_max, band = np.full((8, M), np.nan), np.full((8, M, 2), np.nan)
    f_max[np.arange(8), strong] = 0.3 * f[np.arange(8), strong]
    band[np.arange(8), strong] = l_motor[np.arange(8), strong, None] + [0.003, 0.004]  # loosens the wire 3 mm
    none = np.zeros((8, M), bool)
    for extra in ({"f_max": f_max}, {"l_band": band}):
        cases = FaultCases(q, none, none, np.full((8, M), np.nan), np.full(8, "MIXED"), **extra)
        healthy_cases = FaultCases(q, none, none, np.full((8, M), np.nan), np.full(8, "NONE"))
        assert settle(arm, l_motor, f, healthy_cases).E_q_phys.max() <= 1e-3
        moved = settle(arm, l_motor, f, cases)
        assert np.median(moved.E_q_phys) > 0.01
        if "f_max" in extra:
            assert (moved.f_settle_n[np.arange(8), strong] <= f_max[np.arange(8), strong] + 1e-9).all()


def test_fault_cases_stay_backwards_compatible(tmp_path, healthy):
    q, n = healthy.q[:5], 5
    none = np.zeros((n, M), bool)
    plain = FaultCases(q, none, none, np.full((n, M), np.nan), np.full(n, "NONE"))
    plain.save(tmp_path / "plain.npz")
    with np.load(tmp_path / "plain.npz") as data:
        assert sorted(data.files) == ["cond", "cut", "fix", "l_fixed", "q_ref"]  # the five arrays, as before
    assert FaultCases.load(tmp_path / "plain.npz").f_max is None and plain.faults.l_band_m is None
    band = np.full((n, M, 2), np.nan)
    band[2, 1] = [0.1, 0.2]
    new = FaultCases(q, none, none, np.full((n, M), np.nan), np.full(n, "BAND"), l_band=band)
    new.save(tmp_path / "new.npz")
    loaded = FaultCases.load(tmp_path / "new.npz", 2, M)
    np.testing.assert_array_equal(loaded.l_band, band)
    assert loaded.take([2]).band.tolist() == [[False, True, False, False, False, False]]
    with pytest.raises(BodySchemaInputError, match="l_band has shape"):
        FaultCases(q, none, none, np.full((n, M), np.nan), np.full(n, "BAND"), l_band=band[:, :, 0])


# ---------------------------------------------------------------------------- task-space targets
def test_adapt_to_target_reaches_100_random_targets_within_1_mm(diffusion):
    schema, _ = diffusion
    model = schema.robot_model
    q_true = model.sample_q(np.random.default_rng(7), 100)
    target = model.site_position(q_true, "hand")
    faults = Faults.from_names(model.muscle_names, cut=[["shoulder_flexor"]] * 50 + [[]] * 50)
    result = schema.adapt_to_target(target, faults, check_physics=False)
    assert (result.status == "ok").all()
    q_ref = result.diagnostics["q_ref"]
    lo, hi = model.q_range.T
    assert ((lo <= q_ref) & (q_ref <= hi)).all()
    reached = np.linalg.norm(model.site_position(q_ref, "hand") - target, axis=1)  # MuJoCo, not the twin
    assert reached.max() <= 1e-3
    assert np.abs(result.f_n[:50, 0]).max() < 1.0  # the faults still apply


def test_unreachable_targets_are_flagged_and_never_get_a_command(diffusion):
    schema, _ = diffusion
    model = schema.robot_model
    reachable = model.site_position(np.array([[0.3, -0.2]]), "hand")[0]
    target = np.array([reachable, [5.0, 5.0, 0.0], [0.0, 0.0, 0.0], reachable + [0.0, 0.0, 0.05]])
    result = schema.adapt_to_target(target, Faults.none(4, M))
    assert result.status.tolist() == ["ok", "unreachable", "unreachable", "unreachable"]
    assert np.isnan(result.l_motor_m[1:]).all() and np.isnan(result.f_n[1:]).all()
    assert np.isnan(result.diagnostics["q_ref"][1:]).all() and np.isfinite(result.diagnostics["q_closest"]).all()
    assert (result.diagnostics["target_error_m"][1:] > 0.01).all()
    assert np.isnan(result.diagnostics["f_clipped_n"][1:]).all()
    nothing = schema.adapt_to_target(target[1:2], Faults.none(1, M))
    assert nothing.status.tolist() == ["unreachable"]


def test_bad_target_requests_are_refused(diffusion):
    schema, _ = diffusion
    with pytest.raises(BodySchemaInputError, match="expected \\(B, 3\\)"):
        schema.adapt_to_target(np.zeros((2, 2)), Faults.none(2, M))
    with pytest.raises(BodySchemaInputError, match="one row per case"):
        schema.adapt_to_target(np.zeros((2, 3)), Faults.none(3, M))
    with pytest.raises(BodySchemaInputError, match="unknown site"):
        schema.adapt_to_target(np.zeros((1, 3)), Faults.none(1, M), site="foot")
    with pytest.raises(BodySchemaInputError, match="NaN"):
        schema.adapt_to_target(np.full((1, 3), np.nan), Faults.none(1, M))
