import pytest

from firp.model import EncoderConfig, FIRPConfig, HeadConfig, LossConfig, RSSMConfig


def test_round_trip_through_dict():
    cfg = FIRPConfig(encoder=EncoderConfig(backbone="small_cnn", small_cnn_channels=(4, 8)), head=HeadConfig(temperature=0.1))
    assert FIRPConfig.from_dict(cfg.to_dict()) == cfg


def test_unknown_keys_are_rejected():
    with pytest.raises(ValueError, match="unknown"):
        FIRPConfig.from_dict({"rssm": {"deter": 3}})


@pytest.mark.parametrize("make", [
    lambda: EncoderConfig(backbone="resnet"),
    lambda: EncoderConfig(feature_dim=0),
    lambda: RSSMConfig(min_std=0.0),
    lambda: HeadConfig(temperature=0.0),
    lambda: LossConfig(alpha=-1.0),
])
def test_invalid_values_fail_early(make):
    with pytest.raises(ValueError):
        make()


def test_backbone_dims_and_normalisation():
    assert EncoderConfig().backbone_dim == 1280
    assert EncoderConfig().resolved_normalization == "inception"  # what EfficientNet-Lite was trained with
    assert EncoderConfig(backbone="small_cnn", small_cnn_channels=(4, 8)).backbone_dim == 8
    assert EncoderConfig(backbone="small_cnn").resolved_normalization == "imagenet"
