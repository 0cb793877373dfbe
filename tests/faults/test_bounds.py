"""FaultBounds: the tension box through the spring puts the motor exactly on its length bounds at the box's ends,
crosses exactly when no tension meets the bounds, is the same in numpy and torch (and traced), and its rules are
Faults.validate's."""
import numpy as np
import pytest
import torch
from physics_checks import spring_length_tol

from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.faults import Faults
from lightning_bodyschema.faults.bounds import FaultBounds
from lightning_bodyschema.sim import SpringParams, elongation_from_tension

SPRING = SpringParams()  # k 1000 N, alpha 20 1/m, f_max 150 N


def _cases(n=400, m=6, seed=0):
    """Random lengths and faults: jams and bands near l_geo (some crossing), cuts, weakenings."""
    rng = np.random.default_rng(seed)
    l_geo = rng.uniform(0.1, 0.3, (n, m))
    cut = rng.random((n, m)) < 0.15
    fix = ~cut & (rng.random((n, m)) < 0.3)
    l_fixed = np.where(fix, l_geo - rng.uniform(-0.004, 0.012, (n, m)), np.nan)
    band = ~cut & (rng.random((n, m)) < 0.3)
    lo = l_geo - rng.uniform(-0.002, 0.01, (n, m))
    hi = lo + rng.uniform(0.0, 0.006, (n, m))
    l_band = np.where(band[..., None], np.stack([lo, hi], -1), np.nan)
    weak = ~cut & (rng.random((n, m)) < 0.2)
    f_weak = np.where(weak, rng.uniform(20.0, 140.0, (n, m)), np.nan)
    cut[cut.all(1), 0] = False
    return l_geo, Faults(cut, fix, l_fixed, f_weak, l_band).validate(m, SPRING.f_max_n)


def _motor(l_geo, f):
    return l_geo - elongation_from_tension(f, SPRING)


def test_the_box_ends_put_the_motor_on_its_length_bounds():
    l_geo, faults = _cases()
    bounds = FaultBounds.from_faults(faults, SPRING.f_max_n, SPRING)
    lo, hi = bounds.tension_box(l_geo)
    ok = lo <= hi
    f_limit = faults.f_limit(SPRING.f_max_n)
    assert (hi[ok] <= f_limit[ok]).all() and (lo >= 0).all() and (hi[faults.cut] == 0).all()
    # a taut jam or band hi: the box's low end holds the motor exactly at that bound (f = phi(l_geo - l_hi))
    taut = ok & (lo > 0)
    # l_geo - delta(phi(l_geo - l_hi)): the spring and its inverse, a few roundings at the lengths' scale (~1e-15 m)
    np.testing.assert_allclose(_motor(l_geo, lo)[taut], bounds.l_hi_m[taut], rtol=0, atol=spring_length_tol(l_geo))
    # a band's lo that binds: the box's high end holds the motor exactly at lo
    binds = ok & bounds.band & (hi < f_limit) & (hi > 0)  # hi = 0: slack, the motor anywhere above l_geo
    assert binds.any() and taut.any()
    np.testing.assert_allclose(_motor(l_geo, hi)[binds], faults.l_band_m[..., 0][binds], rtol=0,
                               atol=spring_length_tol(l_geo))


def test_the_box_crosses_exactly_when_no_tension_meets_the_bounds():
    l_geo, faults = _cases(n=200)
    bounds = FaultBounds.from_faults(faults, SPRING.f_max_n, SPRING)
    lo, hi = bounds.tension_box(l_geo)
    f = np.linspace(0.0, SPRING.f_max_n, 30001)[:, None, None]  # every tension, 5 mN apart
    motor = _motor(l_geo, f)
    slack_free = np.where(f == 0, np.inf, motor)  # a slack wire's motor may stand anywhere above l_geo
    meets = ((f <= bounds.f_hi_n) & (motor <= np.where(np.isfinite(bounds.l_hi_m), bounds.l_hi_m, np.inf) + 1e-12)
             & (slack_free >= np.where(np.isfinite(bounds.l_lo_m), bounds.l_lo_m, -np.inf) - 1e-12)).any(0)
    crossed = lo > hi
    assert crossed.any() and (~crossed).any()
    margin = (np.abs(lo - hi) > 0.01)  # away from the grid's resolution
    assert (meets[margin] == ~crossed[margin]).all()


def test_numpy_torch_and_the_traced_graph_agree():
    l_geo, faults = _cases(n=64)
    want = FaultBounds.from_faults(faults, SPRING.f_max_n, SPRING).tension_box(l_geo)
    like = torch.zeros(0, dtype=torch.float64)
    got = FaultBounds.from_faults(faults, SPRING.f_max_n, SPRING, like=like).tension_box(torch.from_numpy(l_geo))
    # one formula, k expm1(alpha stretch), in numpy's and torch's expm1: each within an ulp or so of the exact value
    # (torch's vectorized kernel, or the scalar one under ATEN_CPU_CAPABILITY=default), so a few ulps apart
    ulps = 4 * np.finfo(np.float64).eps
    for a, b in zip(got, want):
        np.testing.assert_allclose(a.numpy(), b, rtol=ulps, atol=0)

    class Box(torch.nn.Module):
        def forward(self, l_geo, cut, jam, l_fixed, f_weak, band_lo, band_hi):
            f_max, k, alpha = (torch.full((l_geo.shape[1],), v, dtype=torch.float64) for v in (150.0, 1000.0, 20.0))
            bounds = FaultBounds.from_tensors(cut, jam, l_fixed, f_weak, band_lo, band_hi, f_max, k, alpha)
            return bounds.tension_box(l_geo) + (bounds.invalid(f_max),)

    inputs = tuple(torch.from_numpy(np.ascontiguousarray(a, dtype=np.float64)) for a in (
        l_geo, faults.cut, faults.fix, faults.l_fixed_m, faults.f_max_n, faults.l_band_m[..., 0],
        faults.l_band_m[..., 1]))
    program = torch.export.export(Box(), inputs, strict=False)
    traced = program.module()(*inputs)
    for a, b in zip(traced[:2], want):
        np.testing.assert_allclose(a.numpy(), b, rtol=ulps, atol=0)
    assert not traced[2].any()


def test_a_kind_of_length_bound_no_muscle_has_leaves_the_tension_limits_and_the_spring_alone():
    """Without a length bound the box is [0, the tension limit] and the motor length the spring's alone; with jams
    only (upper bounds, no lower one) the box's upper end is still the limit; each as where every kind is computed
    (torch, which never skips one); the box is the caller's to change, and lengths that broadcast the bounds get the
    full shape."""
    l_geo, faults = _cases(n=64)
    none = np.full(faults.cut.shape, np.nan)
    f = np.random.default_rng(5).uniform(-5.0, 150.0, l_geo.shape)
    ulps = 4 * np.finfo(np.float64).eps
    for jams, bands in ((False, False), (True, False), (False, True)):
        kept = Faults(faults.cut, faults.fix & jams, np.where(jams, faults.l_fixed_m, np.nan), faults.f_max_n,
                      faults.l_band_m if bands else np.stack([none, none], -1))
        bounds = FaultBounds.from_faults(kept, SPRING.f_max_n, SPRING)
        lo, hi = bounds.tension_box(l_geo)
        l_motor = bounds.motor_length_m(l_geo, f)
        assert ((lo == 0).all() and (l_motor == _motor(l_geo, f)).all()) or jams or bands
        assert (hi == np.where(kept.cut, 0.0, kept.f_limit(SPRING.f_max_n))).all() or bands
        assert (lo > 0).any() or not (jams or bands)  # the other kinds are computed
        on_torch = FaultBounds.from_faults(kept, SPRING.f_max_n, SPRING, like=torch.zeros(0, dtype=torch.float64))
        for a, b in zip(on_torch.tension_box(torch.from_numpy(l_geo)), (lo, hi)):
            np.testing.assert_allclose(a.numpy(), b, rtol=ulps, atol=0)
        np.testing.assert_allclose(on_torch.motor_length_m(torch.from_numpy(l_geo), torch.from_numpy(f)).numpy(),
                                   l_motor, rtol=ulps, atol=0)
        again = [a.copy() for a in (lo, hi)]
        lo[:], hi[:] = np.nan, np.nan  # the caller owns the box: the next one is the same
        assert all(np.array_equal(a, b) for a, b in zip(bounds.tension_box(l_geo), again))
        one = bounds.take(np.arange(1))
        assert [a.shape for a in one.tension_box(l_geo)] == [l_geo.shape] * 2
        assert one.motor_length_m(l_geo, f).shape == l_geo.shape


def test_invalid_rows_are_those_validate_refuses():
    names = ["a", "b", "c"]
    good = Faults.from_names(names, cut=[["a"]], jam=[{"b": 0.2}], band=[{"c": [0.1, 0.2]}])
    bad = [dict(cut=[["a"]], jam=[{"a": 0.2}]), dict(cut=[names]), dict(jam=[{"a": -0.1}]),
           dict(weak=[{"a": 200.0}]), dict(band=[{"b": [0.3, 0.2]}]), dict(cut=[["c"]], band=[{"c": [0.1, 0.2]}])]
    assert not FaultBounds.from_faults(good, 150.0).invalid(150.0).any()
    for spec in bad:
        faults = _unchecked(names, **spec)
        with pytest.raises(BodySchemaInputError):  # validate refuses it ...
            faults.validate(3, 150.0)
        assert FaultBounds.from_faults(faults, 150.0).invalid(150.0).all(), spec  # ... and the package flags it


def _unchecked(names, cut=(), jam=(), weak=(), band=()):
    """The one-case Faults of the spec without validation."""
    m = len(names)
    faults = Faults.none(1, m)
    faults.f_max_n, faults.l_band_m = np.full((1, m), np.nan), np.full((1, m, 2), np.nan)
    for muscles in cut:
        faults.cut[0, [names.index(x) for x in muscles]] = True
    for entry in jam:
        for x, v in entry.items():
            faults.fix[0, names.index(x)], faults.l_fixed_m[0, names.index(x)] = True, v
    for entry in weak:
        for x, v in entry.items():
            faults.f_max_n[0, names.index(x)] = v
    for entry in band:
        for x, v in entry.items():
            faults.l_band_m[0, names.index(x)] = v
    return faults


def test_a_tension_in_the_box_gives_a_motor_length_within_every_bound_in_numpy_and_torch_alike():
    """``motor_length_m``: the spring's inverse at a tension in the box meets the length bounds (to exp/log1p's
    rounding, ~1e-15 m at these 0.1-0.3 m lengths); a slack banded wire's motor stands at l_geo or, where the band
    lies above it, at the band's lower end; the
    torch form (the exported adapter's) is the numpy form to log1p's last bit."""
    l_geo, faults = _cases()
    bounds = FaultBounds.from_faults(faults, SPRING.f_max_n, SPRING)
    lo, hi = bounds.tension_box(l_geo)
    # rows whose length bounds conflict on their own (a band's lo above a jam's l_fixed, both above l_geo) keep an
    # uncrossed box [0, 0] of a slack wire: no motor length meets them; the safe command's check refuses those
    held = (lo <= hi).all(1) & (bounds.l_lo_m <= bounds.l_hi_m).all(1)
    rng = np.random.default_rng(1)
    f = np.where(held[:, None], lo + rng.random(lo.shape) * (np.minimum(hi, 1e3) - lo), np.nan)
    f[:, 0] = np.where(held, lo[:, 0], np.nan)  # a lower end: 0 on a free or banded-slack muscle
    l_motor = bounds.motor_length_m(l_geo, f)
    assert np.isfinite(l_motor[held]).all() and np.isnan(l_motor[~(lo <= hi).all(1)]).all()
    broken_m, _ = bounds.take(held).broken(l_motor[held], f[held])
    assert broken_m.max() <= spring_length_tol(l_geo)  # the spring and its inverse at the lengths' scale (~5e-16 m)
    slack_banded = held[:, None] & (f <= 0) & bounds.band
    at_band = np.minimum(np.maximum(l_geo, bounds.l_lo_m), bounds.l_hi_m)  # at l_geo, else up at the band's lo
    assert (l_motor[slack_banded] == at_band[slack_banded]).all()
    assert (l_motor[slack_banded] > l_geo[slack_banded]).sum() >= 10  # moved up to a band above the slack wire
    like = torch.zeros((), dtype=torch.float64)
    on_torch = FaultBounds.from_faults(faults, SPRING.f_max_n, SPRING, like=like)
    got = on_torch.motor_length_m(torch.as_tensor(l_geo), torch.as_tensor(f)).numpy()
    np.testing.assert_allclose(got, l_motor, rtol=0, atol=4e-16)  # torch's log1p may round one ulp apart


def test_the_learned_body_renames_infeasible_and_nothing_else():
    from lightning_bodyschema.faults.qp import learned_body_status
    from lightning_bodyschema.status import Status

    codes = np.arange(len(Status))
    renamed = learned_body_status(codes)
    assert renamed[Status.INFEASIBLE.code] == Status.INFEASIBLE_LEARNED.code
    keep = codes != Status.INFEASIBLE.code
    np.testing.assert_array_equal(renamed[keep], codes[keep])
    on_torch = learned_body_status(torch.as_tensor(codes, dtype=torch.int32))
    assert on_torch.dtype == torch.int32 and on_torch.tolist() == renamed.tolist()
