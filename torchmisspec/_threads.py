"""Thread count under contention: use no more torch threads than there are free cores.

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

import contextlib
import os
import time

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
