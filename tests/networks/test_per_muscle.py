"""PerMusclePath: each muscle's length over only its own joints; exact moment arms; least squares to 1e-9."""
import numpy as np
import pytest
import torch
from physics_checks import central_differences, rounding_tol, term_sum_tol

from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.networks.basis import legendre
from lightning_bodyschema.networks.per_muscle import PerMusclePath, muscle_degrees

CROSSING = np.array([[1, 0, 0], [1, 1, 0], [0, 1, 1], [1, 1, 1]], dtype=bool)  # 4 muscles, 3 joints
_EXTENSION_ROUNDINGS = 16  # p(c) + p'(c) (x - c) against the same by hand: x - c, a product and a sum, each re-rounded


def _random_path(n_hidden=2, seed=0):
    torch.manual_seed(seed)
    path = PerMusclePath(CROSSING, degree=4, hidden=8, n_hidden=n_hidden).double()
    with torch.no_grad():
        path.coef.normal_()
        for w in path.weights:
            w.normal_(0.0, 0.7)
        for b in path.biases:
            b.normal_(0.0, 0.3)
    return path


def test_moment_arms_are_central_differences_of_the_lengths_and_zero_off_the_crossed_joints():
    path = _random_path()
    x = torch.rand(32, 3, dtype=torch.float64) * 2 - 1
    y, dy = path.with_jacobian(x)
    # the same terms and layers, with or without the slopes: one rounding per term summed at the lengths' scale
    # (~6e-14 here); a term or the network's part missing from either moves lengths of order 1 by O(0.1)
    torch.testing.assert_close(y, path(x), rtol=0, atol=term_sum_tol(path, y))
    np.testing.assert_allclose(dy.detach().numpy(), central_differences(path, x), atol=1e-8, rtol=1e-7)
    crossed = torch.as_tensor(CROSSING)
    assert (dy[:, ~crossed] == 0).all()  # exactly, not approximately
    assert (dy[:, crossed].abs() > 1e-6).all()  # and a real slope where the muscle crosses


def test_uncrossed_joint_does_not_change_the_length():
    path = _random_path()
    x = torch.rand(16, 3, dtype=torch.float64) * 2 - 1
    moved = x.clone()
    moved[:, 2] = -moved[:, 2]  # muscles 0 and 1 do not cross joint 2
    assert torch.equal(path(x)[:, :2], path(moved)[:, :2])


def test_a_known_polynomial_is_recovered_to_1e9():
    path = PerMusclePath(CROSSING, degree=4, n_hidden=0).double()
    truth = torch.zeros_like(path.coef).normal_(generator=torch.Generator().manual_seed(1)) * path.term_mask
    x = torch.rand(3000, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(2)) * 2 - 1
    y = path.basis(x)[0] @ truth.T
    path.fit_polynomial(x, y)
    torch.testing.assert_close(path.coef, truth, atol=1e-9, rtol=0)
    x_new = torch.rand(200, 3, dtype=torch.float64) * 2 - 1
    torch.testing.assert_close(path(x_new), path.basis(x_new)[0] @ truth.T, atol=1e-9, rtol=0)


def test_legendre_values_and_slopes():
    x = torch.linspace(-1, 1, 11, dtype=torch.float64)[:, None]
    values, slopes = legendre(x, 3)
    torch.testing.assert_close(values[:, 0, 2], 1.5 * x[:, 0] ** 2 - 0.5)
    torch.testing.assert_close(values[:, 0, 3], 2.5 * x[:, 0] ** 3 - 1.5 * x[:, 0])
    torch.testing.assert_close(slopes[:, 0, 3], 7.5 * x[:, 0] ** 2 - 1.5)


def test_each_muscle_gets_the_highest_degree_within_its_term_budget():
    # C(1 + d, 1) = d + 1 terms over one joint, C(2 + d, 2) over two, C(3 + d, 3) over three
    np.testing.assert_array_equal(muscle_degrees(CROSSING, 14, 20), [14, 4, 4, 3])


def test_coefficients_stay_float64_when_the_module_is_cast():
    path = _random_path().float()
    assert path.coef.dtype == torch.float64 and path.weights[0].dtype == torch.float32


@pytest.mark.parametrize("kwargs, match", [({"degree": 0}, "degree"), ({"n_hidden": -1}, "n_hidden"),
                                           ({"max_terms": 1}, "max_terms")])
def test_bad_sizes_are_refused(kwargs, match):
    with pytest.raises(BodySchemaInputError, match=match):
        PerMusclePath(CROSSING, **kwargs)


def test_a_muscle_crossing_nothing_is_refused():
    with pytest.raises(BodySchemaInputError, match="every muscle crossing a joint"):
        PerMusclePath(np.array([[1, 0], [0, 0]], dtype=bool))


def test_outside_the_fitted_box_the_polynomial_extends_to_first_order():
    path = PerMusclePath(CROSSING, degree=6, n_hidden=0).double()
    x = torch.rand(2000, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(3)) * 1.2 - 0.6  # [-0.6, 0.6]
    path.fit_polynomial(x, torch.sin(3 * x) @ torch.ones(3, 4, dtype=torch.float64))
    edge = torch.tensor([[0.2, path.x_hi[1], 0.1]], dtype=torch.float64)
    beyond = edge + torch.tensor([[0.0, 0.3, 0.0]], dtype=torch.float64)
    y_edge, dy_edge = path.with_jacobian(edge)
    y, dy = path.with_jacobian(beyond)
    # x - c is 0.3 within a rounding at 1.3, then a product and a sum: a few roundings at the scale of the lengths
    # and arms; the polynomial itself evaluated 0.3 beyond the box (no extension) is off by O(0.1)
    tol = rounding_tol(_EXTENSION_ROUNDINGS, y, dy)
    torch.testing.assert_close(y, y_edge + 0.3 * dy_edge[:, :, 1], rtol=0, atol=tol)
    # both arms are the slopes at the same clamped point c: one rounding per term summed, as another kernel may sum
    torch.testing.assert_close(dy, dy_edge, rtol=0, atol=term_sum_tol(path, dy))
    assert (dy[:, ~torch.as_tensor(CROSSING)] == 0).all()


_TWO_THREADS = """
import torch, numpy as np
torch.set_num_threads(2)
from lightning_bodyschema.networks.per_muscle import PerMusclePath
x = torch.rand(3000, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 2 - 1
y = torch.stack([x[:, 0] ** 3 - x[:, 1] * x[:, 2], x.prod(1) + x[:, 2] ** 5], 1)
path = PerMusclePath(np.ones((2, 3), bool), degree=11, n_hidden=0)  # one batched solve of two 364-term systems
path.fit_polynomial(x, y)
print(torch.get_num_threads(), float((path(x) - y).abs().max()))
"""


def test_a_fit_with_two_torch_threads_ends_and_recovers_the_polynomials():
    """torch 2.13's MKL hangs in batched float64 LU solves with 2 threads (``branches.one_thread``): the fit runs on
    one thread and gives the caller its two back."""
    import subprocess
    import sys
    done = subprocess.run([sys.executable, "-c", _TWO_THREADS], capture_output=True, text=True, timeout=120)
    threads, error = done.stdout.split()
    assert done.returncode == 0 and int(threads) == 2 and float(error) < 1e-9, done.stderr[-2000:]
    assert "DLASWP" not in done.stderr
