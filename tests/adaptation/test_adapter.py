"""The adaptation pipeline: a prepared adapter returns what adapt returns, call after call; its steps are public."""
import numpy as np
import pytest
import torch
from physics_checks import mixed_faults, rounding_tol

from lightning_bodyschema.adaptation import check_postures, flag_infeasible, safe_command
from lightning_bodyschema.adaptation.command import FAULT_TOL_N, motor_length_range
from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.faults import Faults


def _assert_adapter_matches_adapt(schema, dm, **options):
    q, faults = mixed_faults(schema, dm)
    adapter, expected = schema.adapter(faults, **options), schema.adapt(q, faults, **options)
    for _ in range(2):  # reusable: a controller calls it every tick
        got = adapter(q)
        assert (got.status == expected.status).all()
        np.testing.assert_array_equal(got.l_motor_m, expected.l_motor_m)
        np.testing.assert_array_equal(got.f_n, expected.f_n)
    with pytest.raises(BodySchemaInputError, match="postures but"):
        adapter(q[:1])


def test_a_prepared_adapter_returns_what_adapt_returns_diffusion(diff60, dm):
    _assert_adapter_matches_adapt(diff60[0], dm, n_steps=20)


def test_a_prepared_adapter_returns_what_adapt_returns_latent(latent60, dm):
    _assert_adapter_matches_adapt(latent60, dm)


def test_safe_command_never_passes_a_non_finite_row_or_a_tension_outside_its_limits():
    faults = Faults.from_names(["a", "b"], cut=[["a"], [], [], ["a"]], weak=[{}, {"b": 40.0}, {}, {}])
    x = torch.tensor([[0.3, 0.3, 5.0, 80.0], [0.3, 0.3, -3.0, 90.0], [np.nan, 0.3, 10.0, 10.0],
                      [0.3, 0.3, 0.009, 80.0]], dtype=torch.float64)
    result = safe_command(x, faults, faults.f_limit(150.0))
    # a cut muscle pulling 5 N is no command; 9 mN is within the package's tolerance (FAULT_TOL_N)
    assert result.status.tolist() == ["fault_not_met", "ok", "non_finite", "ok"]
    np.testing.assert_array_equal(result.f_n[1], [0.0, 40.0])  # clipped into [0, f_max']
    np.testing.assert_array_equal(result.diagnostics["clipped_f_n"][:2], [[5.0, 80.0], [0.0, 40.0]])
    assert np.isnan(result.f_n[[0, 2]]).all() and np.isnan(result.l_motor_m[[0, 2]]).all()
    np.testing.assert_allclose(result.diagnostics["cut_violation_n"][[0, 1, 3]], [5.0, 0.0, 0.009])
    np.testing.assert_allclose(result.diagnostics["weak_violation_n"][:2], [0.0, 50.0])  # before the clip


def test_a_command_that_breaks_a_jam_or_band_beyond_the_tolerance_is_never_ok():
    """The band-above-jam case: no length meets both, so any command breaks one of them (fault_not_met, NaN)."""
    faults = Faults.from_names(["a", "b"], jam=[{"a": 0.30}, {"a": 0.30}, {"a": 0.30}, {}],
                               band=[{}, {}, {"a": [0.32, 0.35]}, {"b": [0.20, 0.25]}])
    x = torch.tensor([[0.300009, 0.3, 5.0, 5.0], [0.30002, 0.3, 5.0, 5.0], [0.30, 0.3, 5.0, 5.0],
                      [0.3, 0.2501, 5.0, 5.0]], dtype=torch.float64)
    result = safe_command(x, faults, faults.f_limit(150.0))
    assert result.status.tolist() == ["ok", "fault_not_met", "fault_not_met", "fault_not_met"]
    # a length less its bound, both decimals read into binary: a rounding each and one for the difference, at the
    # lengths' scale (~3e-16 m); a violation net of the tolerance (FAULT_TOL_M) would be off by 1e-5 m
    tol_m = rounding_tol(4, x[:, :2])
    np.testing.assert_allclose(result.diagnostics["jam_violation_m"], [9e-6, 2e-5, 0.0, 0.0], rtol=0, atol=tol_m)
    np.testing.assert_allclose(result.diagnostics["band_violation_m"], [0.0, 0.0, 0.02, 1e-4], rtol=0, atol=tol_m)
    assert np.isnan(result.l_motor_m[1:]).all() and np.isnan(result.f_n[1:]).all()


def test_a_finite_but_absurd_motor_length_is_out_of_range_never_ok():
    """A diverged guidance can stay finite (metres of motor length); such a row is no command."""
    faults = Faults.from_names(["a", "b"], n_cases=3)
    l_range = motor_length_range(np.array([0.3, 0.3, 50.0, 50.0]), np.array([0.01, 0.01, 20.0, 20.0]), 2)
    np.testing.assert_allclose(l_range, [[0.1, 0.1], [0.5, 0.5]])  # 20 spreads each way
    x = torch.tensor([[0.31, 0.29, 5.0, 80.0], [4.8, 0.3, 5.0, 80.0], [0.3, -3.9, 5.0, 80.0]], dtype=torch.float64)
    result = safe_command(x, faults, faults.f_limit(150.0), l_range)
    assert result.status.tolist() == ["ok", "out_of_range", "out_of_range"]
    assert np.isnan(result.l_motor_m[1:]).all() and np.isnan(result.f_n[1:]).all()
    np.testing.assert_allclose(result.diagnostics["l_motor_out_of_range_m"], [0.0, 4.3, 4.0])


def test_a_motor_length_at_or_below_zero_is_never_ok():
    """The plausible range (mean -+ 20 spreads) reaches below 0 m for widely spread muscles; a length does not."""
    faults = Faults.from_names(["a", "b"], n_cases=3)
    l_range = motor_length_range(np.array([0.05, 0.3, 50.0, 50.0]), np.array([0.01, 0.01, 20.0, 20.0]), 2)
    assert l_range[0, 0] < 0
    x = torch.tensor([[0.01, 0.3, 5.0, 80.0], [-0.04, 0.3, 5.0, 80.0], [0.0, 0.3, 5.0, 80.0]], dtype=torch.float64)
    limit = faults.f_limit(150.0)
    for result in (safe_command(x, faults, limit, l_range), safe_command(x, faults, limit)):  # with or without range
        assert result.status.tolist() == ["ok", "out_of_range", "out_of_range"]
        assert np.isnan(result.l_motor_m[1:]).all() and np.isnan(result.f_n[1:]).all()
    with pytest.raises(BodySchemaInputError, match="at or below 0 m"):
        Faults.from_names(["a", "b"], band={"a": [-0.05, -0.04]}, n_cases=1)


def test_the_physics_check_blanks_commands_no_physics_can_realize(diff60, dm):
    schema = diff60[0]
    q = dm.splits["val"][0][:2].numpy()
    names = schema.robot_model.muscle_names
    faults = Faults.from_names(names, cut=[names[:5], []])  # five of six muscles cut: nothing holds the arm
    q = check_postures(schema, q, len(faults))
    result = flag_infeasible(safe_command(schema.decode(schema.generate(schema.encode_q(torch.as_tensor(q)))),
                                          faults, faults.f_limit(schema.spring.f_max_n)),
                             schema.robot_model, q, faults, schema.spring)
    assert result.status.tolist() == ["infeasible", "ok"] and np.isnan(result.f_n[0]).all()
    assert np.isfinite(result.diagnostics["best_effort_f_n"][0]).all()
    assert result.diagnostics["cut_violation_n"][0] > FAULT_TOL_N  # its healthy command breaks the cuts too


def test_infeasible_is_reported_before_a_diverged_or_absurd_row(diff60, dm):
    """The physical reason wins: a case no command can hold is infeasible, whatever the sampler returned for it."""
    schema = diff60[0]
    q = check_postures(schema, dm.splits["val"][0][:3].numpy(), 3)
    names = schema.robot_model.muscle_names
    faults = Faults.from_names(names, cut=[names[:5], names[:5], []])  # five of six cut: nothing holds the arm
    x = schema.decode(schema.generate(schema.encode_q(torch.as_tensor(q))))
    x[0, 0], x[1, 0] = float("nan"), 1e3  # a diverged row and an absurd one
    l_range = motor_length_range(schema.normalizer.x_mean, schema.normalizer.x_std, schema.n_muscles)
    raw = safe_command(x, faults, faults.f_limit(schema.spring.f_max_n), l_range)
    assert raw.status.tolist() == ["non_finite", "out_of_range", "ok"]
    checked = flag_infeasible(raw, schema.robot_model, q, faults, schema.spring)
    assert checked.status.tolist() == ["infeasible", "infeasible", "ok"]
