"""Separable paths (``PerMusclePath(blocks=...)``): a muscle's length as a sum of one polynomial per group of its
joints. A sum of high-degree parts is recovered with the terms that a polynomial mixing every joint spends on a low
degree, no term mixes two groups, the moment arms are the learned length's derivative, and the groups of a joint
graph are its connected parts."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from physics_checks import term_sum_tol

from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.networks.cells import cell_degree
from lightning_bodyschema.networks.per_muscle import PerMusclePath
from lightning_bodyschema.networks.polynomial import block_sizes, muscle_degrees, term_count
from lightning_bodyschema.sim.separable import joint_groups

# muscle 0: f(x0, x1) + g(x2); muscle 1: one group over x0 and x2 (they interact); muscle 2: x1 alone
BLOCKS = np.array([[0, 0, 1], [0, -1, 0], [-1, 0, -1]])
CROSSING = BLOCKS >= 0
TERMS = term_count((2, 1), 10)  # 1 + (66 - 1) + (11 - 1) = 76: degree 10 in both groups of muscle 0


def _lengths(x):
    a, b, c = x[:, 0], x[:, 1], x[:, 2]
    separable = 0.2 * (a + 0.5 * b) ** 10 + a ** 3 * b ** 2 - 0.4 * b ** 9 + c ** 10 + 0.3 * c ** 7 - c
    return torch.stack([separable, a * c + c ** 3, b ** 4], 1)


def _samples(n, seed):
    return torch.rand(n, 3, generator=torch.Generator().manual_seed(seed), dtype=torch.float64) * 2 - 1


@pytest.fixture(scope="module")
def fitted():
    x = _samples(4000, 0)
    path = PerMusclePath(CROSSING, degree=10, hidden=1, n_hidden=0, max_terms=TERMS, blocks=BLOCKS)
    path.fit_polynomial(x, _lengths(x))
    return path


def test_term_counts_and_degrees_follow_the_groups():
    assert TERMS == 76 and term_count((3,), 4) == math.comb(7, 3)
    assert block_sizes(BLOCKS) == [(2, 1), (2,), (1,)]
    assert muscle_degrees(CROSSING, 10, TERMS, blocks=BLOCKS)[0] == 10
    assert muscle_degrees(CROSSING, 10, TERMS)[0] == 5  # C(5 + 3, 3) = 56 <= 76 < C(6 + 3, 3) = 84
    assert cell_degree((3, 2), 16, 2, 80000) == 14 and cell_degree(5, 16, 2, 80000) == 7  # myoArm's BIClong


def test_a_sum_of_high_degree_parts_is_recovered_with_few_terms(fitted):
    assert int(fitted.term_mask[0].sum()) == TERMS
    x = _samples(2000, 1).clamp(-0.999, 0.999)
    np.testing.assert_allclose(fitted(x), _lengths(x), atol=1e-9)
    mixed = PerMusclePath(CROSSING, degree=10, hidden=1, n_hidden=0, max_terms=TERMS)  # the same terms mixing every joint: degree 5 (can fail)
    mixed.fit_polynomial(_samples(4000, 0), _lengths(_samples(4000, 0)))
    assert (mixed(x) - _lengths(x))[:, 0].abs().max() > 1e-3


def test_no_term_mixes_two_groups(fitted):
    used = fitted.exponents[fitted.term_mask[0]] > 0
    assert not (used[:, 2:3] & used[:, :2]).any()  # muscle 0: x2 never with x0 or x1
    x = _samples(300, 2)
    moved = x.clone()
    moved[:, :2] = _samples(300, 3)[:, :2]  # other x0, x1: the slope on x2 is g'(x2) alone, unchanged
    slope = fitted.with_jacobian(x)[1][:, 0, 2]
    # the same terms' slopes summed: one rounding per term at the slope's scale (~1e-13); a term mixing x2 with x0
    # or x1 would move it by the size of that term's coefficient
    torch.testing.assert_close(slope, fitted.with_jacobian(moved)[1][:, 0, 2],
                               atol=term_sum_tol(fitted, slope), rtol=0)


def test_moment_arms_are_the_learned_lengths_derivative_and_zero_off_the_crossed_joints(fitted):
    x = _samples(100, 4).clamp(-0.99, 0.99)
    dy = fitted.with_jacobian(x)[1]
    h = 1e-6
    for j in range(3):
        step = torch.zeros(3, dtype=torch.float64)
        step[j] = h
        np.testing.assert_allclose(dy[:, :, j], (fitted(x + step) - fitted(x - step)) / (2 * h), atol=1e-7)
    assert (dy[:, ~torch.as_tensor(CROSSING)] == 0).all()


def test_blocks_that_mark_an_uncrossed_joint_are_refused():
    with pytest.raises(BodySchemaInputError, match="a group id >= 0 on each joint the muscle crosses"):
        PerMusclePath(CROSSING, degree=4, hidden=1, n_hidden=0, blocks=np.array([[0, 0, 1], [0, 0, 0], [-1, 0, -1]]))


def test_joint_groups_are_the_connected_parts_of_the_links():
    crossing = np.array([[1, 1, 1, 1, 0]], dtype=bool)
    linked = np.zeros((1, 5, 5), dtype=bool)
    for a, b in ((0, 1), (1, 2), (3, 4)):  # 0-1-2 a chain (0 and 2 not linked directly); 4 is not crossed
        linked[0, a, b] = linked[0, b, a] = True
    assert joint_groups(crossing, linked).tolist() == [[0, 0, 0, 1, -1]]
