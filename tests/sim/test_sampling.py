"""The chunked dataset generator: what each chunk draws, its bad input, its errors from workers, its progress bar."""
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from lightning_bodyschema.errors import BodySchemaInputError
from lightning_bodyschema.sim import SpringParams, generate_equilibrium_samples, sampling
from lightning_bodyschema.sim.sampling import (CHUNK_SAMPLES, ProgressBar, check_workers, chunk_seed, chunk_sizes,
                                               default_workers, generate_samples)


def _same(a, b):
    return all(np.array_equal(x, y) for x, y in ((a.q, b.q), (a.l_motor, b.l_motor), (a.f, b.f)))


def test_each_chunk_is_its_own_seeded_draw(arm):
    """Rows of chunk k are ``generate_equilibrium_samples`` on chunk k's stream; a dataset of one chunk is the
    single-stream draw of ``seed`` itself."""
    n = CHUNK_SAMPLES + 300
    assert chunk_sizes(n) == [CHUNK_SAMPLES, 300] and chunk_sizes(CHUNK_SAMPLES) == [CHUNK_SAMPLES]
    whole = generate_samples(arm, n, 7, workers=0)
    first = generate_equilibrium_samples(arm, CHUNK_SAMPLES, 7)
    second = generate_equilibrium_samples(arm, 300, chunk_seed(7, 1))
    assert np.array_equal(whole.q, np.concatenate([first.q, second.q]))
    assert np.array_equal(whole.f, np.concatenate([first.f, second.f]))
    assert whole.n_redrawn == first.n_redrawn + second.n_redrawn
    assert _same(generate_samples(arm, 500, 7, workers=3), generate_equilibrium_samples(arm, 500, 7))
    assert not np.array_equal(second.q, generate_equilibrium_samples(arm, 300, 7).q)  # chunk 1 has its own stream


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


def test_a_worker_that_dies_is_an_error_not_a_hang():
    from lightning_bodyschema.sim.process_pool import WorkerPool

    with pytest.raises(RuntimeError, match=r"worker process died \(exit code 3"):
        with WorkerPool(2, "os", "getpid", (), "_exit") as pool:  # the task os._exit(3) ends its worker
            list(pool.map_unordered([(3,), (3,), (3,)]))
