"""The frames store: ingest's output, read by the later stages.

A zarr v3 group ``frames.zarr`` with one subgroup per drive log (``log000``, ``log001``...),
because each log has its own camera (rectified frame size, valid mask) and its own
odometry frame. Per log:

    images        (N, H, W) uint16   rectified frames; intensity = value * intensity_scale
                                     in 8-bit grey levels (0..255); one chunk per frame,
                                     shards of ``shard_frames`` frames; zstd-compressed
                                     only where that pays (:data:`ZSTD_MIN_SAVING`)
    valid         (H, W) bool        rectified pixels that come from inside the raw image
    t             (N,) float64       frame times, seconds
    prior         (N, 3) float64     odometry pose (x, y, theta) at the frame time, in the
                                     log's odometry frame (metres, radians; mapstore.grid)
    source_index  (N,) int32         row of the frame in the log's frames.csv (0-based)
    quality       (N, K) float32     per-frame quality figures, columns in attrs["columns"]
                                     (:data:`QUALITY_COLUMNS`); column ``registrable`` is 1
                                     for frames registration may pair, 0 for frames kept
                                     with too little (or one-directional) texture, placed
                                     by their prior (:attr:`LogFrames.registrable`)

Only accepted frames are stored (registrable or not); rejected ones are listed in the stage
manifest, and so are the stored frames placed by the prior (``placed_by_prior``). The log
group's attributes hold the log's intensity normalization (``photometry``: images =
gain x raw + offset in grey levels) and exposure clip levels (``exposure``).
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np
import zarr
from numcodecs import CRC32C, Zstd
from zarr.codecs import ZstdCodec

from mapstore.bundle import zstd_content_size

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
    "noise_sigma",  # working grey levels
    "hot_pixels",  # count replaced
    "registrable",  # 1 registrable, 0 placed by the prior (too little or one-directional texture)
)
# Values of columns a writer leaves out (a shorter quality tuple: writers of the first six).
QUALITY_DEFAULTS = {"registrable": 1.0}
# A log's frames are stored zstd-compressed (:data:`ZSTD_LEVEL`) only when that makes a frame of its
# first shard (the middle one) at least this much smaller; else as they are. Rectified frames hold interpolated values in
# 1/256 grey level steps, whose low byte is noise: zstd saved 5-12 % on real frames
# rectified this way (a microscope's speckle, a brain section) and 2 % on the render
# benchmark's floor, for 0.45 ms of decoding at every read and 0.6 ms of encoding at ingest
# per 640 x 480 frame; an uncompressed frame is read in ~0.1 ms.
ZSTD_MIN_SAVING = 0.10
ZSTD_LEVEL = 3  # of the frames that are compressed


def quantize(image: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """8-bit grey levels (float) -> the store's uint16 fixed point (1/256 grey level steps),
    into ``out`` (uint16, the image's shape) when given."""
    v = np.multiply(image, np.float32(1.0 / INTENSITY_SCALE), dtype=np.float32)
    np.rint(v, out=v)
    np.clip(v, 0, 65535, out=v)
    if out is None:
        return v.astype(np.uint16)
    np.copyto(out, v, casting="unsafe")
    return out


def dequantize(stored: np.ndarray) -> np.ndarray:
    """The store's uint16 fixed point -> 8-bit grey levels (float32), :func:`quantize`'s inverse."""
    return np.multiply(stored, np.float32(INTENSITY_SCALE), dtype=np.float32)


def store_version(path: Path) -> int:
    """A number that changes when the frames store at ``path`` is rewritten (its root
    metadata's mtime, ns; 0 when absent): the key of per-process frame caches."""
    try:
        return (Path(path) / "zarr.json").stat().st_mtime_ns
    except OSError:
        return 0


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


def pays_to_compress(frame: np.ndarray) -> bool:
    """Whether zstd (:data:`ZSTD_LEVEL`) makes ``frame`` (uint16) at least :data:`ZSTD_MIN_SAVING` smaller."""
    raw = np.ascontiguousarray(frame)
    return len(Zstd(level=ZSTD_LEVEL).encode(raw)) <= (1.0 - ZSTD_MIN_SAVING) * raw.nbytes


class LogFramesWriter:
    """Appends accepted frames of one log, a whole shard at a time (one writer per shard)."""

    def __init__(self, root: zarr.Group, index: int, attrs: dict, valid: np.ndarray, shard_frames: int = 16):
        self.group = root.create_group(f"log{index:03d}")
        self.group.attrs.update(attrs)
        h, w = valid.shape
        self.shard_frames = shard_frames
        self.images: zarr.Array | None = None  # created at the first shard (its codec: :func:`pays_to_compress`)
        self.group.create_array("valid", data=valid.astype(bool))
        # Frames are quantized straight into a shard's block; three blocks take turns (one
        # filling, at most two waiting for the writer), so no block is allocated (and paged
        # in by the kernel) per shard.
        self._blocks = [np.empty((shard_frames, h, w), np.uint16) for _ in range(3)]
        self._turn = 0
        self._fill = 0
        self._rows: list[tuple] = []
        self.count = 0
        # Shards are written by one thread of their own, in order (zarr's write of a shard
        # is ~0.25 s of Python for 16 frames of 1024 x 1024, which held up the frames'
        # processing); at most two wait.
        self._writer = ThreadPoolExecutor(1)
        self._pending: list = []

    def append(self, image: np.ndarray, t: float, prior: np.ndarray, source_index: int, quality: tuple) -> None:
        """One frame (8-bit grey levels, or uint16 as stored: :func:`quantize`'s output,
        copied as is) and its figures; ``quality`` in :data:`QUALITY_COLUMNS` order, the
        trailing columns optional (:data:`QUALITY_DEFAULTS`, else 0)."""
        quality = tuple(quality)
        if len(quality) < len(QUALITY_COLUMNS):
            quality += tuple(QUALITY_DEFAULTS.get(c, 0.0) for c in QUALITY_COLUMNS[len(quality):])
        if image.dtype == np.uint16:
            np.copyto(self._blocks[self._turn][self._fill], image)
        else:
            quantize(image, self._blocks[self._turn][self._fill])
        self._fill += 1
        self._rows.append((t, prior, source_index, quality))
        if self._fill == self.shard_frames:
            self._flush()

    def _create_images(self, sample: np.ndarray | None) -> None:
        """The ``images`` array, zstd-compressed if that pays on ``sample`` (a frame; None:
        compressed)."""
        h, w = self._blocks[0].shape[1:]
        compress = sample is None or pays_to_compress(sample)
        self.images = self.group.create_array(
            "images",
            shape=(0, h, w),
            chunks=(1, h, w),
            shards=(self.shard_frames, h, w),
            dtype="uint16",
            compressors=ZstdCodec(level=ZSTD_LEVEL) if compress else None,
            # every chunk written (a frame is never all fill value): zarr otherwise compares
            # each 2 MB chunk of a 1024 px frame with the fill value first, in the writer's
            # thread, holding up the frames' processing
            config={"write_empty_chunks": True},
        )

    def _write(self, n0: int, block: np.ndarray) -> None:
        self.images.resize((n0 + len(block), *self.images.shape[1:]))
        self.images[n0 : n0 + len(block)] = block

    def _flush(self) -> None:
        if not self._fill:
            return
        n0 = self.count
        block = self._blocks[self._turn][: self._fill]
        if self.images is None:
            self._create_images(block[len(block) // 2])
        self.count = n0 + self._fill
        self._fill = 0
        self._pending.append(self._writer.submit(self._write, n0, block))
        self._turn = (self._turn + 1) % len(self._blocks)
        # (the next block is free once at most two writes are waiting)
        while len(self._pending) >= len(self._blocks):
            self._pending.pop(0).result()

    def close(self) -> int:
        self._flush()
        if self.images is None:  # no frame
            self._create_images(None)
        try:
            for f in self._pending:
                f.result()
        finally:
            self._pending = []
            self._writer.shutdown()
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


# A shard's index (zarr v3 sharding_indexed, index at the end): (offset, nbytes) uint64
# little-endian per chunk, then a crc32c; an absent chunk is (2^64 - 1, 2^64 - 1).
_INDEX_ENTRY_BYTES = 16
_CRC_BYTES = 4
ABSENT_CHUNK = np.uint64(2**64 - 1)  # (pipeline.shardfile writes the same layout)


class ShardFileReader:
    """Direct reader of an ``images`` array's shard files (local store), bypassing zarr.

    zarr costs ~1-3 ms per 640 x 480 frame read (its async pipeline, per-chunk tasks, the
    GIL against other threads); the shard file is the chunks one after the other plus an
    index at its end, so a read here is one ``pread`` of the index, then either one of the
    chunks' byte span and one zstd decode per frame into the output (~0.5 ms), or, for
    uncompressed frames, one ``preadv`` per frame straight into the output (~0.1 ms). Only
    the layouts ingest writes are read this way (:meth:`for_array` checks them: one frame
    per chunk, ``bytes`` little-endian codec with or without ``zstd``, index at the end,
    default chunk keys with ``/``); anything else returns None and callers read through
    zarr.
    """

    def __init__(self, array_dir: Path, shape: tuple[int, ...], shard_frames: int, fill_value: int, *,
                 compressed: bool = True):
        self.dir, self.shape, self.shard_frames, self.fill_value = Path(array_dir), shape, shard_frames, fill_value
        self.compressed = compressed
        self._codec = Zstd()
        self._crc = CRC32C()

    @classmethod
    def for_array(cls, array: zarr.Array) -> "ShardFileReader | None":
        """A reader for ``array`` when its store and codecs allow one, else None."""
        root = getattr(array.store, "root", None)
        if root is None or array.metadata.zarr_format != 3 or array.dtype != np.uint16:
            return None
        meta = array.metadata.to_dict()
        codecs = meta.get("codecs") or ()
        enc = meta.get("chunk_key_encoding") or {}
        if len(codecs) != 1 or codecs[0].get("name") != "sharding_indexed" or enc.get("name") != "default" \
                or (enc.get("configuration") or {}).get("separator", "/") != "/":
            return None
        conf = codecs[0]["configuration"]
        inner = [c.get("name") for c in conf.get("codecs", ())]
        endian = (conf["codecs"][0].get("configuration") or {}).get("endian", "little") if inner else None
        index = [c.get("name") for c in conf.get("index_codecs", ())]
        shards = tuple(meta["chunk_grid"]["configuration"]["chunk_shape"])
        if inner not in (["bytes", "zstd"], ["bytes"]) or endian != "little" or index != ["bytes", "crc32c"] \
                or conf.get("index_location", "end") != "end" or tuple(conf["chunk_shape"]) != (1, *array.shape[1:]) \
                or shards[1:] != tuple(array.shape[1:]):
            return None
        return cls(Path(root) / array.path, tuple(array.shape), int(shards[0]), int(array.fill_value or 0),
                   compressed=inner == ["bytes", "zstd"])

    def read(self, start: int, stop: int, *, separate: bool = False) -> np.ndarray | list[np.ndarray]:
        """Frames ``start:stop`` (clipped to the array), uint16 ``(n, H, W)`` as stored; with
        ``separate`` a list of one ``(H, W)`` array per frame, each decoded straight into its
        own (no copy)."""
        stop = min(stop, self.shape[0])
        start = min(max(start, 0), stop)
        if separate:
            out = [np.empty(self.shape[1:], np.uint16) for _ in range(start, stop)]
        else:
            out = np.empty((stop - start, *self.shape[1:]), np.uint16)
        n_per = self.shard_frames
        for blk in range(start // n_per, -(-stop // n_per)):
            a, b = max(start, blk * n_per), min(stop, (blk + 1) * n_per)
            self._read_shard(blk, a - blk * n_per, b - blk * n_per, out[a - start : b - start])
        return out

    def _read_shard(self, blk: int, i0: int, i1: int, out) -> None:
        """Frames ``i0:i1`` of shard ``blk`` into ``out`` (``out[n]``: frame ``i0 + n``)."""
        path = self.dir / "c" / str(blk) / "/".join("0" * (len(self.shape) - 1))
        n_per = self.shard_frames
        try:
            fd = os.open(path, os.O_RDONLY)
        except FileNotFoundError:  # an absent shard holds the fill value
            for o in out:
                o[...] = self.fill_value
            return
        try:
            size = os.fstat(fd).st_size
            n_index = n_per * _INDEX_ENTRY_BYTES + _CRC_BYTES
            if size < n_index:
                raise OSError(f"{path}: shard of {size} bytes, shorter than its index")
            raw_index = os.pread(fd, n_index, size - n_index)
            try:  # the index's crc32c, as zarr checks it
                raw_index = self._crc.decode(raw_index)
            except RuntimeError as e:
                raise OSError(f"{path}: shard index checksum: {e}") from None
            index = np.frombuffer(raw_index, "<u8", count=2 * n_per).reshape(n_per, 2)
            sel = index[i0:i1]
            present = sel[:, 0] != ABSENT_CHUNK
            if not present.any():
                for o in out:
                    o[...] = self.fill_value
                return
            lo = int(sel[present, 0].min())
            hi = int((sel[present, 0] + sel[present, 1]).max())
            if hi > size - n_index:
                raise OSError(f"{path}: shard index points past its data")
            if not self.compressed:
                self._read_raw(fd, path, i0, sel, out)
                return
            span = memoryview(os.pread(fd, hi - lo, lo))
        finally:
            os.close(fd)
        frame_bytes = out[0].nbytes
        for n, (off, nb) in enumerate(sel):
            if off == ABSENT_CHUNK:
                out[n][...] = self.fill_value
                continue
            o = int(off) - lo
            chunk = span[o : o + int(nb)]
            size_said = zstd_content_size(bytes(chunk[:18]))  # (its header: a few bytes)
            if size_said == frame_bytes:  # straight into the frame's array
                self._codec.decode(chunk, out=out[n])
                continue
            data = self._codec.decode(chunk)  # its own length: a short chunk is caught
            if len(data) != frame_bytes:
                raise OSError(f"{path}: chunk {i0 + n} decodes to {len(data)} bytes, a frame is {frame_bytes}")
            out[n][...] = np.frombuffer(data, "<u2").reshape(out[n].shape)

    def _read_raw(self, fd: int, path: Path, i0: int, sel: np.ndarray, out) -> None:
        """Uncompressed frames: chunk ``n`` of the index rows ``sel`` (frame ``i0 + n``) read
        straight into ``out[n]`` (contiguous uint16 arrays)."""
        frame_bytes = out[0].nbytes
        for n, (off, nb) in enumerate(sel):
            if off == ABSENT_CHUNK:
                out[n][...] = self.fill_value
                continue
            if int(nb) != frame_bytes:
                raise OSError(f"{path}: chunk {i0 + n} holds {int(nb)} bytes, a frame is {frame_bytes}")
            got = os.preadv(fd, [out[n]], int(off))
            if got != frame_bytes:
                raise OSError(f"{path}: chunk {i0 + n}: read {got} of its {frame_bytes} bytes")


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

    @property
    def quality_columns(self) -> list[str]:
        """Names of the ``quality`` columns."""
        return list(self.group["quality"].attrs.get("columns", []))

    @property
    def quality(self) -> np.ndarray:
        """Per-frame quality figures, float32 ``(N, K)`` (columns: :attr:`quality_columns`)."""
        return self.group["quality"][...]

    @property
    def registrable(self) -> np.ndarray:
        """bool ``(N,)``: True for frames registration may pair; False for frames kept with
        too little (or one-directional) texture, which the optimizer and the render place by
        their prior pose
        (their reason is in the ingest manifest's ``placed_by_prior``). All True for stores
        written before the column existed."""
        cols = self.quality_columns
        if "registrable" not in cols:
            return np.ones(self.count, bool)
        return self.group["quality"][:, cols.index("registrable")] > 0.5

    def image(self, i: int) -> np.ndarray:
        """Frame ``i`` as float32 in 8-bit grey levels."""
        return dequantize(self.images_uint16(i, i + 1)[0])

    @cached_property
    def shard_frames(self) -> int:
        return int(self.group["images"].shards[0])

    @cached_property
    def _direct(self) -> ShardFileReader | None:
        return ShardFileReader.for_array(self.group["images"])

    def images_uint16(self, start: int, stop: int, *, separate: bool = False) -> np.ndarray | list[np.ndarray]:
        """Frames ``start:stop`` as stored: uint16, grey level = value x ``INTENSITY_SCALE``
        (the shard files read directly when their layout allows, else through zarr).
        ``separate``: a list of one array per frame (each decoded into its own, without
        a copy where the shard files are read directly), else one ``(n, H, W)`` array."""
        direct = self._direct
        if direct is not None:
            return direct.read(start, stop, separate=separate)
        run = self.group["images"][start:stop]
        return [f.copy() for f in run] if separate else run

    def images(self, start: int, stop: int) -> np.ndarray:
        """Frames ``start:stop`` as float32 (one read; cheapest over whole shards)."""
        return dequantize(self.images_uint16(start, stop))


class FrameStore:
    """Read access to a frames store written by ingest."""

    def __init__(self, path: str | Path):
        self.root = zarr.open_group(str(path), mode="r")
        if self.root.attrs.get("format") != FORMAT:
            raise ValueError(f"{path}: not a mosaicmap frames store")
        self.pixel_size = float(self.root.attrs["pixel_size_m"])
        self.logs = [LogFrames(self.root[f"log{i:03d}"]) for i in range(len(self.root.attrs["logs"]))]
