"""Fit each muscle's path numbers to its lengths, with MuJoCo as the evaluator: ``fit_path_numbers``.

The path's topology is known (``parts``: which bodies its sites ride on, which wrapping spheres or cylinders, with
which side sites); its numbers are not: each site's position in its body, each wrapping geom's position in its body
and radius, each side site's position (3 + 3 + 1 + 3 numbers; the geoms' orientations, a cylinder's axis, kept). The
length is MuJoCo's own function of those numbers: each muscle gets ``P + 1`` private copies of its path in one
expanded MjModel (``Replicas``: its own sites, geoms and side sites on the same bodies; a geom two muscles share is
fitted per muscle), copy 0 at the current numbers, copy ``k`` with number ``k`` moved by ``FD_STEP_M``, so one
``mj_kinematics`` + ``mj_tendon`` per posture (a *pass*) gives every muscle's residual and forward-difference
Jacobian. A Jacobian entry above ``JUMP_SLOPE`` (a length moves at most about 1 m per m of a number: a larger one is
a wrap switching between the two evaluations) is set to 0.

Levenberg-Marquardt per muscle (``LevenbergMarquardt``) on the Cauchy loss of scale ``cauchy_mm`` (0: least
squares; a posture the current numbers wrap otherwise than the truth misses by a jump of millimetres and must not
pull the fit; several scales: one fit after the other, ``fit_stages``), the damped step taken in the column-scaled
Jacobian's singular directions above ``RCOND``, at most ``MAX_STEP_M`` per number, radii kept >= ``MIN_RADIUS_M``.
Side sites are never moved by it (``held``: they act only through which way a path wraps); ``side_search`` rounds
of a pattern search over them, each followed by the fit again. Starts (``starts``): the prior's numbers (the MJCF's,
or with ``prior="centroid"`` each site and geom at the centroid of the MJCF's sites of its body, radii x
``CENTROID_RADIUS_FACTOR``) each moved by +-``prior_error_mm`` (a seeded sign per coordinate; radii by a factor 1 +-
``radius_error``); ``side_sites="geom"``: a side site riding its geom's body starts at the geom's start centre plus
the prior's offset between them (``with_geom_offsets``), ``"scaled"`` (the default): that offset times the start's
radius over the prior's (inside the geom stays inside), ``"mjcf"``: at the MJCF's. ``restarts`` seeded starts
(``fit_restarts``), per muscle the lowest train cost kept; ``retry_mm`` > 0: a restart refits only the muscles whose
train RMS is still above it (and ``retry_medians`` times the median muscle's).

Only numpy and MuJoCo: never Lightning, never torch.
"""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Callable, NamedTuple

import mujoco
import numpy as np

from ..errors import BodySchemaInputError
from .parts import KINDS, numbers, path_parts, true_values

FD_STEP_M = 1e-7  # forward-difference step of every number [m]: lengths are exact to ~1e-16 m
JUMP_SLOPE = 10.0  # |dl / dnumber| beyond this is a wrap switching inside the step, not a slope [m/m]
MIN_RADIUS_M = 1e-4
RCOND = 1e-6  # singular values of the column-scaled Jacobian below this (relative) are directions the data do not see
MAX_STEP_M = 0.01  # a step moves no number by more than this (a number seen only inside a wrap can run away)
CENTROID_RADIUS_FACTOR = 1.5
EXACT_M = 1e-12  # a path whose RMS residual is below this is exact (MuJoCo's lengths: ~1e-16 m)
PRIORS, SIDE_SITES = ("mjcf", "centroid"), ("start", "mjcf", "geom", "scaled")


@dataclass(frozen=True)
class PathFitOptions:
    """How ``fit_path_numbers`` fits (module docstring). Defaults: the recipe that fitted all 50 myoArm and all 80
    myoLegs muscles from a 1 mm prior (``prior_error_mm=1, radius_error=0.05``) to the data module's targets at 2000
    postures, with the prior exact (``prior_error_mm`` 0: a robot whose MJCF is its CAD)."""

    prior_error_mm: float = 0.0  # each prior number moved by +-this [mm] (seeded sign): a simulated CAD error
    radius_error: float = 0.0  # each radius scaled by 1 +- this (relative, seeded sign)
    prior: str = "mjcf"  # or "centroid": each point at the centroid of its body's MJCF sites
    seed: int = 0
    restarts: int = 16  # seeded starts at most: with retry_mm a restart refits only the muscles still off, and
    # none runs once every muscle is within it (myoLegs' bfsh_l: 2 of 8 sign draws fit it)
    max_iter: int = 150  # Levenberg-Marquardt passes per stage
    cauchy_mm: tuple = (0.3,)  # the Cauchy loss' scales [mm], fitted in turn (0: least squares)
    side_search: int = 1  # rounds of the side sites' pattern search, each followed by the fit again
    side_sites: str = "scaled"  # side sites start at the "start"'s numbers, the "mjcf"'s, or by their "geom"
    # ("scaled": by their geom in units of its radius, with_geom_offsets)
    side_steps_mm: tuple = (8.0, 4.0, 2.0, 1.0, 0.5)  # the side search's steps [mm], in turn
    retry_mm: float = 0.01  # > 0: a restart refits only the muscles whose train RMS is above this [mm]
    retry_medians: float = 0.0  # > 0: ... and above this many times the median muscle's (noisy targets leave every
    # muscle at the noise: only the ones far above it are refitted)
    threads: int = 1  # MuJoCo passes over postures on this many threads (MuJoCo releases the GIL)

    def __post_init__(self):
        counts = {"seed": self.seed, "restarts": self.restarts, "max_iter": self.max_iter,
                  "side_search": self.side_search, "threads": self.threads}
        for name, value in counts.items():
            low = 0 if name in ("seed", "side_search") else 1
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
                raise BodySchemaInputError(f"PathFitOptions.{name}={value!r}; give an integer >= {low}")
        for name in ("prior_error_mm", "retry_mm", "retry_medians", "radius_error"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0) or (name == "radius_error" and value >= 1):
                allowed = "in [0, 1)" if name == "radius_error" else "a finite number >= 0"
                raise BodySchemaInputError(f"PathFitOptions.{name}={value!r}; give {allowed}")
        for name, positive in (("cauchy_mm", False), ("side_steps_mm", True)):
            value = np.asarray(getattr(self, name), float).ravel()
            if value.size == 0 or not np.all(np.isfinite(value)) or value.min() < 0 or (positive and value.min() == 0):
                raise BodySchemaInputError(f"PathFitOptions.{name}={getattr(self, name)!r}; give one or more finite "
                                           f"numbers [mm], each {'> 0' if positive else '>= 0'}")
        for name, allowed in (("prior", PRIORS), ("side_sites", SIDE_SITES)):
            if getattr(self, name) not in allowed:
                raise BodySchemaInputError(f"PathFitOptions.{name}={getattr(self, name)!r}; give one of {allowed}")


class PathFit(NamedTuple):
    """``fit_path_numbers``' answer: per muscle (in the fitted order) its numbers (``parts.numbers`` order), train
    RMS [mm], Levenberg-Marquardt iterations and side-search passes of its kept fit, the Jacobian entries its last
    pass zeroed as wrap jumps, the directions of its numbers the lengths do not see (``rank_deficit``), and the
    first restart's starting numbers; ``passes``: MuJoCo passes over the train postures in all."""

    numbers: list
    train_rms_mm: np.ndarray
    passes: int
    iterations: np.ndarray
    jumps: np.ndarray
    rank_deficit: np.ndarray
    start: list


class Replicas:
    """Every fitted muscle's ``P + 1`` private path copies in one expanded MjModel (module docstring)."""

    def __init__(self, model, muscles: list[int]):
        from ..sim import MusculoskeletalModel

        m, self.muscles = model.mj_model, list(muscles)
        self.parts = [path_parts(m, model.muscle_ids[i]) for i in muscles]
        self.tables = [numbers(m, parts) for parts in self.parts]
        self.truth = [true_values(m, parts, table) for parts, table in zip(self.parts, self.tables)]
        spec, first = mujoco.MjSpec.from_string(model.xml), []
        writes = []  # (array, row name, column, muscle, number, copy)
        for a, (parts, table) in enumerate(zip(self.parts, self.tables)):
            first.append(f"fit{a}_0")
            for copy in range(len(table) + 1):
                self._add_path(spec, m, parts, f"fit{a}_{copy}")
                writes += [(kind, f"fit{a}_{copy}_{i}", c, a, n, copy) for n, (kind, i, c) in enumerate(table)]
        self.model = MusculoskeletalModel(spec.to_xml(), muscles=first,
                                          allow_unloaded=True, lock_uncrossed=False)
        # MuJoCo places a geom or site that sits at its body's origin from the body alone ("same frame"), ignoring a
        # position written later: every copy must follow its numbers
        self.model.mj_model.geom_sameframe[:] = 0
        self.model.mj_model.site_sameframe[:] = 0
        self._index(writes)
        self.passes, self._datas = 0, [self.model._data]

    @staticmethod
    def _add_path(spec, m, parts, prefix) -> None:
        """One copy of a path: its sites, geoms and side sites on the original bodies, and its tendon."""
        def body(b):
            return spec.worldbody if b == 0 else spec.body(mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, int(b)))
        tendon = spec.add_tendon(name=prefix)
        for i, part in enumerate(parts):
            if part[0] == "site":
                s = part[1]
                body(m.site_bodyid[s]).add_site(name=f"{prefix}_{i}", pos=m.site_pos[s], quat=m.site_quat[s])
                tendon.wrap_site(f"{prefix}_{i}")
                continue
            g, side = part[1], part[2]
            body(m.geom_bodyid[g]).add_geom(name=f"{prefix}_{i}", type=mujoco.mjtGeom(m.geom_type[g]),
                                            size=m.geom_size[g], pos=m.geom_pos[g], quat=m.geom_quat[g],
                                            contype=0, conaffinity=0, group=5)
            if side >= 0:
                body(m.site_bodyid[side]).add_site(name=f"{prefix}_{i}_side", pos=m.site_pos[side],
                                                   quat=m.site_quat[side])
            tendon.wrap_geom(f"{prefix}_{i}", f"{prefix}_{i}_side" if side >= 0 else "")

    def _index(self, writes):
        """Flat write tables: where each (muscle, copy, number) goes in the expanded model."""
        m = self.model.mj_model
        name_id = lambda kind, name: mujoco.mj_name2id(m, kind, name)  # noqa: E731
        obj = {"site": mujoco.mjtObj.mjOBJ_SITE, "geom": mujoco.mjtObj.mjOBJ_GEOM, "radius": mujoco.mjtObj.mjOBJ_GEOM,
               "side": mujoco.mjtObj.mjOBJ_SITE}
        rows = [name_id(obj[k], name + ("_side" if k == "side" else "")) for k, name, *_ in writes]
        self.w_kind = np.array([KINDS.index(w[0]) for w in writes])
        self.w_row, self.w_col = np.array(rows), np.array([w[2] for w in writes])
        self.w_muscle, self.w_number, self.w_copy = (np.array([w[k] for w in writes]) for k in (3, 4, 5))
        self.tendons = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_TENDON, f"fit{a}_{c}")
                        for a, table in enumerate(self.tables) for c in range(len(table) + 1)]
        offsets = np.cumsum([0] + [len(t) + 1 for t in self.tables])
        self.copies = [np.arange(offsets[a], offsets[a + 1]) for a in range(len(self.tables))]

    def write(self, theta: list[np.ndarray], moves: list[np.ndarray] | None = None) -> None:
        """Copy 0 of muscle ``a`` at ``theta[a]``, copy ``k`` at ``theta[a] + moves[a][k - 1]`` (``(P, P)`` each;
        default: number ``k - 1`` moved by ``FD_STEP_M``)."""
        m = self.model.mj_model
        flat, size = np.concatenate(theta), np.array([len(t) for t in theta])
        start = np.cumsum(np.r_[0, size])[self.w_muscle]
        if moves is None:
            move = FD_STEP_M * (self.w_copy == self.w_number + 1)
        else:  # row 0 of each muscle's padded table: copy 0, not moved
            table = np.concatenate([np.vstack([np.zeros(len(t)), d]).ravel() for t, d in zip(theta, moves)])
            offset = np.cumsum(np.r_[0, size * (size + 1)])[self.w_muscle]
            move = table[offset + self.w_copy * size[self.w_muscle] + self.w_number]
        value = flat[start + self.w_number] + move
        for k, array in enumerate((m.site_pos, m.geom_pos, m.geom_size, m.site_pos)):
            at = self.w_kind == k
            array[self.w_row[at], self.w_col[at]] = value[at]

    def lengths(self, full: np.ndarray, threads: int = 1) -> np.ndarray:
        """``(B, copies)`` every copy's length [m] at full postures ``(B, nq)`` (one pass): MuJoCo, one posture per
        call, the postures split in ``threads`` chunks, each on its own ``MjData`` (the same numbers whatever the
        count: each posture's lengths depend on it alone)."""
        m, out = self.model.mj_model, np.empty((len(full), len(self.tendons)))
        self.passes += 1
        chunks = np.array_split(np.arange(len(full)), max(1, min(threads, len(full))))
        if len(chunks) == 1:
            self._fill(full, chunks[0], self._datas[0], out)
            return out
        self._datas += [mujoco.MjData(m) for _ in range(len(chunks) - len(self._datas))]
        with ThreadPoolExecutor(len(chunks)) as pool:  # MuJoCo releases the GIL inside its calls
            list(pool.map(self._fill, [full] * len(chunks), chunks, self._datas, [out] * len(chunks)))
        return out

    def _fill(self, full: np.ndarray, rows: np.ndarray, d: mujoco.MjData, out: np.ndarray) -> None:
        m, ids = self.model.mj_model, np.array(self.tendons)
        for b in rows:
            d.qpos[:] = full[b]
            mujoco.mj_kinematics(m, d)
            mujoco.mj_tendon(m, d)
            out[b] = d.ten_length[ids]


class LevenbergMarquardt:
    """One muscle's Levenberg-Marquardt state: numbers, the accepted cost and Jacobian, the damping. ``held``: numbers
    never moved (side sites: their slope is nonzero only where a finite difference straddles a switch, at a few
    postures, and a step along such a column is noise). ``cauchy_m`` > 0:
    the Cauchy loss ``c^2 log(1 + (r / c)^2)`` instead of ``r^2`` (a posture in another wrapping state, its residual a
    jump of millimetres, weighs little), by reweighted Gauss-Newton steps."""

    def __init__(self, theta: np.ndarray, radius: np.ndarray, held: np.ndarray, cauchy_m: float = 0.0):
        self.held, self.theta, self.radius, self.lam = held, theta, radius, 1e-6
        self.cost, self.J, self.r = np.inf, None, None
        self.iterations, self.done, self.jumps, self.c = 0, False, 0, cauchy_m

    def loss(self, r: np.ndarray) -> float:
        return float(r @ r) if self.c <= 0 else float(self.c ** 2 * np.log1p((r / self.c) ** 2).sum())

    def offer(self, theta: np.ndarray, r: np.ndarray, J: np.ndarray) -> None:
        """The residual ``r (N,)`` and Jacobian ``J (N, P)`` at the trial ``theta``: accept it or raise the damping."""
        cost, J = self.loss(r), np.where(self.held, 0.0, J)
        if cost < self.cost:
            step, improved = np.abs(theta - self.theta).max(), (self.cost - cost) / max(cost, 1e-300)
            settled = np.isfinite(self.cost) and (improved < 1e-10 or step < 1e-12)
            self.theta, self.cost, self.r, self.J, self.lam = theta, cost, r, J, max(self.lam / 3, 1e-15)
            self.done = settled or float(r @ r) < len(r) * EXACT_M ** 2  # nothing left to fit
        else:
            self.lam *= 4
            self.done = self.lam > 1e12
        self.iterations += 1

    def trial(self) -> np.ndarray:
        """The next numbers to try: the damped Gauss-Newton step from the accepted ones in the column-scaled
        Jacobian's singular directions above ``RCOND`` of the largest (the lengths do not see the others: a segment
        riding one body sees only its length; those numbers stay), no number moved by more than ``MAX_STEP_M``,
        radii kept positive."""
        w = np.sqrt(np.ones_like(self.r) if self.c <= 0 else 1 / (1 + (self.r / self.c) ** 2))
        norm = np.linalg.norm(self.J, axis=0)
        norm[norm <= 0] = 1.0  # a number without gradient: never moved
        U, sv, Vt = np.linalg.svd(w[:, None] * self.J / norm, full_matrices=False)
        keep = sv > RCOND * sv.max() if sv.max() > 0 else np.zeros_like(sv, bool)
        damped = np.where(keep, sv / (sv ** 2 + self.lam * sv.max() ** 2), 0.0)
        step = -(Vt.T @ (damped * (U.T @ (w * self.r)))) / norm
        theta = self.theta + step * min(1.0, MAX_STEP_M / max(np.abs(step).max(), 1e-300))
        theta[self.radius] = np.maximum(theta[self.radius], MIN_RADIUS_M)
        return theta


def jacobian(lengths: np.ndarray, copies: np.ndarray, step_m: float) -> tuple[np.ndarray, np.ndarray, int]:
    """Copy 0's lengths ``(N,)``, the forward-difference Jacobian ``(N, P)`` with wrap jumps zeroed, their count."""
    l0, J = lengths[:, copies[0]], (lengths[:, copies[1:]] - lengths[:, copies[:1]]) / step_m
    jumps = np.abs(J) > JUMP_SLOPE
    return l0, np.where(jumps, 0.0, J), int(jumps.sum())


def fit(rep: Replicas, full: np.ndarray, target: np.ndarray, starts: list[np.ndarray], max_iter: int,
        cauchy_m: float = 0.0, threads: int = 1) -> list:
    """Levenberg-Marquardt for every muscle at once (one MuJoCo pass per step); ``target (N, A)`` [m]."""
    kinds = [np.array([k for k, *_ in table]) for table in rep.tables]
    solvers = [LevenbergMarquardt(t.copy(), kind == "radius", kind == "side", cauchy_m)
               for t, kind in zip(starts, kinds)]
    theta = [s.theta for s in solvers]
    for _ in range(max_iter):
        rep.write(theta)
        lengths = rep.lengths(full, threads)
        for a, s in enumerate(solvers):
            if s.done:
                continue
            l0, J, jumps = jacobian(lengths, rep.copies[a], FD_STEP_M)
            s.offer(theta[a], l0 - target[:, a], J)
            s.jumps = jumps
        if all(s.done for s in solvers):
            break
        theta = [s.theta if s.done else s.trial() for s in solvers]
    return solvers


def side_search(rep: Replicas, full: np.ndarray, target: np.ndarray, solvers: list, steps_mm=(8, 4, 2, 1, 0.5),
                threads: int = 1) -> int:
    """A pattern search over the held side sites (they act only through which way a path wraps, a cost piecewise
    constant in them): per step each side-site coordinate moved by +-step in the copies, one MuJoCo pass; each
    muscle takes its best move while it lowers the cost, then the step halves. Returns the passes made."""
    passes = 0
    for step in steps_mm:
        for _ in range(4):
            moves = [np.zeros((len(s.theta), len(s.theta))) for s in solvers]
            for move, s in zip(moves, solvers):
                held = np.flatnonzero(s.held)
                rows = 2 * np.arange(len(held))
                move[rows, held], move[rows + 1, held] = 1e-3 * step, -1e-3 * step
            rep.write([s.theta for s in solvers], moves)
            lengths, passes, moved = rep.lengths(full, threads), passes + 1, False
            for a, s in enumerate(solvers):
                cost = [s.loss(lengths[:, c] - target[:, a]) for c in rep.copies[a][: 2 * s.held.sum() + 1]]
                best = int(np.argmin(cost))  # a gain below 1e-12 m per posture is rounding: the site stays
                if best and cost[best] < cost[0] * (1 - 1e-9) - len(target) * EXACT_M ** 2:
                    s.theta, s.cost, moved = s.theta + moves[a][best - 1], cost[best], True
            if not moved:
                break
    return passes


def starts(rep: Replicas, m: mujoco.MjModel, options: PathFitOptions, rng: np.random.Generator) -> list[np.ndarray]:
    """Each muscle's starting numbers (module docstring: ``prior``, ``prior_error_mm``, ``radius_error``,
    ``side_sites``)."""
    out = []
    for parts, table, truth in zip(rep.parts, rep.tables, rep.truth):
        sign = rng.choice([-1.0, 1.0], len(table))
        kind = np.array([k for k, *_ in table])
        base = truth.copy() if options.prior == "mjcf" else centroid_prior(m, parts, table, truth)
        radius = kind == "radius"
        factor = 1 + options.radius_error * sign if options.prior == "mjcf" else CENTROID_RADIUS_FACTOR
        start = np.where(radius, base * factor, base + 1e-3 * options.prior_error_mm * sign)
        if options.side_sites in ("geom", "scaled"):
            start = with_geom_offsets(m, parts, table, truth, start, options.side_sites == "scaled")
        out.append(np.where((kind == "side") & (options.side_sites == "mjcf"), truth, start))
    return out


def with_geom_offsets(m: mujoco.MjModel, parts, table, truth: np.ndarray, start: np.ndarray,
                      scaled: bool = False) -> np.ndarray:
    """``side_sites="geom"``: each side site that rides its geom's body started at the geom's start centre plus the
    prior's offset between them (which side of the geom it lies on, inside it or not: what decides the wrap, kept as
    the prior has it; a side site at its small geom's centre moved apart from it by +-1 mm lands outside a 1.5 mm
    sphere and turns MuJoCo's inside wrap into another mode). ``scaled`` (``"scaled"``): the offset times the start's
    radius over the prior's, so the side site keeps its place in units of the radius (myoArm's PECM1 has its side
    site 0.58 mm inside a 22 mm sphere: a radius 5 % smaller leaves it outside, in the other mode)."""
    out, index = start.copy(), {row: n for n, row in enumerate(table)}
    for i, part in enumerate(parts):
        if part[0] == "geom" and part[2] >= 0 and m.site_bodyid[part[2]] == m.geom_bodyid[part[1]]:
            radius = index[("radius", i, 0)]
            factor = start[radius] / truth[radius] if scaled else 1.0
            for c in range(3):
                side, centre = index[("side", i, c)], index[("geom", i, c)]
                out[side] = start[centre] + factor * (truth[side] - truth[centre])
    return out


def centroid_prior(m: mujoco.MjModel, parts, table, truth: np.ndarray) -> np.ndarray:
    """Each position at the centroid of the MJCF's sites on its body (a body without sites: its origin)."""
    def centroid(body: int) -> np.ndarray:
        on = m.site_bodyid == body
        return m.site_pos[on].mean(0) if on.any() else np.zeros(3)
    body = {"site": lambda p: m.site_bodyid[p[1]], "geom": lambda p: m.geom_bodyid[p[1]],
            "side": lambda p: m.site_bodyid[p[2]]}
    return np.array([value if kind == "radius" else centroid(body[kind](parts[i]))[c]
                     for (kind, i, c), value in zip(table, truth)])


def rank_deficit(J: np.ndarray) -> int:
    """Directions of the numbers the lengths do not see: the column-scaled Jacobian's singular values below 1e-8 of
    its largest (a number without gradient counts one)."""
    norm = np.linalg.norm(J, axis=0)
    s = np.linalg.svd(J / np.where(norm > 0, norm, 1.0), compute_uv=False)
    return int(J.shape[1] - (s > 1e-8 * s.max()).sum())


def fit_stages(rep: Replicas, full: np.ndarray, target: np.ndarray, start: list[np.ndarray],
               options: PathFitOptions) -> list:
    """The fit at each scale of ``cauchy_mm`` in turn (a graduated loss: a wide scale pulls from afar, where a
    narrow one is flat; the last ignores the postures wrapped otherwise), then ``side_search`` rounds of the side
    sites' search, each followed by the fit at the last scale; iterations summed."""
    cauchy = list(options.cauchy_mm)
    solvers, stages = None, [("fit", c) for c in cauchy] + [("side", cauchy[-1])] * options.side_search
    for kind, scale_mm in stages:
        passes = side_search(rep, full, target, solvers, options.side_steps_mm, options.threads) \
            if kind == "side" else 0
        again = fit(rep, full, target, start if solvers is None else [s.theta for s in solvers], options.max_iter,
                    1e-3 * scale_mm, options.threads)
        for new, old in zip(again, solvers or []):
            new.iterations += old.iterations + passes
        solvers = again
    return solvers


def fit_restarts(rep: Replicas, model, full: np.ndarray, target: np.ndarray, options: PathFitOptions,
                 progress: Callable[[int, int], None] | None = None) -> PathFit:
    """``restarts`` seeded fits of ``rep``'s muscles (``model``'s indices ``rep.muscles``) at full postures ``(N,
    nq)`` to ``target (N, A)`` [m]; per muscle the one with the lowest train cost. With ``retry_mm`` > 0 a restart
    refits only the muscles whose best train RMS is still above it (their own copies). ``progress(passes,
    passes_at_most)`` after each restart and at the end (``passes == passes_at_most``)."""
    best, first, passes = None, None, 0
    for restart in range(options.restarts):
        again = list(range(len(rep.tables))) if best is None or options.retry_mm <= 0 else _still_off(best, options)
        if not again:
            break
        sub = rep if len(again) == len(rep.tables) else Replicas(model, [rep.muscles[a] for a in again])
        start = starts(sub, model.mj_model, options, np.random.default_rng([options.seed, 7, restart]))
        before = sub.passes
        solvers = fit_stages(sub, full, target[:, again], start, options)
        passes += sub.passes - before
        if best is None:
            best, first = solvers, start
        for a, s in zip(again, solvers):
            best[a] = s if s.cost < best[a].cost else best[a]
        if progress is not None:
            progress(passes, passes + _passes_at_most(options) * (options.restarts - restart - 1))
    if progress is not None:  # done: the bar full, whether or not every restart ran
        progress(passes, passes)
    return PathFit([s.theta for s in best], np.array([1e3 * np.sqrt(np.mean(s.r ** 2)) for s in best]), passes,
                   np.array([s.iterations for s in best]), np.array([s.jumps for s in best]),
                   np.array([rank_deficit(s.J) for s in best]), first)


def _still_off(solvers: list, options: PathFitOptions) -> list[int]:
    """The muscles whose train RMS is above ``retry_mm`` and ``retry_medians`` times the median muscle's."""
    rms_mm = np.array([1e3 * np.sqrt(np.mean(s.r ** 2)) for s in solvers])
    limit = max(options.retry_mm, options.retry_medians * float(np.median(rms_mm)))
    return [int(a) for a in np.flatnonzero(rms_mm > limit)]


def _passes_at_most(options: PathFitOptions) -> int:
    """One restart's most MuJoCo passes: each stage's fit, each side round's 4 passes per step."""
    stages = len(options.cauchy_mm) + options.side_search
    return stages * options.max_iter + options.side_search * 4 * len(options.side_steps_mm)


def fit_path_numbers(model, q_rad: np.ndarray, target_m: np.ndarray, options: PathFitOptions = PathFitOptions(),
                     progress: Callable[[int, int], None] | None = None,
                     muscles: list[int] | None = None) -> PathFit:
    """Fit the path numbers of ``model``'s muscles (a ``sim.MusculoskeletalModel``; ``muscles``: indices into its
    muscles, default all) to their geometric lengths ``target_m (S, M)`` [m] at postures ``q_rad (S, N)`` (free
    joints, or ``(S, nq)``). Returns ``PathFit`` (per muscle its numbers in ``parts.numbers``' order); prints
    nothing. ``progress(passes, passes_at_most)``: called after each restart and at the end (MuJoCo passes over the
    postures so far, and at most in all)."""
    muscles = list(range(model.n_muscles)) if muscles is None else [int(i) for i in muscles]
    if not muscles or min(muscles) < 0 or max(muscles) >= model.n_muscles:
        raise BodySchemaInputError(f"muscles={muscles}; give indices of the model's {model.n_muscles} muscles")
    q = model.check_q(q_rad)
    target = np.asarray(target_m, float)
    if target.shape != (len(q), len(muscles)) or not np.all(np.isfinite(target)):
        raise BodySchemaInputError(f"target_m has shape {target.shape} (finite: {bool(np.isfinite(target).all())}); "
                                   f"give finite lengths [m] of shape ({len(q)}, {len(muscles)}): one per posture "
                                   "and fitted muscle")
    if not isinstance(options, PathFitOptions):
        raise BodySchemaInputError(f"options={options!r}; give a PathFitOptions")
    rep = Replicas(model, muscles)
    return fit_restarts(rep, model, model.joint_map.full_q(q), target, options, progress)
