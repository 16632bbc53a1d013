"""The paper's tests run their studies with one torch thread, as ``reproduce()`` does.

The matrices are small; with every core's thread spinning, a busy neighbour on a shared machine made these studies
ten times slower (measured: 4 s with one thread, 35 s with two, under load).
"""

import pytest
import torch


@pytest.fixture(autouse=True, scope="module")
def one_torch_thread():
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)
