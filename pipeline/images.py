"""Decoding image files with OpenImageIO into grey float32 arrays in 8-bit grey levels, and
the per-log intensity normalization ingest applies to them.

Any bit depth (8, 16 bit, float) is scaled so that the file's full scale maps to 255, so
every later stage works in one unit: grey levels of an 8-bit scale (0..255). A log that
uses only a small part of its format's range (16-bit microscope tiles at ~2 % of full
scale, 12-bit data in 16-bit files) is then stretched by :class:`IntensityMap`, a linear map
from the log's own robust range (:func:`estimate_intensity_map`) to the working range.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import OpenImageIO as oiio

from pipeline.errors import BadInput

# Rec. 601 luma weights for RGB(A) -> grey.
_LUMA = np.array([0.299, 0.587, 0.114], dtype=np.float32)
# Full-scale values of the unsigned integer formats read as stored.
_UNSIGNED_MAX = {oiio.UINT8: 255.0, oiio.UINT16: 65535.0, oiio.UINT32: 4294967295.0}
# Bits of integer pixel formats; float files get the code step of a 16-bit file.
_FORMAT_BITS = {oiio.UINT8: 8, oiio.INT8: 7, oiio.UINT16: 16, oiio.INT16: 15, oiio.UINT32: 32, oiio.INT32: 31}


# More channels than this in an image header is not a camera image (and would multiply the
# decoded size): refused before decoding.
MAX_CHANNELS = 8


@dataclass(frozen=True)
class ImageLimits:
    """Caps an outside image must pass, checked from its file size and header before any
    pixel is decoded (``[ingest] max_image_pixels``, ``max_image_bytes``).

    Attributes:
        max_pixels: most pixels (width x height x depth) one image may declare; an image is
            decoded as float32 per channel, so 100 MPix of RGB take 1.2 GB.
        max_bytes: largest image file (bytes on disk).
    """

    max_pixels: int = 100_000_000
    max_bytes: int = 500_000_000
    pixels_cap: str = "[ingest] max_image_pixels"  # how messages name the caps
    bytes_cap: str = "[ingest] max_image_bytes"

    @classmethod
    def from_config(cls, ingest: dict) -> "ImageLimits":
        """The caps of an ``[ingest]`` table (read through its schema, :mod:`pipeline.schema`:
        positive integers)."""
        from pipeline.schema import settings
        from pipeline.schema_floor import IngestConfig

        ing = settings(IngestConfig, ingest)
        return cls(ing.max_image_pixels, ing.max_image_bytes)


DEFAULT_LIMITS = ImageLimits()


def check_image_size(path: str | Path, limits: ImageLimits | None = None) -> None:
    """The file-size cap (before the file is opened); :class:`BadInput` naming the file and cap."""
    limits = limits or DEFAULT_LIMITS
    try:
        size = os.stat(path).st_size
    except OSError:
        return  # missing or unreachable: the reader says which
    if size > limits.max_bytes:
        raise BadInput(path, f"image file is {size} bytes, more than {limits.bytes_cap} = {limits.max_bytes}")


PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# The last 12 bytes of every complete PNG: the IEND chunk (length 0, type, CRC).
PNG_END = b"\x00\x00\x00\x00IEND\xaeB`\x82"
# How far from the end the IEND chunk is looked for (trailing bytes after it are harmless).
PNG_TAIL_BYTES = 4096


def check_png_end(path: str | Path) -> None:
    """A PNG file cut short (a copy or a write interrupted) is refused here, before libpng
    reads it: libpng would print its own ``libpng error: ...`` line on stderr besides our
    one-line error. :class:`BadInput` when the file starts as a PNG and holds no IEND chunk
    in its last :data:`PNG_TAIL_BYTES` bytes; anything else is left to the reader."""
    try:
        with open(path, "rb") as f:
            if f.read(len(PNG_SIGNATURE)) != PNG_SIGNATURE:
                return
            f.seek(0, os.SEEK_END)
            size = f.tell()
            f.seek(max(len(PNG_SIGNATURE), size - PNG_TAIL_BYTES))
            if PNG_END[4:] in f.read():  # (bytes after IEND are tolerated, as by libpng)
                return
    except OSError:
        return  # missing or unreadable: the reader says which
    raise BadInput(path, "corrupt or truncated image: the PNG file ends before its IEND chunk (cut short?)")


def check_image_header(path: str | Path, spec, limits: ImageLimits | None = None) -> None:
    """The pixel and channel caps from an image header (an OpenImageIO ``ImageSpec``), before
    any pixel is decoded; :class:`BadInput` naming the file and the cap."""
    limits = limits or DEFAULT_LIMITS
    w, h, d = int(spec.width), int(spec.height), max(1, int(spec.depth))
    if w <= 0 or h <= 0:
        raise BadInput(path, f"image header declares {w}x{h} pixels")
    if w * h * d > limits.max_pixels:
        size = f"{w}x{h}" + (f"x{d}" if d > 1 else "")
        raise BadInput(path, f"image is {size} = {w * h * d} pixels, more than {limits.pixels_cap} = "
                             f"{limits.max_pixels} (checked before decoding)")
    if not 1 <= spec.nchannels <= MAX_CHANNELS:
        raise BadInput(path, f"image header declares {spec.nchannels} channels (at most {MAX_CHANNELS})")


def read_grey(path: str | Path, *, limits: ImageLimits | None = None) -> np.ndarray:
    """Read an image file as grey float32 ``(H, W)`` in 8-bit grey levels (0..255).

    ``limits``: the caps checked before decoding (default :data:`DEFAULT_LIMITS`).

    Raises:
        BadInput: the file is missing, not an image, corrupt, truncated or over a cap.
    """
    return read_grey_coded(path, limits=limits)[0]


def code_step_of(spec) -> float:
    """One code of the file's pixel format, in grey levels of full scale 255: 1.0 for 8-bit,
    255/65535 for 16-bit, 255/4095 for 12-bit data declared as such (``oiio:BitsPerSample``);
    float files count as 16-bit."""
    bits = _FORMAT_BITS.get(spec.format.basetype, 16)
    declared = spec.get_int_attribute("oiio:BitsPerSample", 0)
    if 0 < declared < bits:
        bits = declared
    return 255.0 / float(2**bits - 1)


def read_grey_coded(path: str | Path, *, limits: ImageLimits | None = None) -> tuple[np.ndarray, float]:
    """:func:`read_grey` and the file's code step (grey levels per code, :func:`code_step_of`).

    Raises:
        BadInput: the file is missing, not an image, corrupt, truncated or over a cap of
            ``limits`` (checked from the file size and header, before decoding).
    """
    path = Path(path)
    check_image_size(path, limits)
    check_png_end(path)
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        msg = oiio.geterror().strip() or "cannot open"
        if not path.exists():
            msg = "image file not found"
        raise BadInput(path, f"unreadable image: {msg.splitlines()[0]}")
    try:
        spec = inp.spec()
        check_image_header(path, spec, limits)
        # Unsigned integer and float files are read as stored and scaled here (4-5x faster
        # than OpenImageIO's conversion to float, and exact: 8-bit codes stay whole numbers);
        # other formats through OpenImageIO's normalization to [0, 1].
        base = spec.format.basetype
        native = base in _UNSIGNED_MAX or base in (oiio.FLOAT, oiio.HALF)
        pixels = inp.read_image(0, 0, 0, spec.nchannels, oiio.UNKNOWN if native else "float")
        err = inp.geterror()
        if pixels is None or err:
            raise BadInput(path, f"corrupt or truncated image: {(err or 'no pixels').strip().splitlines()[0]}")
    finally:
        inp.close()
    # Integer formats count their full range as [0, 1] (OpenImageIO's normalization); float
    # files are taken as already in [0, 1] full scale. Grey levels of full scale 255.
    arr = np.asarray(pixels).reshape(spec.height, spec.width, spec.nchannels)
    scale = np.float32(255.0 / _UNSIGNED_MAX[base] if base in _UNSIGNED_MAX else 255.0)
    if spec.nchannels >= 3:
        grey = (arr[..., :3].astype(np.float32) @ _LUMA) * scale
    else:
        grey = np.multiply(arr[..., 0], scale, dtype=np.float32)
    if base not in _UNSIGNED_MAX and not np.isfinite(grey).all():
        raise BadInput(path, "image has NaN or infinite pixel values")
    return np.ascontiguousarray(grey, dtype=np.float32), code_step_of(spec)


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


def read_raw(path: str | Path, *, limits: ImageLimits | None = None) -> np.ndarray:
    """First channel of an image as float32 ``(H, W)`` in its stored units (float images),
    or normalized to [0, 1] (integer images). ``limits``: the caps checked before decoding
    (default :data:`DEFAULT_LIMITS`)."""
    path = Path(path)
    check_image_size(path, limits)
    buf = oiio.ImageBuf(str(path))
    if not buf.has_error:
        check_image_header(path, buf.spec(), limits)  # ImageBuf reads the header only until the pixels are asked for
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


# The largest working grey level the frames store holds (uint16 / 256).
WORKING_MAX = 65535.0 / 256.0
PHOTOMETRY_MODES = ("auto", "always", "none")


@dataclass(frozen=True)
class IntensityMap:
    """A log's linear intensity normalization: ``working = gain x raw + offset``.

    ``raw`` in grey levels of the file's full scale (0..255, :func:`read_grey`), ``working``
    in the grey levels every later stage uses (0..255; clipped to the frames store's range
    0..255.996). The identity (gain 1, offset 0) leaves frames bit for bit unchanged.
    """

    gain: float = 1.0
    offset: float = 0.0

    @property
    def identity(self) -> bool:
        return self.gain == 1.0 and self.offset == 0.0

    def apply(self, image: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
        """``image`` (float32 grey levels) mapped to working grey levels; pixels outside
        ``valid`` (bool, same shape) are set to 0, as rectified frames have them."""
        if self.identity:
            return image
        out = image * np.float32(self.gain) + np.float32(self.offset)
        np.clip(out, 0.0, WORKING_MAX, out=out)
        if valid is not None:
            out[~valid] = 0.0
        return out


def check_photometry_config(p: dict) -> None:
    """Validate the ``[ingest.photometry]`` table (:class:`BadInput` naming the knob)."""
    where = "config[ingest.photometry.{}]".format
    if p["normalize"] not in PHOTOMETRY_MODES:
        raise BadInput(where("normalize"), f"unknown mode {p['normalize']!r} ({', '.join(PHOTOMETRY_MODES)})")
    if not 0.0 <= p["low_percentile"] < p["high_percentile"] <= 100.0:
        raise BadInput(where("low_percentile"), f"need 0 <= low_percentile < high_percentile <= 100, got "
                                                f"{p['low_percentile']} and {p['high_percentile']}")
    t = p["target_levels"]
    if len(t) != 2 or not all(isinstance(v, (int, float)) for v in t) or not 0.0 <= t[0] < t[1] <= 255.0:
        raise BadInput(where("target_levels"), f"need [low, high] grey levels with 0 <= low < high <= 255, got {t!r}")
    if not 0.0 < p["auto_max_used_fraction"] <= 1.0:
        raise BadInput(where("auto_max_used_fraction"), f"must be in (0, 1], got {p['auto_max_used_fraction']}")
    if p["sample_frames"] < 1:
        raise BadInput(where("sample_frames"), f"must be >= 1, got {p['sample_frames']}")


def estimate_intensity_map(values: np.ndarray, p: dict, code_step: float) -> tuple[IntensityMap, dict]:
    """A log's :class:`IntensityMap` from a sample of its raw pixel values, per ``[ingest.photometry]``.

    ``values``: raw grey levels (0..255 of full scale) sampled evenly over the log's frames,
    hot pixels removed and flat field applied (what the map is applied to). Its
    ``low_percentile`` and ``high_percentile`` (the log's used range) map linearly to
    ``target_levels``. ``normalize = "auto"`` applies the map only when the used range is
    below ``auto_max_used_fraction`` of full scale (full-range 8-bit logs stay unchanged),
    ``"always"`` always, ``"none"`` never. ``code_step``: one code of the files' format in
    grey levels (for the figures in counts).

    Returns the map and its description for the manifest and the report: ``normalize``,
    ``applied``, ``gain`` and ``offset`` (working = gain x raw + offset, grey levels),
    ``low_level``/``high_level`` (grey levels of full scale) and ``low_counts``/``high_counts``
    (codes of the files' format), ``used_fraction`` (of full scale), ``sampled_pixels``.
    """
    mode = p["normalize"]
    info: dict = {"normalize": mode, "applied": False, "gain": 1.0, "offset": 0.0}
    values = np.asarray(values, np.float32).ravel()
    if values.size == 0:
        info["note"] = "no pixel sampled: not normalized"
        return IntensityMap(), info
    lo, hi = (float(v) for v in np.percentile(values, [p["low_percentile"], p["high_percentile"]]))
    used = (hi - lo) / 255.0
    info.update({"low_level": lo, "high_level": hi, "low_counts": lo / code_step, "high_counts": hi / code_step,
                 "used_fraction": used, "sampled_pixels": int(values.size)})
    if mode == "none" or (mode == "auto" and used >= p["auto_max_used_fraction"]):
        return IntensityMap(), info
    if hi - lo < 2.0 * code_step:
        info["note"] = "the log's used range is under 2 codes: not normalized"
        return IntensityMap(), info
    t0, t1 = (float(v) for v in p["target_levels"])
    gain = (t1 - t0) / (hi - lo)
    m = IntensityMap(gain, t0 - gain * lo)
    info.update({"applied": True, "gain": m.gain, "offset": m.offset})
    return m, info
