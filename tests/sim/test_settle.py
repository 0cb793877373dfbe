"""Physical settle check: MuJoCo simulation of commands until the arm is at rest (sim/settle.py)."""
import subprocess
import sys

import numpy as np
import pytest
from physics_checks import rounding_tol

from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.evaluation import FaultCases
from lightning_bodyschema.sim.settle import SettleParams, SettleStatus, settle

N_MUSCLES = 6


def _same_rest_tol(arm, q_rad) -> float:
    """Two settles whose forces agree but for roundings: at most one rounding of the posture per step (the damped
    arm shrinks them), at its scale (~7e-13 rad at 1 rad over 3 s at 1 ms); a force missed or added moves the rest
    posture by 1e-4 rad or more."""
    return rounding_tol(round(SettleParams().max_time_s / arm.mj_model.opt.timestep), q_rad)


def no_faults(batch):
    return np.zeros((batch, N_MUSCLES), bool), np.zeros((batch, N_MUSCLES), bool), np.full((batch, N_MUSCLES), np.nan)


# ---------------------------------------------------------------------------- (a) healthy commands
@pytest.mark.parametrize("mode", ["length", "tension"])
def test_healthy_commands_hold_their_own_posture(arm, healthy, mode):
    """Acceptance: every dataset command keeps the arm within 1e-4 rad of its q (measured: 2.2e-15 rad)."""
    res = settle(arm, healthy.l_motor, healthy.f, healthy.q, params=SettleParams(mode=mode))
    assert np.all(res.status == SettleStatus.SETTLED)
    assert res.E_q_phys.max() <= 1e-4
    assert np.abs(res.f_settle_n - healthy.f).max() <= 1e-6  # the springs carry the dataset tensions
    assert np.all(res.time_s <= 0.05)  # at rest from the start


# ---------------------------------------------------------------------------- (b) a command that cannot hold
def test_all_slack_command_falls_to_the_hanging_posture(arm, healthy):
    rows = np.flatnonzero(np.linalg.norm(healthy.q, axis=1) > 0.6)[:4]
    q_ref, slack = healthy.q[rows], healthy.l_motor[rows] + 1.0  # every wire 1 m too long
    res = settle(arm, slack, healthy.f[rows], q_ref)
    assert np.all(res.E_q_phys > 0.5)
    assert np.all(np.isin(res.status, [SettleStatus.SETTLED, SettleStatus.NOT_SETTLED]))
    np.testing.assert_allclose(res.q_settle, 0.0, atol=0.02)  # q = 0 hangs straight down
    assert np.all(res.f_settle_n[res.settled] == 0.0)
    short = settle(arm, slack, healthy.f[rows], q_ref, params=SettleParams(max_time_s=0.2))
    assert np.all(short.status == SettleStatus.NOT_SETTLED) and np.allclose(short.time_s, 0.2)
    assert short.status_names == ["NOT_SETTLED"] * len(rows)
    # an arm still falling is no rest posture: E_q_phys says where it was, E_q_rest scores nothing and counts it apart
    assert np.all(short.E_q_phys > 0.05) and np.all(np.isnan(short.E_q_rest)) and np.all(short.unsettled)
    np.testing.assert_array_equal(res.E_q_rest[res.settled], res.E_q_phys[res.settled])


# ---------------------------------------------------------------------------- (c) cuts
def test_cutting_a_slack_muscle_changes_nothing(arm, healthy):
    rows, muscles = np.nonzero(healthy.f == 0.0)
    rows, first = np.unique(rows, return_index=True)
    assert len(rows) >= 5
    cut, fix, l_fixed = no_faults(len(rows))
    cut[np.arange(len(rows)), muscles[first]] = True
    args = (healthy.l_motor[rows], healthy.f[rows], healthy.q[rows])
    intact, broken = settle(arm, *args), settle(arm, *args, cut=cut, fix=fix, l_fixed=l_fixed)
    assert np.all(broken.settled) and broken.E_q_phys.max() <= 1e-9
    np.testing.assert_allclose(broken.q_settle, intact.q_settle, rtol=0, atol=_same_rest_tol(arm, intact.q_settle))


def test_cutting_a_loaded_muscle_moves_the_arm_the_way_the_lost_torque_says(arm, healthy):
    """Without muscle i the joints lose -G_i f_i, i.e. feel +G_i f_i more: the arm must move along it."""
    b = np.arange(30)
    strongest = np.argmax(healthy.f[b], axis=1)
    cut, fix, l_fixed = no_faults(len(b))
    cut[b, strongest] = True
    res = settle(arm, healthy.l_motor[b], healthy.f[b], healthy.q[b], cut=cut, fix=fix, l_fixed=l_fixed)
    _, G, _ = arm.kinematics(healthy.q[b])
    freed = G[b, strongest] * healthy.f[b, strongest][:, None]  # (B, N) torque the cut muscle no longer cancels
    assert np.all(res.settled)
    assert np.all(res.E_q_phys > 1e-2)  # measured: >= 0.038 rad
    assert np.all(np.einsum("bn,bn->b", res.q_settle - healthy.q[b], freed) > 0)
    assert np.all(res.f_settle_n[b, strongest] == 0.0)


# ---------------------------------------------------------------------------- (d) jams
def test_jam_at_the_commanded_length_changes_nothing(arm, healthy):
    """l_fixed = the commanded l_motor: the jammed motor sits where the command puts it anyway.

    Commands 2 mm too long, so the arm actually moves and the comparison means something.
    """
    b = np.arange(12)
    l_motor = healthy.l_motor[b] + 0.002
    cut, fix, _ = no_faults(len(b))
    fix[b, b % N_MUSCLES] = True
    l_fixed = np.where(fix, l_motor, np.nan)
    free = settle(arm, l_motor, healthy.f[b], healthy.q[b])
    assert np.all(free.settled) and np.all(free.E_q_phys > 1e-4)  # measured >= 5.8e-4 rad
    for jam in ("immobile", "one_sided"):
        stuck = settle(arm, l_motor, healthy.f[b], healthy.q[b], cut=cut, fix=fix, l_fixed=l_fixed,
                       params=SettleParams(jam=jam))
        np.testing.assert_allclose(stuck.q_settle, free.q_settle, rtol=0, atol=_same_rest_tol(arm, free.q_settle))


def test_held_jam_ignores_the_command_one_way_jam_lets_the_motor_reel_in(arm, healthy):
    """l_fixed 1 mm above the command: 'held' rests the spring at l_fixed (the arm moves), 'one_way' at l_motor."""
    b = np.arange(8)
    cut, fix, _ = no_faults(len(b))
    fix[b, np.argmax(healthy.f[b], axis=1)] = True
    l_fixed = np.where(fix, healthy.l_motor[b] + 0.001, np.nan)
    args = (healthy.l_motor[b], healthy.f[b], healthy.q[b], cut, fix, l_fixed)
    held = settle(arm, *args, params=SettleParams(jam="immobile"))
    one_way = settle(arm, *args, params=SettleParams(jam="one_sided"))
    assert np.all(held.E_q_phys > 1e-3)
    assert one_way.E_q_phys.max() <= 1e-9


def test_fault_cases_give_the_same_result_as_arrays(arm, healthy):
    b = np.arange(6)
    cut, fix, l_fixed = no_faults(len(b))
    cut[0, 1] = fix[1, 2] = True
    l_fixed[1, 2] = healthy.l_motor[1, 2] - 0.001
    cases = FaultCases(healthy.q[b], cut, fix, l_fixed, np.full(len(b), "BOTH"))
    a = settle(arm, healthy.l_motor[b], healthy.f[b], cases)
    c = settle(arm, healthy.l_motor[b], healthy.f[b], healthy.q[b], cut, fix, l_fixed)
    np.testing.assert_array_equal(a.q_settle, c.q_settle)
    with pytest.raises(BodySchemaInputError, match="not both"):
        settle(arm, healthy.l_motor[b], healthy.f[b], cases, cut=cut)


# ---------------------------------------------------------------------------- (e) bad commands
def test_nonfinite_commands_get_a_status_not_an_exception(arm, healthy):
    b = np.arange(6)
    l_motor, f = healthy.l_motor[b].copy(), healthy.f[b].copy()
    l_motor[1, 2], f[3, 0] = np.nan, np.inf
    res = settle(arm, l_motor, f, healthy.q[b])
    bad = np.isin(b, [1, 3])
    assert np.all(res.status[bad] == SettleStatus.NONFINITE_COMMAND)
    assert np.all(np.isnan(res.q_settle[bad])) and np.all(np.isnan(res.E_q_phys[bad]))
    assert np.all(res.settled[~bad]) and res.E_q_phys[~bad].max() <= 1e-9
    all_bad = settle(arm, np.full((2, N_MUSCLES), np.nan), healthy.f[:2], healthy.q[:2])
    assert all_bad.status_names == ["NONFINITE_COMMAND"] * 2


def test_absurd_stretch_is_reported_not_printed(arm, healthy, capfd):
    """A wire 1 m too short pulls with ~1e11 N: UNSTABLE; 10 cm too short pins a joint past its limit."""
    l_motor = healthy.l_motor[:2].copy()
    l_motor[0, 0] -= 1.0
    l_motor[1, 0] -= 0.1
    res = settle(arm, l_motor, healthy.f[:2], healthy.q[:2])
    assert res.status[0] == SettleStatus.UNSTABLE and np.all(np.isfinite(res.q_settle[0]))
    # its last checked state may be q_ref itself (it blew up before the first check): never a small error
    assert res.E_q_phys[0] == np.inf and np.isfinite(res.E_q_phys[1])
    assert res.status[1] in (SettleStatus.BEYOND_LIMIT, SettleStatus.SETTLED)
    out = capfd.readouterr()
    assert out.out == "" and out.err == ""  # MuJoCo never gets to print its blow-up warning


def test_an_overflowing_spring_blows_up_alone(arm, healthy):
    """A wire 100 m too short overflows its spring (inf tension and stiffness in the implicit step): that case is
    UNSTABLE, the cases beside it settle exactly as they do alone, and nothing is warned."""
    l_motor = healthy.l_motor[:4].copy()
    l_motor[1, 2] -= 100.0
    res = settle(arm, l_motor, healthy.f[:4], healthy.q[:4])
    alone = settle(arm, l_motor[[0, 2, 3]], healthy.f[[0, 2, 3]], healthy.q[[0, 2, 3]])
    assert res.status_names[1] == "UNSTABLE" and res.E_q_phys[1] == np.inf
    np.testing.assert_array_equal(res.q_settle[[0, 2, 3]], alone.q_settle)
    assert np.all(alone.settled)


def test_a_singular_step_is_that_cases_alone():
    """A spring stiffness of ~1e36 N/m (tools/reproduce_paper.py --quick's barely trained commands) left a case's
    implicit system exactly singular in floats: numpy's batched solve raised for the whole chunk. Now that case's
    row is NaN (reported UNSTABLE by the step) and the others are solved."""
    from lightning_bodyschema.sim.settle import solve_or_nan

    a = np.stack([np.eye(2) * 2.0, np.ones((2, 2)) * 1e29, np.full((2, 2), np.inf)])  # regular, singular, overflow
    out = solve_or_nan(a, np.ones((3, 2, 1)))
    np.testing.assert_array_equal(out[0], 0.5)
    assert np.isnan(out[1:]).all()


@pytest.mark.parametrize("kwargs, match", [
    ({"l_motor": np.zeros((3, 6))}, "l_motor has shape"),
    ({"f": None}, "f is required"),
    ({"cut": np.zeros((2, 6), int)}, "bool"),
    ({"cut": np.eye(2, 6, dtype=bool), "fix": np.eye(2, 6, dtype=bool)}, "both cut and jammed"),
    ({"fix": np.eye(2, 6, dtype=bool)}, "l_fixed is NaN"),
    ({"q_ref": np.full((2, 2), np.nan)}, "q contains NaN"),
])
def test_bad_input_raises_naming_the_value(arm, healthy, kwargs, match):
    args = {"l_motor": healthy.l_motor[:2], "f": healthy.f[:2], "q_ref": healthy.q[:2]}
    args.update(kwargs)
    q_ref = args.pop("q_ref")
    with pytest.raises(BodySchemaInputError, match=match):
        settle(arm, args.pop("l_motor"), args.pop("f"), q_ref, **args)


@pytest.mark.parametrize("kwargs, match", [
    ({"mode": "force"}, "mode"), ({"jam": "stuck"}, "jam"), ({"max_time_s": 0.0}, "max_time_s"),
    ({"mass_damping_per_s": -1.0}, "mass_damping_per_s"), ({"chunk_size": 2.5}, "chunk_size"),
    ({"n_threads": 0}, "n_threads"), ({"n_threads": 1.5}, "n_threads"),
])
def test_bad_params_raise(kwargs, match):
    with pytest.raises(BodySchemaInputError, match=match):
        SettleParams(**kwargs)


@pytest.mark.parametrize("chunk_size, n_threads", [(128, 1), (128, 2), (7, 3)])
def test_a_case_settles_the_same_whatever_runs_beside_it(arm, healthy, chunk_size, n_threads):
    """Blow-ups mid-interval used to make every case of their chunk check its rest there and then: a case's
    result depended on its chunk. Each case alone (chunk_size=1) is the reference, byte for byte."""
    b = np.arange(24)
    l_motor = healthy.l_motor[b].copy()
    # joint forces above max_torque_nm: these blow up in the first step, between checks (0.4 m did with the explicit
    # spring; the implicit step holds it: the antagonists balance it at 3 MN, within the joint range)
    l_motor[::3] -= 0.8
    args = (l_motor, healthy.f[b], healthy.q[b])
    alone = settle(arm, *args, params=SettleParams(chunk_size=1, n_threads=1))
    together = settle(arm, *args, params=SettleParams(chunk_size=chunk_size, n_threads=n_threads))
    assert np.sum(alone.status == SettleStatus.UNSTABLE) >= 4 and np.sum(alone.settled) >= 8
    for name in ("q_settle", "E_q_phys", "status", "time_s", "qvel_rad_s", "f_settle_n"):
        np.testing.assert_array_equal(getattr(together, name), getattr(alone, name), err_msg=name)


def test_chunking_does_not_change_results(arm, healthy):
    b = np.arange(10)
    args = (healthy.l_motor[b] + 0.002, healthy.f[b], healthy.q[b])
    whole, chunks = settle(arm, *args), settle(arm, *args, params=SettleParams(chunk_size=3))
    np.testing.assert_array_equal(whole.q_settle, chunks.q_settle)
    np.testing.assert_array_equal(whole.status, chunks.status)


def test_settle_imports_neither_torch_nor_lightning():
    code = ("import sys, numpy as np\n"
            "from lightning_bodyschema.sim import MusculoskeletalModel\n"
            "from lightning_bodyschema.sim.settle import settle\n"
            "m = MusculoskeletalModel()\n"
            "settle(m, np.full((1, 6), 0.3), np.zeros((1, 6)), np.zeros((1, 2)))\n"
            "bad = [k for k in sys.modules if k.split('.')[0] in ('torch', 'lightning', 'pytorch_lightning')]\n"
            "print(bad); sys.exit(1 if bad else 0)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr
