"""The worst muscle per posture (evaluation/body_errors.py): one muscle off at a few postures is found, counted and
located, where per-muscle percentiles pooled over every pair hide it."""
import numpy as np

from lightning_bodyschema.evaluation.body_errors import bad_regions, jump_distance, summary, worst_per_posture
from lightning_bodyschema.sim import MusculoskeletalModel


def test_one_muscle_off_in_one_joint_region_is_the_worst_there_and_located():
    arm = MusculoskeletalModel("paper_arm")
    q = arm.sample_q(np.random.default_rng(0), 2000)
    true = arm.kinematics(q)
    l_geo, G, tau = (a.copy() for a in true)
    region = q[:, 1] > 0.9  # the elbow bent past 0.9 rad: 5 % of the postures, under 1 % of the pairs
    l_geo[region, 3] += 0.002  # muscle 3 misses its length by 2 mm there
    G[region, 3, 1] += 0.004  # and its elbow moment arm by 4 mm/rad
    tau[region, 0] += 0.3  # the shoulder torque by 0.3 N m
    crossed = np.abs(true[1]).max(axis=0) > 1e-12
    worst = worst_per_posture((l_geo, G, tau), true, crossed)
    assert np.all(worst.length_muscle[region] == 3) and np.all(worst.arm_joint[region] == 1)
    np.testing.assert_allclose(worst.length_mm[region], 2.0, rtol=1e-9)
    np.testing.assert_allclose(worst.arm_mm_per_rad[region], 4.0, rtol=1e-9)
    assert np.all(worst.length_mm[~region] == 0.0) and np.all(worst.torque_joint[region] == 0)
    s = summary(worst)
    # lengths of ~0.3 m carry ~1e-16 relative rounding: 2 mm is met to ~1e-12 mm
    assert s["bad_posture_fraction"] == region.mean() and abs(s["worst_length_mm_p99"] - 2.0) < 1e-9
    assert s["worst_length_mm_p50"] == 0.0  # most postures are exact: the median hides the region, p99 does not
    pooled_p99 = np.percentile(1e3 * np.abs(l_geo - true[0]), 99)  # every (posture, muscle) pair pooled
    assert pooled_p99 < s["worst_length_mm_p99"]
    (muscle, n_bad, largest, joint, lo, hi), = bad_regions(worst, q, arm.q_range, crossed)
    assert (muscle, n_bad, joint) == (3, region.sum(), 1) and abs(largest - 2.0) < 1e-9
    assert 0.9 < lo < hi <= arm.q_range[1, 1]  # the bad postures' elbow interval lies in the region


def test_a_true_jump_is_found_where_the_wrap_switches_and_not_on_a_smooth_path():
    """myoArm's TMAJ jumps by 17 mm where its wrap switches sides at high shoulder elevation; the probe finds it from
    postures a known distance away along the elevation (or nearer along another joint it crosses), and finds none
    on BRA, an elbow muscle whose path is smooth there."""
    import yaml
    locks = yaml.safe_load(open("configs/myoarm.yaml"))["data"]["locked_joints"]
    arm = MusculoskeletalModel("myo:myoarm", locked_joints=locks)
    crossed, names = arm.crossing(), arm.muscle_names
    tmaj, bra = names.index("TMAJ_tendon"), names.index("BRA_tendon")
    q = np.array([[-0.687, 2.911, 1.402, 0.159, 0.344, 0.427, 0.037]])  # one of TMAJ's worst postures (seed 1)
    scan = np.repeat(q, 601, 0)
    scan[:, 1] += np.linspace(-0.3, 0.15, 601)  # the elevation, inside its range (0 .. 3.1 rad)
    length = 1e3 * arm.kinematics(scan)[0][:, tmaj]
    at = int(np.argmax(np.abs(np.diff(length))))
    assert abs(length[at + 1] - length[at]) > 10.0  # the jump: two scan points 0.75 mrad apart
    edge = 0.5 * (scan[at, 1] + scan[at + 1, 1])
    probes = np.repeat(q, 2, 0)
    probes[:, 1] = edge + np.array([-0.05, 0.02])
    found = jump_distance(arm, probes, np.full(2, tmaj), crossed, reach_rad=0.1)
    assert np.all(found <= np.array([0.05, 0.02]) + 1e-3) and np.all(found > 0)  # within one probe step
    assert np.isinf(jump_distance(arm, probes, np.full(2, bra), crossed, reach_rad=0.1)).all()
    assert jump_distance(arm, probes[:0], np.zeros(0, np.int64), crossed).shape == (0,)  # no posture: none probed
