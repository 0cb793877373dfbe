#!/usr/bin/env python
"""Does a *geometric* path model close the learned body's tail? Fit each muscle's path numbers to its lengths.

    python tools/fit_path_geometry.py [--config configs/myoarm.yaml] [--muscles TMAJ,BIClong,... | all]
                                      [--postures 2000] [--perturb-mm 5] [--perturb-radius 0.05] [--noise-mm 0]
                                      [--seed 0] [--prior mjcf | centroid] [--restarts 1] [--max-iter 40]
                                      [--cauchy-mm 0.3 | 30,3,0.3] [--side-search 0] [--side-sites start | mjcf | geom]
                                      [--side-steps-mm 8,4,2,1,0.5] [--retry-mm 0] [--equilibrium]
                                      [--flag-mm 0.1,0.5] [--flag-share 0.01] [--test-postures 2000] [--test-seed 1]
    python tools/fit_path_geometry.py --census [--config configs/myolegs-per-muscle.yaml]

The path's topology is known (MuJoCo's spatial tendon: which bodies its sites ride on, which wrapping geoms, sphere
or cylinder, it may wrap and with which side site); its numbers are not: each site's position in its body, each
wrapping geom's position in its body and radius, each side site's position (3 + 3 + 1 + 3 numbers; the geoms'
orientations, a cylinder's axis, kept from the MJCF). The length is MuJoCo's own function of those numbers: each
muscle gets ``P + 1`` private copies of its path in one expanded MjModel (its own sites, geoms and side sites on the
same bodies: a geom two muscles share is fitted per muscle), copy 0 at the current numbers, copy ``k`` with number
``k`` moved by ``FD_STEP_M``, so one ``mj_kinematics`` + ``mj_tendon`` per posture gives every muscle's residual and
forward-difference Jacobian. A Jacobian entry above ``JUMP_SLOPE`` (a length moves at most about 1 m per m of a
number: a larger one is a wrap switching between the two evaluations) is set to 0.

Levenberg-Marquardt per muscle on the Cauchy loss of scale ``--cauchy-mm`` (0: least squares; a posture the current
numbers wrap otherwise than the truth misses by a jump of millimetres and must not pull the fit; several scales: one
fit after the other, ``fit_stages``), the damped step taken in the column-scaled Jacobian's singular directions
above ``RCOND`` (the lengths do not see the others), at most ``MAX_STEP_M`` per number, radii kept >=
``MIN_RADIUS_M``. Side sites are never moved by it (``held``: they act only through which way a path wraps);
``--side-search N``: N rounds of a pattern search over them (``side_search``, steps ``--side-steps-mm``), each
followed by the fit again. Starts: the MJCF's numbers each moved by +-``--perturb-mm`` (a seeded sign per
coordinate; radii by a factor 1 +- ``--perturb-radius``; ``--side-sites mjcf`` leaves the side sites at the MJCF's),
or with ``--prior centroid`` a weak prior (each site and geom at the centroid of the MJCF's sites of its body, plus
+-``--perturb-mm`` per coordinate, radii x ``CENTROID_RADIUS_FACTOR``); ``--side-sites geom``: a side site riding
its geom's body starts at the geom's start centre plus the MJCF's offset between them (``with_geom_offsets``);
``--restarts`` seeded starts, per muscle the lowest train cost kept (``--retry-mm``: a restart refits only the
muscles still above that train RMS). Targets: MuJoCo's lengths at ``--postures`` seeded uniform postures
(``--seed``), or with ``--equilibrium`` the data module's: ``generate_equilibrium_samples`` and ``l_motor +
elongation_from_tension(f)`` with the config's spring; plus Gaussian noise of ``--noise-mm``.

Printed per muscle: its numbers, iterations (MuJoCo passes), the train RMS, the numbers' largest error [mm] per kind
(sites, geom centres, radii, side sites; a number the lengths do not see keeps its start's error, so read it with
the rank deficit: the column-scaled Jacobian's singular values below 1e-8 of its largest), the Jacobian entries
zeroed as wrap jumps, then, scored at the ``--test-postures`` postures of ``tools/body_errors.py --seed 1`` (the
same draw), its length p99 [mm] at the start and fitted and the share of postures its fitted path wraps otherwise
than the true one (``sim.wrapping.wrap_states``' codes: a mirrored geometry of the same lengths counts as wrong);
then the worst of the fitted muscles per posture: length p50 / p90 / p99 / max [mm] and moment arm (MuJoCo's tendon
Jacobian of the fitted paths: the length's exact derivative) p50 / p90 / p99 [mm/rad], start and fit; the fit's CPU
time (every muscle together: one pass serves all). ``--flag-mm``: the path-switch flag on the fitted paths' exact
margins (``switch_distance_mm``: a posture is flagged where a margin that decides a jump lies within the band of
zero), per band and for the band that flags ``--flag-share`` of the test postures: the share flagged, the bad
postures it catches, the worst muscle over the others. ``--census``: per muscle of the config's body its numbers and
wrap cases (sphere / cylinder, with or without a side site, the side site inside the geom at some of the test
postures). One thread.
"""
import argparse
import time

import mujoco
import numpy as np

from lightning_bodyschema.apps.common import exits_cleanly, robot_from_config
from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.evaluation.body_errors import BAD_LENGTH_MM as BAD_MM
from lightning_bodyschema.paths.parts import KINDS, numbers, path_parts, true_values

TAIL = "TMAJ,BIClong,DELT1,TRIlong,PECM3,LAT3,SUP"
FD_STEP_M = 1e-7  # forward-difference step of every number [m]: lengths are exact to ~1e-16 m
JUMP_SLOPE = 10.0  # |dl / dnumber| beyond this is a wrap switching inside the step, not a slope [m/m]
MIN_RADIUS_M = 1e-4
RCOND = 1e-6  # singular values of the column-scaled Jacobian below this (relative) are directions the data do not see
MAX_STEP_M = 0.01  # a step moves no number by more than this (a number seen only inside a wrap can run away)
CENTROID_RADIUS_FACTOR = 1.5
# the margins whose zero is a jump of the length: the side site behind the geom (the long way round) and inside it
# (the inside wrap); a wrap's onset where the line turns tangent (upper, lower) or a site meets the geom only bends it,
# so a state wrong there costs a length error of second order in the margin (sim/wrapping.py's docstring)
JUMP_MARGINS = ("before", "after", "inside")


class Replicas:
    """Every fitted muscle's ``P + 1`` private path copies in one expanded MjModel (module docstring)."""

    def __init__(self, model, muscles: list[int]):
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
        from lightning_bodyschema.sim import MusculoskeletalModel

        self.model = MusculoskeletalModel(spec.to_xml(), muscles=first,
                                          allow_unloaded=True, lock_uncrossed=False)
        self._index(writes)

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

    def lengths(self, full: np.ndarray) -> np.ndarray:
        """``(B, copies)`` every copy's length [m] at full postures ``(B, nq)``: MuJoCo, one posture per call."""
        m, d, ids = self.model.mj_model, self.model._data, np.array(self.tendons)
        out = np.empty((len(full), len(ids)))
        for b in range(len(full)):
            d.qpos[:] = full[b]
            mujoco.mj_kinematics(m, d)
            mujoco.mj_tendon(m, d)
            out[b] = d.ten_length[ids]
        return out


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
            self.done = settled or float(r @ r) < len(r) * 1e-24  # exact to 1e-12 m: nothing left to fit
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
        cauchy_m: float = 0.0) -> list:
    """Levenberg-Marquardt for every muscle at once (one MuJoCo pass per step); ``target (N, A)`` [m]."""
    kinds = [np.array([k for k, *_ in table]) for table in rep.tables]
    solvers = [LevenbergMarquardt(t.copy(), kind == "radius", kind == "side", cauchy_m)
               for t, kind in zip(starts, kinds)]
    theta = [s.theta for s in solvers]
    for _ in range(max_iter):
        rep.write(theta)
        lengths = rep.lengths(full)
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


def side_search(rep: Replicas, full: np.ndarray, target: np.ndarray, solvers: list, steps_mm=(8, 4, 2, 1, 0.5)) -> int:
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
            lengths, passes, moved = rep.lengths(full), passes + 1, False
            for a, s in enumerate(solvers):
                cost = [s.loss(lengths[:, c] - target[:, a]) for c in rep.copies[a][: 2 * s.held.sum() + 1]]
                best = int(np.argmin(cost))
                if best and cost[best] < cost[0] * (1 - 1e-9):
                    s.theta, s.cost, moved = s.theta + moves[a][best - 1], cost[best], True
            if not moved:
                break
    return passes


def starts(rep: Replicas, m: mujoco.MjModel, args, rng: np.random.Generator) -> list[np.ndarray]:
    """Each muscle's starting numbers (module docstring: ``--prior``, ``--perturb-mm``, ``--perturb-radius``)."""
    out = []
    for parts, table, truth in zip(rep.parts, rep.tables, rep.truth):
        sign = rng.choice([-1.0, 1.0], len(table))
        kind = np.array([k for k, *_ in table])
        base = truth.copy() if args.prior == "mjcf" else centroid_prior(m, parts, table, truth)
        radius = kind == "radius"
        factor = 1 + args.perturb_radius * sign if args.prior == "mjcf" else CENTROID_RADIUS_FACTOR
        start = np.where(radius, base * factor, base + 1e-3 * args.perturb_mm * sign)
        if args.side_sites == "geom":
            start = with_geom_offsets(m, parts, table, truth, start)
        out.append(np.where((kind == "side") & (args.side_sites == "mjcf"), truth, start))
    return out


def with_geom_offsets(m: mujoco.MjModel, parts, table, truth: np.ndarray, start: np.ndarray) -> np.ndarray:
    """``--side-sites geom``: each side site that rides its geom's body started at the geom's start centre plus the
    prior's offset between them (which side of the geom it lies on, inside it or not: what decides the wrap, kept as
    the prior has it; a side site at its small geom's centre moved apart from it by +-1 mm lands outside a 1.5 mm
    sphere and turns MuJoCo's inside wrap into another mode)."""
    out, index = start.copy(), {row: n for n, row in enumerate(table)}
    for i, part in enumerate(parts):
        if part[0] == "geom" and part[2] >= 0 and m.site_bodyid[part[2]] == m.geom_bodyid[part[1]]:
            for c in range(3):
                side, centre = index[("side", i, c)], index[("geom", i, c)]
                out[side] = start[centre] + truth[side] - truth[centre]
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


def number_errors_mm(table, theta: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    """The largest |error| [mm] of each kind of number (NaN: the path has none)."""
    kind, err = np.array([k for k, *_ in table]), 1e3 * np.abs(theta - truth)
    return {k: float(err[kind == k].max()) if (kind == k).any() else float("nan") for k in KINDS}


def rank_deficit(J: np.ndarray) -> int:
    """Directions of the numbers the lengths do not see: the column-scaled Jacobian's singular values below 1e-8 of
    its largest (a number without gradient counts one)."""
    norm = np.linalg.norm(J, axis=0)
    s = np.linalg.svd(J / np.where(norm > 0, norm, 1.0), compute_uv=False)
    return int(J.shape[1] - (s > 1e-8 * s.max()).sum())


def score(rep: Replicas, model, muscles: list[int], theta: list[np.ndarray], q: np.ndarray, truth) -> dict:
    """The fitted paths against MuJoCo's at postures ``q``: worst muscle per posture, per muscle p99, states."""
    from lightning_bodyschema.sim.wrapping import wrap_states

    l_true, G_true, states_true = truth
    rep.write(theta)
    l_fit, G_fit, _ = rep.model.kinematics(q)
    crossed = np.abs(G_true).max(0) > 1e-12
    length_mm = 1e3 * np.abs(l_fit - l_true)
    arm = np.where(crossed, 1e3 * np.abs(G_fit - G_true), 0.0).reshape(len(q), -1).max(1)
    return {**worst_figures(length_mm.max(1), arm), "p99": np.percentile(length_mm, 99, axis=0),
            "wrong_state": (wrap_states(rep.model, q) != states_true).mean(0), "bad": (length_mm > BAD_MM).mean(0),
            "worst_mm": length_mm.max(1), "worst_arm": arm}


def worst_figures(worst_mm: np.ndarray, worst_arm: np.ndarray) -> dict:
    """p50 / p90 / p99 / max of the worst muscle's length [mm] and moment arm [mm/rad] per posture, the bad share."""
    pct = lambda a: [float(np.percentile(a, p)) if len(a) else float("nan") for p in (50, 90, 99, 100)]  # noqa: E731
    return {"length": pct(worst_mm), "arm": pct(worst_arm),
            "bad_postures": float((worst_mm > BAD_MM).mean()) if len(worst_mm) else float("nan")}


def switch_distance_mm(rep: Replicas, q: np.ndarray) -> np.ndarray:
    """``(B,)`` per posture the smallest |margin| [mm] of the fitted paths (``sim.wrapping.wrap_margins`` of copy 0:
    exact) whose sign decides its muscle's state: a margin counts where flipping its sign alone changes the state code
    (``states_from_margins``: MuJoCo's rule), among ``JUMP_MARGINS`` only, and a margin constant over ``q`` (its points
    ride one body) never switches; inf where nothing can switch."""
    from lightning_bodyschema.sim.wrapping import MARGINS, states_from_margins, wrap_margins

    margins = wrap_margins(rep.model, q)  # (B, M, J, 9) [m]
    moving = np.ptp(np.nan_to_num(margins), axis=0) > 1e-9  # (M, J, 9): a constant margin never crosses zero
    codes, out = states_from_margins(margins), np.full(margins.shape[:2], np.inf)
    for j in range(margins.shape[2]):
        for k in [MARGINS.index(name) for name in JUMP_MARGINS]:
            flipped = margins.copy()
            flipped[:, :, j, k] *= -1
            decides = (states_from_margins(flipped) != codes) & moving[None, :, j, k]
            out = np.where(decides, np.minimum(out, 1e3 * np.abs(margins[:, :, j, k])), out)
    return out.min(1)


def census(model, q: np.ndarray) -> str:
    """Per muscle its numbers and wrap cases (module docstring, ``--census``), and the totals."""
    from lightning_bodyschema.sim.wrapping import wrap_margins

    inside = wrap_margins(model, q)[..., -1] > 0  # (B, M, J): the side site inside its geom
    m, cases = model.mj_model, {}
    lines = ["| muscle | numbers | sites | spheres | cylinders | side sites | side site inside its geom "
             "[% of postures] |",
             "|---|---|---|---|---|---|---|"]
    for a, tendon in enumerate(model.muscle_ids):
        parts = path_parts(m, tendon)
        geoms = [p for p in parts if p[0] == "geom"]
        for j, (_, g, side) in enumerate(geoms):
            key = ("sphere" if m.geom_type[g] == mujoco.mjtGeom.mjGEOM_SPHERE else "cylinder",
                   "side site" if side >= 0 else "no side site", "inside" if inside[:, a, j].any() else "")
            cases[key] = cases.get(key, 0) + 1
        lines.append(f"| {model.muscle_names[a]} | {len(numbers(m, parts))} | {len(parts) - len(geoms)} | "
                     f"{sum(m.geom_type[p[1]] == mujoco.mjtGeom.mjGEOM_SPHERE for p in geoms)} | "
                     f"{sum(m.geom_type[p[1]] == mujoco.mjtGeom.mjGEOM_CYLINDER for p in geoms)} | "
                     f"{sum(p[2] >= 0 for p in geoms)} | "
                     + " ".join(f"{100 * inside[:, a, j].mean():.3g}" for j in range(len(geoms))) + " |")
    total = sum(len(numbers(m, path_parts(m, t))) for t in model.muscle_ids)
    lines += ["", f"{model.n_muscles} muscles, {total} numbers; wrap cases (geom slots): "
              + ", ".join(f"{' '.join(k).strip()}: {n}" for k, n in sorted(cases.items()))]
    return "\n".join(lines)


def pick_muscles(model, spec: str) -> list[int]:
    """Muscle indices from ``--muscles`` (names or name prefixes before ``_tendon``; ``all``)."""
    if spec == "all":
        return list(range(model.n_muscles))
    names, out = model.muscle_names, []
    for name in spec.split(","):
        hits = [i for i, n in enumerate(names) if n in (name, f"{name}_tendon")]
        if not hits:
            raise BodySchemaInputError(f"--muscles: unknown muscle {name!r}; the body's muscles are "
                                       f"{[n.removesuffix('_tendon') for n in names]} (or 'all')")
        out += hits
    return out


def scales(text: str) -> list[float]:
    """``--cauchy-mm``: comma-separated numbers."""
    try:
        return [float(x) for x in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected numbers [mm], comma separated (e.g. 30,3,0.3)") from None


def check_args(args) -> None:
    if args.postures < 1 or args.test_postures < 1 or args.restarts < 1 or args.max_iter < 1 or args.side_search < 0:
        raise BodySchemaInputError(f"--postures {args.postures}, --test-postures {args.test_postures}, --restarts "
                                   f"{args.restarts}, --max-iter {args.max_iter}: each must be an integer >= 1 "
                                   f"(--side-search {args.side_search}: >= 0)")
    if args.perturb_mm < 0 or args.noise_mm < 0 or min(args.cauchy_mm) < 0 or not 0 <= args.perturb_radius < 1:
        raise BodySchemaInputError(f"--perturb-mm {args.perturb_mm}, --noise-mm {args.noise_mm}, --cauchy-mm "
                                   f"{args.cauchy_mm} must be >= 0 and "
                                   f"--perturb-radius {args.perturb_radius} in [0, 1)")
    if (args.flag_mm is not None and min(args.flag_mm) < 0) or not 0 <= args.flag_share < 1:
        raise BodySchemaInputError(f"--flag-mm {args.flag_mm} must be >= 0 [mm] and --flag-share {args.flag_share} "
                                   "in [0, 1)")
    if args.seed == args.test_seed and not args.equilibrium:
        raise BodySchemaInputError(f"--seed {args.seed} is --test-seed: the train postures would be the test ones")


def fit_restarts(rep: Replicas, model, full: np.ndarray, target: np.ndarray, args) -> tuple[list, list, float]:
    """``--restarts`` seeded fits; per muscle the one with the lowest train cost; its start; CPU seconds. With
    ``--retry-mm`` > 0 a restart refits only the muscles whose best train RMS is still above it (their own copies)."""
    best, first, cpu = None, None, time.process_time()
    for restart in range(args.restarts):
        again = list(range(len(rep.tables))) if best is None or args.retry_mm <= 0 else [
            a for a, b in enumerate(best) if 1e3 * np.sqrt(np.mean(b.r ** 2)) > args.retry_mm]
        if not again:
            break
        sub = rep if len(again) == len(rep.tables) else Replicas(model, [rep.muscles[a] for a in again])
        start = starts(sub, model.mj_model, args, np.random.default_rng([args.seed, 7, restart]))
        solvers = fit_stages(sub, full, target[:, again], start, args)
        if best is None:
            best, first = solvers, start
        for a, s in zip(again, solvers):
            best[a] = s if s.cost < best[a].cost else best[a]
    return best, first, time.process_time() - cpu


def fit_stages(rep: Replicas, full: np.ndarray, target: np.ndarray, start: list[np.ndarray], args) -> list:
    """The fit at each scale of ``--cauchy-mm`` in turn (a graduated loss: a wide scale pulls from afar, where a
    narrow one is flat; the last ignores the postures wrapped otherwise), then ``--side-search`` rounds of the side
    sites' search, each followed by the fit at the last scale; iterations summed."""
    solvers, stages = None, [("fit", c) for c in args.cauchy_mm] + [("side", args.cauchy_mm[-1])] * args.side_search
    for kind, scale_mm in stages:
        passes = side_search(rep, full, target, solvers, args.side_steps_mm) if kind == "side" else 0
        again = fit(rep, full, target, start if solvers is None else [s.theta for s in solvers], args.max_iter,
                    1e-3 * scale_mm)
        for new, old in zip(again, solvers or []):
            new.iterations += old.iterations + passes
        solvers = again
    return solvers


def row(label: str, s: dict) -> str:
    f = lambda v: " / ".join(f"{x:.3g}" for x in v)  # noqa: E731
    return f"| {label} | {f(s['length'])} | {f(s['arm'][:3])} | {100 * s['bad_postures']:.3g} % |"


@exits_cleanly
def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default="configs/myoarm.yaml")
    parser.add_argument("--muscles", default=TAIL, help="names (without _tendon), comma separated, or 'all'")
    parser.add_argument("--postures", type=int, default=2000, help="train postures")
    parser.add_argument("--perturb-mm", type=float, default=5.0)
    parser.add_argument("--perturb-radius", type=float, default=0.05, help="radii's relative perturbation")
    parser.add_argument("--noise-mm", type=float, default=0.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--prior", choices=("mjcf", "centroid"), default="mjcf")
    parser.add_argument("--restarts", type=int, default=1)
    parser.add_argument("--retry-mm", type=float, default=0.0,
                        help="> 0: restarts refit only the muscles whose train RMS is above this [mm]")
    parser.add_argument("--side-sites", choices=("start", "mjcf", "geom"), default="start",
                        help="side sites (never fitted) at the start's numbers, the MJCF's, or their geom's start "
                             "centre plus the MJCF's offset")
    parser.add_argument("--cauchy-mm", type=scales, default=[0.3],
                        help="Cauchy loss scales, comma separated, fitted in turn (0: least squares)")
    parser.add_argument("--side-search", type=int, default=0,
                        help="rounds of a pattern search over the side sites, each followed by the fit again")
    parser.add_argument("--side-steps-mm", type=scales, default=[8, 4, 2, 1, 0.5],
                        help="the side search's steps [mm], comma separated, in turn")
    parser.add_argument("--max-iter", type=int, default=40)
    parser.add_argument("--test-postures", type=int, default=2000)
    parser.add_argument("--test-seed", type=int, default=1)
    parser.add_argument("--census", action="store_true")
    parser.add_argument("--equilibrium", action="store_true",
                        help="train on generate_equilibrium_samples' postures and l_motor + elongation(f)")
    parser.add_argument("--flag-mm", type=scales, default=None,
                        help="flag bands [mm], comma separated: postures with a deciding margin within one")
    parser.add_argument("--flag-share", type=float, default=0.01, help="also the band that flags this share")
    args = parser.parse_args(argv)
    check_args(args)
    model, spring, _ = robot_from_config(args.config)
    q_test = model.sample_q(np.random.default_rng(args.test_seed), args.test_postures)  # tools/body_errors.py's draw
    if args.census:
        print(census(model, q_test))
        return
    run(model, spring, pick_muscles(model, args.muscles), q_test, args)


def run(model, spring, muscles: list[int], q_test: np.ndarray, args) -> None:
    """Fit, score and print (module docstring)."""
    from lightning_bodyschema.sim.wrapping import wrap_states

    rep = Replicas(model, muscles)
    rng = np.random.default_rng(args.seed)
    q, l_true = train_targets(model, spring, muscles, rng, args)
    target = l_true + 1e-3 * args.noise_mm * rng.standard_normal(l_true.shape)
    full = model.joint_map.full_q(q)
    rep.write(rep.truth)
    exact = float(np.abs(rep.lengths(full[:50])[:, [c[0] for c in rep.copies]] - l_true[:50]).max())
    solvers, start, cpu = fit_restarts(rep, model, full, target, args)
    l_t, G_t, _ = model.kinematics(q_test)
    truth = (l_t[:, muscles], G_t[:, muscles], wrap_states(model, q_test)[:, muscles])
    print(f"{len(muscles)} muscles, {args.postures} train postures (seed {args.seed}), start: prior {args.prior}, "
          f"+-{args.perturb_mm} mm, radii {args.perturb_radius if args.prior == 'mjcf' else CENTROID_RADIUS_FACTOR}, "
          f"restarts {args.restarts}, side sites at the {args.side_sites}'s; Cauchy {args.cauchy_mm} mm; side search "
          f"{args.side_search}; noise {args.noise_mm} mm; the copies at the MJCF's numbers reproduce MuJoCo's lengths "
          f"to {exact:.2g} m; fit CPU {cpu:.1f} s")
    s0, s1 = (score(rep, model, muscles, th, q_test, truth) for th in (start, [s.theta for s in solvers]))
    print(muscle_table(rep, solvers, (s0, s1), [model.muscle_names[i].removesuffix("_tendon") for i in muscles]))
    print()
    print(f"| worst of the {len(muscles)} per test posture ({args.test_postures}) | length p50 / p90 / p99 / max [mm] "
          f"| moment arm p50 / p90 / p99 [mm/rad] | postures > {BAD_MM} mm |")
    print("|---|---|---|---|")
    print(row("start", s0))
    print(row("fit", s1))
    if args.flag_mm is not None:
        rep.write([s.theta for s in solvers])
        print()
        print(flag_table(switch_distance_mm(rep, q_test), s1, args))


def train_targets(model, spring, muscles: list[int], rng: np.random.Generator, args) -> tuple[np.ndarray, np.ndarray]:
    """Train postures ``(N, n)`` and their lengths ``(N, A)`` [m]: MuJoCo's at seeded uniform postures, or with
    ``--equilibrium`` what the schema learns from: ``generate_equilibrium_samples`` (postures the muscles hold, seed
    ``--seed``) and its ``l_motor + elongation_from_tension(f)`` (the spring law of the config)."""
    if not args.equilibrium:
        q = model.sample_q(rng, args.postures)
        return q, model.kinematics(q)[0][:, muscles]
    from lightning_bodyschema.sim.equilibrium import generate_equilibrium_samples
    from lightning_bodyschema.sim.spring import elongation_from_tension

    data = generate_equilibrium_samples(model, args.postures, args.seed, spring)
    l_geo = (data.l_motor + elongation_from_tension(data.f, spring))[:, muscles]
    off_m = np.abs(l_geo - model.kinematics(data.q)[0][:, muscles]).max()
    print(f"train: {args.postures} equilibrium postures ({data.n_redrawn} unholdable draws re-drawn), l_motor + "
          f"elongation(f) off MuJoCo's lengths by {off_m:.2g} m")
    return data.q, l_geo


def flag_table(distance_mm: np.ndarray, s: dict, args) -> str:
    """Per band of ``--flag-mm`` (and the band that flags ``--flag-share`` of the postures): postures whose fitted
    paths have a deciding margin within the band of zero (``switch_distance_mm``), flagged share, the bad postures
    caught, and the worst muscle over the others."""
    order = np.sort(distance_mm)
    share_band = float(order[int(np.floor(args.flag_share * len(order)))])  # distance < band: at most the share
    bad = s["worst_mm"] > BAD_MM
    lines = [f"| flag band [mm] | flagged | bad (> {BAD_MM} mm) caught | the others: worst length p50 / p90 / p99 / "
             "max [mm] | worst moment arm p50 / p90 / p99 / max [mm/rad] |", "|---|---|---|---|---|"]
    for band in sorted(args.flag_mm) + [share_band]:
        flagged, keep = distance_mm < band, distance_mm >= band
        other = worst_figures(s["worst_mm"][keep], s["worst_arm"][keep])
        label = f"{band:.3g}" + (f" (the {100 * args.flag_share:.3g} % band)" if band == share_band else "")
        lines.append(f"| {label} | {flagged.sum()} ({100 * flagged.mean():.3g} %) | {(flagged & bad).sum()} of "
                     f"{bad.sum()} | " + " / ".join(f"{x:.3g}" for x in other["length"]) + " | "
                     + " / ".join(f"{x:.3g}" for x in other["arm"]) + " |")
    return "\n".join(lines)


def muscle_table(rep: Replicas, solvers: list, scores: tuple[dict, dict], names: list[str]) -> str:
    """Per muscle: the fit's figures and its test scores (module docstring)."""
    (s0, s1), lines = scores, [
        "| muscle | numbers | iterations | train RMS [mm] | error [mm] sites / geom centres / radii / side sites | "
        f"rank deficit | wrap jumps in J | test p99 start -> fit [mm] | > {BAD_MM} mm | wrong state |",
        "|---|---|---|---|---|---|---|---|---|---|"]
    for a, s in enumerate(solvers):
        err = number_errors_mm(rep.tables[a], s.theta, rep.truth[a])
        lines.append(f"| {names[a]} | {len(s.theta)} | {s.iterations} | {1e3 * np.sqrt(np.mean(s.r ** 2)):.3g} | "
                     + " / ".join(f"{err[k]:.3g}" for k in KINDS) + f" | {rank_deficit(s.J)} | {s.jumps} | "
                     f"{s0['p99'][a]:.3g} -> {s1['p99'][a]:.3g} | {100 * float(s1['bad'][a]):.3g} % | "
                     f"{100 * float(s1['wrong_state'][a]):.3g} % |")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
