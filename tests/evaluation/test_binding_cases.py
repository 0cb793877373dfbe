"""The binding case protocol: every case has a physical solution and its healthy command breaks every fault;
seeded, byte-deterministic files. Also: the torque-reach screen that lets the feasibility QP skip hopeless cases."""
import numpy as np
import pytest

from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.evaluation import (FaultCases, ForwardSolverParams, check_feasible, evaluate_commands,
                                             make_fault_cases, oracle_commands)
from lightning_bodyschema.evaluation.cases import (BINDING_CONDITIONS, MIN_PAYOUT_M, MIN_PULL_N, REJECT_REASONS,
                                                   HealthyPool, make_binding_cases)
from lightning_bodyschema.evaluation.feasibility import outside_torque_reach, tension_bounds
from lightning_bodyschema.evaluation.metrics import band_error, cut_error, fix_error, weak_error
from lightning_bodyschema.sim import MusculoskeletalModel, SpringParams, generate_equilibrium_samples
from lightning_bodyschema.sim.equilibrium import solve_equilibrium_qp

N_PER_CONDITION = 12


@pytest.fixture(scope="module")
def model():
    return MusculoskeletalModel("paper_arm")


@pytest.fixture(scope="module")
def pool(model):
    data = generate_equilibrium_samples(model, 80, seed=3)
    return HealthyPool(data.q, data.l_motor, data.f)


@pytest.fixture(scope="module")
def drawn(model, pool):
    return make_binding_cases(model, pool, N_PER_CONDITION, seed=0)


def healthy_commands(pool, cases):
    """The pool's healthy (l_motor, f) at each case's q_ref (the posture it was drawn from)."""
    row = np.array([np.flatnonzero((pool.q == q).all(1))[0] for q in cases.q_ref])
    return pool.l_motor[row], pool.f[row]


def test_every_condition_has_its_cases_and_faults(drawn):
    cases, rejected = drawn
    assert cases.cond.tolist() == [c for c in BINDING_CONDITIONS for _ in range(N_PER_CONDITION)]
    counts = {"CUT": (2, 0, 0, 0), "FIX": (0, 2, 0, 0), "BOTH": (1, 1, 0, 0), "WEAK": (0, 0, 1, 0),
              "BAND": (0, 0, 0, 1)}
    for cond, expected in counts.items():
        rows = cases.cond == cond
        got = tuple(int(m[rows].sum(1).max()) for m in (cases.cut, cases.fix, cases.weak, cases.band))
        assert got == expected and all(m[rows].sum(1).min() == e for m, e in
                                       zip((cases.cut, cases.fix, cases.weak, cases.band), expected)), cond
    assert set(rejected) == set(BINDING_CONDITIONS)
    assert all(set(r) <= set(REJECT_REASONS) for r in rejected.values())


def test_every_case_is_feasible_and_the_oracle_scores_zero(model, drawn):
    cases, _ = drawn
    feasible, l_motor, f = oracle_commands(model, cases)  # the physical reading: a jammed wire still pulls
    assert feasible.all()
    met = evaluate_commands(model, cases, l_motor, f, params=ForwardSolverParams(jammed_tension_in_torque=True))
    for name in ("E_cut", "E_fix", "E_weak", "E_band", "E_tau", "E_q"):
        assert np.nanmax(met[name]) <= 1e-6, name


def test_the_healthy_command_breaks_every_fault(pool, drawn):
    cases, _ = drawn
    l_h, f_h = healthy_commands(pool, cases)
    # per muscle: a cut muscle pulls, a jammed motor must pay out >= 0.5 mm, a weakened muscle is over its limit,
    # a banded motor is >= 0.5 mm outside its band
    assert np.all(f_h[cases.cut] > MIN_PULL_N)
    assert np.all(l_h[cases.fix] - cases.l_fixed[cases.fix] >= MIN_PAYOUT_M - 1e-12)
    assert np.all(f_h[cases.weak] - cases.f_max[cases.weak] >= MIN_PULL_N - 1e-9)
    lo, hi = cases.l_band[..., 0][cases.band], cases.l_band[..., 1][cases.band]
    assert np.all(np.maximum(lo - l_h[cases.band], l_h[cases.band] - hi) >= MIN_PAYOUT_M - 1e-12)
    # the same through the benchmark's own metrics, per condition
    for cond, metric, floor in (("CUT", cut_error(cases, f_h), MIN_PULL_N), ("FIX", fix_error(cases, l_h), MIN_PAYOUT_M),
                                ("BOTH", fix_error(cases, l_h), MIN_PAYOUT_M), ("BOTH", cut_error(cases, f_h), MIN_PULL_N),
                                ("WEAK", weak_error(cases, f_h), MIN_PULL_N), ("BAND", band_error(cases, l_h), MIN_PAYOUT_M)):
        assert np.all(metric[cases.cond == cond] >= floor - 1e-9), cond


def test_jam_windows_span_the_reachable_range(model, pool, drawn):
    """l_fixed lies between the tightest length the spring allows and 0.5 mm below the healthy length, and both
    shallow and deep jams occur (the draw is not stuck at one end of the window)."""
    cases, _ = drawn
    l_h, _ = healthy_commands(pool, cases)
    l_geo = model.kinematics(cases.q_ref)[0]
    depth = (l_h - cases.l_fixed)[cases.fix]
    assert np.all(cases.l_fixed[cases.fix] >= (l_geo - SpringParams().delta_max_m)[cases.fix] - 1e-12)
    assert depth.min() < 2e-3 and depth.max() > 3e-3


def test_same_seed_same_bytes_other_seed_other_cases(model, pool, drawn, tmp_path):
    cases, _ = drawn
    again, _ = make_binding_cases(model, pool, N_PER_CONDITION, seed=0)
    cases.save(tmp_path / "a.npz")
    again.save(tmp_path / "b.npz")
    assert (tmp_path / "a.npz").read_bytes() == (tmp_path / "b.npz").read_bytes()
    other, _ = make_binding_cases(model, pool, N_PER_CONDITION, seed=1)
    assert not np.array_equal(other.q_ref, cases.q_ref)
    loaded = FaultCases.load(tmp_path / "a.npz")
    for name, array in cases.arrays().items():
        assert np.array_equal(getattr(loaded, name), array, equal_nan=array.dtype.kind == "f"), name


def test_a_robot_without_binding_cases_is_refused_clearly(model, pool):
    slack = HealthyPool(pool.q, pool.l_motor, np.zeros_like(pool.f))  # no muscle pulls: nothing to cut
    with pytest.raises(BodySchemaInputError, match="CUT: only 0 of 3 cases"):
        make_binding_cases(model, slack, 3, seed=0, conditions=("CUT",), max_draws_per_case=40)
    with pytest.raises(BodySchemaInputError, match="unknown binding conditions"):
        make_binding_cases(model, pool, 3, conditions=("NONE",))


@pytest.mark.parametrize("jammed_pull", [True, False])
def test_torque_reach_screen_agrees_with_the_qp(model, pool, jammed_pull):
    """The screen only ever drops cases the QP also finds infeasible, and on this 2-joint arm it finds them all."""
    cases = make_fault_cases(pool.q, pool.l_motor, 30, seed=5)
    l_geo, G, tau_bias = model.kinematics(cases.q_ref)
    lo, hi, _, _ = tension_bounds(l_geo, cases.faults, SpringParams(), jammed_tension_in_torque=jammed_pull)
    outside = outside_torque_reach(G, tau_bias, lo, hi)
    _, solved = solve_equilibrium_qp(G, tau_bias, np.full(lo.shape, 75.0), f_lo_n=lo, f_hi_n=hi)
    assert outside.any() and not (outside & solved).any()
    assert np.array_equal(outside, ~solved)
    feasible, _ = check_feasible(model, cases, jammed_tension_in_torque=jammed_pull)
    assert not (feasible & outside).any()


def test_torque_reach_screen_on_many_joints_counts_facets_and_keeps_every_feasible_case():
    """myoHand's 15 joints and 31 muscles have C(31, 14) = 265 million facets: the screen must count them, not list
    them (listing filled 22 GB and was OOM-killed), and test along other directions instead: a torque far out of
    reach is dropped, and a torque some tension in the box gives is never dropped."""
    rng = np.random.default_rng(0)
    G = rng.normal(scale=0.01, size=(40, 31, 15))
    lo, hi = np.zeros((40, 31)), np.full((40, 31), 100.0)
    reachable = -np.einsum("bmn,bm->bn", G, rng.uniform(0.0, 100.0, size=(40, 31)))
    assert not outside_torque_reach(G, reachable, lo, hi).any()
    far = reachable + 50.0 * rng.normal(size=reachable.shape)  # 50 N m: beyond 31 muscles x 100 N x ~1 cm
    outside = outside_torque_reach(G, far, lo, hi)
    _, solved = solve_equilibrium_qp(G, far, np.full(lo.shape, 50.0), f_lo_n=lo, f_hi_n=hi)
    assert outside.all() and not solved.any()


@pytest.mark.parametrize("name", ["paper_arm", "arm3_8"])
def test_the_physics_checks_screen_agrees_with_the_feasibility_qp(name):
    """Where the torque zonotope's facets are enumerable, the physics check decides feasibility by the exact screen
    alone (``sim.feasibility.feasible_cases``): the same answer as the QP on random cuts, jams and weakened muscles
    (about half the cases feasible, so neither answer is trivial)."""
    from lightning_bodyschema.faults.faults import Faults
    from lightning_bodyschema.sim.feasibility import feasible_cases, feasible_tensions
    from lightning_bodyschema.solvers import screen_is_exact

    robot = MusculoskeletalModel(name)
    assert screen_is_exact(robot.n_muscles, robot.n_joints)
    rng = np.random.default_rng(7)
    n, m = 600, robot.n_muscles
    q = robot.sample_q(rng, n)
    l_geo = robot.kinematics(q)[0]
    cut = rng.random((n, m)) < 0.15
    fix = ~cut & (rng.random((n, m)) < 0.15)
    l_fixed = np.where(fix, l_geo - rng.uniform(-0.002, 0.006, (n, m)), np.nan)
    weak = np.where(~cut & ~fix & (rng.random((n, m)) < 0.2), rng.uniform(5.0, 60.0, (n, m)), np.nan)
    faults = Faults(cut, fix, l_fixed, f_max_n=weak)
    expected = feasible_tensions(robot, q, faults, SpringParams())[0]
    assert 0.2 < expected.mean() < 0.8
    np.testing.assert_array_equal(feasible_cases(robot, q, faults, SpringParams()), expected)
