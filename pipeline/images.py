"""Decoding image files with OpenImageIO into grey float32 arrays in 8-bit grey levels.

Any bit depth (8, 16 bit, float) is scaled so that the file's full scale maps to 255, so
every later stage works in one unit: grey levels of an 8-bit scale (0..255).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import OpenImageIO as oiio

from pipeline.errors import BadInput

# Rec. 601 luma weights for RGB(A) -> grey.
_LUMA = np.array([0.299, 0.587, 0.114], dtype=np.float32)


def read_grey(path: str | Path) -> np.ndarray:
    """Read an image file as grey float32 ``(H, W)`` in 8-bit grey levels (0..255).

    Raises:
        BadInput: the file is missing, not an image, corrupt or truncated.
    """
    path = Path(path)
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        msg = oiio.geterror().strip() or "cannot open"
        if not path.exists():
            msg = "image file not found"
        raise BadInput(path, f"unreadable image: {msg.splitlines()[0]}")
    try:
        spec = inp.spec()
        pixels = inp.read_image(0, 0, 0, spec.nchannels, "float")
        err = inp.geterror()
        if pixels is None or err:
            raise BadInput(path, f"corrupt or truncated image: {(err or 'no pixels').strip().splitlines()[0]}")
    finally:
        inp.close()
    # OpenImageIO returns integer formats normalized to [0, 1]; float files are taken as
    # already in [0, 1] full scale.
    arr = np.asarray(pixels, dtype=np.float32).reshape(spec.height, spec.width, spec.nchannels)
    if spec.nchannels >= 3:
        grey = arr[..., :3] @ _LUMA
    else:
        grey = arr[..., 0]
    if not np.isfinite(grey).all():
        raise BadInput(path, "image has NaN or infinite pixel values")
    return np.ascontiguousarray(grey * 255.0, dtype=np.float32)


def write_image(path: str | Path, pixels: np.ndarray, attributes: dict | None = None) -> None:
    """Write pixels (H, W) or (H, W, C) of uint8, uint16 or float32 as they are.

    The format follows the extension; ``attributes`` are OpenImageIO spec attributes
    (e.g. ``{"png:compressionLevel": 1}``, ``{"compression": "none"}``). Pixels are passed
    as (H, W, C): OpenImageIO misreads a 2-D array given to ``write_image``.
    """
    data = np.ascontiguousarray(pixels)
    if data.ndim == 2:
        data = data[:, :, None]
    fmt = {np.dtype(np.uint8): oiio.UINT8, np.dtype(np.uint16): oiio.UINT16, np.dtype(np.float32): oiio.FLOAT}.get(data.dtype)
    if fmt is None:
        raise TypeError(f"cannot write {data.dtype} pixels")
    spec = oiio.ImageSpec(data.shape[1], data.shape[0], data.shape[2], fmt)
    for key, value in (attributes or {}).items():
        spec.attribute(key, value)
    out = oiio.ImageOutput.create(str(path))
    if out is None or not out.open(str(path), spec):
        raise OSError(f"{path}: cannot write image: {oiio.geterror()}")
    ok = out.write_image(data)
    err = out.geterror()
    out.close()
    if not ok:
        raise OSError(f"{path}: cannot write image: {err}")


def read_raw(path: str | Path) -> np.ndarray:
    """First channel of an image as float32 ``(H, W)`` in its stored units (float images),
    or normalized to [0, 1] (integer images)."""
    path = Path(path)
    buf = oiio.ImageBuf(str(path))
    px = buf.get_pixels(oiio.FLOAT)
    if buf.has_error or px is None:
        raise BadInput(path, f"unreadable image: {buf.geterror().strip() or 'no pixels'}")
    spec = buf.spec()
    return np.asarray(px, np.float32).reshape(spec.height, spec.width, spec.nchannels)[..., 0].copy()


def write_grey(path: str | Path, image: np.ndarray, *, bits: int = 8, attributes: dict | None = None) -> None:
    """Write a grey image given in 8-bit grey levels as an 8- or 16-bit file."""
    scale = 1.0 if bits == 8 else 65535.0 / 255.0
    dtype = np.uint8 if bits == 8 else np.uint16
    data = np.clip(np.rint(np.asarray(image, np.float64) * scale), 0, np.iinfo(dtype).max).astype(dtype)
    write_image(path, data, attributes)
