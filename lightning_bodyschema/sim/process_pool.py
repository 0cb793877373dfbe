"""A pool of worker processes that start clean: ``python -c`` children that import one module, never the caller's.

``multiprocessing``'s spawn and forkserver contexts re-run the caller's main script in every worker (a script
without ``if __name__ == "__main__":`` then breaks, and the ``bodyschema`` command would import Lightning and torch
in each worker), and ``fork`` copies a process holding MuJoCo and torch state. Here each worker is a fresh
interpreter with the caller's ``sys.path`` and one BLAS/OpenMP thread (the workers fill the cores): it imports
``module`` (a row of ``WORKER_MODULES``: the package's own), calls ``module.<setup>(*setup_args)`` once, then
answers tasks ``module.<task>(*args)`` over its stdin and stdout (pickles; the worker's own prints go to stderr).
One thread per worker feeds it tasks from a shared queue, so a free worker takes the next task.
"""
from __future__ import annotations

import os
import pickle
import queue
import subprocess
import sys
import threading
import traceback

ONE_THREAD = {name: "1" for name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}  # one per core
# the modules a worker may run: a fixed table of import statements, so nothing a caller passes chooses what a worker
# imports (the name only selects a row)
WORKER_MODULES = {"lightning_bodyschema.sim.sampling": "import lightning_bodyschema.sim.sampling as module"}
_CHILD = ("import pickle, sys; sys.path[:0] = pickle.load(sys.stdin.buffer); "
          "from lightning_bodyschema.sim.process_pool import answers_pipe, serve; answers = answers_pipe(); "
          "{imports}; serve(module, answers)")


def _child_program(module_name: str) -> str:
    if module_name not in WORKER_MODULES:
        raise ValueError(f"worker module {module_name!r}; allowed: {sorted(WORKER_MODULES)}")
    return _CHILD.format(imports=WORKER_MODULES[module_name])


def answers_pipe():
    """The worker's answer channel (its stdout, duplicated); from here on prints, Python's or a C library's (the
    module's import included), go to stderr, never into the answers."""
    answers = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)
    return answers


def serve(module, answers) -> None:
    """The worker's loop (run by ``_CHILD`` with its ``module``): setup once, then one answer per task until stdin
    closes."""
    requests = sys.stdin.buffer
    setup, setup_args, task = pickle.load(requests)
    getattr(module, setup)(*setup_args)
    while True:
        try:
            args = pickle.load(requests)
        except EOFError:
            return
        try:
            answer = ("ok", getattr(module, task)(*args))
        except Exception as err:  # sent back to the caller, who raises it
            answer = ("error", _portable(err))
        pickle.dump(answer, answers, protocol=pickle.HIGHEST_PROTOCOL)
        answers.flush()


def _portable(err: Exception) -> Exception:
    """``err`` itself when it pickles (a ``BodySchemaInputError`` stays one), else its traceback as a RuntimeError."""
    try:
        pickle.loads(pickle.dumps(err))
        return err
    except (pickle.PickleError, TypeError, AttributeError, ValueError):  # an exception that does not travel
        return RuntimeError(f"dataset worker failed:\n{traceback.format_exc()}")


def _quietly(close) -> None:
    try:
        close()
    except OSError:  # a pipe to a worker that is gone
        pass


class WorkerPool:
    """``workers`` clean processes running ``module.task`` (see the module docstring); use as a context manager.

    ``map_unordered(tasks)`` yields ``(index, result)`` as the workers finish; an exception in a task is raised in
    the caller (the workers are stopped first), as is a worker that dies.
    """

    def __init__(self, workers: int, module: str, setup: str, setup_args: tuple, task: str):
        program = _child_program(module)
        self._threads = []
        self._procs = [subprocess.Popen([sys.executable, "-c", program], stdin=subprocess.PIPE,
                                        stdout=subprocess.PIPE, env={**os.environ, **ONE_THREAD})
                       for _ in range(int(workers))]
        try:
            for proc in self._procs:
                self._send(proc, list(sys.path))
                self._send(proc, (setup, setup_args, task))
        except BaseException:
            self.close(kill=True)
            raise

    @staticmethod
    def _send(proc, obj) -> None:
        pickle.dump(obj, proc.stdin, protocol=pickle.HIGHEST_PROTOCOL)
        proc.stdin.flush()

    def _feed(self, proc, tasks: queue.SimpleQueue, done: queue.SimpleQueue) -> None:
        """One worker's thread: take a task, send it, put ``(index, status, answer)`` in ``done``."""
        while True:
            try:
                index, args = tasks.get_nowait()
            except queue.Empty:
                return
            try:
                self._send(proc, args)
                status, answer = pickle.load(proc.stdout)
            except (OSError, ValueError, EOFError, pickle.UnpicklingError):  # ValueError: a pipe closed by close()
                status, answer = "error", RuntimeError(
                    f"a dataset worker process died (exit code {proc.wait()}; its messages are above): out of memory? "
                    "fewer workers, or workers=1 to draw in this process")
            done.put((index, status, answer))
            if status != "ok":
                return

    def map_unordered(self, tasks: list[tuple]):
        todo, done = queue.SimpleQueue(), queue.SimpleQueue()
        for item in enumerate(tasks):
            todo.put(item)
        self._threads = [threading.Thread(target=self._feed, args=(proc, todo, done), daemon=True)
                         for proc in self._procs]
        for thread in self._threads:
            thread.start()
        for _ in range(len(tasks)):
            index, status, answer = done.get()
            if status != "ok":
                self.close(kill=True)
                raise answer
            yield index, answer

    def close(self, kill: bool = False) -> None:
        """Stop the workers: close their stdin (they exit when idle), or kill them; then reap them."""
        for proc in self._procs:
            if kill:
                proc.kill()
            else:
                _quietly(proc.stdin.close)
        for proc in self._procs:
            proc.wait()
        for thread in self._threads:
            thread.join()  # each ends at its worker's exit (end of file) or with the tasks
        for proc in self._procs:
            _quietly(proc.stdin.close)
            proc.stdout.close()

    def __enter__(self):
        return self

    def __exit__(self, exc_type, *exc):
        self.close(kill=exc_type is not None)
