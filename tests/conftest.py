import contextlib
import os

import pytest
import torch

import torchmisspec as tms

if os.environ.get("PYTEST_XDIST_WORKER"):  # one torch thread per worker: the workers share the cores
    torch.set_num_threads(1)


@pytest.fixture(autouse=True)
def _same_global_stream():
    """Every test starts from the same global torch stream, so a draw made without a generator of its own is the same
    whichever tests ran before it in its worker (a slow tutorial check failed in CI, and passed alone, for this)."""
    torch.manual_seed(0)


@pytest.fixture
def generator():
    return torch.Generator().manual_seed(1234)


@pytest.fixture
def linear_system():
    return tms.systems.paper_linear()


@pytest.fixture
def paper_times():
    return torch.linspace(0.0, 6.0, 11, dtype=torch.float64)


@contextlib.contextmanager
def _torch_threads(n: int):
    previous = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


@pytest.fixture(scope="module")
def one_thread():
    """One torch thread for a module's small problems (threads only add overhead there, and oversubscribed OpenMP
    threads on a busy machine made small fits several times slower); torch's setting is restored afterwards."""
    with _torch_threads(1):
        yield


@pytest.fixture
def two_threads():
    with _torch_threads(2):
        yield


@pytest.fixture(scope="session")
def fast_linear():
    """``make(K) -> (system, trajectories)``: a linear system faster than the paper's with a larger quadratic F, and K
    noise-free experiments of 11 times on [0, 3] (the fits through the ODE's test problem)."""
    return _fast_linear


def _fast_linear(num_experiments: int):
    from torchmisspec.systems import LinearField, QuadraticField

    A = 5 * torch.tensor([[0.02, 0.10], [-0.10, -0.06]], dtype=torch.float64)
    system = tms.MisspecifiedSystem(
        LinearField(A), 2, correction=QuadraticField(0.2), domain=((-1, 1), (-1, 1)), known_matrix=A, name="fast"
    )
    gen = torch.Generator().manual_seed(0)
    y0 = torch.rand(num_experiments, 2, generator=gen, dtype=torch.float64) * 2 - 1
    return system, tms.simulate(system, y0, torch.linspace(0, 3, 11, dtype=torch.float64))


@pytest.fixture
def study_smoke(tmp_path):
    """``run(script) -> (saved JSON, completed process)``: ``scripts/<script> --smoke --json ...`` in a child
    process (checked to exit 0), and what it saved."""
    import json
    import subprocess
    import sys
    from pathlib import Path

    scripts = Path(__file__).resolve().parents[1] / "scripts"

    def run(script: str):
        out = tmp_path / f"{Path(script).stem}.json"
        proc = subprocess.run(
            [sys.executable, str(scripts / script), "--smoke", "--json", str(out)],
            check=True,
            capture_output=True,
            text=True,
            timeout=1500,  # a guard against a hang: the longest smoke takes 3.5 min alone, 10 beside other work
        )
        return json.loads(out.read_text()), proc

    return run
