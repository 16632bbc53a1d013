"""Independent work through an executor: studies' realizations, the folds of :func:`~torchmisspec.calibrate_bands`,
the chunks of a design's proxy trajectories.

Any :class:`concurrent.futures.Executor` runs the tasks: a local process pool (:func:`process_pool`), a Dask
cluster's ``Client.get_executor()``, Ray's ``ray.util`` executors. Results come back in the tasks' order, and every
task seeds its own generator, so a run through an executor gives the numbers of the serial run.

A task must be picklable for a process pool (a module-level function and plain arguments). Each worker of
:func:`process_pool` uses one torch thread: two workers on two cores then run side by side instead of four OpenMP
threads fighting over them.

**Threads under contention** (:func:`adaptive_threads`): use no more torch threads than there are free cores.

On a machine where another process keeps a core busy, torch's OpenMP threads spin waiting for a core that is taken:
small batched work (a 440-sample fit, a batched ODE solve, a design) then runs several times slower with two threads
than with one (``scripts/benchmark.py --only contention`` measures it; the figures are in BENCHMARKS.md). One
thread on the free core is the fastest choice there, and the default thread count is the fastest on a quiet machine.

:func:`adaptive_threads` wraps the package's heavy calls (``CorrectionGP.fit``, ``CorrectedODE.predict``,
``simulate``, ``design.greedy``): at entry it counts the runnable threads of *other* processes (Linux
``/proc/loadavg`` minus this process's running threads, an instantaneous count, not the slow load average) and, if
they leave fewer free cores than torch's thread count, lowers ``torch.set_num_threads`` for the duration of the call
and restores it afterwards. Elsewhere (no ``/proc``) it does nothing. Set the environment variable
``TORCHMISSPEC_THREADS=torch`` to keep torch's setting untouched.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import multiprocessing
import os
import time
from collections.abc import Callable, Iterable

import torch

from ._errors import InputError, TorchMisspecError
from ._user_code import one_line
from ._validation import check_arity, check_callable, check_positive_int

__all__ = ["map_tasks", "process_pool", "check_executor", "adaptive_threads", "free_cores"]


def check_executor(executor) -> concurrent.futures.Executor | None:
    """``None`` (serial) or a :class:`concurrent.futures.Executor`."""
    if executor is None or isinstance(executor, concurrent.futures.Executor):
        return executor
    raise InputError(
        f"executor: expected a concurrent.futures.Executor (a process pool, Dask's client.get_executor(), ...) or "
        f"None, got {type(executor).__name__}"
    )


def map_tasks(fn: Callable, tasks: Iterable, executor=None, *, each: Callable | None = None) -> list:
    """``[fn(task) for task in tasks]``, through ``executor`` when one is given (results in the tasks' order);
    ``each(result)`` is called as each result arrives (a progress bar's update).

    Raises:
        InputError: an executor that was shut down or broke (pass a running one, or ``None``), or whose ``map``
            gives another number of results than tasks. The tasks' own errors pass unchanged.
    """
    executor = check_executor(executor)
    check_arity(check_callable(fn, "fn", "fn(task)"), 1, "fn", "fn(task) giving the task's result")
    if each is not None:
        check_arity(check_callable(each, "each", "each(result)"), 1, "each", "each(result) called as each arrives")
    if isinstance(tasks, (str, bytes)) or not isinstance(tasks, Iterable):
        raise InputError(f"tasks: expected a list (an iterable) of tasks, got {tasks!r:.60} ({type(tasks).__name__})")
    tasks = list(tasks)
    results = []
    if executor is None:
        for result in map(fn, tasks):
            results.append(result)
            if each is not None:
                each(result)
        return results
    try:
        returned = executor.map(fn, tasks)
        if not isinstance(returned, Iterable):
            raise InputError(
                f"executor: expected its map to return an iterable of results, got {type(returned).__name__} from "
                f"{_kind(executor)}; pass a concurrent.futures.Executor, or None to run serially"
            )
        for result in returned:
            results.append(result)
            if len(results) > len(tasks):
                break  # an executor that never stops giving results
            if each is not None:
                each(result)
    except RuntimeError as exc:
        if _unusable(exc):
            raise InputError(
                f"executor: expected a running executor, got {_kind(executor)} that was shut down or broke "
                f"({one_line(exc)}); pass a running executor, or None to run serially"
            ) from exc
        raise
    if len(results) != len(tasks):
        got = f"{len(results)}" if len(results) <= len(tasks) else f"more than {len(tasks)}"
        raise InputError(
            f"executor: expected {len(tasks)} {'result' if len(tasks) == 1 else 'results'} (one per task) from the "
            f"executor's map, got {got} from {_kind(executor)}; its map must give one result per task, in the "
            "tasks' order (concurrent.futures.Executor.map does): fix the executor, or pass None to run serially"
        )
    return results


def _kind(executor) -> str:
    return f"a {type(executor).__name__}"


def _unusable(exc: RuntimeError) -> bool:
    """Whether ``exc`` says that the executor itself cannot run tasks (shut down, or a broken pool); a task's own
    error (a package error, a RuntimeError of the task's code) is not."""
    if isinstance(exc, TorchMisspecError):
        return False
    if isinstance(exc, concurrent.futures.BrokenExecutor):
        return True
    text = f"{type(exc).__name__} {exc}".lower()
    return "shutdown" in text or "shut down" in text


def _one_thread() -> None:
    torch.set_num_threads(1)


def process_pool(workers: int) -> concurrent.futures.ProcessPoolExecutor:
    """A local pool of ``workers`` processes (started by spawn: no state copied from this one), one torch thread
    each. Use it as a context manager (``with process_pool(2) as pool: ...``) so that the workers stop."""
    workers = check_positive_int(workers, "workers")
    context = multiprocessing.get_context("spawn")
    return concurrent.futures.ProcessPoolExecutor(workers, mp_context=context, initializer=_one_thread)


def _cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def _own_running_threads() -> int:
    running = 0
    for tid in os.listdir("/proc/self/task"):
        try:
            with open(f"/proc/self/task/{tid}/stat") as fh:
                state = fh.read().rsplit(")", 1)[1].split()[0]
        except (OSError, IndexError):
            continue
        running += state == "R"
    return running


def _others_running() -> int:
    """Runnable threads of other processes in one look: the system's runnable count minus this process's running
    threads, read before and after it (this process's OpenMP workers go from spinning to sleeping within
    milliseconds; counting them as ours on either side avoids taking them for another process)."""
    before = _own_running_threads()
    with open("/proc/loadavg") as fh:
        runnable = int(fh.read().split()[3].split("/")[0])
    return max(0, runnable - max(before, _own_running_threads()))


def free_cores(looks: int = 4, gap: float = 1e-3) -> int | None:
    """Cores not taken by other processes' runnable threads; ``None`` where this cannot be read.

    The smallest count of ``looks`` looks ``gap`` seconds apart (about 3 ms in all): a process that keeps a core busy
    is runnable at every look, a transient one (a kernel thread, this process's own workers going to sleep) is not
    (a few quick looks without a gap gave false alarms right after torch operations on a quiet machine).
    """
    try:
        counts = []
        for i in range(looks):
            if i:
                time.sleep(gap)
            counts.append(_others_running())
    except (OSError, ValueError, IndexError):
        return None
    return max(1, _cores() - min(counts))


@contextlib.contextmanager
def adaptive_threads():
    """Lower torch's thread count to the free cores for the duration of a call (see the module docstring)."""
    if os.environ.get("TORCHMISSPEC_THREADS", "adaptive") != "adaptive":
        yield
        return
    current = torch.get_num_threads()
    free = free_cores() if current > 1 else None
    if free is None or free >= current:
        yield
        return
    torch.set_num_threads(free)
    try:
        yield
    finally:
        torch.set_num_threads(current)
