"""The frames store: ingest's output, read by the later stages.

A zarr v3 group ``frames.zarr`` with one subgroup per drive log (``log000``, ``log001``...),
because each log has its own camera (rectified frame size, valid mask) and its own
odometry frame. Per log:

    images        (N, H, W) uint16   rectified frames; intensity = value * intensity_scale
                                     in 8-bit grey levels (0..255); one chunk per frame,
                                     shards of ``shard_frames`` frames
    valid         (H, W) bool        rectified pixels that come from inside the raw image
    t             (N,) float64       frame times, seconds
    prior         (N, 3) float64     odometry pose (x, y, theta) at the frame time, in the
                                     log's odometry frame (metres, radians; mapstore.grid)
    source_index  (N,) int32         row of the frame in the log's frames.csv (0-based)
    quality       (N, K) float32     per-frame quality figures, columns in attrs["columns"]

Only accepted frames are stored; rejected ones are listed in the stage manifest.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np
import zarr
from zarr.codecs import ZstdCodec

STORE_NAME = "frames.zarr"
FORMAT = "mosaicmap-frames"
FORMAT_VERSION = 1
INTENSITY_SCALE = 1.0 / 256.0  # uint16 value -> 8-bit grey levels
QUALITY_COLUMNS = (
    "texture_median",
    "textured_fraction",
    "isotropy",
    "mean_level",
    "saturated_fraction",
    "dark_fraction",
)


def quantize(image: np.ndarray) -> np.ndarray:
    """8-bit grey levels (float) -> the store's uint16 fixed point (1/256 grey level steps)."""
    return np.clip(np.rint(image / INTENSITY_SCALE), 0, 65535).astype(np.uint16)


def create_store(path: Path, pixel_size: float) -> zarr.Group:
    root = zarr.open_group(str(path), mode="w")
    root.attrs.update(
        {
            "format": FORMAT,
            "format_version": FORMAT_VERSION,
            "pixel_size_m": pixel_size,
            "intensity_scale": INTENSITY_SCALE,
            "frame_convention": "mapstore.grid: columns +x, rows -y, pose = image centre",
            "logs": [],
        }
    )
    return root


class LogFramesWriter:
    """Appends accepted frames of one log, a whole shard at a time (one writer per shard)."""

    def __init__(self, root: zarr.Group, index: int, attrs: dict, valid: np.ndarray, shard_frames: int = 16):
        self.group = root.create_group(f"log{index:03d}")
        self.group.attrs.update(attrs)
        h, w = valid.shape
        self.shard_frames = shard_frames
        self.images = self.group.create_array(
            "images",
            shape=(0, h, w),
            chunks=(1, h, w),
            shards=(shard_frames, h, w),
            dtype="uint16",
            compressors=ZstdCodec(level=3),
        )
        self.group.create_array("valid", data=valid.astype(bool))
        self._buf: list[np.ndarray] = []
        self._rows: list[tuple] = []
        self.count = 0

    def append(self, image: np.ndarray, t: float, prior: np.ndarray, source_index: int, quality: tuple) -> None:
        self._buf.append(quantize(image))
        self._rows.append((t, prior, source_index, quality))
        if len(self._buf) == self.shard_frames:
            self._flush()

    def _flush(self) -> None:
        if not self._buf:
            return
        n0 = self.count
        n1 = n0 + len(self._buf)
        self.images.resize((n1, *self.images.shape[1:]))
        self.images[n0:n1] = np.stack(self._buf)
        self.count = n1
        self._buf = []

    def close(self) -> int:
        self._flush()
        n = len(self._rows)
        t = np.array([r[0] for r in self._rows], dtype=np.float64)
        prior = np.array([r[1] for r in self._rows], dtype=np.float64).reshape(n, 3)
        src = np.array([r[2] for r in self._rows], dtype=np.int32)
        q = np.array([r[3] for r in self._rows], dtype=np.float32).reshape(n, len(QUALITY_COLUMNS))
        self.group.create_array("t", data=t)
        self.group.create_array("prior", data=prior)
        self.group.create_array("source_index", data=src)
        qa = self.group.create_array("quality", data=q)
        qa.attrs["columns"] = list(QUALITY_COLUMNS)
        return n


@dataclass
class LogFrames:
    """Read access to one log's frames (images are read lazily, one frame at a time)."""

    group: zarr.Group

    @property
    def attrs(self) -> dict:
        return self.group.attrs.asdict()

    @property
    def count(self) -> int:
        return int(self.group["images"].shape[0])

    @property
    def valid(self) -> np.ndarray:
        return self.group["valid"][...]

    @property
    def t(self) -> np.ndarray:
        return self.group["t"][...]

    @property
    def prior(self) -> np.ndarray:
        return self.group["prior"][...]

    @property
    def source_index(self) -> np.ndarray:
        return self.group["source_index"][...]

    def image(self, i: int) -> np.ndarray:
        """Frame ``i`` as float32 in 8-bit grey levels."""
        return self.group["images"][i].astype(np.float32) * np.float32(INTENSITY_SCALE)

    @cached_property
    def shard_frames(self) -> int:
        return int(self.group["images"].shards[0])

    def images(self, start: int, stop: int) -> np.ndarray:
        """Frames ``start:stop`` as float32 (one read; cheapest over whole shards)."""
        return self.group["images"][start:stop].astype(np.float32) * np.float32(INTENSITY_SCALE)


class FrameStore:
    """Read access to a frames store written by ingest."""

    def __init__(self, path: str | Path):
        self.root = zarr.open_group(str(path), mode="r")
        if self.root.attrs.get("format") != FORMAT:
            raise ValueError(f"{path}: not a mosaicmap frames store")
        self.pixel_size = float(self.root.attrs["pixel_size_m"])
        self.logs = [LogFrames(self.root[f"log{i:03d}"]) for i in range(len(self.root.attrs["logs"]))]
