"""The projection samplers inpaint with: known answers on a spring whose values are computed by hand."""
import numpy as np
import pytest
import torch
from physics_checks import rounding_tol

from lightning_bodyschema.faults import Faults
from lightning_bodyschema.faults.constraints import AdaptWeights
from lightning_bodyschema.faults.penalty import PenaltyBuilder
from lightning_bodyschema.faults.projection import projection_for
from lightning_bodyschema.sim import SpringParams, elongation_from_tension, tension_from_elongation

SPRING = SpringParams()
# to normalized units and back (and, in spring mode, g = l + e less e): a few roundings at the SI values' scale
_ROUND_TRIP_ROUNDINGS = 16
MEAN = np.array([0.20, 0.25, 0.30, 40.0, 50.0, 60.0])  # 3 muscles: l_motor [m] then f [N]
STD = np.array([0.01, 0.02, 0.01, 20.0, 30.0, 25.0])


def _projection(faults: Faults, mode="spring", f_max=150.0):
    builder = PenaltyBuilder(AdaptWeights(1, 1, 1, 1, 1), STD[:3], STD[3:], MEAN, STD, torch.float64)
    penalty = builder(faults.constraints(f_max))
    return projection_for(penalty, mode, MEAN, STD, SPRING)


def _normalized(l_motor, f):
    return torch.as_tensor((np.concatenate([l_motor, f], -1) - MEAN) / STD)


def _si(x_n):
    x = x_n.numpy() * STD + MEAN
    return x[..., :3], x[..., 3:]


def test_a_jammed_motor_stops_at_its_jam_and_its_spring_gives_the_tension():
    l, f = np.array([[0.21, 0.25, 0.30]]), np.array([[50.0, 40.0, 60.0]])
    l_fixed = 0.207  # the motor must pay out 3 mm it cannot
    faults = Faults(np.zeros((1, 3), bool), np.array([[True, False, False]]), np.array([[l_fixed, np.nan, np.nan]]))
    l_new, f_new = _si(_projection(faults)(_normalized(l, f)))
    g = l[0, 0] + elongation_from_tension(f[0, 0], SPRING)  # eq:muscle-elongation-inv: the geometric length kept
    assert l_new[0, 0] == pytest.approx(l_fixed, abs=1e-12)
    assert f_new[0, 0] == pytest.approx(tension_from_elongation(g - l_fixed, SPRING), rel=1e-9)
    assert f_new[0, 0] > f[0, 0]  # held back, the muscle stretches: more tension
    # the other muscles untouched but for the round trip (~1e-15 m, ~2e-13 N); a coupled update moves them by mm, N
    np.testing.assert_allclose(l_new[:, 1:], l[:, 1:], rtol=0, atol=rounding_tol(_ROUND_TRIP_ROUNDINGS, l, MEAN[:3]))
    np.testing.assert_allclose(f_new[:, 1:], f[:, 1:], rtol=0, atol=rounding_tol(_ROUND_TRIP_ROUNDINGS, f, MEAN[3:]))


def test_a_cut_muscle_goes_slack_where_its_geometry_is():
    l, f = np.array([[0.21, 0.25, 0.30]]), np.array([[50.0, 40.0, 60.0]])
    faults = Faults(np.array([[False, True, False]]), np.zeros((1, 3), bool), np.full((1, 3), np.nan))
    l_new, f_new = _si(_projection(faults)(_normalized(l, f)))
    assert f_new[0, 1] == pytest.approx(0.0, abs=1e-9)
    assert l_new[0, 1] == pytest.approx(l[0, 1] + elongation_from_tension(40.0, SPRING), abs=1e-12)


def test_a_tension_above_a_weakened_limit_is_capped_and_the_motor_pays_out():
    l, f = np.array([[0.21, 0.25, 0.30]]), np.array([[50.0, 40.0, 60.0]])
    faults = Faults(np.zeros((1, 3), bool), np.zeros((1, 3), bool), np.full((1, 3), np.nan),
                    f_max_n=np.array([[np.nan, np.nan, 30.0]]))
    l_new, f_new = _si(_projection(faults)(_normalized(l, f)))
    g = l[0, 2] + elongation_from_tension(60.0, SPRING)
    assert f_new[0, 2] == pytest.approx(30.0, abs=1e-9)
    assert l_new[0, 2] == pytest.approx(g - elongation_from_tension(30.0, SPRING), abs=1e-12)


def test_a_feasible_command_is_left_exactly_as_it_is_and_the_projection_is_idempotent():
    l, f = np.array([[0.21, 0.25, 0.30]]), np.array([[50.0, 40.0, 60.0]])
    faults = Faults(np.zeros((1, 3), bool), np.array([[True, False, False]]), np.array([[0.215, np.nan, np.nan]]),
                    l_band_m=np.array([[[np.nan] * 2, [0.24, 0.26], [np.nan] * 2]]))
    for mode in ("box", "spring"):
        proj = _projection(faults, mode)
        x = _normalized(l, f)
        assert proj.offset(x).abs().max() < 1e-12, mode  # exactly 0 in box mode, rounding in spring mode
        bad = _normalized(l + 0.02, f)
        once = proj(bad)
        # in normalized units: the round trip's roundings at the SI values' scale over STD (~1e-13); a second
        # projection that moves the command again is off by O(0.1)
        torch.testing.assert_close(proj(once), once, rtol=0,
                                   atol=rounding_tol(_ROUND_TRIP_ROUNDINGS, once, MEAN / STD))


def test_box_mode_clamps_into_the_constraints_box():
    l, f = np.array([[0.21, 0.25, 0.30]]), np.array([[50.0, 200.0, -5.0]])
    faults = Faults(np.array([[True, False, False]]), np.array([[False, False, True]]),
                    np.array([[np.nan, np.nan, 0.295]]))
    l_new, f_new = _si(_projection(faults, "box")(_normalized(l, f)))
    np.testing.assert_allclose(f_new, [[0.0, 150.0, 0.0]], atol=1e-9)
    np.testing.assert_allclose(l_new, [[0.21, 0.25, 0.295]], rtol=0, atol=rounding_tol(_ROUND_TRIP_ROUNDINGS, MEAN[:3]))
