"""MuJoCo 4.0's tendon wrap (``mju_wrap``) in torch: batched, float64, branchless.

A spatial tendon's segment from ``p0`` to ``p1`` meets a wrapping sphere or cylinder. MuJoCo maps both points into
the geom's frame, picks a 2D plane (a cylinder: the plane normal to its axis; a sphere: the plane through its centre,
``p0`` and ``p1``, a fixed choice where they are parallel) and wraps in that plane:

* **no side site**: both points outside the circle, the path wraps where the segment cuts the circle, along the
  shorter of the two tangent pairs (a pair whose tangent segments cross is refused);
* **side site outside the geom** (MuJoCo 4.0's rule, which replaced the older half-plane test): the path is the
  shortest one with the winding angle about the centre of the polyline ``p0 -> side point -> p1`` (the side site
  projected to the plane): straight where the segment clears the circle with that winding, else round the circle
  in the winding's sense, even the long way; it jumps where an end crosses the ray opposite the side site;
* **side site inside the geom** (3D distance from the centre below the radius): the path touches the circle at one
  point where it reflects, found by Newton's method in the angle (MuJoCo's start, stop and clamp); arc 0; where both
  ends lie on one ray from the centre, MuJoCo's fallback, the normalised average of the ends;
* a cylinder spreads the height between the points over the path's planar length (a helix on the arc).

Checked against MuJoCo 4.0.0 itself (tests/paths/test_wrap.py): lengths and tangent points to rounding. The sources
of earlier MuJoCo versions differ (side rule, inside solve, an arc's ``acos``); this follows 4.0's results.

Every case is computed for every element and selected with ``torch.where``; compiled or exported, with no
data-dependent control flow (it traces under ``torch.export`` with a symbolic batch); eager, the inside wrap runs on
its elements only and its Newton steps stop once all have converged (the same numbers). Guards keep every output
finite for finite inputs below 1e150 m (and autograd free of NaN); where MuJoCo divides unguarded (a cylinder's
height over a zero-length path) this returns the unwrapped segment's values. Never imports Lightning.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import torch

from ..errors import BodySchemaInputError

MINVAL = 1e-15  # MuJoCo's mjMINVAL: its floor on norms, squared lengths and determinants (same units as compared)
REFLECTION_STEPS = 20  # Newton steps of the inside wrap's reflection angle (MuJoCo's maxiter)
REFLECTION_TOL = 1e-6  # its stop: |residual| [rad]
PENALTY = -10000.0  # wrap_circle's goodness of a tangent pair whose segments cross

# branch codes of ``wrap_branches`` (what MuJoCo did for each element)
NO_WRAP, CIRCLE, CIRCLE_SIDED, SIDED_LONG, INSIDE, INSIDE_AVERAGE = range(6)
BRANCHES = ("no_wrap", "circle", "circle_sided", "sided_long", "inside", "inside_average")


class Wrap(NamedTuple):
    """One wrap per element; see ``wrap``."""
    wrapped: torch.Tensor   # (...) bool: MuJoCo wraps (its mju_wrap returned >= 0)
    t0: torch.Tensor        # (..., 3) world tangent point after p0 (where not wrapped: p0)
    t1: torch.Tensor        # (..., 3) world tangent point before p1 (where not wrapped: p1)
    arc_m: torch.Tensor     # (...) MuJoCo's wrap length between t0 and t1 (incl. a cylinder's height); 0 where not
    side_margin_m: torch.Tensor    # (...) [m] an end crossing the ray opposite the side site (see ``wrap``)
    inside_margin_m: torch.Tensor  # (...) [m] the side site crossing the geom's surface
    end_margin_m: torch.Tensor     # (...) [m] an end crossing the circle while the wrap is on


def wrap(p0, p1, centre, rot, radius, sphere, side, has_side) -> Wrap:
    """MuJoCo's wrap of the segment ``p0 -> p1`` around one geom, elementwise.

    p0, p1 (..., 3) world path points before/after the geom [m]; centre (..., 3) and rot (..., 3, 3) the geom's
    world position and orientation (columns = geom axes, MuJoCo's xmat); radius (...) [m]; sphere (...) bool
    (False: cylinder, its axis the geom's z); side (..., 3) world side-site position, has_side (...) bool (where
    False, ``side`` is ignored). All broadcast together; float64 tensors, bool masks.

    The path's length through the geom is ``where(wrapped, |t0-p0| + arc_m + |p1-t1|, |p1-p0|)``, MuJoCo's to
    rounding. The margins (metres; for a "near a path switch" flag): every jump of that length is where one of them
    changes sign between finite values (checked along lines through myoArm's and myoLegs' joint boxes,
    tests/paths/test_wrap_switches.py). +inf means "does not apply here" (a change to or from +inf is no switch). A wrap
    that starts or ends where the segment touches the circle is not a jump (length and slope continue): no margin.

    * ``side_margin_m``: with a side site outside the geom and both ends outside the circle, the ends' signed
      distances ``c = cross(-sd_unit, end)`` (2D wrapping plane) from the line of the ray opposite the side site, for
      the ends on that ray's side (``dot(end, -sd) > 0``), combined as ``c0 c1 / (|c0| + |c1|)`` (one end: its ``c``).
      It crosses zero where an end crosses the ray: the side rule's winding jumps by 2 pi there and the path jumps
      (on/off the geom, or round the other side). It flips sign without a zero where an end leaves the ray's side on
      the negative side while the other end is on it (a discontinuity, far from zero: no flag). +inf otherwise.
    * ``inside_margin_m``: ``|s| - radius``, ``s`` the side site in the geom's frame (3D), where both ends are
      outside the circle: < 0 selects the inside wrap instead of the sided circle wrap (the path jumps where it
      changes sign). +inf without a side site or with an end inside (nothing wraps either way).
    * ``end_margin_m``: ``min(|end0|, |end1|) - radius`` in the wrapping plane, where the circle wrap would be on
      but for the ends (the segment cuts the circle with its centre's foot between the ends, or the side site sends
      it the long way round): an end entering the circle turns that wrap off (MuJoCo wraps only with both ends
      outside) and the straight path is shorter, so the length jumps (myoArm's DELT1: 1.85 mm). +inf elsewhere and
      where the inside wrap applies (there the touching point follows the end onto the circle: no jump).
    """
    return wrap_branches(p0, p1, centre, rot, radius, sphere, side, has_side)[0]


def wrap_branches(p0, p1, centre, rot, radius, sphere, side, has_side) -> tuple[Wrap, torch.Tensor]:
    """``wrap`` and the branch MuJoCo took per element, int64 codes of ``BRANCHES``: NO_WRAP; CIRCLE (no side site,
    the segment cuts the circle); CIRCLE_SIDED (a side site outside, the segment cuts the circle); SIDED_LONG (a side
    site outside, the segment clears the circle but passes it the other way than the side site: round the geom);
    INSIDE (inside wrap, the reflection point); INSIDE_AVERAGE (inside wrap, MuJoCo's fallback for ends on one ray
    from the centre: the average point, arc 0)."""
    p0, p1, centre, rot, radius, sphere, side, has_side = _checked(p0, p1, centre, rot, radius, sphere, side, has_side)
    local0, local1, s = _to_local(torch.stack((p0, p1, side), -2), centre, rot).unbind(-2)
    far = (_norm(local0) >= MINVAL) & (_norm(local1) >= MINVAL)  # too close to the centre: no wrap
    axis0, axis1 = _plane(local0, local1, sphere)
    end0, end1 = _project(local0, axis0, axis1), _project(local1, axis0, axis1)
    sd_unit = _unit(_project(s, axis0, axis1))
    s_out = _norm(s) - radius
    inside = has_side & (s_out < 0)
    circ = _wrap_circle(end0, end1, sd_unit, has_side, radius)
    ins = _inside_where(inside, end0, end1, radius, circ.straight)
    ok = far & torch.where(inside, ins.ok, circ.ok)
    pnt0 = torch.where(inside[..., None], ins.pnt, circ.pnt0)
    pnt1 = torch.where(inside[..., None], ins.pnt, circ.pnt1)
    arc = torch.where(inside, torch.zeros_like(radius), circ.arc)
    res0 = axis0 * pnt0[..., :1] + axis1 * pnt0[..., 1:]
    res1 = axis0 * pnt1[..., :1] + axis1 * pnt1[..., 1:]
    res0, res1, arc = _helix(local0, local1, res0, res1, arc, sphere)
    world0, world1 = _to_world(torch.stack((res0, res1), -2), centre, rot).unbind(-2)
    out = Wrap(ok, torch.where(ok[..., None], world0, p0), torch.where(ok[..., None], world1, p1),
               torch.where(ok, arc, 0.0), torch.where(has_side & ~inside, circ.ray_margin, math.inf),
               torch.where(has_side & circ.outside, s_out, math.inf),
               torch.where(inside, math.inf, circ.end_margin))
    return out, _branch_codes(ok, inside, has_side, circ.cuts, ins.solved)


def _branch_codes(ok, inside, has_side, cuts, solved) -> torch.Tensor:
    circle = torch.where(cuts, torch.where(has_side, CIRCLE_SIDED, CIRCLE), SIDED_LONG)
    code = torch.where(inside, torch.where(solved, INSIDE, INSIDE_AVERAGE), circle)
    return torch.where(ok, code, NO_WRAP).to(torch.int64)


def _checked(p0, p1, centre, rot, radius, sphere, side, has_side):
    """The inputs broadcast to one batch shape; a clear error for a wrong dtype or trailing shape."""
    named = {"p0": p0, "p1": p1, "centre": centre, "rot": rot, "radius": radius, "side": side}
    for name, x in named.items():
        if not isinstance(x, torch.Tensor) or x.dtype != torch.float64:
            raise BodySchemaInputError(f"wrap: {name} must be a float64 tensor, got {getattr(x, 'dtype', type(x))}")
    for name, x in {"sphere": sphere, "has_side": has_side}.items():
        if not isinstance(x, torch.Tensor) or x.dtype != torch.bool:
            raise BodySchemaInputError(f"wrap: {name} must be a bool tensor, got {getattr(x, 'dtype', type(x))}")
    for name, x in {"p0": p0, "p1": p1, "centre": centre, "side": side}.items():
        if x.ndim < 1 or x.shape[-1] != 3:
            raise BodySchemaInputError(f"wrap: {name} must have shape (..., 3), got {tuple(x.shape)}")
    if rot.ndim < 2 or tuple(rot.shape[-2:]) != (3, 3):
        raise BodySchemaInputError(f"wrap: rot must have shape (..., 3, 3), got {tuple(rot.shape)}")
    batch = torch.broadcast_shapes(p0.shape[:-1], p1.shape[:-1], centre.shape[:-1], rot.shape[:-2], radius.shape,
                                   sphere.shape, side.shape[:-1], has_side.shape)
    vec = (*batch, 3)
    return (p0.expand(vec), p1.expand(vec), centre.expand(vec), rot.expand((*batch, 3, 3)), radius.expand(batch),
            sphere.expand(batch), side.expand(vec), has_side.expand(batch))


# ---------------------------------------------------------------- guarded elementary operations (finite everywhere)

def _sqrt(x: torch.Tensor) -> torch.Tensor:
    """sqrt, 0 at and below 0 (value and gradient finite)."""
    pos = x > 0
    return torch.where(pos, torch.sqrt(torch.where(pos, x, 1.0)), 0.0)


def _norm(v: torch.Tensor) -> torch.Tensor:
    return _sqrt(_dot(v, v))


def _div(a: torch.Tensor, b: torch.Tensor, ok: torch.Tensor) -> torch.Tensor:
    """a / b where ``ok`` (the caller's guarantee that b is nonzero there), 0 elsewhere."""
    return torch.where(ok, a / torch.where(ok, b, 1.0), 0.0)


def _unit(v: torch.Tensor) -> torch.Tensor:
    """MuJoCo's mju_normalize: v / |v|, or the first basis vector where |v| < MINVAL."""
    n = _norm(v)
    small = n < MINVAL
    basis = torch.eye(v.shape[-1], dtype=v.dtype, device=v.device)[0]
    return torch.where(small[..., None], basis, v / torch.where(small, 1.0, n)[..., None])


def _asin(x: torch.Tensor) -> torch.Tensor:
    """asin clamped to [-1, 1] (MuJoCo's plain asin is NaN beyond; its arguments stay inside)."""
    inner = x.abs() < 1
    return torch.where(inner, torch.asin(torch.where(inner, x, 0.0)), torch.sign(x) * (math.pi / 2))


def _cross2(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]


def _dot(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """The dot product over the last axis (2 or 3) by components: a sum over so short an axis is many times slower."""
    prod = u * v
    out = prod[..., 0] + prod[..., 1]
    return out + prod[..., 2] if prod.shape[-1] == 3 else out


def _cross3(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """u x v of (..., 3) vectors by components (linalg.cross is several times slower on short rows)."""
    ux, uy, uz = u.unbind(-1)
    vx, vy, vz = v.unbind(-1)
    return torch.stack((uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx), -1)


# ---------------------------------------------------------------- frames

def _to_local(x, centre, rot):
    """xmat^T (x - centre) for points ``x (..., P, 3)``: in the geom's frame (rows times xmat: one product)."""
    return (x - centre[..., None, :]) @ rot


def _to_world(x, centre, rot):
    """xmat x + centre for points ``x (..., P, 3)`` in the geom's frame."""
    return x @ rot.transpose(-1, -2) + centre[..., None, :]


def _project(v, axis0, axis1):
    return torch.stack((_dot(v, axis0), _dot(v, axis1)), -1)


def _plane(local0, local1, sphere):
    """The 2D wrapping frame's axes in the geom's frame: a cylinder's x, y; a sphere's p0 direction and the direction
    normal to it in the plane of p0, the centre and p1 (p0, p1 parallel: MuJoCo's fixed choice of a normal)."""
    axis0 = _unit(local0)
    normal = _cross3(local0, local1)
    parallel = _norm(normal) < MINVAL
    normal = torch.where(parallel[..., None], _unit(_cross3(axis0, _off_axis(axis0))), _unit(normal))
    axis1 = _unit(_cross3(normal, axis0))
    ex, ey = torch.eye(3, dtype=local0.dtype, device=local0.device)[:2]
    return (torch.where(sphere[..., None], axis0, ex), torch.where(sphere[..., None], axis1, ey))


def _off_axis(axis0):
    """MuJoCo's helper vector for a degenerate sphere normal: ones, with 0 at axis0's strictly largest |component|
    (component 0 on ties)."""
    a = axis0.abs()
    big1 = (a[..., 1] > a[..., 0]) & (a[..., 1] > a[..., 2])
    big2 = (a[..., 2] > a[..., 0]) & (a[..., 2] > a[..., 1])
    index = torch.where(big2, 2, torch.where(big1, 1, 0))
    return (torch.arange(3, device=axis0.device) != index[..., None]).to(axis0.dtype)


def _helix(local0, local1, res0, res1, arc, sphere):
    """A cylinder's tangent points raised along its axis in proportion to the planar path length before them, and
    the arc lengthened by the height it climbs (MuJoCo's correction); spheres unchanged."""
    len0 = _norm(local0[..., :2] - res0[..., :2])
    len1 = _norm(local1[..., :2] - res1[..., :2])
    total = len0 + arc + len1
    rise = local1[..., 2] - local0[..., 2]
    ok = total > 0  # MuJoCo divides by it unguarded; 0 only for a zero-length wrap between points on the circle
    z0 = local0[..., 2] + _div(rise * len0, total, ok)
    z1 = local0[..., 2] + _div(rise * (len0 + arc), total, ok)
    height = (z1 - z0).abs()
    cyl = ~sphere
    res0 = torch.where(cyl[..., None], torch.cat((res0[..., :2], z0[..., None]), -1), res0)
    res1 = torch.where(cyl[..., None], torch.cat((res1[..., :2], z1[..., None]), -1), res1)
    return res0, res1, torch.where(cyl, _sqrt(arc * arc + height * height), arc)


# ---------------------------------------------------------------- circle wrap

class _Circle(NamedTuple):
    ok: torch.Tensor        # wrap_circle returned >= 0
    pnt0: torch.Tensor      # (..., 2)
    pnt1: torch.Tensor      # (..., 2)
    arc: torch.Tensor       # (...) arc length [m]
    ray_margin: torch.Tensor  # _ray_margin [m] (+inf where an end is inside the circle)
    end_margin: torch.Tensor  # _end_margin [m]
    outside: torch.Tensor   # both ends outside (or on) the circle
    cuts: torch.Tensor      # the segment cuts (or touches) the circle
    straight: torch.Tensor  # the signed angle from end0 to end1 [rad]


def _wrap_circle(end0, end1, sd_unit, has_side, radius) -> _Circle:
    """MuJoCo 4.0's circle wrap on 2D end points, ``sd_unit`` the side site's projection normalised.

    Without a side site: wrap where the segment cuts the circle, the shorter of the two tangent pairs whose tangent
    segments do not cross. With one: the shortest path homotopic to the polyline end0 -> side point -> end1 in the
    plane without the disc, i.e. with the polyline's winding angle about the centre; straight where the segment
    clears the circle with that winding, else around it in the winding's sense."""
    sqlen0, sqlen1, sqrad = _dot(end0, end0), _dot(end1, end1), radius * radius
    dif = end1 - end0
    dd = _dot(dif, dif)
    apart = dd >= MINVAL
    foot = _div(-_dot(dif, end0), dd, apart)  # the centre's foot on the line, in units of the segment
    line_foot = end0 + foot[..., None] * dif
    along = torch.clamp(foot, 0.0, 1.0)
    closest = end0 + along[..., None] * dif
    cuts = _dot(closest, closest) <= sqrad
    winding = _angle(end0, sd_unit) + _angle(sd_unit, end1)  # the polyline's winding about the centre [rad]
    straight = _angle(end0, end1)
    other_class = (winding - straight).abs() > math.pi  # the polyline goes round the other side: 2 pi apart
    outside = (sqlen0 >= sqrad) & (sqlen1 >= sqrad)
    candidate = outside & (radius >= MINVAL) & apart & (cuts | (has_side & other_class))
    pairs = [_tangents(end0, end1, sqlen0, sqlen1, radius, sgn) for sgn in (1.0, -1.0)]
    crossed = [_intersect(end0, t0, end1, t1) for t0, t1 in pairs]
    good = [_goodness(t0, t1, x) for (t0, t1), x in zip(pairs, crossed)]
    first = torch.where(has_side, winding < 0, good[0] > good[1])  # pair 0 turns clockwise, pair 1 counter-
    pnt0 = torch.where(first[..., None], pairs[0][0], pairs[1][0])
    pnt1 = torch.where(first[..., None], pairs[0][1], pairs[1][1])
    ok = candidate & ~torch.where(first, crossed[0], crossed[1])
    arc = _arc(pnt0, pnt1, first, radius)
    interior = apart & (foot > 0) & (foot < 1) & (_dot(line_foot, line_foot) < sqrad)  # cuts, an end inside or not
    end_margin = _end_margin(sqlen0, sqlen1, radius, interior | (has_side & other_class))
    ray_margin = torch.where(outside, _ray_margin(end0, end1, sd_unit), math.inf)
    return _Circle(ok, pnt0, pnt1, arc, ray_margin, end_margin, outside, cuts, straight)


def _ray_margin(end0, end1, sd_unit):
    """The polyline's winding jumps by 2 pi, and the sided path with it, exactly where an end crosses the ray from the
    centre opposite the side point (direction -sd). Per end on that ray's side (``dot(end, -sd) > 0``; the other
    ends: +inf, the margin does not apply) its signed distance from the ray's line ``c = cross(-sd, end)``; the two
    combined as ``c0 c1 / (|c0| + |c1|)`` [m]: zero where either is (the sign flips as either end crosses), within a
    factor 2 of the nearer one's distance, and smooth through its zero (no switch of which end is nearer)."""
    away = -sd_unit
    c0, c1 = (torch.where(_dot(away, end) > 0, _cross2(away, end), math.inf) for end in (end0, end1))
    finite = torch.isfinite(c0) & torch.isfinite(c1)
    a, b = torch.where(finite, c0, 0.0), torch.where(finite, c1, 0.0)
    both = _div(a * b, a.abs() + b.abs(), (a != 0) | (b != 0))
    return torch.where(finite, both, torch.where(torch.isfinite(c0), c0, c1))


def _end_margin(sqlen0, sqlen1, radius, applies):
    """``min(|end0|, |end1|) - radius`` [m] where ``applies`` (the segment cuts the circle between the ends, or the
    side site sends the path the long way round), else +inf: there an end entering the circle turns the wrap off, and
    the wrapped path (round the circle to the end) is longer than the straight one, so the length jumps (MuJoCo
    4.0 wraps only with both ends outside). Where the segment misses the circle, or meets it only at the end (heading
    in), the path is straight on both sides of the crossing: no jump, no margin."""
    return torch.where(applies, _sqrt(torch.minimum(sqlen0, sqlen1)) - radius, math.inf)


def _angle(u, v):
    """The signed angle from u to v in (-pi, pi] [rad] (0 where either is zero, its gradient too)."""
    cross, dot = _cross2(u, v), _dot(u, v)
    zero = (cross == 0) & (dot == 0)
    return torch.atan2(torch.where(zero, 0.0, cross), torch.where(zero, 1.0, dot))


def _tangents(end0, end1, sqlen0, sqlen1, radius, sgn):
    """The tangent points from each end on one side (MuJoCo's solution ``sgn`` = +1: i = 0, -1: i = 1)."""
    sqrad = radius * radius
    root0, root1 = _sqrt(sqlen0 - sqrad), _sqrt(sqlen1 - sqrad)
    t0 = torch.stack((end0[..., 0] * sqrad + sgn * radius * end0[..., 1] * root0,
                      end0[..., 1] * sqrad - sgn * radius * end0[..., 0] * root0), -1)
    t1 = torch.stack((end1[..., 0] * sqrad - sgn * radius * end1[..., 1] * root1,
                      end1[..., 1] * sqrad + sgn * radius * end1[..., 0] * root1), -1)
    return (_div(t0, sqlen0[..., None], (sqlen0 > 0)[..., None]), _div(t1, sqlen1[..., None], (sqlen1 > 0)[..., None]))


def _goodness(t0, t1, crossed):
    """Minus the chord's square (the shorter arc is better); a pair whose tangent segments cross: PENALTY."""
    chord = t0 - t1
    return torch.where(crossed, PENALTY, -_dot(chord, chord))


def _intersect(p1, p2, p3, p4):
    """MuJoCo's is_intersect: the 2D segments p1-p2 and p3-p4 cross (parameters in [0, 1]; |det| < MINVAL: no)."""
    d12, d34, d31 = p2 - p1, p4 - p3, p1 - p3
    det = _cross2(d12, d34)
    ok = det.abs() >= MINVAL
    a = _div(_cross2(d34, d31), det, ok)
    b = _div(_cross2(d12, d31), det, ok)
    return ok & (a >= 0) & (a <= 1) & (b >= 0) & (b <= 1)


def _arc(pnt0, pnt1, first, radius):
    """MuJoCo's length_circle: the angle between the tangent points, the reflex one where the pair's turn disagrees
    with the chosen solution's sense."""
    angle = _angle(pnt0, pnt1).abs()
    turn = pnt0[..., 1] * pnt1[..., 0] - pnt0[..., 0] * pnt1[..., 1]
    flip = ((turn > 0) & ~first) | ((turn < 0) & first)
    return radius * torch.where(flip, 2 * math.pi - angle, angle)


# ---------------------------------------------------------------- inside wrap

class _Inside(NamedTuple):
    ok: torch.Tensor       # the inside wrap applies (both ends outside the circle, the segment clear of it)
    pnt: torch.Tensor      # (..., 2) the touching point (both tangent points)
    solved: torch.Tensor   # the reflection point solved for, not the collinear fallback (the normalised average)


def _inside_where(inside, end0, end1, radius, straight) -> _Inside:
    """``_wrap_inside`` where ``inside`` (elsewhere not ok). Compiled or exported, on every element with the fixed
    Newton steps (no data-dependent shape or loop); eager, on the inside elements only and Newton's steps stopping
    once every lane has (the same numbers: a stopped lane keeps its angle)."""
    if torch.compiler.is_compiling() or torch.compiler.is_exporting():
        return _wrap_inside(end0, end1, radius, straight.abs(), until_done=False)
    rows = inside.reshape(-1).nonzero().squeeze(1)
    take = lambda x: x.reshape(-1, *x.shape[inside.ndim:]).index_select(0, rows)  # noqa: E731
    part = _wrap_inside(take(end0), take(end1), take(radius), take(straight).abs(), until_done=True)
    put = lambda x: x.new_zeros((inside.numel(), *x.shape[1:])).index_copy(0, rows, x).reshape(  # noqa: E731
        inside.shape + x.shape[1:])
    return _Inside(*(put(x) for x in part))


def _wrap_inside(end0, end1, radius, g, until_done: bool) -> _Inside:
    """The inside wrap on 2D end points: the path touches the circle at the one point where it reflects.

    MuJoCo's refusals (an end inside or on the circle, the segment cutting it, the ends opposite about the centre)
    and its fallback for ends on one ray from the centre (the normalised average of the two ends); elsewhere the
    reflection condition ``asin(A sin t) + asin(B sin t) - 2 t + G = 0`` solved to rounding (``_reflection``); ``g``
    the angle between the ends, ``|_angle(end0, end1)|`` [rad]."""
    len0, len1 = _norm(end0), _norm(end1)
    dif = end1 - end0
    dd = _dot(dif, dif)
    apart = dd > MINVAL
    along = _div(-_dot(dif, end0), dd, apart)
    between = apart & (along > 0) & (along < 1)
    cut = between & (_norm(end0 + along[..., None] * dif) <= radius)
    ok = (len0 > radius) & (len1 > radius) & (radius >= MINVAL) & (len0 >= MINVAL) & (len1 >= MINVAL) & ~cut
    average = _unit(0.5 * (end0 + end1)) * radius[..., None]
    a_ratio = _div(radius, len0, len0 > 0)
    b_ratio = _div(radius, len1, len1 > 0)
    cos_g = _div(len0 * len0 + len1 * len1 - dd, 2 * len0 * len1, (len0 > 0) & (len1 > 0))
    ok = ok & (cos_g >= -1 + MINVAL)
    solved = cos_g <= 1 - MINVAL
    theta = _reflection(a_ratio, b_ratio, g, ok & solved if until_done else None)
    turn_left = _cross2(end0, end1) > 0
    vec = _unit(torch.where(turn_left[..., None], end0, end1))
    ang = theta - _asin(torch.where(turn_left, a_ratio, b_ratio) * torch.sin(theta))
    c, s = torch.cos(ang), torch.sin(ang)
    touch = radius[..., None] * torch.stack((c * vec[..., 0] - s * vec[..., 1], s * vec[..., 0] + c * vec[..., 1]), -1)
    return _Inside(ok, torch.where(solved[..., None], touch, average), solved)


def _reflection(a_ratio, b_ratio, g, used: torch.Tensor | None):
    """MuJoCo 4.0's reflection angle ``t`` in [0, pi/2]: Newton's method on ``asin(A sin t) + asin(B sin t) - 2 t + G``
    (A, B = radius / |end| < 1, G the angle between the ends) from pi/2, each step clamped to pi/2, a lane stopping
    once |value| <= REFLECTION_TOL (then within ~1e-8 rad of the root: MuJoCo's own point, not the exact root). The
    function falls from G at 0 with slope in [-2, A + B - 2] and is concave, so the steps approach the root from the
    right without overshooting; REFLECTION_STEPS steps (lanes that stopped keep their angle); given ``used`` (the
    lanes whose angle is used), fewer once all of those have stopped (a data-dependent exit: eager only; the others'
    angles are then not MuJoCo's, and unused)."""
    theta = torch.full_like(g, math.pi / 2)
    for _ in range(REFLECTION_STEPS):
        sin, cos = torch.sin(theta), torch.cos(theta)
        a_sin, b_sin = a_ratio * sin, b_ratio * sin
        value = _asin(a_sin) + _asin(b_sin) - 2 * theta + g
        slope = (a_ratio * cos / _sqrt(1 - a_sin * a_sin).clamp(min=MINVAL)
                 + b_ratio * cos / _sqrt(1 - b_sin * b_sin).clamp(min=MINVAL) - 2)  # <= A + B - 2 < 0
        step = torch.clamp(theta - _div(value, slope, slope != 0), max=math.pi / 2)
        going = value.abs() > REFLECTION_TOL
        if used is not None and not bool((going & used).any()):
            break
        theta = torch.where(going, step, theta)
    return theta
