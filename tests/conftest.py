"""Shared test settings."""

import pytest
import torch


@pytest.fixture(autouse=True, scope="module")
def one_torch_thread():
    # pytest runs two workers on the two cores; more torch threads per worker only fight
    # over them (and spinning OpenMP threads slow everything down many times over).
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
