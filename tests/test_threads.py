"""The adaptive thread count: it sees another process's busy core, lowers torch's threads only for the call, and
restores them; TORCHMISSPEC_THREADS=torch turns it off. (Speed is measured by scripts/benchmark.py, not here.)"""

import subprocess
import sys
import time

import pytest
import torch

from torchmisspec import parallel as _threads


@pytest.fixture
def busy_core():
    spinner = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    time.sleep(0.3)
    yield
    spinner.kill()
    spinner.wait()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_a_busy_process_takes_a_core_and_the_call_uses_fewer_threads(two_threads, busy_core, monkeypatch):
    cores = _threads._cores()
    seen = [_threads.free_cores() for _ in range(5)]
    assert max(seen) <= cores - 1  # the spinner is runnable at every look
    monkeypatch.setattr(_threads, "free_cores", lambda: 1)
    with _threads.adaptive_threads():
        inside = torch.get_num_threads()
    assert inside == 1 and torch.get_num_threads() == 2


def test_nothing_changes_when_cores_are_free_or_the_policy_is_off(two_threads, monkeypatch):
    monkeypatch.setattr(_threads, "free_cores", lambda: 2)
    with _threads.adaptive_threads():
        assert torch.get_num_threads() == 2
    monkeypatch.setattr(_threads, "free_cores", lambda: 1)
    monkeypatch.setenv("TORCHMISSPEC_THREADS", "torch")
    with _threads.adaptive_threads():
        assert torch.get_num_threads() == 2


def test_the_count_is_restored_when_the_call_fails(two_threads, monkeypatch):
    monkeypatch.setattr(_threads, "free_cores", lambda: 1)
    with pytest.raises(RuntimeError, match="boom"), _threads.adaptive_threads():
        raise RuntimeError("boom")
    assert torch.get_num_threads() == 2
