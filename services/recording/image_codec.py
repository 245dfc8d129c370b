"""Compressed images for recordings: lossless PNG and lossy JPEG, with OpenCV's codecs.

PNG keeps every value (8-bit grey or BGR, 16-bit grey such as depth counts); JPEG takes 8-bit grey or BGR images
and loses detail (about 2 grey levels rms at quality 75 on the sim camera's images). An image is ``(H, W)`` or
``(H, W, C)`` with C = 1 or 3 channels in OpenCV's BGR order; ``(H, W, 1)`` is encoded as ``(H, W)`` and decoded
back to the shape asked for.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

PNG = "png"
JPEG = "jpeg"
FORMATS = (PNG, JPEG)
#: PNG's zlib level (OpenCV's default): a 160 x 120 depth frame of the sim stack took 2-3 ms and 12.7 kB.
PNG_LEVEL = 3
_DTYPES = {PNG: (np.dtype(np.uint8), np.dtype(np.uint16)), JPEG: (np.dtype(np.uint8),)}


class ImageCodecError(ValueError):
    """An image that the format cannot hold, or bytes that do not decode to the expected image."""


@dataclass(frozen=True)
class EncodedImage:
    """An image in a compressed format. format: ``png`` or ``jpeg``; data: the file's bytes."""

    format: str
    data: bytes


def encode_image(image: np.ndarray, image_format: str, jpeg_quality: int = 75) -> EncodedImage:
    """``image`` (see the module docstring) as ``image_format``; ``jpeg_quality`` 1..100 for JPEG. Raises
    ImageCodecError when the format cannot hold the image's dtype or shape."""
    if image_format not in FORMATS:
        raise ImageCodecError(f"unknown image format {image_format!r} (one of {', '.join(FORMATS)})")
    array = np.asarray(image)
    if array.dtype not in _DTYPES[image_format]:
        raise ImageCodecError(f"{image_format} cannot hold {array.dtype} images")
    if array.ndim == 3 and array.shape[2] == 1:
        array = array[..., 0]
    if array.ndim not in (2, 3) or (array.ndim == 3 and array.shape[2] != 3) or 0 in array.shape:
        raise ImageCodecError(f"not an (H, W), (H, W, 1) or (H, W, 3) image: shape {image.shape}")
    if image_format == PNG:
        params, suffix = [cv2.IMWRITE_PNG_COMPRESSION, PNG_LEVEL], ".png"
    else:
        if not 1 <= jpeg_quality <= 100:
            raise ImageCodecError(f"JPEG quality must be 1..100, got {jpeg_quality}")
        params, suffix = [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)], ".jpg"
    ok, data = cv2.imencode(suffix, np.ascontiguousarray(array), params)
    if not ok:
        raise ImageCodecError(f"OpenCV could not encode a {array.dtype} {array.shape} image as {image_format}")
    return EncodedImage(image_format, data.tobytes())


def decode_image(data: bytes, dtype: np.dtype | str, shape: tuple[int, ...]) -> np.ndarray:
    """The image of ``dtype`` and ``shape`` that the PNG or JPEG bytes ``data`` hold. Raises ImageCodecError when
    they do not decode, or decode to another dtype or size."""
    decoded = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if decoded is None:
        raise ImageCodecError(f"{len(data)} bytes are not a PNG or JPEG image")
    expected = np.dtype(dtype)
    if decoded.dtype != expected or decoded.size != int(np.prod(shape)):
        raise ImageCodecError(f"the image decodes to {decoded.dtype} {decoded.shape}, expected {expected} {shape}")
    return decoded.reshape(shape)
