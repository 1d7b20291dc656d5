"""Autouse fixtures shared by every torch test directory (imported by their conftest.py files).

One CPU thread: the tensors in tests are tiny, and with two OpenMP threads each op waits at a
barrier for the second core; when that core is busy (a benchmark or a sim worker next to the tests)
every op costs a scheduler slice (~8 ms instead of ~0.02 ms), which turns a 5 s test file into
minutes. A fixed seed: every test starts from the same random state.
"""

import pytest
import torch


@pytest.fixture(autouse=True, scope="session")
def _one_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)
