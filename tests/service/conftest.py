"""Service tests: one CPU thread (see tests/firp/conftest.py for why), a tiny bundle, clients.

The bundle is tiny (three random FIRP members on a small CNN, T in [8, 16], 32 px images): the
service's behaviour does not depend on the weights, and every test stays in milliseconds. No test
needs the shipped bundle.
"""

from __future__ import annotations

import pytest
import torch

from tests.torch_fixtures import _one_thread, _seed  # noqa: F401  (autouse fixtures)

from service.app import create_app
from service.settings import ServiceSettings
from tests.firp.bundle_helpers import export_tiny

from .helpers import ServiceClient

#: Limits small enough that the refusal tests stay small, large enough for every valid request here.
STRICT = dict(max_body_bytes=256 * 1024, max_image_bytes=16 * 1024, min_image_side=16, max_image_side=256,
              max_image_pixels=256 * 128, max_aspect_ratio=4.0, max_batch=4)


@pytest.fixture(scope="session")
def tiny_bundle(tmp_path_factory):
    torch.manual_seed(0)
    return export_tiny(tmp_path_factory.mktemp("service") / "tiny")


@pytest.fixture(scope="session")
def settings(tiny_bundle) -> ServiceSettings:
    return ServiceSettings(bundle=tiny_bundle, threads=1, **STRICT)


@pytest.fixture(scope="session")
def client(settings):
    """A ready service on the tiny bundle, shared by the tests that do not change it."""
    with ServiceClient(create_app(settings)) as c:
        yield c
