"""A tiny exported bundle shared by the scorer and fused-path tests."""

import pytest

from firp.bundle import load_bundle

from ..bundle_helpers import export_tiny, tiny_backbone, tiny_members


@pytest.fixture
def exported(tmp_path):
    """(members, backbone, bundle) of a 3-member FIRP ensemble, before and after the round trip."""
    members, backbone = tiny_members(), tiny_backbone()
    return members, backbone, load_bundle(export_tiny(tmp_path / "b", members, backbone))
