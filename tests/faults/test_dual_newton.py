"""The batched dual Newton solves the command QPs exactly: proxsuite's answers, KKT conditions, unholdable cases."""
import numpy as np

from lightning_bodyschema.sim.dual_newton import dual_newton
from lightning_bodyschema.sim.equilibrium import solve_equilibrium_qp


def _body(batch, m=12, n=4, seed=0):
    rng = np.random.default_rng(seed)
    G = rng.normal(scale=0.02, size=(batch, m, n))  # moment arms ~2 cm
    f_true = rng.uniform(0.0, 200.0, size=(batch, m))
    tau = -np.einsum("bmn,bm->bn", G, f_true)  # holdable by construction
    return rng, G, tau, np.zeros((batch, m)), np.full((batch, m), 200.0)


def test_equilibrium_matches_proxsuite_with_active_bounds():
    rng, G, tau, lo, hi = _body(64)
    f_ref = rng.uniform(-100.0, 300.0, size=lo.shape)  # far out of the box: many bounds active
    f, ok = dual_newton(G, tau, f_ref, lo, hi, 0.0, 1e-9)
    f_qp, ok_qp = solve_equilibrium_qp(G, tau, f_ref, hi, lo)
    assert ok.all() and ok_qp.all()
    assert ((f <= lo) | (f >= hi)).sum() > 64  # the test exercises the active set
    assert np.abs(np.einsum("bmn,bm->bn", G, f) + tau).max() <= 1e-9
    np.testing.assert_allclose(f, f_qp, atol=1e-6)


def test_a_torque_the_box_cannot_hold_does_not_converge():
    _, G, tau, lo, hi = _body(8, seed=1)
    f, ok = dual_newton(G, 100.0 * tau + 50.0, np.full(lo.shape, 100.0), lo, hi, 0.0, 1e-9)
    assert not ok.any() and np.all((f >= lo) & (f <= hi))


def test_least_squares_meets_its_kkt_conditions():
    rng, G, tau, lo, hi = _body(32, seed=2)
    tau = 50.0 * tau + rng.normal(scale=20.0, size=tau.shape)  # mostly out of reach
    f_ref, w = np.full(lo.shape, 100.0), np.full(32, 1e-6)
    f, ok = dual_newton(G, tau, f_ref, lo, hi, w, 1e-9)
    assert ok.all() and np.all((f >= lo) & (f <= hi))
    grad = (f - f_ref) + np.einsum("bmn,bn->bm", G, np.einsum("bmn,bm->bn", G, f) + tau) / w[:, None]
    free = (f > lo + 1e-9) & (f < hi - 1e-9)
    scale = np.abs(grad).max()
    assert np.abs(grad[free]).max() <= 1e-6 * scale  # stationary on the free tensions
    assert grad[f <= lo + 1e-9].min() >= -1e-6 * scale and grad[f >= hi - 1e-9].max() <= 1e-6 * scale
