"""paths.wrap against MuJoCo itself: a spatial tendon site-geom-site in small MJCFs (every point on a free body, the
geom turned arbitrarily), read back through mj_kinematics + mj_tendon (ten_length, the tangent points in wrap_xpos),
over seeded configurations chosen to reach every branch of mju_wrap; then every wrap of every myoArm muscle; then
torch.export with a symbolic batch, and autograd free of NaN at degenerate inputs."""

import mujoco
import numpy as np
import pytest
import torch

from physics_checks import rounding_tol

from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.paths.wrap import (BRANCHES, CIRCLE, CIRCLE_SIDED, INSIDE, INSIDE_AVERAGE, NO_WRAP,
                                             wrap, wrap_branches)

# a path length is a dozen roundings at the configuration's scale (frames, tangent points' sqrt, an atan2, an arc;
# measured: 3e-15 m at 0.5 m); the tangent points agree to 3e-16 m, the inside wrap's reflection point included
# (the same Newton steps), but near-tangent configurations amplify rounding, so the points get 1e-10 m
LENGTH_ROUNDINGS = 64
POINT_TOL_M = 1e-10

_BODY = '<body name="{0}"><freejoint/><inertial pos="0 0 0" mass="1" diaginertia="1 1 1"/>{1}</body>'


def tendon_xml(sphere: bool, sided: bool) -> str:
    """One tendon from site s0 (body a) around geom g (body g) to site s1 (body b); side site ss (body s)."""
    kind = "sphere" if sphere else "cylinder"
    side = ' sidesite="ss"' if sided else ""
    bodies = (_BODY.format("a", '<site name="s0"/>') + _BODY.format("b", '<site name="s1"/>')
              + _BODY.format("g", f'<geom name="g" type="{kind}" size="0.05 0.2" contype="0" conaffinity="0"/>')
              + _BODY.format("s", '<site name="ss"/>'))
    return (f'<mujoco><worldbody>{bodies}</worldbody><tendon><spatial name="t"><site site="s0"/>'
            f'<geom geom="g"{side}/><site site="s1"/></spatial></tendon></mujoco>')


def _unit_rows(rng, n):
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def local_configs(rng, n: int, radius: np.ndarray, sphere: bool, sided: bool):
    """Points p0, p1 and side site in the geom's frame [m], ``n`` per family: random; a segment grazing the circle
    (offset r (1 +- delta), delta from 1e-7 to 0.1: the tangency switch and wrap_inside's f > 0 start); end points
    within 1e-3 r of the circle; p0, p1 on one line through the centre (the sphere's degenerate normal, MuJoCo's
    fallback frame; the cylinder's p1 = k p0 in 2D makes the inside wrap's average fallback; on opposite sides only
    with a side site: without one, the two ways round tie and rounding picks one). Side sites: outside the geom at
    half the configurations, inside at the other half (a cylinder's: near its mid-plane)."""
    r = radius[:, None]
    fam = np.repeat(np.arange(4), n)
    p0 = _unit_rows(rng, 4 * n) * r * rng.uniform(0.3, 4.0, (4 * n, 1))
    p1 = _unit_rows(rng, 4 * n) * r * rng.uniform(0.3, 4.0, (4 * n, 1))
    graze = fam == 1  # a line at distance r (1 + delta) from the axis, the two points on either side of its foot
    u, w = _unit_rows(rng, 4 * n), _unit_rows(rng, 4 * n)
    if not sphere:
        u[:, 2] = w[:, 2] = 0.0
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    w = w - (w * u).sum(1, keepdims=True) * u
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    delta = rng.choice([-1, 1], 4 * n) * 10 ** rng.uniform(-7, -1, 4 * n)
    foot = u * r * (1 + delta[:, None])
    lift = rng.uniform(-1, 1, (4 * n, 1)) * r * (0.0 if sphere else 1.0) * np.array([0, 0, 1.0])
    p0[graze] = (foot - w * r * rng.uniform(0.2, 3, (4 * n, 1)) + lift)[graze]
    p1[graze] = (foot + w * r * rng.uniform(0.2, 3, (4 * n, 1)) - lift)[graze]
    near = fam == 2
    for p in (p0, p1):
        p[near] *= (r * (1 + rng.uniform(-1e-3, 1e-3, (4 * n, 1))) / np.linalg.norm(p, axis=1, keepdims=True))[near]
    line = fam == 3
    sign = rng.choice([-1.0, 1.0], (4 * n, 1)) if sided else np.ones((4 * n, 1))
    p1[line] = p0[line] * sign[line] * rng.uniform(1.2, 3.0, (4 * n, 1))[line]
    inside = rng.uniform(size=4 * n) < 0.5
    s_dir = _unit_rows(rng, 4 * n)
    if not sphere:
        s_dir[inside, 2] *= 0.2
    s = s_dir * r * np.where(inside, rng.uniform(0.0, 0.95, 4 * n), rng.uniform(1.05, 3.0, 4 * n))[:, None]
    return p0, p1, s


def _quat(rng, n):
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def run_mujoco(sphere: bool, sided: bool, seed: int, n: int):
    """MuJoCo's world points, tendon length and tangent points (NaN where not wrapped) for ``4 n`` configurations."""
    rng = np.random.default_rng(seed)
    m = mujoco.MjModel.from_xml_string(tendon_xml(sphere, sided))
    d = mujoco.MjData(m)
    radius = 10 ** rng.uniform(-2.5, -1, 4 * n)
    p0, p1, s = local_configs(rng, n, radius, sphere, sided)
    centre, quat = rng.uniform(-0.5, 0.5, (4 * n, 3)), _quat(rng, 4 * n)
    sites = [m.site(name).id for name in ("s0", "s1", "ss")]
    g = m.geom("g").id
    out = {k: np.empty((4 * n, 3)) for k in ("p0", "p1", "side", "centre", "t0", "t1")}
    out["rot"], out["length"], out["radius"] = np.empty((4 * n, 3, 3)), np.empty(4 * n), radius
    for i in range(4 * n):  # MuJoCo evaluates one configuration per call
        rot = np.empty(9)
        mujoco.mju_quat2Mat(rot, quat[i])
        rot = rot.reshape(3, 3)
        m.geom_size[g, 0] = radius[i]
        for body, local in zip("abs", (p0[i], p1[i], s[i])):
            adr = m.jnt_qposadr[m.body(body).jntadr[0]]
            d.qpos[adr:adr + 7] = np.r_[centre[i] + rot @ local, 1.0, 0, 0, 0]
        adr = m.jnt_qposadr[m.body("g").jntadr[0]]
        d.qpos[adr:adr + 7] = np.r_[centre[i], quat[i]]
        mujoco.mj_kinematics(m, d)
        mujoco.mj_tendon(m, d)
        out["p0"][i], out["p1"][i], out["side"][i] = (d.site_xpos[k] for k in sites)
        out["centre"][i], out["rot"][i] = d.geom_xpos[g], d.geom_xmat[g].reshape(3, 3)
        out["length"][i] = d.ten_length[0]
        wrapped = d.ten_wrapnum[0] == 4
        out["t0"][i] = d.wrap_xpos.reshape(-1, 3)[1] if wrapped else np.nan
        out["t1"][i] = d.wrap_xpos.reshape(-1, 3)[2] if wrapped else np.nan
    return out


def ours(cfg, sphere: bool, sided: bool):
    t = {k: torch.as_tensor(cfg[k]) for k in ("p0", "p1", "centre", "rot", "side", "radius")}
    n = len(cfg["radius"])
    w, branch = wrap_branches(t["p0"], t["p1"], t["centre"], t["rot"], t["radius"], torch.full((n,), sphere),
                              t["side"], torch.full((n,), sided))
    return w, branch.numpy()


def path_length(w, p0, p1):
    return torch.where(w.wrapped, (w.t0 - p0).norm(dim=-1) + w.arc_m + (p1 - w.t1).norm(dim=-1), (p1 - p0).norm(dim=-1))


@pytest.fixture(scope="module")
def against_mujoco():
    """Per (sphere, sided): the configurations, our wrap and branches."""
    out = {}
    for seed, (sphere, sided) in enumerate([(True, False), (True, True), (False, False), (False, True)]):
        cfg = run_mujoco(sphere, sided, seed, 120)
        out[sphere, sided] = cfg, *ours(cfg, sphere, sided)
    return out


@pytest.mark.parametrize("sphere", [True, False], ids=["sphere", "cylinder"])
@pytest.mark.parametrize("sided", [False, True], ids=["plain", "sided"])
def test_wrap_equals_mujoco(against_mujoco, sphere, sided):
    cfg, w, branch = against_mujoco[sphere, sided]
    wrapped = ~np.isnan(cfg["t0"][:, 0])
    np.testing.assert_array_equal(w.wrapped.numpy(), wrapped)
    length = path_length(w, torch.as_tensor(cfg["p0"]), torch.as_tensor(cfg["p1"])).numpy()
    scale = np.abs(cfg["p0"]).max() + np.abs(cfg["p1"]).max()
    assert np.abs(length - cfg["length"]).max() <= rounding_tol(LENGTH_ROUNDINGS, scale)
    for key in ("t0", "t1"):
        assert np.abs(getattr(w, key).numpy()[wrapped] - cfg[key][wrapped]).max() <= POINT_TOL_M
        np.testing.assert_array_equal(getattr(w, key).numpy()[~wrapped], cfg["p" + key[1]][~wrapped])
    assert (w.arc_m.numpy()[~wrapped] == 0).all() and (w.arc_m.numpy() >= 0).all()


def test_every_branch_is_exercised(against_mujoco):
    """Each branch of mju_wrap is reached by at least 10 configurations (the counts: the report's)."""
    counts = {name: 0 for name in BRANCHES}
    for _, _, branch in against_mujoco.values():
        for code, name in enumerate(BRANCHES):
            counts[name] += int((branch == code).sum())
    assert min(counts.values()) >= 10, counts
    plain = np.concatenate([against_mujoco[s, False][2] for s in (True, False)])
    assert set(np.unique(plain)) == {NO_WRAP, CIRCLE}  # no side site: only the plain circle wrap


def test_inside_margin_selects_the_inside_wrap(against_mujoco):
    """inside_margin_m < 0 exactly where MuJoCo took the inside branches; without a side site both margins are inf;
    where the inside wrap applies the side margin is inf; with an end inside the circle (nothing wraps either way) the
    inside margin is inf."""
    for (sphere, sided), (cfg, w, branch) in against_mujoco.items():
        inside_margin, side_margin = w.inside_margin_m.numpy(), w.side_margin_m.numpy()
        if not sided:
            assert np.isinf(side_margin).all() and np.isinf(inside_margin).all()
            continue
        inside = np.isin(branch, [INSIDE, INSIDE_AVERAGE])
        assert (inside_margin[inside] < 0).all() and np.isinf(side_margin[inside_margin < 0]).all()
        assert not (w.wrapped.numpy() & ~inside & (inside_margin < 0)).any()
        # it applies where both ends are outside the circle (in the wrapping plane: a cylinder's xy), else +inf
        ends = [np.einsum("bji,bj->bi", cfg["rot"], cfg[p] - cfg["centre"])[:, :3 if sphere else 2]
                for p in ("p0", "p1")]
        applies = np.minimum(*(np.linalg.norm(e, axis=1) for e in ends)) >= cfg["radius"]
        assert np.isinf(inside_margin[~applies]).all() and applies.sum() >= 100
        side_m = np.linalg.norm(cfg["side"] - cfg["centre"], axis=1)[applies]  # |s|: a norm and a subtraction
        np.testing.assert_allclose(inside_margin[applies] + cfg["radius"][applies], side_m, rtol=0,
                                   atol=rounding_tol(8, side_m, cfg["centre"]))


@pytest.mark.parametrize("sphere", [True, False], ids=["sphere", "cylinder"])
def test_side_margin_zero_is_mujocos_jump(sphere):
    """p0 slides across the ray from the centre opposite the side site (side site below the geom, the ray straight
    up, p1 to the right, on the ray's side too): side_margin_m combines p0's and p1's signed distances from the ray's
    line, ``c0 c1 / (|c0| + |c1|)``, zero where p0's is, and MuJoCo's length jumps by more than 1 cm between +-1 um of
    its zero (the path lets go of the geom) while 2 mm on either side it moves less."""
    radius, x = 0.05, np.array([-2e-3, -1e-6, 1e-6, 2e-3])
    p0 = np.stack([x, np.full(4, 0.1), np.zeros(4)], 1)
    p1, side = np.array([0.15, 0.03, 0.0]), np.array([0.0, -0.08, 0.0])
    lengths = _mujoco_lengths(sphere, True, radius, p0, np.broadcast_to(p1, p0.shape), side)
    t = lambda a: torch.as_tensor(a, dtype=torch.float64)  # noqa: E731
    w = wrap(t(p0), t(p1), t(np.zeros(3)), torch.eye(3, dtype=torch.float64), t(radius), torch.tensor(sphere),
             t(side), torch.tensor(True))
    margin = w.side_margin_m.numpy()
    if sphere:  # the sphere's plane holds p0, p1 and the centre: the ray's line is met where p0's x is 0 as well
        assert (np.sign(margin) == -np.sign(margin[::-1])).all() and (np.abs(margin[1:3]) < 2e-6).all()
    else:
        c0, c1 = -x, -p1[0]  # cross(ray direction +y, end)
        np.testing.assert_allclose(margin, c0 * c1 / (np.abs(c0) + np.abs(c1)), rtol=1e-12)
        assert np.sign(margin[1]) == -np.sign(margin[2])
    jump = abs(lengths[2] - lengths[1])
    assert jump > 0.01 and abs(lengths[1] - lengths[0]) < 0.01 and abs(lengths[3] - lengths[2]) < 0.01
    ours = path_length(w, t(p0), t(p1)).numpy()
    np.testing.assert_allclose(ours, lengths, rtol=0, atol=rounding_tol(LENGTH_ROUNDINGS, 0.2))


def _mujoco_lengths(sphere: bool, sided: bool, radius: float, p0, p1, side) -> np.ndarray:
    """MuJoCo's tendon length per row of ``p0``, ``p1`` (geom at the origin, unturned)."""
    m = mujoco.MjModel.from_xml_string(tendon_xml(sphere, sided))
    d = mujoco.MjData(m)
    m.geom_size[m.geom("g").id, 0] = radius
    lengths = []
    for start, end in zip(p0, p1):
        for body, point in zip("abgs", (start, end, np.zeros(3), side)):
            adr = m.jnt_qposadr[m.body(body).jntadr[0]]
            d.qpos[adr:adr + 7] = np.r_[point, 1.0, 0, 0, 0]
        mujoco.mj_kinematics(m, d)
        mujoco.mj_tendon(m, d)
        lengths.append(d.ten_length[0])
    return np.array(lengths)


@pytest.mark.parametrize("sphere", [True, False], ids=["sphere", "cylinder"])
@pytest.mark.parametrize("sided", [False, True], ids=["plain", "sided"])
def test_end_margin_zero_is_mujocos_jump(sphere, sided):
    """p1 moves radially into the circle while the segment from p0 cuts it (myoArm's DELT1 at its 1.85 mm jump):
    end_margin_m is p1's distance outside the circle, and MuJoCo's length jumps by more than 5 mm between +-1 nm
    of its zero (the wrap round the circle to p1 turns off), while 1 mm on either side it moves about 1 mm."""
    radius, scale = 0.05, 1 + np.array([2e-2, 2e-8, -2e-8, -2e-2])
    p1 = radius * scale[:, None] * np.array([np.cos(np.pi / 6), np.sin(np.pi / 6), 0.0])
    p0, side = np.broadcast_to([-0.15, 0.0, 0.0], p1.shape), np.array([0.0, 0.2, 0.0])
    lengths = _mujoco_lengths(sphere, sided, radius, p0, p1, side)
    t = lambda a: torch.as_tensor(np.ascontiguousarray(a), dtype=torch.float64)  # noqa: E731
    w = wrap(t(p0), t(p1), t(np.zeros(3)), torch.eye(3, dtype=torch.float64), t(radius), torch.tensor(sphere),
             t(side), torch.tensor(sided))
    np.testing.assert_allclose(w.end_margin_m.numpy(), radius * (scale - 1), rtol=0, atol=rounding_tol(8, radius))
    assert abs(lengths[2] - lengths[1]) > 5e-3
    assert abs(lengths[1] - lengths[0]) < 2e-3 and abs(lengths[3] - lengths[2]) < 2e-3
    np.testing.assert_allclose(path_length(w, t(p0), t(p1)).numpy(), lengths, rtol=0,
                               atol=rounding_tol(LENGTH_ROUNDINGS, 0.2))


def test_inside_average_is_mujocos_fallback(against_mujoco):
    """Where Newton's method is not used, both tangent points are the normalised average of the two end points
    (in the 2D frame: its z, for a cylinder, interpolated), on the circle, and the wrap adds no arc."""
    for sphere in (True, False):
        cfg, w, branch = against_mujoco[sphere, True]
        fallback = branch == INSIDE_AVERAGE
        assert fallback.sum() >= 3
        assert (w.arc_m.numpy()[fallback] == 0).all()
        np.testing.assert_array_equal(w.t0.numpy()[fallback], w.t1.numpy()[fallback])
        local = np.einsum("bji,bj->bi", cfg["rot"], w.t0.numpy() - cfg["centre"])[fallback]
        np.testing.assert_allclose(np.linalg.norm(local[:, :2 if not sphere else 3], axis=1),
                                   cfg["radius"][fallback], rtol=1e-12)


@pytest.fixture(scope="module")
def myoarm():
    from lightning_bodyschema.sim import MusculoskeletalModel
    return MusculoskeletalModel("myo:myoarm")


def _path_slots(m):
    """Per muscle tendon: its segments (site before, geom or -1, side site or -1, site after)."""
    out = []
    for tendon in range(m.ntendon):
        adr, num = m.tendon_adr[tendon], m.tendon_num[tendon]
        types, objs, prm = m.wrap_type[adr:adr + num], m.wrap_objid[adr:adr + num], m.wrap_prm[adr:adr + num]
        sites = [k for k in range(num) if types[k] == mujoco.mjtWrap.mjWRAP_SITE]
        for a, b in zip(sites[:-1], sites[1:]):
            geom = b - a == 2
            out.append((tendon, objs[a], objs[a + 1] if geom else -1, int(round(prm[a + 1])) if geom else -1, objs[b]))
    return np.array(out, np.int64)


def test_myoarm_lengths_are_mujocos(myoarm):
    """Every muscle tendon of myoArm at 50 seeded postures: the sum over its segments (a site to the next site,
    around the geom between them with ``wrap``) is MuJoCo's ten_length; the wrap states are MuJoCo's."""
    m, d = myoarm.mj_model, mujoco.MjData(myoarm.mj_model)
    slots = _path_slots(m)
    assert (slots[:, 2] >= 0).sum() >= 50  # the wrapping slots, about 85 on myoArm
    full = myoarm.full_q(myoarm.sample_q(np.random.default_rng(7), 50))
    site_xpos, geom_xpos, geom_xmat, lengths, wrapnum = [], [], [], [], []
    for q in full:  # MuJoCo evaluates one posture per call
        d.qpos[:] = q
        mujoco.mj_kinematics(m, d)
        mujoco.mj_tendon(m, d)
        site_xpos.append(d.site_xpos.copy())
        geom_xpos.append(d.geom_xpos.copy())
        geom_xmat.append(d.geom_xmat.reshape(-1, 3, 3).copy())
        lengths.append(d.ten_length.copy())
        wrapnum.append(d.ten_wrapnum.copy())
    site_xpos, geom_xpos, geom_xmat = (torch.as_tensor(np.array(x)) for x in (site_xpos, geom_xpos, geom_xmat))
    tendon, s0, geom, side, s1 = (torch.as_tensor(c) for c in slots.T)
    g = geom.clamp(min=0)
    w = wrap(site_xpos[:, s0], site_xpos[:, s1], geom_xpos[:, g], geom_xmat[:, g],
             torch.as_tensor(m.geom_size[g.numpy(), 0]),
             torch.as_tensor(m.geom_type[g.numpy()] == mujoco.mjtGeom.mjGEOM_SPHERE),
             site_xpos[:, side.clamp(min=0)], side >= 0)
    wrapped = w.wrapped & (geom >= 0)
    seg = torch.where(wrapped, path_length(w, site_xpos[:, s0], site_xpos[:, s1]),
                      (site_xpos[:, s1] - site_xpos[:, s0]).norm(dim=-1))
    total = torch.zeros(len(full), m.ntendon, dtype=torch.float64).index_add_(1, tendon, seg)
    tendons = np.unique(slots[:, 0])
    assert np.abs(total.numpy() - np.array(lengths))[:, tendons].max() <= 1e-12
    expected_wrapnum = np.zeros((len(full), m.ntendon), np.int64)
    np.add.at(expected_wrapnum.T, slots[:, 0], (1 + 2 * wrapped.numpy()).T)
    np.testing.assert_array_equal(expected_wrapnum[:, tendons] + 1, np.array(wrapnum)[:, tendons])
    assert wrapped.any(dim=0).sum() >= 20  # many geoms wrap somewhere in these postures


class _Wrapper(torch.nn.Module):
    def forward(self, p0, p1, centre, rot, radius, sphere, side, has_side):
        w = wrap(p0, p1, centre, rot, radius, sphere, side, has_side)
        return path_length(w, p0, p1), w.t0, w.t1, w.wrapped


def test_export_with_a_symbolic_batch(against_mujoco):
    """torch.export traces ``wrap`` with a dynamic batch; the exported program equals eager at another batch size."""
    cfg, _, _ = against_mujoco[False, True]
    n = len(cfg["radius"])
    args = tuple(torch.as_tensor(cfg[k]) for k in ("p0", "p1", "centre", "rot", "radius"))
    args = (*args, torch.rand(n) < 0.5, torch.as_tensor(cfg["side"]), torch.rand(n) < 0.7)
    batch = torch.export.Dim("batch", min=2)
    shapes = tuple({0: batch} for _ in args)
    program = torch.export.export(_Wrapper(), tuple(a[:8] for a in args), dynamic_shapes=shapes)
    for got, want in zip(program.module()(*args), _Wrapper()(*args)):
        torch.testing.assert_close(got, want, rtol=0, atol=0)


def test_finite_values_and_gradients_at_degenerate_inputs():
    """Coincident points, points at the centre, on the circle, radius 0, a side site at the centre, p1 = -p0: every
    output finite (margins may be +inf by definition) and every gradient of the path length finite."""
    d = torch.float64
    cases = torch.tensor([[0, 0, 0, 1, 0, 0], [1, 0, 0, 1, 0, 0], [1, 0, 0, -1, 0, 0], [0.1, 0, 0, 0.2, 0, 0],
                          [0.1, 0, 0, -0.1, 0, 0], [0.1, 0.1, 0, 0.1, -0.1, 0], [0.1, 0, 0.5, 0.1, 0, -0.5],
                          [0.1000001, 0, 0, 0.1, 1e-9, 0], [2, 1, 0, -2, 1, 0], [0.3, 0.1, 0, 0.3, -0.1, 0]], dtype=d)
    n = len(cases)
    p0, p1 = cases[:, :3].clone().requires_grad_(), cases[:, 3:].clone().requires_grad_()
    radius = torch.tensor([0.1] * (n - 1) + [0.0], dtype=d).requires_grad_()
    for sphere in (True, False):
        for side in (torch.zeros(3, dtype=d), torch.tensor([0, -0.2, 0], dtype=d), torch.tensor([0, 0.01, 0], dtype=d)):
            w = wrap(p0, p1, torch.zeros(3, dtype=d), torch.eye(3, dtype=d), radius, torch.tensor(sphere),
                     side, torch.tensor(True))
            for x in (w.t0, w.t1, w.arc_m):
                assert torch.isfinite(x).all()
            assert not torch.isnan(w.side_margin_m).any() and not torch.isnan(w.inside_margin_m).any()
            grads = torch.autograd.grad(path_length(w, p0, p1).sum(), (p0, p1, radius))
            assert all(torch.isfinite(g).all() for g in grads)


def test_one_unbatched_wrap_is_the_batched_ones(against_mujoco):
    """Inputs without a batch axis (every branch, the inside wrap's included) answer as the same rows batched."""
    cfg, w, branch = against_mujoco[True, True]
    rows = [int(np.flatnonzero(branch == code)[0]) for code in range(len(BRANCHES)) if (branch == code).any()]
    assert {int(branch[r]) for r in rows} >= {INSIDE, CIRCLE_SIDED}
    for r in rows:
        args = [torch.as_tensor(cfg[k][r]) for k in ("p0", "p1", "centre", "rot", "radius")]
        one = wrap(*args, torch.tensor(True), torch.as_tensor(cfg["side"][r]), torch.tensor(True))
        for got, want in zip(one, w):
            torch.testing.assert_close(got, want[r], rtol=0, atol=0)


def test_bad_input_is_named():
    x = torch.zeros(3, dtype=torch.float64)
    with pytest.raises(BodySchemaInputError, match="p0 must be a float64"):
        wrap(x.float(), x, x, torch.eye(3, dtype=torch.float64), x[0], torch.tensor(True), x, torch.tensor(False))
    with pytest.raises(BodySchemaInputError, match=r"rot must have shape \(\.\.\., 3, 3\)"):
        wrap(x, x, x, x, x[0], torch.tensor(True), x, torch.tensor(False))
    with pytest.raises(BodySchemaInputError, match="sphere must be a bool"):
        wrap(x, x, x, torch.eye(3, dtype=torch.float64), x[0], torch.tensor(1.0), x, torch.tensor(False))
