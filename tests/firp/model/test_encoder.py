"""Image encoder: the small CNN (fast) and EfficientNet-Lite0 with its real ImageNet weights."""

import dataclasses
import hashlib
from pathlib import Path

import numpy as np
import pytest
import torch

from firp.model import EncoderConfig, ImageEncoder, efficientnet_lite0_weights_path
from firp.model.encoder import EFFICIENTNET_LITE0_SHA256

from .helpers import TINY, assert_finite_grads


def _images(*lead: int, h: int = 40, w: int = 40) -> torch.Tensor:
    return torch.randint(0, 256, (*lead, h, w, 3), dtype=torch.uint8)


# ---- small CNN --------------------------------------------------------------------------------


def test_small_cnn_shapes_and_gradients_end_to_end():
    cfg = dataclasses.replace(TINY.encoder, freeze_backbone=False)
    enc = ImageEncoder(cfg)
    e_seq = enc(_images(2, 3))  # (B, T, H, W, 3)
    e_one = enc(_images(2))  # (B, H, W, 3)
    assert e_seq.shape == (2, 3, cfg.feature_dim) and e_one.shape == (2, cfg.feature_dim)
    (e_seq.square().sum() + e_one.sum()).backward()
    assert_finite_grads(enc)


def test_frozen_backbone_stays_frozen_and_in_eval_mode_projection_trains():
    enc = ImageEncoder(TINY.encoder)  # freeze_backbone=True by default
    enc.train()
    assert not enc.backbone.training and enc.projection.training
    assert not any(p.requires_grad for p in enc.backbone.parameters())
    feats = enc.backbone_features(_images(2, 3))
    assert feats.shape == (2, 3, TINY.encoder.backbone_dim) and feats.grad_fn is None  # cacheable
    enc.project(feats).sum().backward()
    assert_finite_grads(enc.projection)


def test_chunking_does_not_change_features_and_numpy_input_works():
    enc = ImageEncoder(TINY.encoder).eval()
    imgs = _images(2, 5)
    whole = enc.backbone_features(imgs)
    chunked = enc.backbone_features(imgs.numpy(), chunk_size=3)
    torch.testing.assert_close(whole, chunked)


def test_non_uint8_images_are_rejected():
    enc = ImageEncoder(TINY.encoder)
    with pytest.raises(TypeError, match="uint8"):
        enc.backbone_features(torch.rand(2, 32, 32, 3))


def test_preprocess_resizes_to_the_configured_size():
    enc = ImageEncoder(TINY.encoder)
    x = enc.preprocess(_images(2, h=48, w=64))
    assert x.shape == (2, 3, TINY.encoder.image_size, TINY.encoder.image_size)


# ---- EfficientNet-Lite0 (real weights) -----------------------------------------------------------


@pytest.fixture(scope="module")
def lite0_84() -> ImageEncoder:
    return ImageEncoder(EncoderConfig(backbone="efficientnet_lite0", image_size=84)).eval()


def test_shipped_weights_file_is_the_expected_one(lite0_84):
    path = efficientnet_lite0_weights_path()
    assert hashlib.sha256(Path(path).read_bytes()).hexdigest() == EFFICIENTNET_LITE0_SHA256


def test_lite0_gives_1280_features_that_tell_images_apart(lite0_84):
    yy, xx = torch.meshgrid(torch.arange(96), torch.arange(96), indexing="ij")
    gradient = torch.stack([xx * 2, yy * 2, (xx + yy)], dim=-1).to(torch.uint8)
    noise = _images(1, h=96, w=96)[0]
    feats = lite0_84.backbone_features(torch.stack([gradient, noise]))
    assert feats.shape == (2, 1280) and torch.isfinite(feats).all()
    assert (feats[0] - feats[1]).abs().max() > 0.1
    e = lite0_84(torch.stack([gradient, noise]).unsqueeze(1))  # (B, T=1, H, W, 3)
    assert e.shape == (2, 1, 64)


def test_lite0_classifies_a_real_photo_with_its_imagenet_head():
    """End to end check of weights + preprocessing: the pooled features through the checkpoint's
    own classifier put Grace Hopper's photo (matplotlib sample data) in ImageNet class 652,
    'military uniform' -- the classic result for this image."""
    import matplotlib as mpl  # declared dependencies (pyproject.toml): a missing install must fail, not skip
    from PIL import Image

    photo = Path(mpl.get_data_path()) / "sample_data" / "grace_hopper.jpg"  # in every matplotlib wheel
    img = np.array(Image.open(photo).convert("RGB"))
    enc = ImageEncoder(EncoderConfig(backbone="efficientnet_lite0", image_size=224)).eval()
    feats = enc.backbone_features(img[None])  # (1, 1280)
    state = torch.load(efficientnet_lite0_weights_path(), map_location="cpu", weights_only=True)
    logits = feats @ state["_fc.weight"].T + state["_fc.bias"]
    assert int(logits.argmax()) == 652
