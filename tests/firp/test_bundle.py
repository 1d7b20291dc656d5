"""Bundles: what the manifest records, an exact round trip, and every way a bundle is refused."""

import dataclasses
import json
import pickle
from datetime import datetime
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file, save_file

from firp.bundle import (
    BACKBONE_FILE,
    BUNDLE_FORMAT_VERSION,
    MANIFEST_NAME,
    Bundle,
    BundleError,
    BundleMember,
    export_bundle,
    load_bundle,
    sha256_file,
)
from firp.core.contract import CATEGORIES, CONTRACT_VERSION, PLAN_WIDTH, PlanLimits
from firp.model import EncoderConfig, FIRPConfig, build_model

from .bundle_helpers import T_RANGE, export_tiny, tiny_backbone, tiny_members
from .model.helpers import TINY


@pytest.fixture
def bundle_dir(tmp_path: Path) -> Path:
    return export_tiny(tmp_path / "bundle", tiny_members(("firp", "firp", "a_mlp_image")))


def _manifest(path: Path) -> dict:
    return json.loads((path / MANIFEST_NAME).read_text())


def _write_manifest(path: Path, manifest: dict) -> None:
    (path / MANIFEST_NAME).write_text(json.dumps(manifest))


def _refused(path: Path, rule: str, *fragments: str) -> BundleError:
    with pytest.raises(BundleError) as info:
        load_bundle(path)
    err = info.value
    assert err.rule == rule, str(err)
    for fragment in fragments:
        assert fragment in str(err), f"{fragment!r} not in {err}"
    return err


# round trip ----------------------------------------------------------------------------------


def test_manifest_records_what_the_service_needs(bundle_dir):
    m = _manifest(bundle_dir)
    assert m["format_version"] == BUNDLE_FORMAT_VERSION
    assert m["contract_version"] == CONTRACT_VERSION
    assert m["plan"]["width"] == PLAN_WIDTH and m["plan"]["categories"] == list(CATEGORIES)
    assert m["t_range"] == {"t_min": T_RANGE[0], "t_max": T_RANGE[1]}
    assert m["image_size"] == TINY.encoder.image_size
    assert m["backbone"]["name"] == "small_cnn" and m["backbone"]["file"] == BACKBONE_FILE
    assert m["backbone"]["sha256"] == sha256_file(bundle_dir / BACKBONE_FILE)
    assert [e["kind"] for e in m["members"]] == ["firp", "firp", "a_mlp_image"]
    for k, entry in enumerate(m["members"]):
        assert entry["file"] == f"member_{k}.safetensors"
        assert entry["sha256"] == sha256_file(bundle_dir / entry["file"])
        assert FIRPConfig.from_dict(entry["config"]) == TINY
        assert entry["validation"]["balanced_accuracy"] == pytest.approx(0.5 + 0.1 * k)
    assert m["threshold"] == 0.5
    assert m["calibration"] == {"ece": 0.05, "n_val": 40, "n_bins": 10}
    assert isinstance(m["calibration"]["n_val"], int)
    assert m["validation"] == {"balanced_accuracy": 0.7}
    assert m["training_data"] == {"sha256": "ab" * 32, "path": "data/tiny.hdf5"}
    assert m["extra"] == {"seed": 0, "note": "test"}
    assert datetime.fromisoformat(m["created_utc"]).utcoffset().total_seconds() == 0
    assert sorted(p.name for p in bundle_dir.iterdir()) == [
        BACKBONE_FILE, MANIFEST_NAME, "member_0.safetensors", "member_1.safetensors", "member_2.safetensors"]


def test_round_trip_restores_every_weight(tmp_path):
    members, backbone = tiny_members(("firp", "a_mlp", "gru")), tiny_backbone()
    bundle = load_bundle(export_tiny(tmp_path / "b", members, backbone))
    assert isinstance(bundle, Bundle)
    assert bundle.kinds == ("firp", "a_mlp", "gru")
    assert bundle.threshold == 0.5 and bundle.t_range == PlanLimits(*T_RANGE)
    assert bundle.name == "tiny" and bundle.task == "stacking"
    assert bundle.encoder_config == TINY.encoder
    for original, loaded in zip(members, bundle.models):
        assert not loaded.training
        assert all(not p.requires_grad for p in loaded.parameters())
        for key, value in original.model.state_dict().items():
            torch.testing.assert_close(loaded.state_dict()[key], value, rtol=0, atol=0)
    for key, value in backbone.state_dict().items():
        torch.testing.assert_close(bundle.backbone.state_dict()[key], value, rtol=0, atol=0)


def test_export_is_atomic_and_refuses_to_overwrite_by_default(tmp_path):
    out = export_tiny(tmp_path / "b")
    assert [p.name for p in tmp_path.iterdir()] == ["b"]  # no temp directory left behind
    with pytest.raises(FileExistsError):
        export_tiny(out)
    before = _manifest(out)["members"][0]["sha256"]
    export_tiny(out, overwrite=True)  # new random members
    assert _manifest(out)["members"][0]["sha256"] != before
    assert [p.name for p in tmp_path.iterdir()] == ["b"]
    load_bundle(out)


def test_failed_export_leaves_nothing(tmp_path):
    with pytest.raises(ValueError):
        export_tiny(tmp_path / "b", extra={"bad": float("nan")})  # not JSON: fails while writing
    assert list(tmp_path.iterdir()) == []


def test_loading_never_unpickles(bundle_dir, monkeypatch):
    def refuse(*_: object, **__: object) -> None:
        raise AssertionError("a bundle must never be unpickled")

    monkeypatch.setattr(torch, "load", refuse)
    monkeypatch.setattr(pickle, "load", refuse)
    monkeypatch.setattr(pickle, "loads", refuse)
    load_bundle(bundle_dir)


def test_efficientnet_bundle_references_the_pinned_weights(tmp_path):
    cfg = dataclasses.replace(TINY, encoder=EncoderConfig(backbone="efficientnet_lite0", image_size=32, feature_dim=6,
                                                          projection_hidden=0))
    members = [BundleMember("firp", cfg, build_model("firp", cfg)) for _ in range(2)]
    path = export_bundle(  # no backbone=: the pinned pretrained weights are referenced by hash
        tmp_path / "b", members, name="e", task="stacking", threshold=0.4, calibration={"ece": 0.0, "n_val": 1},
        metrics={}, training_data_hash="0", training_data_path="x", t_range=T_RANGE)
    manifest = _manifest(path)
    assert manifest["backbone"]["file"] is None and manifest["backbone"]["dim"] == 1280
    assert sorted(p.name for p in path.iterdir()) == [MANIFEST_NAME, "member_0.safetensors", "member_1.safetensors"]
    bundle = load_bundle(path)
    assert bundle.encoder_config.backbone == "efficientnet_lite0" and len(bundle.models) == 2
    assert bundle.backbone(torch.zeros(1, 3, 32, 32)).shape == (1, 1280)


# export refuses what load would refuse --------------------------------------------------------


def test_export_refuses_bad_members(tmp_path):
    with pytest.raises(ValueError, match="oracle"):
        export_tiny(tmp_path / "a", tiny_members(("firp", "oracle")))
    other = dataclasses.replace(TINY, encoder=dataclasses.replace(TINY.encoder, image_size=64))
    mixed = tiny_members() + [BundleMember("firp", other, build_model("firp", other))]
    with pytest.raises(ValueError, match="backbone"):
        export_tiny(tmp_path / "b", mixed)
    unfrozen = dataclasses.replace(TINY, encoder=dataclasses.replace(TINY.encoder, freeze_backbone=False))
    with pytest.raises(ValueError, match="unfrozen"):
        export_tiny(tmp_path / "g", [BundleMember("firp", unfrozen, build_model("firp", unfrozen))])
    wrong_kind = [BundleMember("a_mlp", TINY, build_model("firp", TINY))]
    with pytest.raises(ValueError, match="do not fit"):
        export_tiny(tmp_path / "c", wrong_kind)
    with pytest.raises(ValueError, match="backbone="):
        export_bundle(tmp_path / "d", tiny_members(), name="x", task="x", threshold=0.5,
                      calibration={"ece": 0, "n_val": 0}, metrics={}, training_data_hash="0",
                      training_data_path="x", t_range=T_RANGE)
    with pytest.raises(ValueError, match="max_T"):  # TINY's A-MLP flattens at most 16 steps
        export_tiny(tmp_path / "e", tiny_members(("a_mlp",)), t_range=(8, 120))
    with pytest.raises(ValueError, match="threshold"):
        export_tiny(tmp_path / "f", threshold=1.5)
    assert list(tmp_path.iterdir()) == []


# tampering -----------------------------------------------------------------------------------


def test_flipped_byte_is_caught_by_the_hash(bundle_dir):
    path = bundle_dir / "member_1.safetensors"
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0x01
    path.write_bytes(bytes(data))
    _refused(bundle_dir, "sha256", "member_1.safetensors", "sha256")


def test_tampered_backbone_is_caught(bundle_dir):
    path = bundle_dir / BACKBONE_FILE
    data = bytearray(path.read_bytes())
    data[-1] ^= 0xFF
    path.write_bytes(bytes(data))
    _refused(bundle_dir, "sha256", BACKBONE_FILE)


def test_missing_member_file(bundle_dir):
    (bundle_dir / "member_2.safetensors").unlink()
    _refused(bundle_dir, "missing", "member_2.safetensors", "missing")


def test_missing_or_corrupt_manifest(bundle_dir, tmp_path):
    _refused(tmp_path / "nowhere", "missing", "nowhere")
    text = (bundle_dir / MANIFEST_NAME).read_text()
    (bundle_dir / MANIFEST_NAME).write_text(text[: len(text) // 2])
    _refused(bundle_dir, "corrupt", MANIFEST_NAME, "JSON")
    (bundle_dir / MANIFEST_NAME).unlink()
    _refused(bundle_dir, "missing", MANIFEST_NAME)


def test_incompatible_contract_or_format(bundle_dir):
    good = _manifest(bundle_dir)
    _write_manifest(bundle_dir, {**good, "contract_version": "2.0"})
    _refused(bundle_dir, "contract_version", MANIFEST_NAME, "2.0", CONTRACT_VERSION)
    _write_manifest(bundle_dir, {**good, "format_version": BUNDLE_FORMAT_VERSION + 1})
    _refused(bundle_dir, "format_version", MANIFEST_NAME)
    _write_manifest(bundle_dir, {**good, "plan": {**good["plan"], "categories": list(reversed(CATEGORIES))}})
    _refused(bundle_dir, "contract", "categories")
    _write_manifest(bundle_dir, {**good, "t_range": {"t_min": 2, "t_max": 16}})
    _refused(bundle_dir, "contract", "t_range")
    _write_manifest(bundle_dir, {k: v for k, v in good.items() if k != "threshold"})
    _refused(bundle_dir, "schema", "threshold")


def _rewrite_member(bundle_dir: Path, k: int, state: dict) -> None:
    """Replace member k's weights and re-hash them, as a careless tool (not bit rot) would."""
    path = bundle_dir / f"member_{k}.safetensors"
    save_file(state, str(path))
    manifest = _manifest(bundle_dir)
    manifest["members"][k]["sha256"] = sha256_file(path)
    _write_manifest(bundle_dir, manifest)


def test_wrong_shape_with_a_correct_hash(bundle_dir):
    state = load_file(str(bundle_dir / "member_0.safetensors"))
    state["head.prototypes"] = torch.zeros(TINY.head.n_prototypes + 1, TINY.head.q_dim)
    _rewrite_member(bundle_dir, 0, state)
    _refused(bundle_dir, "state_dict", "member_0.safetensors", "head.prototypes", "(4, 5)")


def test_missing_and_unexpected_keys_with_a_correct_hash(bundle_dir):
    state = load_file(str(bundle_dir / "member_1.safetensors"))
    state["extra.weight"] = state.pop("rssm.rnn.weight_ih")
    _rewrite_member(bundle_dir, 1, state)
    _refused(bundle_dir, "state_dict", "member_1.safetensors", "rssm.rnn.weight_ih", "extra.weight")


def test_config_that_does_not_fit_the_weights(bundle_dir):
    manifest = _manifest(bundle_dir)
    manifest["members"][0]["config"]["rssm"]["deter_dim"] = 13
    _write_manifest(bundle_dir, manifest)
    _refused(bundle_dir, "state_dict", "member_0.safetensors")
    manifest["members"][0]["config"]["rssm"]["deter_dimm"] = 13  # a typo is not silently ignored
    _write_manifest(bundle_dir, manifest)
    _refused(bundle_dir, "config", "deter_dimm")


def test_garbage_with_a_correct_hash_is_corrupt(bundle_dir):
    path = bundle_dir / "member_0.safetensors"
    path.write_bytes(b"\x10\x00\x00\x00\x00\x00\x00\x00{not json at all")
    manifest = _manifest(bundle_dir)
    manifest["members"][0]["sha256"] = sha256_file(path)
    _write_manifest(bundle_dir, manifest)
    _refused(bundle_dir, "corrupt", "member_0.safetensors", "safetensors")


def test_member_file_must_stay_inside_the_bundle(bundle_dir):
    manifest = _manifest(bundle_dir)
    manifest["members"][0]["file"] = "../member_0.safetensors"
    _write_manifest(bundle_dir, manifest)
    _refused(bundle_dir, "schema", "plain file name")


def test_oracle_member_in_a_manifest_is_refused(bundle_dir):
    manifest = _manifest(bundle_dir)
    manifest["members"][0]["kind"] = "oracle"
    _write_manifest(bundle_dir, manifest)
    _refused(bundle_dir, "config", "oracle")
