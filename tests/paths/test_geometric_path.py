"""GeometricPath: MuJoCo's tendon lengths and moment arms from a PathLayout's numbers, in torch (float64).

Compared with MuJoCo itself (``MusculoskeletalModel.kinematics``) on the paper arm, arm3_8, myoArm (hand locked,
couplings) and myoLegs (fixed base, knees' slide joints coupled to the knee angles), at the MJCF's numbers and at
numbers moved by about a millimetre. Until ``paths/wrap.py`` is there the module wraps nothing, and the comparisons
keep the (posture, muscle) pairs that MuJoCo does not wrap either.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch
import yaml

from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.paths import module as path_module
from lightning_bodyschema.paths.layout import path_layout, segments
from lightning_bodyschema.paths.module import GeometricPath
from lightning_bodyschema.paths.parts import numbers, path_parts, true_values
from lightning_bodyschema.sim import MusculoskeletalModel
from lightning_bodyschema.sim.wrapping import wrap_states

WRAPS = path_module._wrap is not path_module._no_wrap  # paths/wrap.py is there
LENGTH_TOL_M, ARM_TOL_M = 1e-12, 1e-10  # MuJoCo's own roundings over a chain of frames (arms are mm, lengths dm)
EPS = np.finfo(float).eps
BODIES = ["paper_arm", "arm3_8", "myoarm", "myolegs"]
_CONFIGS = {"myoarm": "configs/myoarm.yaml", "myolegs": "configs/myolegs-per-muscle.yaml"}
_BUILT: dict = {}


def _body(name: str) -> MusculoskeletalModel:
    """The body (built once per run): a packaged model, or a config's robot as its data module builds it."""
    if name not in _BUILT:
        if name in _CONFIGS:
            pytest.importorskip("myo_sim")
            data = yaml.safe_load(open(_CONFIGS[name]))["data"]
            _BUILT[name] = MusculoskeletalModel(data["model"], **{k: data[k] for k in ("locked_joints", "fixed_base")
                                                                  if k in data})
        else:
            _BUILT[name] = MusculoskeletalModel(name)
    return _BUILT[name]


def _compared(model, q: np.ndarray) -> np.ndarray:
    """``(B, M)`` the pairs compared: all, or without ``paths/wrap.py`` those MuJoCo does not wrap (skipped where
    there are none: the paper arm's paths always wrap)."""
    keep = np.ones((len(q), model.n_muscles), bool) if WRAPS else wrap_states(model, q) == 0
    if not keep.any():
        pytest.skip("every path wraps here: needs paths/wrap.py")
    return keep


def _assert_mujocos(path: GeometricPath, model, q: np.ndarray) -> None:
    length, arm = (t.numpy() for t in path(torch.as_tensor(q)))
    want_length, want_arm, _ = model.kinematics(q)
    keep = _compared(model, q)
    assert np.abs(length - want_length)[keep].max() <= LENGTH_TOL_M
    assert np.abs(arm - want_arm).max(-1)[keep].max() <= ARM_TOL_M
    assert np.abs(want_arm).max(-1)[keep].max() > 1e3 * ARM_TOL_M  # the compared pairs have moment arms


@pytest.mark.parametrize("name", BODIES)
def test_the_mjcfs_numbers_give_mujocos_lengths_and_moment_arms(name):
    model = _body(name)
    path = GeometricPath(path_layout(model))
    _assert_mujocos(path, model, model.sample_q(np.random.default_rng(0), 50))


def _moved_copy(model, rng) -> MusculoskeletalModel:
    """A second instance of ``model`` whose muscles' sites, wrapping geoms' centres and side sites are moved by up
    to 1 mm per coordinate and radii by up to 0.5 mm (a site two muscles share moves for both)."""
    copy = MusculoskeletalModel(model.xml, muscles=model.muscle_names, lock_uncrossed=False, allow_unloaded=True)
    m = copy.mj_model
    parts = [p for t in model.muscle_ids for p in path_parts(m, int(t))]
    sites = sorted({p[1] for p in parts if p[0] == "site"} | {p[2] for p in parts if p[0] == "geom" and p[2] >= 0})
    geoms = sorted({p[1] for p in parts if p[0] == "geom"})
    m.site_pos[sites] += rng.uniform(-1e-3, 1e-3, (len(sites), 3))
    m.geom_pos[geoms] += rng.uniform(-1e-3, 1e-3, (len(geoms), 3))
    m.geom_size[geoms, 0] += rng.uniform(-5e-4, 5e-4, len(geoms))
    return copy


@pytest.mark.parametrize("name", ["paper_arm", "myoarm", "myolegs"])
def test_moved_numbers_give_the_moved_models_lengths_and_moment_arms(name):
    model = _body(name)
    moved = _moved_copy(model, np.random.default_rng(3))
    path = GeometricPath(path_layout(model))
    m = moved.mj_model
    per_muscle = []
    for t in model.muscle_ids:
        parts = path_parts(m, int(t))
        per_muscle.append(true_values(m, parts, numbers(m, parts)))
    path.set_numbers(per_muscle)
    assert max(np.abs(path.muscle_numbers(a) - path_layout(model).muscle_numbers(a)).max()
               for a in range(model.n_muscles)) > 5e-4  # the numbers moved
    _assert_mujocos(path, moved, model.sample_q(np.random.default_rng(1), 50))


@pytest.mark.parametrize("name", ["paper_arm", "myoarm", "myolegs"])
def test_moment_arms_are_the_lengths_central_differences(name):
    """Step 1e-6 on every free joint, at the pairs whose wrapping state (MuJoCo's) is the same at every step: the
    error allowed is the difference quotient's rounding, ``64 eps max|l| / h`` (its truncation, ``h^2 l''' / 6``,
    is below 1e-12 at l''' of a few m)."""
    model, h = _body(name), 1e-6
    path = GeometricPath(path_layout(model))
    q = model.sample_q(np.random.default_rng(2), 30)
    n = model.n_joints
    steps = np.concatenate([q, (q[:, None] + h * np.eye(n)).reshape(-1, n), (q[:, None] - h * np.eye(n))
                            .reshape(-1, n)])
    length, arm = (t.numpy() for t in path(torch.as_tensor(steps)))
    up, down = length[len(q):len(q) * (n + 1)], length[len(q) * (n + 1):]
    slope = ((up - down) / (2 * h)).reshape(len(q), n, -1).transpose(0, 2, 1)  # (B, M, N)
    states = wrap_states(model, steps).reshape(2 * n + 1, len(q), -1) if WRAPS else None
    keep = (states == states[0]).all(0) if WRAPS else _compared(model, steps).reshape(2 * n + 1, len(q), -1).all(0)
    tol = 64 * EPS * np.abs(length).max() / h
    assert np.abs(slope - arm[:len(q)]).max(-1)[keep].max() <= tol
    assert np.abs(arm[:len(q)]).max(-1)[keep].max() > 1e3 * tol


def test_exports_with_a_dynamic_batch_and_answers_as_eager():
    """``torch.export`` with a symbolic batch (myoLegs: couplings and slides), run at other batches."""
    model = _body("myolegs")
    path = GeometricPath(path_layout(model))
    q = torch.as_tensor(model.sample_q(np.random.default_rng(4), 9))
    batch = torch.export.Dim("batch", min=1, max=4096)
    program = torch.export.export(path, (q[:5],), dynamic_shapes={"q": {0: batch}}).module()
    for rows in (1, 9):
        for got, want in zip(program(q[:rows]), path(q[:rows])):
            # the exported graph may compose the chain's frames in another order: roundings at the length's scale
            torch.testing.assert_close(got, want, rtol=0, atol=8192 * EPS * want.abs().max().item())


def test_only_the_numbers_are_state_and_stay_float64_on_a_cast():
    model = _body("paper_arm")
    path = GeometricPath(path_layout(model))
    assert list(path.state_dict()) == ["numbers"]
    numbers_a = [path.muscle_numbers(a) * 1.01 for a in range(model.n_muscles)]
    path.set_numbers(numbers_a)
    other = GeometricPath(path_layout(model))
    other.load_state_dict(path.state_dict())
    other.float()
    assert all(b.dtype in (torch.float64, torch.long, torch.bool) for b in other.buffers())
    q = torch.as_tensor(model.sample_q(np.random.default_rng(5), 4), dtype=torch.float32)
    for got, want in zip(other(q), path(q.double())):
        assert got.dtype == torch.float64
        torch.testing.assert_close(got, want, rtol=0, atol=0)
    np.testing.assert_array_equal(other.muscle_numbers(1), numbers_a[1])
    with torch.device("meta"):  # a checkpoint's skeleton
        assert GeometricPath(path_layout(model)).numbers.shape == path.numbers.shape


def test_margins_have_a_slot_per_wrapping_geom_and_inf_elsewhere():
    model = _body("arm3_8")
    layout = path_layout(model)
    margins = GeometricPath(layout).margins(torch.as_tensor(model.sample_q(np.random.default_rng(6), 3)))
    assert len(margins) == 3 and all(m.shape == (3, model.n_muscles, layout.wrap_slot.shape[1]) for m in margins)
    empty = torch.as_tensor(np.broadcast_to(layout.wrap_slot == layout.n_wraps, margins[0].shape).copy())
    assert all(torch.isinf(m[empty]).all() for m in margins)
    assert empty.any() and (~empty).any()


def test_set_numbers_refuses_what_no_path_has():
    model = _body("paper_arm")
    path = GeometricPath(path_layout(model))
    good = [path.muscle_numbers(a) for a in range(model.n_muscles)]
    radius = int(np.flatnonzero(path.number_kind[:len(good[0])] == 2)[0])
    for bad, match in ((good[:-1], "muscles' numbers"), (good[:1] + [good[1][:-1]] + good[2:], "give"),
                       ([np.where(np.arange(len(good[0])) == radius, -1e-3, good[0])] + good[1:], "radii > 0"),
                       ([good[0] * np.nan] + good[1:], "finite")):
        with pytest.raises(BodySchemaInputError, match=match):
            path.set_numbers(bad)
    torch.testing.assert_close(path.numbers, torch.as_tensor(np.concatenate(good)), rtol=0, atol=0)


_PULLEY = """<mujoco><option gravity="0 -9.81 0"/><worldbody><site name="a" pos="0 0.1 0"/>
<site name="b" pos="0 0.2 0"/><body name="arm"><joint name="j" type="hinge" axis="0 0 1" range="-1 1"/>
<geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.02" mass="1"/><site name="c" pos="0.2 0.02 0"/>
<site name="d" pos="0.2 -0.02 0"/></body></worldbody><tendon><spatial name="t"><site site="a"/><site site="c"/>
<pulley divisor="2"/><site site="b"/><site site="d"/></spatial></tendon></mujoco>"""


def test_a_pulley_is_refused_by_name():
    with pytest.raises(BodySchemaInputError, match="tendon 't'.*only sites, spheres and cylinders"):
        path_layout(MusculoskeletalModel(_PULLEY))


def test_segments_cut_a_path_site_to_site_and_refuse_a_geom_not_between_sites():
    site, geom = ("site", 0), ("geom", 0, -1)
    assert segments([site, site, geom, site], "t") == [(0, -1, 1), (1, 2, 3)]
    for parts in ([site, geom], [geom, site], [site, geom, geom, site], [site]):
        with pytest.raises(BodySchemaInputError, match="tendon 't' has path"):
            segments(parts, "t")
