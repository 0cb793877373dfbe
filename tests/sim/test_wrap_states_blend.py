"""tools/wrap_states.py's blend (``Blend``): a C1 partition of unity across the cell cuts, on a known function."""
import importlib.util
import os

import numpy as np
import torch

_SPEC = importlib.util.spec_from_file_location(
    "wrap_states_tool", os.path.join(os.path.dirname(__file__), "..", "..", "tools", "wrap_states.py"))
wrap_states_tool = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(wrap_states_tool)


def _fitted_blend():
    """Two joints cut in 4, degree 3 pieces of a length that no cubic matches: the pieces differ at the cuts."""
    rng = np.random.default_rng(0)
    x = torch.as_tensor(rng.uniform(-1, 1, (6000, 2)))
    length_mm = lambda x: 40 * torch.sin(3 * x[:, 0]) * torch.cos(2 * x[:, 1])  # noqa: E731
    blend = wrap_states_tool.Blend((np.array([0, 0]), np.array([True, True]), 4, 3), 0.1)
    labels = np.zeros(len(x), np.int64)
    fits = blend.fit(x, length_mm(x), labels)
    return blend, fits


def test_blend_is_continuous_across_cuts_and_its_slope_is_its_derivative():
    blend, fits = _fitted_blend()
    rad_per_unit = torch.tensor([0.8, 1.3], dtype=torch.float64)
    x = torch.as_tensor(np.random.default_rng(1).uniform(-0.95, 0.95, (400, 2)))
    x[::2, 0] = torch.as_tensor(np.random.default_rng(2).choice([-0.5, 0.0, 0.5], 200))  # on a cut of joint 0
    labels, fallback = np.zeros(len(x), np.int64), (torch.zeros(len(x), dtype=torch.float64),
                                                    torch.zeros(len(x), 2, dtype=torch.float64))
    step = torch.tensor([1e-9, 0.0], dtype=torch.float64)
    up = blend.predict(fits, x + step, labels, fallback, rad_per_unit)
    down = blend.predict(fits, x - step, labels, fallback, rad_per_unit)
    own_cell_jump = (up["b"][0] - down["b"][0]).abs()[::2]
    assert float(own_cell_jump.max()) > 1e-3  # the pieces do differ at a cut: the check can fail
    assert float((up["c"][0] - down["c"][0]).abs()[::2].max()) < 1e-6  # [mm]: the blend does not jump
    h = 1e-6  # [rad]: central differences of the blended length against its moment arms
    base = blend.predict(fits, x, labels, fallback, rad_per_unit)
    for j in range(2):
        dx = torch.zeros(2, dtype=torch.float64)
        dx[j] = h / rad_per_unit[j]
        slope = (blend.predict(fits, x + dx, labels, fallback, rad_per_unit)["c"][0]
                 - blend.predict(fits, x - dx, labels, fallback, rad_per_unit)["c"][0]) / (2 * h)
        scale = float(base["c"][1][:, j].abs().max())
        assert float((slope - base["c"][1][:, j]).abs()[1::2].max()) < 1e-6 * scale


def test_blend_equals_the_own_piece_far_from_every_cut():
    blend, fits = _fitted_blend()
    x = torch.tensor([[-0.75, 0.25], [0.25, -0.75], [0.75, 0.75]], dtype=torch.float64)  # cell centres
    labels = np.zeros(3, np.int64)
    fallback = (torch.zeros(3, dtype=torch.float64), torch.zeros(3, 2, dtype=torch.float64))
    out = blend.predict(fits, x, labels, fallback, torch.ones(2, dtype=torch.float64))
    assert torch.equal(out["c"][0], out["b"][0]) and torch.equal(out["c"][1], out["b"][1])
