"""The healthy dataset in fixed chunks, on worker processes: the same bytes whatever the number of workers.

``n`` samples are cut into chunks of ``CHUNK_SAMPLES`` (the last one shorter); chunk ``k`` draws its postures and
reference tensions from its own seeded stream (``chunk_seed``) and re-draws its unholdable postures itself
(``generate_equilibrium_samples``). The chunks are concatenated in chunk order, so the data depend on ``(n, seed)``
and never on how many processes drew them; every tension vector is recomputed in closed form from its active set
(``reproducible_qp``), so the few postures proxsuite settles are the same bytes in every process too. Workers are
clean interpreters (``process_pool``: no fork of a process holding MuJoCo and torch, no re-run of the caller's
script) that rebuild the robot from its self-contained XML (``MusculoskeletalModel.xml``: locks, couplings, a welded
base and gravity are in it), the same model to the bit.
"""
from __future__ import annotations

import os
import sys

import numpy as np

from ..errors import BodySchemaInputError
from .equilibrium import EquilibriumSamples, generate_equilibrium_samples, solve_equilibrium_qp
from .model import MusculoskeletalModel
from .process_pool import WorkerPool
from .spring import SpringParams

CHUNK_SAMPLES = 2048  # samples per chunk: part of what shapes the data (a dataset of at most one chunk draws the
# postures of the stream of SeedSequence(seed) alone, as the single-stream generator drew them)

ACTIVE_SET_TOL_N = 1e-7  # a tension this close to a bound [N] is on it (the solvers hold bounds to ~1e-12 N)
EXACT_TOL_NM = 1e-9  # the closed-form answer may miss the equilibrium by this much [N m] (the Newton's own stop)
_WORKER: dict = {}  # the robot a worker process rebuilt once (``init_worker``)


def default_workers() -> int:
    """The CPU cores this process may run on (``sched_getaffinity``, else ``os.cpu_count``)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def check_workers(workers) -> int:
    """Worker processes to use: ``None`` -> every core; 0 or 1 -> in this process; refuse anything but an int >= 0."""
    if workers is None:
        return default_workers()
    if isinstance(workers, bool) or not isinstance(workers, (int, np.integer)) or workers < 0:
        raise BodySchemaInputError(f"workers={workers!r} must be an integer >= 0 (0 or 1: in this process; "
                                   "None: every core)")
    return int(workers)


def chunk_sizes(n: int) -> list[int]:
    """Samples of each chunk: ``CHUNK_SAMPLES`` each, the last one the remainder."""
    full, rest = divmod(int(n), CHUNK_SAMPLES)
    return [CHUNK_SAMPLES] * full + ([rest] if rest else [])


def chunk_seed(seed: int, chunk: int) -> np.random.SeedSequence:
    """The stream of chunk ``chunk``: ``SeedSequence(seed)`` for chunk 0, its ``chunk``-th spawned child otherwise."""
    return np.random.SeedSequence(int(seed), spawn_key=(int(chunk),) if chunk else ())


def _draw_chunk(model, chunk: int, n: int, seed: int, spring: SpringParams, solver: str) -> EquilibriumSamples:
    return generate_equilibrium_samples(model, n, chunk_seed(seed, chunk), spring, solver=solver,
                                        qp=reproducible_qp)


def reproducible_qp(G, tau_bias, f_ref, *, f_hi_n, solver: str = "newton"):
    """``solve_equilibrium_qp``, its answers then recomputed by ``exact_from_active_set``: the same bytes in every
    process. (proxsuite, which settles the few postures the batched Newton leaves, can differ in the last bits from
    process to process: its answer depends on the process's earlier allocations. The active set it finds does not.)"""
    f, ok = solve_equilibrium_qp(G, tau_bias, f_ref, f_hi_n=f_hi_n, solver=solver)
    return exact_from_active_set(G, tau_bias, f_ref, f, f_hi_n), ok


def exact_from_active_set(G, tau_bias, f_ref, f, f_max):
    """The equilibrium QP's answer (``-G^T f = tau_bias``, ``0 <= f <= f_max``, closest to ``f_ref``) in closed form
    from the active set of an answer ``f``: a function of that set alone, not of ``f``'s last bits.

    The tensions more than ``ACTIVE_SET_TOL_N`` inside their bounds (F) are free, the others sit on their bounds; the
    KKT conditions make ``f_F`` the point closest to ``f_ref_F`` with ``G_F^T f_F = -(G_A^T f_A + tau_bias)``:
    ``f_F = f_ref_F - G_F lam`` with ``(G_F^T G_F) lam = G_F^T f_ref_F + G_A^T f_A + tau_bias``, solved with a ridge of
    1e-14 of the Gram matrix's mean eigenvalue (G may be rank-deficient) and refined twice on the remaining residual
    (G_F^T G_F squares G's conditioning). A row whose recomputed answer leaves the box or misses the equilibrium by
    more than both ``f`` and ``EXACT_TOL_NM`` keeps ``f``.
    """
    hi = np.broadcast_to(np.asarray(f_max, float), f.shape)
    free = (f > ACTIVE_SET_TOL_N) & (f < hi - ACTIVE_SET_TOL_N)
    exact = np.where(free, f_ref, np.where(f <= ACTIVE_SET_TOL_N, 0.0, hi))
    G_free = G * free[..., None]  # the bound tensions' rows are 0
    gram = np.einsum("bmn,bmk->bnk", G_free, G_free)  # numpy's own loops: no BLAS threading in the bytes
    mean_eig = np.maximum(np.trace(gram, axis1=1, axis2=2) / G.shape[2], 1e-30)
    gram += 1e-14 * mean_eig[:, None, None] * np.eye(G.shape[2])
    for _ in range(3):  # the projection, then two refinements
        lam = np.linalg.solve(gram, _balance(G, exact, tau_bias)[..., None])[..., 0]
        exact = exact - np.einsum("bmn,bn->bm", G_free, lam)
    within = np.all((exact >= -ACTIVE_SET_TOL_N) & (exact <= hi + ACTIVE_SET_TOL_N), axis=1)
    missed_nm, solver_missed_nm = (np.abs(_balance(G, x, tau_bias)).max(axis=1) for x in (exact, f))
    kept = within & (missed_nm <= np.maximum(solver_missed_nm, EXACT_TOL_NM))
    return np.where(kept[:, None], np.clip(exact, 0.0, hi), f)


def _balance(G, f, tau_bias):
    """``G^T f + tau_bias`` (B, N) [N m]: zero in equilibrium."""
    return np.einsum("bmn,bm->bn", G, f) + tau_bias


def init_worker(xml: str, muscles: list[str]) -> None:
    """A worker's setup (``process_pool``): the robot, rebuilt once from its self-contained XML."""
    _WORKER["model"] = MusculoskeletalModel(xml, muscles=muscles, allow_unloaded=True, lock_uncrossed=False)


def worker_chunk(chunk: int, n: int, seed: int, spring: SpringParams, solver: str) -> EquilibriumSamples:
    """A worker's task (``process_pool``): chunk ``chunk``'s samples."""
    return _draw_chunk(_WORKER["model"], chunk, n, seed, spring, solver)


def _chunks(model: MusculoskeletalModel, jobs: list[tuple], workers: int):
    """(chunk, samples) of every job, on ``workers`` processes in the order they finish (> 1), else here in order.
    Workers rebuild the robot from its XML alone: any other kind of model (a subclass, a stand-in) is drawn here."""
    if workers <= 1 or type(model) is not MusculoskeletalModel:
        yield from ((job[0], _draw_chunk(model, *job)) for job in jobs)
        return
    with WorkerPool(workers, __name__, "init_worker", (model.xml, model.muscle_names), "worker_chunk") as pool:
        yield from pool.map_unordered(jobs)


def generate_samples(model: MusculoskeletalModel, n: int, seed: int, spring: SpringParams = SpringParams(),
                     solver: str = "newton", workers: int | None = None,
                     progress: bool | None = None) -> EquilibriumSamples:
    """``n`` healthy equilibrium samples drawn chunk by chunk (module docstring), on ``workers`` processes.

    Args:
        workers: worker processes (``None``: every core; 0 or 1: in this process; never more than there are
            chunks). The samples are the same bytes for every value.
        progress: a progress bar on stderr while more than one chunk is drawn (``None``: when stderr is a terminal).
    Raises ``BodySchemaInputError`` for bad ``n`` or ``workers``, and as ``generate_equilibrium_samples`` when a
    chunk's postures cannot be held.
    """
    if isinstance(n, bool) or int(n) != n or n <= 0:
        raise BodySchemaInputError(f"dataset size n={n!r} must be a positive integer")
    workers, sizes = check_workers(workers), chunk_sizes(n)
    starts = np.concatenate([[0], np.cumsum(sizes)])
    out = EquilibriumSamples(q=np.empty((int(n), model.n_joints)), l_motor=np.empty((int(n), model.n_muscles)),
                             f=np.empty((int(n), model.n_muscles)), n_redrawn=0)
    jobs = [(k, size, int(seed), spring, solver) for k, size in enumerate(sizes)]
    with ProgressBar(int(n), enabled=len(jobs) > 1 and progress is not False, tty_only=progress is None) as bar:
        for k, samples in _chunks(model, jobs, min(workers, len(jobs))):
            rows = slice(starts[k], starts[k + 1])
            out.q[rows], out.l_motor[rows], out.f[rows] = samples.q, samples.l_motor, samples.f
            out.n_redrawn += samples.n_redrawn
            bar.update(len(samples.q))
    return out


class ProgressBar:
    """Samples done out of ``total`` on stderr: tqdm's bar when tqdm is installed, else one rewritten line.

    enabled: draw at all; tty_only: only when stderr is a terminal (quiet in logs and pipes).
    """

    def __init__(self, total: int, enabled: bool = True, tty_only: bool = True, desc: str = "equilibrium samples"):
        self.total, self.done, self.desc = int(total), 0, desc
        self.enabled = enabled and (not tty_only or sys.stderr.isatty())
        self._tqdm = None
        if self.enabled:
            try:
                from tqdm import tqdm
            except ImportError:
                return
            self._tqdm = tqdm(total=self.total, desc=desc, unit="sample", unit_scale=True, file=sys.stderr)

    def update(self, count: int) -> None:
        self.done += int(count)
        if self._tqdm is not None:
            self._tqdm.update(int(count))
        elif self.enabled:
            print(f"\r{self.desc}: {self.done}/{self.total} ({100 * self.done / self.total:.0f} %)", end="",
                  file=sys.stderr, flush=True)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        if self._tqdm is not None:
            self._tqdm.close()
        elif self.enabled:
            print(file=sys.stderr)
