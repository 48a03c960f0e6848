"""Whole chunks and shards of a local zarr v3 array written straight to their files.

zarr's own write path costs ~5x the compression it performs on a render's shards (~45 ms of
CPU per 2048 x 2048 uint8 shard of 64 chunks against ~10 ms of zstd: asyncio, per-chunk
codec pipelines, buffer copies). The render writes whole shards (level 0, level 1 and the
pyramid) and whole chunks (a layer's chunk is one shard's cells) of its staging map, a plain
local zarr directory, so :class:`DirectWriter` writes the same files itself: each chunk
through the array's ``bytes`` + ``zstd`` codecs (numcodecs' Zstd, as zarr uses it) and, for a
sharded array, the shard's index (offset and length of each chunk, ``uint64`` little-endian,
``(2^64 - 1, 2^64 - 1)`` for an absent chunk, then its crc32c) at the end, as zarr's
``sharding_indexed`` codec lays it out (:class:`pipeline.framestore.ShardFileReader` reads the
same layout). As zarr does by default (``write_empty_chunks = False``), a chunk holding only
the fill value is not stored, and a shard or chunk file left without data is removed.
Chunks reaching past the array's edge are stored whole, padded with the fill value.

Arrays with other codecs, stores or layouts get ``None`` from :meth:`DirectWriter.for_array`:
their callers write through zarr.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import zarr
from numcodecs import CRC32C, Zstd

from pipeline.framestore import ABSENT_CHUNK

__all__ = ["DirectWriter", "write_region"]


class DirectWriter:
    """Writes whole shards (or, unsharded, whole chunks) of one 2-D local zarr v3 array.

    ``shard``: the shard's (or chunk's) side in elements, rows and columns; ``chunk``: the
    inner chunk's (equal to ``shard`` when the array has no sharding codec)."""

    def __init__(self, array_dir: Path, shape: tuple[int, int], dtype: np.dtype, fill, shard: tuple[int, int],
                 chunk: tuple[int, int], zstd_level: int, sharded: bool):
        self.dir, self.shape, self.dtype = Path(array_dir), shape, np.dtype(dtype)
        self.fill = np.asarray(fill, self.dtype)
        self.shard, self.chunk, self.sharded = shard, chunk, sharded
        self._zstd = Zstd(level=zstd_level)
        self._crc = CRC32C()

    @classmethod
    def for_array(cls, array: zarr.Array) -> "DirectWriter | None":
        """A writer for ``array`` when it is a 2-D zarr v3 array of a local directory store,
        default ``/`` chunk keys, little-endian ``bytes`` + ``zstd`` (no checksum) chunks, as
        a ``sharding_indexed`` codec (index at the end, ``bytes`` + ``crc32c``) or alone;
        else None."""
        root = getattr(array.store, "root", None)
        if root is None or array.metadata.zarr_format != 3 or array.ndim != 2 or array.dtype.kind not in "uif":
            return None
        meta = array.metadata.to_dict()
        enc = meta.get("chunk_key_encoding") or {}
        if enc.get("name") != "default" or (enc.get("configuration") or {}).get("separator", "/") != "/":
            return None
        outer = tuple(int(v) for v in meta["chunk_grid"]["configuration"]["chunk_shape"])
        codecs = list(meta.get("codecs") or ())
        sharded = len(codecs) == 1 and codecs[0].get("name") == "sharding_indexed"
        inner_shape = outer
        if sharded:
            conf = codecs[0]["configuration"]
            index = [(c.get("name"), (c.get("configuration") or {}).get("endian", "little"))
                     for c in conf.get("index_codecs", ())]
            if index != [("bytes", "little"), ("crc32c", "little")] or conf.get("index_location", "end") != "end":
                return None
            inner_shape = tuple(int(v) for v in conf["chunk_shape"])
            if any(o % i for o, i in zip(outer, inner_shape)):
                return None
            codecs = list(conf.get("codecs") or ())
        names = [c.get("name") for c in codecs]
        if names != ["bytes", "zstd"]:
            return None
        if (codecs[0].get("configuration") or {}).get("endian", "little") != "little" and array.dtype.itemsize > 1:
            return None
        zconf = codecs[1].get("configuration") or {}
        if zconf.get("checksum", False):
            return None
        return cls(Path(root) / array.path, tuple(array.shape), array.dtype, array.fill_value, outer, inner_shape,
                   int(zconf.get("level", 0)), sharded)

    def _empty(self, block: np.ndarray) -> bool:
        if self.dtype.kind == "f" and np.isnan(self.fill):
            return bool(np.isnan(block).all())
        return not np.any(block != self.fill)

    def _encode(self, block: np.ndarray) -> bytes | None:
        """One chunk's stored bytes (None when it holds only the fill value): ``block`` is the
        part inside the array, padded here to the whole chunk."""
        if self._empty(block):
            return None
        ch, cw = self.chunk
        if block.shape != (ch, cw):
            full = np.full((ch, cw), self.fill, self.dtype)
            full[: block.shape[0], : block.shape[1]] = block
            block = full
        return bytes(self._zstd.encode(np.ascontiguousarray(block, self.dtype.newbyteorder("<"))))

    def _put(self, ij: tuple[int, int], payload: bytes | None) -> None:
        path = self.dir / "c" / str(ij[0]) / str(ij[1])
        if payload is None:
            path.unlink(missing_ok=True)
            return
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        tmp.write_bytes(payload)
        os.replace(tmp, path)

    def write(self, ij: tuple[int, int], data: np.ndarray) -> None:
        """Store shard (or chunk) ``ij`` (row, column of the outer chunk grid): ``data`` is its
        part inside the array (``shape`` clipped at the array's edge), replacing what it held."""
        sh, sw = self.shard
        r0, c0 = ij[0] * sh, ij[1] * sw
        want = (min(sh, self.shape[0] - r0), min(sw, self.shape[1] - c0))
        if data.shape != want or r0 < 0 or c0 < 0:
            raise ValueError(f"shard {ij} of {self.dir}: data {data.shape}, the shard holds {want}")
        if not self.sharded:
            self._put(ij, self._encode(data))
            return
        ch, cw = self.chunk
        nr, nc = sh // ch, sw // cw
        index = np.full((nr, nc, 2), ABSENT_CHUNK, np.dtype("<u8"))
        parts, offset = [], 0
        for a in range(nr):
            for b in range(nc):
                block = data[a * ch : (a + 1) * ch, b * cw : (b + 1) * cw]
                if block.size == 0:
                    continue  # past the array's edge
                enc = self._encode(block)
                if enc is None:
                    continue
                index[a, b] = (offset, len(enc))
                parts.append(enc)
                offset += len(enc)
        if not parts:
            self._put(ij, None)
            return
        parts.append(bytes(self._crc.encode(index.tobytes())))
        self._put(ij, b"".join(parts))


def write_region(array: zarr.Array, writer: DirectWriter | None, r0: int, c0: int, data: np.ndarray) -> None:
    """``array[r0:r0 + h, c0:c0 + w] = data``: straight to the file when ``writer`` is given and
    the region is one whole shard (chunk) clipped to the array, else through zarr."""
    if writer is not None and r0 % writer.shard[0] == 0 and c0 % writer.shard[1] == 0:
        ij = (r0 // writer.shard[0], c0 // writer.shard[1])
        if data.shape == (min(writer.shard[0], writer.shape[0] - r0), min(writer.shard[1], writer.shape[1] - c0)):
            writer.write(ij, data)
            return
    array[r0 : r0 + data.shape[0], c0 : c0 + data.shape[1]] = data
