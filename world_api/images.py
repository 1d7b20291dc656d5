"""Camera images on the wire: lossless PNG in base64, so a client gets the exact pixels a dataset holds.

A lossy format would hand the scoring model images it never saw in training; PNG round-trips the
uint8 array bit for bit.
"""

from __future__ import annotations

import base64
import io

import numpy as np
from PIL import Image

__all__ = ["decode_png_b64", "encode_png_b64"]


def encode_png_b64(image: np.ndarray) -> str:
    """An (H, W, 3) uint8 RGB image as base64 PNG: lossless, so a client gets the exact pixels a dataset holds."""
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"image: expected an (H, W, 3) uint8 array, got {image.shape} {image.dtype}")
    buffer = io.BytesIO()
    # compress_level 1: frames are tiny and this runs once per plan step when frames are asked for
    Image.fromarray(image, mode="RGB").save(buffer, format="PNG", compress_level=1)
    return base64.b64encode(buffer.getvalue()).decode("ascii")


def decode_png_b64(text: str) -> np.ndarray:
    """Inverse of :func:`encode_png_b64`: the (H, W, 3) uint8 RGB array."""
    with Image.open(io.BytesIO(base64.b64decode(text, validate=True))) as img:
        return np.asarray(img.convert("RGB"), dtype=np.uint8).copy()
