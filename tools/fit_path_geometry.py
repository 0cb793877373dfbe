#!/usr/bin/env python
"""Does a *geometric* path model close the learned body's tail? Fit each muscle's path numbers to its lengths.

    python tools/fit_path_geometry.py [--config configs/myoarm.yaml] [--muscles TMAJ,BIClong,... | all]
                                      [--postures 2000] [--perturb-mm 5] [--perturb-radius 0.05] [--noise-mm 0]
                                      [--seed 0] [--prior mjcf | centroid] [--restarts 1] [--max-iter 40]
                                      [--cauchy-mm 0.3 | 30,3,0.3] [--side-search 0]
                                      [--side-sites start | mjcf | geom | scaled]
                                      [--side-steps-mm 8,4,2,1,0.5] [--retry-mm 0] [--equilibrium]
                                      [--flag-mm 0.1,0.5] [--flag-share 0.01] [--test-postures 2000] [--test-seed 1]
                                      [--threads 1]
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
its geom's body starts at the geom's start centre plus the MJCF's offset between them (``with_geom_offsets``;
``scaled``: the offset times the start's radius over the MJCF's, the side site's place in units of the radius kept);
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
postures). ``--threads``: MuJoCo's passes over the train postures on that many threads (the same numbers). The
fitting core is the library's ``lightning_bodyschema.paths.fit`` (``fit_restarts``, its options from these).
"""
import argparse
import time

import mujoco
import numpy as np

from lightning_bodyschema.apps.common import exits_cleanly, robot_from_config
from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.evaluation.body_errors import BAD_LENGTH_MM as BAD_MM
from lightning_bodyschema.paths.fit import CENTROID_RADIUS_FACTOR, PathFit, PathFitOptions, Replicas, fit_restarts
from lightning_bodyschema.paths.parts import KINDS, numbers, path_parts

TAIL = "TMAJ,BIClong,DELT1,TRIlong,PECM3,LAT3,SUP"
# the margins whose zero is a jump of the length: the side site behind the geom (the long way round) and inside it
# (the inside wrap); a wrap's onset where the line turns tangent (upper, lower) or a site meets the geom only bends it,
# so a state wrong there costs a length error of second order in the margin (sim/wrapping.py's docstring)
JUMP_MARGINS = ("before", "after", "inside")


def number_errors_mm(table, theta: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    """The largest |error| [mm] of each kind of number (NaN: the path has none)."""
    kind, err = np.array([k for k, *_ in table]), 1e3 * np.abs(theta - truth)
    return {k: float(err[kind == k].max()) if (kind == k).any() else float("nan") for k in KINDS}


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
    if min(args.postures, args.test_postures, args.restarts, args.max_iter, args.threads) < 1 or args.side_search < 0:
        raise BodySchemaInputError(f"--postures {args.postures}, --test-postures {args.test_postures}, --restarts "
                                   f"{args.restarts}, --max-iter {args.max_iter}, --threads {args.threads}: each must "
                                   f"be an integer >= 1 (--side-search {args.side_search}: >= 0)")
    if args.perturb_mm < 0 or args.noise_mm < 0 or min(args.cauchy_mm) < 0 or not 0 <= args.perturb_radius < 1:
        raise BodySchemaInputError(f"--perturb-mm {args.perturb_mm}, --noise-mm {args.noise_mm}, --cauchy-mm "
                                   f"{args.cauchy_mm} must be >= 0 and "
                                   f"--perturb-radius {args.perturb_radius} in [0, 1)")
    if (args.flag_mm is not None and min(args.flag_mm) < 0) or not 0 <= args.flag_share < 1:
        raise BodySchemaInputError(f"--flag-mm {args.flag_mm} must be >= 0 [mm] and --flag-share {args.flag_share} "
                                   "in [0, 1)")
    if args.seed == args.test_seed and not args.equilibrium:
        raise BodySchemaInputError(f"--seed {args.seed} is --test-seed: the train postures would be the test ones")


def fit_options(args) -> PathFitOptions:
    """The library fit's options from the command line (``--perturb-mm`` and ``--perturb-radius``: the prior's
    error)."""
    return PathFitOptions(prior_error_mm=args.perturb_mm, radius_error=args.perturb_radius, prior=args.prior,
                          seed=args.seed, restarts=args.restarts, max_iter=args.max_iter,
                          cauchy_mm=tuple(args.cauchy_mm), side_search=args.side_search, side_sites=args.side_sites,
                          side_steps_mm=tuple(args.side_steps_mm), retry_mm=args.retry_mm, threads=args.threads)


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
    parser.add_argument("--side-sites", choices=("start", "mjcf", "geom", "scaled"), default="start",
                        help="side sites (never fitted) at the start's numbers, the MJCF's, or their geom's start "
                             "centre plus the MJCF's offset (scaled: times the start's radius over the MJCF's)")
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
    parser.add_argument("--threads", type=int, default=1, help="MuJoCo's passes over the postures on this many "
                        "threads (the same numbers whatever the count)")
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
    cpu = time.process_time()
    fitted = fit_restarts(rep, model, full, target, fit_options(args))
    cpu = time.process_time() - cpu
    l_t, G_t, _ = model.kinematics(q_test)
    truth = (l_t[:, muscles], G_t[:, muscles], wrap_states(model, q_test)[:, muscles])
    print(f"{len(muscles)} muscles, {args.postures} train postures (seed {args.seed}), start: prior {args.prior}, "
          f"+-{args.perturb_mm} mm, radii {args.perturb_radius if args.prior == 'mjcf' else CENTROID_RADIUS_FACTOR}, "
          f"restarts {args.restarts}, side sites at the {args.side_sites}'s; Cauchy {args.cauchy_mm} mm; side search "
          f"{args.side_search}; noise {args.noise_mm} mm; the copies at the MJCF's numbers reproduce MuJoCo's lengths "
          f"to {exact:.2g} m; fit CPU {cpu:.1f} s")
    s0, s1 = (score(rep, model, muscles, th, q_test, truth) for th in (fitted.start, fitted.numbers))
    print(muscle_table(rep, fitted, (s0, s1), [model.muscle_names[i].removesuffix("_tendon") for i in muscles]))
    print()
    print(f"| worst of the {len(muscles)} per test posture ({args.test_postures}) | length p50 / p90 / p99 / max [mm] "
          f"| moment arm p50 / p90 / p99 [mm/rad] | postures > {BAD_MM} mm |")
    print("|---|---|---|---|")
    print(row("start", s0))
    print(row("fit", s1))
    if args.flag_mm is not None:
        rep.write(fitted.numbers)
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


def muscle_table(rep: Replicas, fitted: PathFit, scores: tuple[dict, dict], names: list[str]) -> str:
    """Per muscle: the fit's figures and its test scores (module docstring)."""
    (s0, s1), lines = scores, [
        "| muscle | numbers | iterations | train RMS [mm] | error [mm] sites / geom centres / radii / side sites | "
        f"rank deficit | wrap jumps in J | test p99 start -> fit [mm] | > {BAD_MM} mm | wrong state |",
        "|---|---|---|---|---|---|---|---|---|---|"]
    for a, theta in enumerate(fitted.numbers):
        err = number_errors_mm(rep.tables[a], theta, rep.truth[a])
        lines.append(f"| {names[a]} | {len(theta)} | {fitted.iterations[a]} | {fitted.train_rms_mm[a]:.3g} | "
                     + " / ".join(f"{err[k]:.3g}" for k in KINDS) + f" | {fitted.rank_deficit[a]} | "
                     f"{fitted.jumps[a]} | {s0['p99'][a]:.3g} -> {s1['p99'][a]:.3g} | "
                     f"{100 * float(s1['bad'][a]):.3g} % | {100 * float(s1['wrong_state'][a]):.3g} % |")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
