"""diagnose on the paper arm's true body (MuJoCo): each fault kind, two at once, a healthy noisy log, an ambiguous
pair, a cut that left no trace, and a cut seen only through the arm's sag (no load cells). Logs come from MuJoCo's
settle of the healthy commands under the faults, with the documented sensor noise."""
from __future__ import annotations

import numpy as np
import pytest

from lightning_bodyschema.diagnosis import SensorLog, SensorNoise, diagnose
from lightning_bodyschema.diagnosis.result import BAND, CUT, HEALTHY, JAM, WEAK
from lightning_bodyschema.diagnosis.sensors import noisy, true_readings
from lightning_bodyschema.faults import Faults
from lightning_bodyschema.sim import SpringParams
from lightning_bodyschema.status import Status

SPRING = SpringParams()
NOISE = SensorNoise()


@pytest.fixture(scope="module")
def pool(healthy):
    """Postures the healthy paper arm holds with every muscle pulling at least 20 N (so a cut always shows)."""
    keep = healthy.f.min(1) > 20.0
    return healthy.q[keep], healthy.l_motor[keep], healthy.f[keep]


def _log(arm, pool, rows, faults_one, seed=0, load_cells=True):
    """A log of the pool's ``rows`` under ``faults_one`` (a one-row Faults, the same in every row), settled in
    MuJoCo, with noise; returns (log, true readings)."""
    q, l_cmd, f_cmd = (a[rows] for a in pool)
    faults = faults_one.take(np.zeros(len(rows), int))
    truth = true_readings(arm, SPRING, q, l_cmd, f_cmd, faults)
    assert truth.at_rest.all()
    has_f = None if load_cells else np.zeros(arm.n_muscles, bool)
    q_read, l_read, f_read = noisy(truth, SPRING, NOISE, np.random.default_rng(seed), has_f)
    return SensorLog.from_rows(arm.joint_names, arm.muscle_names, q_read, l_read, l_cmd, f_cmd, f_read), truth


def _faults(arm, **kinds):
    return Faults.from_names(arm.muscle_names, **{k: [v] if k == "cut" else v for k, v in kinds.items()})


def _one(arm, pool, rows, faults, **kw):
    log, truth = _log(arm, pool, rows, faults, **kw)
    return diagnose(log, arm.kinematics, SPRING, NOISE), truth


def test_a_healthy_noisy_log_is_no_fault(arm, pool):
    d, _ = _one(arm, pool, [0, 1, 2], Faults.none(1, arm.n_muscles))
    assert d.status[0] == Status.NO_FAULT and (d.kind == HEALTHY).all()
    assert not d.faults.cut.any() and not d.faults.fix.any()


def test_a_cut_muscle_is_named(arm, pool):
    d, _ = _one(arm, pool, [3, 4], _faults(arm, cut=["elbow_flexor"]))
    assert d.status[0] == Status.IDENTIFIED
    assert [d.muscles[m] for m in np.flatnonzero(d.kind[0])] == ["elbow_flexor"] and d.kind[0].max() == CUT
    assert d.faults.cut[0].tolist() == (np.array(arm.muscle_names) == "elbow_flexor").tolist()


def test_a_cut_without_load_cells_shows_in_the_sag(arm, pool):
    """No f_ columns: the cut muscle is the one whose missing pull explains how the arm came to rest."""
    d, _ = _one(arm, pool, [5, 6, 7], _faults(arm, cut=["shoulder_extensor"]), load_cells=False)
    assert d.status[0] == Status.IDENTIFIED and d.kind[0, arm.muscle_names.index("shoulder_extensor")] == CUT
    assert (d.kind[0] != HEALTHY).sum() == 1


def test_a_jam_is_found_with_its_length(arm, pool):
    m = arm.muscle_names.index("shoulder_flexor")
    l_fixed = pool[1][8, m] - 3e-3  # 3 mm below the command of the first row: the winch cannot pay out
    d, _ = _one(arm, pool, [8, 9], _faults(arm, jam={"shoulder_flexor": l_fixed}))
    assert d.status[0] == Status.IDENTIFIED and d.kind[0, m] == JAM and (d.kind[0] != HEALTHY).sum() == 1
    assert abs(d.l_fixed_m[0, m] - l_fixed) < 0.2e-3
    assert d.faults.fix[0, m] and abs(d.faults.l_fixed_m[0, m] - l_fixed) < 0.2e-3


def test_a_weak_motor_is_found_with_its_limit_at_two_postures(arm, pool):
    """At two postures a slipping motor keeps its tension and changes its length: weak, not a band."""
    m = arm.muscle_names.index("elbow_extensor")
    rows = [r for r in range(10, len(pool[0])) if pool[2][r, m] > 60.0][:2]
    f_weak = 0.5 * pool[2][rows, m].min()
    d, _ = _one(arm, pool, rows, _faults(arm, weak={"elbow_extensor": f_weak}))
    assert d.status[0] == Status.IDENTIFIED and d.kind[0, m] == WEAK and (d.kind[0] != HEALTHY).sum() == 1
    assert abs(d.f_weak_n[0, m] - f_weak) < 0.03 * f_weak


def test_one_slipping_row_is_ambiguous_between_weak_and_band(arm, pool):
    """One row: a motor slipping at f_w and one stopped at its band's lower edge read the same; both are named."""
    m = arm.muscle_names.index("elbow_extensor")
    row = int(np.flatnonzero(pool[2][:, m] > 60.0)[0])
    d, _ = _one(arm, pool, [row], _faults(arm, weak={"elbow_extensor": 0.5 * pool[2][row, m]}))
    assert d.status[0] == Status.AMBIGUOUS
    kinds = [next(k for k in ("weak", "band") if k in c) for c in d.candidates[0]]
    assert sorted(kinds) == ["band", "weak"]
    assert not d.faults.weak.any() and not d.faults.band.any()  # nothing certain to adapt to


def test_a_band_reached_at_both_edges(arm, pool):
    m = arm.muscle_names.index("biarticular_flexor")
    l_cmd = pool[1][:, m]
    rows = [int(np.argmin(l_cmd)), int(np.argmax(l_cmd))]
    lo, hi = l_cmd[rows[0]] + 1e-3, l_cmd[rows[1]] - 1e-3
    d, _ = _one(arm, pool, rows, _faults(arm, band={"biarticular_flexor": [lo, hi]}))
    assert d.status[0] == Status.IDENTIFIED and d.kind[0, m] == BAND
    np.testing.assert_allclose(d.l_band_m[0, m], [lo, hi], atol=0.2e-3)


def test_two_faults_at_once(arm, pool):
    m_cut, m_jam = arm.muscle_names.index("elbow_flexor"), arm.muscle_names.index("shoulder_extensor")
    l_fixed = pool[1][11, m_jam] - 2e-3
    d, _ = _one(arm, pool, [11, 12, 13], _faults(arm, cut=["elbow_flexor"], jam={"shoulder_extensor": l_fixed}))
    assert d.status[0] == Status.IDENTIFIED
    assert d.kind[0, m_cut] == CUT and d.kind[0, m_jam] == JAM and (d.kind[0] != HEALTHY).sum() == 2


def test_a_cut_muscle_that_stayed_slack_is_not_named(arm, healthy):
    """A muscle the command left slack pulls nothing either way: the log cannot tell, so nothing is claimed and the
    muscle is marked unobserved."""
    m = int(np.argmin(healthy.f.min(0)))
    rows = np.flatnonzero(healthy.f[:, m] == 0.0)[:2]
    assert rows.size == 2
    pool = (healthy.q, healthy.l_motor, healthy.f)
    faults = Faults.from_names(arm.muscle_names, cut=[[m]])
    d, _ = _one(arm, pool, rows, faults)
    assert d.status[0] == Status.NO_FAULT and not d.observed[0, m] and not d.faults.cut.any()


def test_logs_are_answered_together_as_they_are_alone(arm, pool):
    """Two logs in one SensorLog (a case column): each diagnosis is the one it gets alone."""
    a, _ = _log(arm, pool, [3, 4], _faults(arm, cut=["elbow_flexor"]), seed=1)
    b, _ = _log(arm, pool, [0], Faults.none(1, arm.n_muscles), seed=2)
    both = SensorLog.from_rows(arm.joint_names, arm.muscle_names,
                               *(np.concatenate([x[0, x_rows] for x, x_rows in ((getattr(a, k), a.rows[0]),
                                                                                 (getattr(b, k), b.rows[0]))])
                                 for k in ("q_rad", "l_m", "l_cmd_m", "f_cmd_n", "f_n")),
                               case=np.r_[np.zeros(2), np.ones(1)])
    together = diagnose(both, arm.kinematics, SPRING, NOISE)
    alone = [diagnose(x, arm.kinematics, SPRING, NOISE) for x in (a, b)]
    assert list(together.status) == [alone[0].status[0], alone[1].status[0]]
    np.testing.assert_array_equal(together.kind, np.concatenate([x.kind for x in alone]))
