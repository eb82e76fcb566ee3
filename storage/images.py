"""The frames a policy saw, as MCAP messages: ``foxglove.CompressedImage`` with PNG data.

PNG, not JPEG: a policy trained on recorded frames must see what it saw when it acted, pixel for
pixel, and PNG is lossless; Foxglove and any MCAP reader show it as an image. The bytes travel as
base64 in the JSON message, as Foxglove's JSON schema has them.
"""

from __future__ import annotations

import base64
import io

import numpy as np
from PIL import Image

from storage.mcap_io import stamp

COMPRESSED_IMAGE_SCHEMA = {  # Foxglove's JSON schema: the bytes as base64, so a JSON reader gets them back
    "title": "foxglove.CompressedImage",
    "type": "object",
    "properties": {
        "timestamp": {"type": "object", "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}},
        "frame_id": {"type": "string"},
        "data": {"type": "string", "contentEncoding": "base64"},
        "format": {"type": "string"},
    },
}


class ImageDecodeError(ValueError):
    """A recorded frame is not a PNG of the expected size."""


def check_frame(image, camera: str) -> np.ndarray:
    """``image`` as a (h, w, 3) uint8 array; ValueError naming ``camera`` otherwise."""
    arr = np.asarray(image)
    if arr.dtype != np.uint8 or arr.ndim != 3 or arr.shape[2] != 3:
        raise ValueError(f"camera {camera!r}: a frame must be (h, w, 3) uint8 RGB, got {arr.dtype} {arr.shape}")
    return arr


def png_message(image: np.ndarray, frame_id: str, ns: int) -> dict:
    """A ``foxglove.CompressedImage`` payload of ``image`` (h, w, 3) uint8, PNG-encoded."""
    buf = io.BytesIO()
    Image.fromarray(image, "RGB").save(buf, format="PNG", compress_level=1)
    return {
        "timestamp": stamp(ns),
        "frame_id": frame_id,
        "data": base64.b64encode(buf.getvalue()).decode("ascii"),
        "format": "png",
    }


def decode_png_bytes(data: bytes, size: tuple[int, int] | None = None) -> np.ndarray:
    """The (h, w, 3) uint8 frame of PNG (or any image file's) ``data``; ImageDecodeError for anything else,
    or another (h, w) than ``size``."""
    try:
        with Image.open(io.BytesIO(data)) as im:
            arr = np.asarray(im.convert("RGB"))
    except (ValueError, OSError, TypeError) as exc:
        raise ImageDecodeError(f"not an image: {exc}") from exc
    if size is not None and arr.shape[:2] != tuple(size):
        raise ImageDecodeError(f"frame of {arr.shape[1]}x{arr.shape[0]} pixels, expected {size[1]}x{size[0]}")
    return arr


def decode_png(message: dict, size: tuple[int, int] | None = None) -> np.ndarray:
    """The (h, w, 3) uint8 frame of a ``png_message``; ImageDecodeError for anything else, or another
    (h, w) than ``size``."""
    if message.get("format") != "png":
        raise ImageDecodeError(f"frame format {message.get('format')!r}, expected 'png'")
    try:
        data = base64.b64decode(message["data"], validate=True)
    except (KeyError, ValueError, TypeError) as exc:
        raise ImageDecodeError(f"not a PNG frame: {exc}") from exc
    if not data.startswith(b"\x89PNG"):
        raise ImageDecodeError("not a PNG frame")
    return decode_png_bytes(data, size)
