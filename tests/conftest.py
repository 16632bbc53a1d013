import pytest
import torch

import torchmisspec as tms


@pytest.fixture
def generator():
    return torch.Generator().manual_seed(1234)


@pytest.fixture
def linear_system():
    return tms.systems.paper_linear()


@pytest.fixture
def paper_times():
    return torch.linspace(0.0, 6.0, 11, dtype=torch.float64)
