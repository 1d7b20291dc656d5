"""The analyses that train or load models share the method tests' fixtures (tests/firp/conftest.py)."""

from tests.firp.conftest import tiny_dataset  # noqa: F401  (fixture)
from tests.torch_fixtures import _one_thread, _seed  # noqa: F401  (autouse fixtures)
