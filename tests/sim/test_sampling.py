"""The chunked dataset generator: what each chunk draws, its bad input, its errors from workers, its progress bar."""
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.sim import SpringParams, generate_equilibrium_samples, sampling
from lightning_bodyschema.sim.equilibrium import solve_equilibrium_qp
from lightning_bodyschema.sim.sampling import (CHUNK_SAMPLES, ProgressBar, check_workers, chunk_seed, chunk_sizes,
                                               default_workers, exact_from_active_set, generate_samples,
                                               reproducible_qp)


def test_each_chunk_is_its_own_seeded_draw(arm):
    """Rows of chunk k are ``generate_equilibrium_samples`` on chunk k's stream with the reproducible QP; a dataset
    of one chunk has the postures of the single-stream draw of ``seed`` and its tensions to 1e-7 N."""
    n = CHUNK_SAMPLES + 300
    assert chunk_sizes(n) == [CHUNK_SAMPLES, 300] and chunk_sizes(CHUNK_SAMPLES) == [CHUNK_SAMPLES]
    whole = generate_samples(arm, n, 7, workers=0)
    first = generate_equilibrium_samples(arm, CHUNK_SAMPLES, 7, qp=reproducible_qp)
    second = generate_equilibrium_samples(arm, 300, chunk_seed(7, 1), qp=reproducible_qp)
    for name in ("q", "l_motor", "f"):
        assert np.array_equal(getattr(whole, name), np.concatenate([getattr(first, name), getattr(second, name)]))
    assert whole.n_redrawn == first.n_redrawn + second.n_redrawn
    assert not np.array_equal(second.q, generate_equilibrium_samples(arm, 300, 7).q)  # chunk 1 has its own stream
    single, plain = generate_samples(arm, 500, 7, workers=3), generate_equilibrium_samples(arm, 500, 7)
    assert np.array_equal(single.q, plain.q)
    np.testing.assert_allclose(single.f, plain.f, atol=1e-7)


@pytest.mark.parametrize("workers", [-1, 1.5, True, "2", np.float64(2.0)])
def test_bad_workers_is_one_line(arm, workers):
    with pytest.raises(BodySchemaInputError, match=r"workers=.* must be an integer >= 0") as err:
        generate_samples(arm, 10, 0, workers=workers)
    assert "\n" not in str(err.value)


def test_default_and_in_process_workers():
    assert check_workers(None) == default_workers() >= 1
    assert check_workers(0) == 0 and check_workers(np.int64(3)) == 3


def test_unholdable_chunk_on_a_worker_stops_with_the_joints(arm, monkeypatch):
    """A chunk that cannot be held raises in its worker; the caller gets the same one-line error naming the joints."""
    monkeypatch.setattr(sampling, "CHUNK_SAMPLES", 8)  # the parent cuts the chunks: small ones keep the test quick
    with pytest.raises(BodySchemaInputError, match="can be held in equilibrium .* joints") as err:
        generate_samples(arm, 20, 0, SpringParams(f_max_n=1.0), workers=2)
    assert "\n" not in str(err.value)


def test_progress_bar_only_when_asked_or_on_a_terminal(arm, capsys, monkeypatch):
    generate_samples(arm, CHUNK_SAMPLES + 5, 0, workers=1)  # progress None and stderr not a terminal: quiet
    assert capsys.readouterr().err == ""
    generate_samples(arm, CHUNK_SAMPLES + 5, 0, workers=1, progress=True)
    assert "100%" in capsys.readouterr().err  # tqdm's bar reached the end
    monkeypatch.setitem(sys.modules, "tqdm", None)  # without tqdm: one rewritten line
    with ProgressBar(10, tty_only=False) as bar:
        bar.update(4)
        bar.update(6)
    assert capsys.readouterr().err == "\requilibrium samples: 4/10 (40 %)\requilibrium samples: 10/10 (100 %)\n"


def test_workers_never_rerun_the_callers_script(tmp_path, monkeypatch):
    """Workers are clean interpreters: a script without ``if __name__ == "__main__":`` runs once, on 2 workers, and
    gets the samples drawn in-process."""
    script = tmp_path / "unguarded.py"
    script.write_text("import hashlib\n"
                      "from lightning_bodyschema.sim import MusculoskeletalModel\n"
                      "from lightning_bodyschema.sim.sampling import generate_samples, CHUNK_SAMPLES\n"
                      "print('script ran')\n"
                      "arm = MusculoskeletalModel('paper_arm')\n"
                      "for workers in (2, 1):\n"
                      "    s = generate_samples(arm, CHUNK_SAMPLES + 1, 0, workers=workers)\n"
                      "    print(hashlib.sha256(s.q.tobytes() + s.l_motor.tobytes() + s.f.tobytes()).hexdigest())\n")
    monkeypatch.setenv("PYTHONPATH", str(Path(__file__).resolve().parents[2]))
    run = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120)
    lines = run.stdout.splitlines()
    assert run.returncode == 0 and lines.count("script ran") == 1, run.stderr
    assert len(lines) == 3 and lines[1] == lines[2]


def test_a_worker_that_dies_is_an_error_not_a_hang(arm):
    from lightning_bodyschema.sim.process_pool import WorkerPool

    with pytest.raises(RuntimeError, match=r"worker process died \(exit code -9"):
        with WorkerPool(2, "lightning_bodyschema.sim.sampling", "init_worker", (arm.xml, arm.muscle_names),
                        "worker_chunk") as pool:
            for proc in pool._procs:
                proc.kill()  # as the kernel's out-of-memory killer would
            list(pool.map_unordered([(0,), (1,), (2,)]))


def test_a_worker_runs_only_the_packages_own_modules():
    from lightning_bodyschema.sim.process_pool import WorkerPool

    with pytest.raises(ValueError, match=r"worker module 'os'; allowed: \['lightning_bodyschema.sim.sampling'\]"):
        WorkerPool(1, "os", "getpid", (), "_exit")


def test_exact_answer_from_the_active_set_ignores_the_last_bits(arm, rng):
    """The dataset's tensions are a function of the QP's active set: proxsuite's answer and the same answer off in
    its last bits give the same bytes, which hold the equilibrium to 1e-10 N m and equal proxsuite's to 1e-7 N."""
    f_max = SpringParams().f_max_n
    q = arm.sample_q(rng, 300)
    f_ref = f_max * rng.random((300, arm.n_muscles))
    _, G, tau_bias = arm.kinematics(q)
    f, ok = solve_equilibrium_qp(G, tau_bias, f_ref, f_hi_n=f_max, solver="proxqp")
    exact = exact_from_active_set(G, tau_bias, f_ref, f, f_max)
    nudged = np.clip(f + 1e-11 * rng.standard_normal(f.shape), 0.0, f_max)
    assert np.array_equal(exact_from_active_set(G, tau_bias, f_ref, nudged, f_max), exact)
    assert ok.mean() > 0.9 and (exact[ok] == 0).any() and ((exact[ok] > 0) & (exact[ok] < f_max)).any()
    assert np.abs(np.einsum("bmn,bm->bn", -G[ok], exact[ok]) - tau_bias[ok]).max() <= 1e-10
    assert exact.min() >= 0.0 and exact.max() <= f_max
    np.testing.assert_allclose(exact[ok], f[ok], atol=1e-7)


def test_workers_rebuild_locks_and_gravity_from_the_xml():
    """A robot with a locked joint and its own gravity: the workers' samples are the in-process ones, and each an
    equilibrium of the robot as built here (the locked wrist held, gravity as overridden)."""
    from lightning_bodyschema.sim import MusculoskeletalModel

    robot = MusculoskeletalModel("arm3_8", locked_joints={"wrist": 0.2}, gravity=[0.0, -7.0, 0.0])
    here, there = (generate_samples(robot, CHUNK_SAMPLES + 50, 2, workers=w) for w in (1, 2))
    assert all(np.array_equal(getattr(here, k), getattr(there, k)) for k in ("q", "l_motor", "f"))
    _, G, tau_bias = robot.kinematics(there.q)
    assert robot.joint_names == ["shoulder", "elbow"] and np.abs(tau_bias).max() > 0.1
    assert np.abs(np.einsum("bmn,bm->bn", -G, there.f) - tau_bias).max() <= 1e-10
