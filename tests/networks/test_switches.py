"""Where a learned path switches (networks.switches): the distance to a gate's zero set, against a known surface."""
import numpy as np
import torch

from lightning_bodyschema.networks.per_muscle import PerMusclePath
from lightning_bodyschema.networks.switches import JUMP_FLOOR_M, SWITCH_REACH_RAD, PostureSwitches, switch_diagnostics

CROSSING = np.array([[1, 1, 0], [0, 1, 0], [1, 0, 1]], dtype=bool)  # muscle 0 jumps; 1 and 2 are smooth
NORMAL = np.array([1.0, 0.3, 0.0])  # muscle 0's switching surface: NORMAL . x = 0.2 (normalized units)
HALF_RANGE = torch.tensor([0.5, 2.0, 1.0], dtype=torch.float64)  # rad per normalized unit, unequal on purpose


def _fitted():
    """A path fitted to three random polynomials of degree <= 3, muscle 0's plus 1.5 and other slopes beyond the
    plane (as tests/networks/test_branches.py: a jump of 0.9 to 2.1)."""
    path = PerMusclePath(CROSSING, degree=8, n_hidden=0, branches=2, gate_degree=2).double()
    g = torch.Generator().manual_seed(3)
    first = torch.randn(path.coef.shape, dtype=torch.float64, generator=g) * (
        (path.exponents.sum(1) <= 3)[None, :] & path.term_mask)
    linear = (path.exponents.sum(1) == 1) & path.term_mask[0]
    second = first[0] + 0.3 * torch.randn(path.coef.shape[1], dtype=torch.float64, generator=g) * linear
    second[0] += 1.5  # the constant term
    x = torch.rand(20000, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(4)) * 2 - 1
    phi = path.basis(x)[0]
    y = phi @ first.T
    y[:, 0] = torch.where(torch.as_tensor(x.numpy() @ NORMAL > 0.2), phi @ second, y[:, 0])
    path.fit_polynomial(x, y)
    return path


def switch_distance(path, x, length_scale_m):
    """``PostureSwitches``' answer at normalized postures ``x``: radians ``x * HALF_RANGE`` in a range of
    ``+-HALF_RANGE`` (its normalization gives ``x`` back)."""
    return PostureSwitches(path, path.snapshot(), -HALF_RANGE, HALF_RANGE, length_scale_m).on_host()(
        (x * HALF_RANGE).numpy())


def _true_distance_rad(x):
    """Distance [rad] from ``x`` to the plane in joint space: the plane's normal in rad is NORMAL / HALF_RANGE."""
    normal_rad = NORMAL / HALF_RANGE.numpy()
    return np.abs(x @ NORMAL - 0.2) / np.linalg.norm(normal_rad)


def test_the_distance_to_a_learned_switch_is_the_distance_to_the_true_surface_near_it():
    path = _fitted()
    assert PostureSwitches(path, path.snapshot(), -HALF_RANGE, HALF_RANGE, torch.ones(3)).muscles.tolist() == [0]
    x = torch.rand(3000, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(5)) * 1.8 - 0.9
    distance, muscle = switch_distance(path, x, torch.ones(3, dtype=torch.float64))
    truth = _true_distance_rad(x.numpy())
    near = truth < 0.1  # where the flag matters: within 0.1 rad (a tenth of the smallest joint's half range)
    assert near.sum() > 100 and (muscle == 0).all()
    # the gate is placed from samples (spacing ~0.01 normalized, ~0.005-0.02 rad): within that of the surface
    assert np.percentile(np.abs(distance[near] - truth[near]), 90) < 0.01
    flagged = switch_diagnostics(distance, muscle)["near_path_switch"]
    assert flagged[truth < 0.5 * SWITCH_REACH_RAD].all() and not flagged[truth > 2 * SWITCH_REACH_RAD].any()


def test_a_gate_whose_branches_agree_within_the_floor_is_no_switch():
    """The same path read in units where its jump (0.9 to 2.1 length units) is below ``JUMP_FLOOR_M``: no switch
    within reach (beyond it the branches are not compared: nothing is flagged there anyway)."""
    path = _fitted()
    x = torch.rand(200, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(7)) * 1.8 - 0.9
    offset_rad = torch.linspace(-SWITCH_REACH_RAD, SWITCH_REACH_RAD, 200, dtype=torch.float64)  # across the plane
    x[:, 0] = 0.2 - 0.3 * x[:, 1] + offset_rad * float(np.linalg.norm(NORMAL / HALF_RANGE.numpy()))
    scale_m = torch.full((3,), 0.5 * JUMP_FLOOR_M / 2.1, dtype=torch.float64)  # the largest jump: half the floor
    near = _true_distance_rad(x.numpy()) < 0.5 * SWITCH_REACH_RAD
    distance, muscle = switch_distance(path, x, scale_m)
    assert near.sum() > 50 and np.isinf(distance[near]).all() and (muscle[near] == -1).all()
    assert not switch_diagnostics(distance, muscle)["near_path_switch"].any()
    flagged = switch_diagnostics(*switch_distance(path, x, 4 * scale_m))["near_path_switch"]
    assert flagged[near].all()  # the smallest jump: twice the floor


def test_a_path_without_switches_reports_none():
    path = PerMusclePath(CROSSING, degree=4, n_hidden=0).double()
    x = torch.rand(50, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(6)) * 2 - 1
    path.fit_polynomial(x, x[:, :3] ** 2)
    distance, muscle = switch_distance(path, x, torch.ones(3, dtype=torch.float64))
    assert np.isinf(distance).all() and (muscle == -1).all()
    assert not switch_diagnostics(distance, muscle)["near_path_switch"].any()
