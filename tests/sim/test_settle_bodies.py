"""The settle check on every body we ship: exact, stable equilibria come to rest where they are (sim/settle.py).

The oracle's commands (``evaluation.feasibility.oracle_commands``) balance every torque at q_ref to float rounding, so
a physical check must leave them there. On myoLegs the check used to move them by a median 0.22 rad (every run
NOT_SETTLED after 3 s): its knee couplings were MuJoCo soft constraints (followers off their polynomials by 0.2-0.3 mm,
which the legs' soft directions, down to 0.7 N m/rad, turned into 0.01-0.02 rad) and the explicit muscle damping rang
at the light toes' ~1000 rad/s modes with myoLegs' 2 ms step.
"""
import os

import numpy as np
import pytest

from lightning_bodyschema.evaluation import FaultCases
from lightning_bodyschema.evaluation.feasibility import oracle_commands
from lightning_bodyschema.sim.settle import SettleParams, SettleStatus, settle
from lightning_bodyschema.sim.spring import tension_from_elongation

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
MYO = ["myoelbow.yaml", "myoarm.yaml", "myolegs-per-muscle.yaml", "myolegs_osl.yaml", "myohand.yaml"]


def _body(config):
    from lightning_bodyschema.apps.common import robot_from_config

    if config.startswith("myo"):
        pytest.importorskip("myo_sim")
    model, spring, _ = robot_from_config(os.path.join(REPO, "configs", config))
    return model, spring


def _net_torque_nm(model, spring, q, l_motor):
    """Free-joint torque (B, N) [N m] of the spring law at rest lengths l_motor, against gravity and passive forces."""
    l_geo, G, tau = model.kinematics(q)
    f = tension_from_elongation(np.maximum(l_geo - l_motor, 0.0), spring)
    return np.einsum("bmn,bm->bn", -G, np.where(l_geo > l_motor, f, 0.0)) - tau


def _smallest_stiffness(model, spring, q, l_motor, step_rad=1e-6):
    """(B,) smallest eigenvalue [N m/rad] of the symmetric part of -d torque/dq, by central differences."""
    n = q.shape[1]
    stiff = np.empty((len(q), n, n))
    for j in range(n):
        dq = np.zeros(n)
        dq[j] = step_rad
        stiff[:, :, j] = -(_net_torque_nm(model, spring, q + dq, l_motor)
                           - _net_torque_nm(model, spring, q - dq, l_motor)) / (2 * step_rad)
    return np.linalg.eigvalsh(0.5 * (stiff + stiff.transpose(0, 2, 1))).min(axis=1)


def _stable_oracle_commands(model, spring, n_draws, n_keep, seed=0):
    """(q, l_motor, f) at up to n_keep random healthy postures where the oracle is feasible and the stiffness PD."""
    q = model.sample_q(np.random.default_rng(seed), n_draws)
    m = model.n_muscles
    cases = FaultCases(q, np.zeros((n_draws, m), bool), np.zeros((n_draws, m), bool), np.full((n_draws, m), np.nan),
                       np.array(["NONE"] * n_draws))
    feasible, l_motor, f = oracle_commands(model, cases, spring)
    keep = np.flatnonzero(feasible)
    keep = keep[_smallest_stiffness(model, spring, q[keep], l_motor[keep]) > 0.0][:n_keep]
    assert keep.size >= 1, "no feasible, statically stable posture drawn"
    return q[keep], l_motor[keep], f[keep]


def _assert_rests_at_q_ref(model, spring, q, l_motor, f):
    assert np.abs(_net_torque_nm(model, spring, q, l_motor)).max() <= 1e-6  # exact equilibria [N m]
    out = settle(model, l_motor, f, q, spring=spring)
    assert out.status_names == ["SETTLED"] * len(q)
    assert out.E_q_phys.max() <= 1e-4  # [rad]; measured <= 1.7e-11 on every body


@pytest.mark.parametrize("config", ["diff.yaml", "arm3_8-diff.yaml"] + MYO)
def test_oracle_commands_settle_at_q_ref_on_every_shipped_body(config):
    model, spring = _body(config)
    _assert_rests_at_q_ref(model, spring, *_stable_oracle_commands(model, spring, 12, 4))


def test_where_myolegs_comes_to_rest_its_free_joints_balance():
    """Commands 1 mm off move the legs; where settle says SETTLED, the free-joint torques of MuJoCo's kinematics with
    the spring law balance (the soft couplings left 0.08-0.7 N m there: the arm rested where the physics does not)."""
    model, spring = _body("myolegs-per-muscle.yaml")
    q, l_motor, f = _stable_oracle_commands(model, spring, 12, 4)
    out = settle(model, l_motor + 0.001, f, q, spring=spring)
    rest = out.status == SettleStatus.SETTLED
    assert rest.sum() >= 3 and np.all(out.E_q_phys[rest] > 1e-3)  # they did move
    # at rest |qacc| < 1e-3 rad/s^2 and |qvel| < 1e-4 rad/s: with the legs' inertia (< 1 kg m^2 a joint) and the
    # mass damping (8 1/s) that leaves at most ~2e-3 N m unbalanced (measured: 1.7e-3). A joint pressed into its
    # limit is held by the limit's force as well (one toe here: 0.12 N m), so only joints clear of their limits count.
    q_rest = out.q_settle[rest]
    residual = _net_torque_nm(model, spring, q_rest, l_motor[rest] + 0.001)
    clear = np.minimum(q_rest - model.q_range[:, 0], model.q_range[:, 1] - q_rest) > 1e-3
    assert clear.mean() > 0.9 and np.abs(residual[clear]).max() <= 1e-2


def test_exact_commands_rest_whatever_the_damping():
    """The rest posture does not depend on the dampers: with none of them the paper arm's exact commands stay."""
    model, spring = _body("diff.yaml")
    q, l_motor, f = _stable_oracle_commands(model, spring, 8, 8)
    out = settle(model, l_motor, f, q, spring=spring, params=SettleParams(mass_damping_per_s=0.0, muscle_damping_s=0.0))
    assert np.all(out.settled) and out.E_q_phys.max() <= 1e-4
