"""Independent work through an executor: studies' realizations, the folds of :func:`~torchmisspec.calibrate_bands`,
the chunks of a design's proxy trajectories.

Any :class:`concurrent.futures.Executor` runs the tasks: a local process pool (:func:`process_pool`), a Dask
cluster's ``Client.get_executor()``, Ray's ``ray.util`` executors. Results come back in the tasks' order, and every
task seeds its own generator, so a run through an executor gives the numbers of the serial run.

A task must be picklable for a process pool (a module-level function and plain arguments). Each worker of
:func:`process_pool` uses one torch thread: two workers on two cores then run side by side instead of four OpenMP
threads fighting over them.
"""

from __future__ import annotations

import concurrent.futures
import multiprocessing
from collections.abc import Callable, Iterable

import torch

from ._errors import InputError
from ._validation import check_positive_int

__all__ = ["map_tasks", "process_pool", "check_executor"]


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
    ``each(result)`` is called as each result arrives (a progress bar's update)."""
    executor = check_executor(executor)
    tasks = list(tasks)
    results = []
    for result in map(fn, tasks) if executor is None else executor.map(fn, tasks):
        results.append(result)
        if each is not None:
            each(result)
    return results


def _one_thread() -> None:
    torch.set_num_threads(1)


def process_pool(workers: int) -> concurrent.futures.ProcessPoolExecutor:
    """A local pool of ``workers`` processes (started by spawn: no state copied from this one), one torch thread
    each. Use it as a context manager (``with process_pool(2) as pool: ...``) so that the workers stop."""
    workers = check_positive_int(workers, "workers")
    context = multiprocessing.get_context("spawn")
    return concurrent.futures.ProcessPoolExecutor(workers, mp_context=context, initializer=_one_thread)
