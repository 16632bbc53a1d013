"""The paper's tests run their studies with one torch thread, as ``reproduce()`` does.

The matrices are small; with every core's thread spinning, a busy neighbour on a shared machine made these studies
ten times slower (measured: 4 s with one thread, 35 s with two, under load).
"""

import pytest


@pytest.fixture(autouse=True, scope="module")
def _paper_threads(one_thread):  # the root conftest's fixture
    yield
