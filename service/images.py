"""Request images -> uint8 ``(H, W, 3)`` arrays, refusing what could hurt the service first.

Why the order of checks matters: an attacker (or a buggy client) can send a 100-byte PNG that
declares 50,000 x 50,000 pixels, which decodes to 7.5 GB. PIL's ``Image.open`` reads only the
header, so the declared size is checked against the limits *before* ``load()`` decodes a single
pixel, and only PNG and JPEG are opened at all (fewer decoders, less attack surface).

Size: the backbone wants ``image_size x image_size`` (the bundle's manifest). Images of another
size are not resized here: the scorer's encoder resizes every image exactly as it resized the
training frames (bilinear, antialiased, to a square: a non-square image is stretched), so that a
planner sending the camera's own 84 x 84 frame gets the same features as training did. The limits
only refuse dimensions no camera produces (tiny, huge, or extreme aspect ratios).
"""

from __future__ import annotations

import base64
import binascii
import io
import warnings
from dataclasses import dataclass

import numpy as np
from PIL import Image, UnidentifiedImageError

from service.errors import ServiceError
from service.settings import ServiceSettings

__all__ = ["ALLOWED_FORMATS", "ImageLimits", "check_dimensions", "decode_base64_image", "decode_image_bytes",
           "image_from_array"]

ALLOWED_FORMATS = ("PNG", "JPEG")


@dataclass(frozen=True)
class ImageLimits:
    max_bytes: int
    min_side: int
    max_side: int
    max_pixels: int
    max_aspect_ratio: float

    @classmethod
    def from_settings(cls, s: ServiceSettings) -> ImageLimits:
        return cls(s.max_image_bytes, s.min_image_side, s.max_image_side, s.max_image_pixels, s.max_aspect_ratio)


def check_dimensions(width: int, height: int, limits: ImageLimits, field: str) -> None:
    """Refuse extreme dimensions with a 422 naming the rule (``dimensions``)."""
    problem = None
    if min(width, height) < limits.min_side:
        problem = f"{width}x{height} has a side below the minimum {limits.min_side}"
    elif max(width, height) > limits.max_side:
        problem = f"{width}x{height} has a side above the maximum {limits.max_side}"
    elif width * height > limits.max_pixels:
        problem = f"{width}x{height} has more than {limits.max_pixels} pixels"
    elif max(width, height) / min(width, height) > limits.max_aspect_ratio:
        problem = f"{width}x{height} has an aspect ratio above {limits.max_aspect_ratio:g}"
    if problem:
        raise ServiceError(422, field, "dimensions", problem)


def decode_base64_image(data: str, limits: ImageLimits, field: str = "image") -> np.ndarray:
    """A base64 PNG or JPEG -> uint8 ``(H, W, 3)`` RGB (grey, palette and alpha are converted).

    Raises :class:`~service.errors.ServiceError`: 413 ``max_bytes`` (too large before or after
    base64 decoding), 422 ``base64``, ``format`` (not a PNG/JPEG), ``dimensions``, ``decode``
    (header fine, pixel data broken).
    """
    # 4 base64 characters carry 3 bytes: refuse an oversized string before decoding it.
    if len(data) > (limits.max_bytes + 2) // 3 * 4 + 4:
        raise ServiceError(413, field, "max_bytes", f"the encoded image is larger than {limits.max_bytes} bytes")
    try:
        raw = base64.b64decode(data, validate=True)
    except (binascii.Error, ValueError):
        raise ServiceError(422, field, "base64", "must be standard base64 (RFC 4648, with padding) of a PNG "
                           "or JPEG file") from None
    return decode_image_bytes(raw, limits, field)


def decode_image_bytes(raw: bytes, limits: ImageLimits, field: str = "image") -> np.ndarray:
    """A PNG or JPEG file's bytes -> uint8 ``(H, W, 3)`` RGB; the checks of :func:`decode_base64_image`
    after its base64 step (413 ``max_bytes``, 422 ``format``, ``dimensions``, ``decode``)."""
    if len(raw) > limits.max_bytes:
        raise ServiceError(413, field, "max_bytes", f"the encoded image is larger than {limits.max_bytes} bytes")
    try:
        img = Image.open(io.BytesIO(raw), formats=list(ALLOWED_FORMATS))
    except Image.DecompressionBombError as exc:  # PIL's own header check: more than twice its pixel limit
        raise ServiceError(422, field, "dimensions", f"the image declares too many pixels ({exc})") from None
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError):
        raise ServiceError(422, field, "format", f"not a readable {' or '.join(ALLOWED_FORMATS)} image") from None
    with img:
        check_dimensions(img.width, img.height, limits, field)
        try:
            with warnings.catch_warnings():
                # Our limits are stricter than PIL's; should a format slip past them, its
                # decompression-bomb warning must stop the decode, not just print.
                warnings.simplefilter("error", Image.DecompressionBombWarning)
                rgb = img.convert("RGB")  # decodes: the only expensive step, now bounded
        except (OSError, ValueError, SyntaxError, Image.DecompressionBombWarning, Image.DecompressionBombError) as exc:
            raise ServiceError(422, field, "decode", f"the image data cannot be decoded ({exc})") from None
    arr = np.asarray(rgb, dtype=np.uint8)
    if arr.ndim != 3 or arr.shape[2] != 3:  # pragma: no cover - convert("RGB") guarantees it
        raise ServiceError(422, field, "decode", f"decoded to shape {arr.shape}, not (H, W, 3)")
    return arr


def image_from_array(arr: np.ndarray, limits: ImageLimits, field: str) -> np.ndarray:
    """An already numeric ``(H, W, 3)`` array (the V2 UINT8 tensor) checked against the same limits."""
    if arr.ndim != 3 or arr.shape[2] != 3:
        raise ServiceError(422, field, "shape", f"an image tensor is H x W x 3, got shape {list(arr.shape)}")
    check_dimensions(int(arr.shape[1]), int(arr.shape[0]), limits, field)
    return np.ascontiguousarray(arr, dtype=np.uint8)
