"""Thread count under contention: use no more torch threads than there are free cores.

On a machine where another process keeps a core busy, torch's OpenMP threads spin waiting for a core that is taken:
small batched work (a 440-sample fit, a batched ODE solve, a design) then runs 2.5-5x slower with two threads than
with one (measured on 2 cores; ``scripts/benchmark.py --only contention``). One thread on the free core is the
fastest choice there, and the default thread count is the fastest on a quiet machine.

:func:`adaptive_threads` wraps the package's heavy calls (``CorrectionGP.fit``, ``CorrectedODE.predict``,
``simulate``, ``design.greedy``): at entry it counts the runnable threads of *other* processes (Linux
``/proc/loadavg`` minus this process's running threads, an instantaneous count, not the slow load average) and, if
they leave fewer free cores than torch's thread count, lowers ``torch.set_num_threads`` for the duration of the call
and restores it afterwards. Elsewhere (no ``/proc``) it does nothing. Set the environment variable
``TORCHMISSPEC_THREADS=torch`` to keep torch's setting untouched.
"""

from __future__ import annotations

import contextlib
import os

import torch

__all__ = ["adaptive_threads", "free_cores"]


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


def free_cores() -> int | None:
    """Cores not taken by other processes' runnable threads right now; ``None`` where this cannot be read."""
    try:
        with open("/proc/loadavg") as fh:
            runnable = int(fh.read().split()[3].split("/")[0])
        others = max(0, runnable - _own_running_threads())
    except (OSError, ValueError, IndexError):
        return None
    return max(1, _cores() - others)


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
